"""What the command modules share: option types that check every number when it is
parsed (``must be a positive integer, got '0'``), a :class:`Parser` that prints argparse's
errors as one line with exit code 2, and the checks every command runs before its work
(outputs, repeated names, the memory a request needs) and its ``--json`` writer; the
wording of library messages as flags (:func:`flag_wording`).

Light on purpose: the parsers (and ``--help``) need only this module, never JAX.
"""

from __future__ import annotations

import argparse
import math
import os
import re

from jaxinertia.errors import UsageError
from jaxinertia.fileio import check_output, write_json

__all__ = ["MEMORY_ENV", "Parser", "check_memory", "check_outputs", "distinct", "enable_x64",
           "finite_float", "flag_wording", "fraction", "memory_limit_bytes", "nonnegative_float",
           "positive_float", "positive_int", "seed_int", "unit_fraction", "write_json_option",
           "zero_to_one"]

#: Environment variable: the memory [GB] a request may need before it is refused
#: (default: half the machine's memory).
MEMORY_ENV = "JAXINERTIA_MAX_MEMORY_GB"

#: Arguments whose flag is not the argument's name with dashes, by command.
_FLAGS = {"calibrate": {"objects": "--real-objects"}}
_ARGUMENT = re.compile(r"`([a-z][a-z0-9_]*)`")


def flag_wording(message: str, command: str | None = None) -> str:
    """A library message as the command line says it: each argument it names in
    back-quotes (`` `step_deg` ``) becomes the command's flag (``--step-deg``)."""
    flags = _FLAGS.get(command, {})
    return _ARGUMENT.sub(lambda m: flags.get(m[1], "--" + m[1].replace("_", "-")), message)


#: Seeds: what numpy and JAX both take (``--seed -1`` or ``1e23`` are refused when parsed).
SEED_MAX = 2**32 - 1


class Parser(argparse.ArgumentParser):
    """Bad options: one line naming the option and exit code 2 (not argparse's usage block)."""

    #: The help that the error points to (the command's, for options it does not know).
    help_hint: str | None = None

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.help_hint or self.prog} "
                  "--help)\n")


def _number(kind, test, what):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            v = None
        if v is None or not math.isfinite(v) or not test(v):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return v
    parse.__name__ = what  # argparse names the type in its messages
    return parse


positive_int = _number(int, lambda v: v > 0, "a positive integer")
positive_float = _number(float, lambda v: v > 0, "a positive number")
nonnegative_float = _number(float, lambda v: v >= 0, "a number >= 0")
fraction = _number(float, lambda v: 0 < v < 1, "a number in (0, 1)")
unit_fraction = _number(float, lambda v: 0 < v <= 1, "a number in (0, 1]")
zero_to_one = _number(float, lambda v: 0 <= v <= 1, "a number in [0, 1]")
finite_float = _number(float, lambda v: True, "a finite number")
seed_int = _number(int, lambda v: 0 <= v <= SEED_MAX, f"an integer in 0..{SEED_MAX}")


def enable_x64() -> None:
    """Identification is float64 (see jaxinertia.identification); networks stay float32."""
    import jax  # when the work starts: the parsers never load JAX

    jax.config.update("jax_enable_x64", True)


def memory_limit_bytes() -> float:
    """What one request may need: ``$JAXINERTIA_MAX_MEMORY_GB`` gigabytes, else half the
    machine's memory."""
    env = os.environ.get(MEMORY_ENV)
    if env:
        try:
            gb = float(env)
        except ValueError:
            gb = float("nan")
        if not (math.isfinite(gb) and gb > 0):
            raise UsageError(f"{MEMORY_ENV}={env!r} must be a positive number of gigabytes")
        return gb * 1e9
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2
    except (ValueError, OSError, AttributeError):
        return 8e9


def check_memory(needed_bytes: float, what: str) -> None:
    """Refuses, before allocating, a request estimated to need more than the limit."""
    limit = memory_limit_bytes()
    if needed_bytes > limit:
        raise UsageError(f"{what} needs about {needed_bytes / 1e9:.3g} GB, above the limit "
                         f"{limit / 1e9:.3g} GB: ask for less, or raise the limit with "
                         f"{MEMORY_ENV}=<GB>")


def distinct(names: list[str] | None, option: str) -> None:
    """Refuses a name given twice to ``option``."""
    if names and len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise UsageError(f"{option}: {', '.join(dup)} given more than once")


def check_outputs(args, *options: str) -> None:
    """Checks every output option given, before any work (``fileio.check_output``; the
    command has ``--overwrite``)."""
    for option in options:
        name = option.lstrip("-").replace("-", "_")
        path = getattr(args, name)
        if path is not None:
            check_output(path, overwrite=args.overwrite, option=name)


def write_json_option(args, obj) -> int:
    """``obj`` into ``--json`` when given; the command's exit code."""
    if args.json:
        write_json(args.json, obj)
        print(f"wrote {args.json}")
    return 0


def add_session_strength(parser) -> None:
    """``--session-strength`` of ``estimate`` and ``evaluate``."""
    parser.add_argument("--session-strength", type=zero_to_one, default=None, metavar="S",
                        help="how strongly the file's discrepancy is read in the models' "
                        "recording session, from its own current gain (0: off, 1: fully; "
                        "default: the model folder's)")


def session_line(name: str, strength: float, ratio) -> str:
    """How ``estimate`` and ``evaluate`` read an object's file: in the models' session
    (the per-joint factors), or not."""
    if strength > 0:
        factors = ", ".join(f"{r:.3f}" for r in ratio)
        return (f"{name}: session: discrepancy read in the models' session, x ({factors}) "
                f"per joint (the file's own current gain against the models', strength "
                f"{strength:g}; --session-strength 0: off)")
    return f"{name}: session adaptation off (the models' strength 0, or --session-strength 0)"


def _span(values, unit: str, digits: int) -> str:
    """Per-joint values as one number where they agree to the digits shown, else a range
    (None in ``values``: a joint that did not record it)."""
    known = [v for v in values if v is not None]
    lo, hi = (f"{v:.{digits}f}" for v in (min(known), max(known)))
    return f"{lo} {unit}" if lo == hi else f"{lo}-{hi} {unit}"


def servo_state_line(name: str, state: dict) -> str | None:
    """The servos' supply and temperature that an object's file recorded
    (:func:`jaxinertia.session.servo_state_change`), against the models' session where
    their files recorded them too; None for a file that recorded neither."""
    mine = [(k, unit, d) for k, unit, d in (("supply_voltage", "V", 2), ("temperature", "deg C", 0))
            if state.get(k) and any(v is not None for v in state[k])]
    if not mine:
        return None
    line = f"{name}: servo state recorded: " + ", ".join(_span(state[k], u, d)
                                                           for k, u, d in mine)
    theirs = [(k, u, d) for k, u, d in mine if state.get("reference_" + k)
              and any(v is not None for v in state["reference_" + k])]
    if not theirs:
        return line + " (the models' files recorded none to compare with)"
    line += "; the models' session: " + ", ".join(_span(state["reference_" + k], u, d)
                                                   for k, u, d in theirs)
    changes = []
    if state.get("supply_ratio"):
        changes.append("supply x " + _span(state["supply_ratio"], "", 3).strip())
    dt = [v for v in state.get("temperature_change") or () if v is not None]
    if dt:
        lo, hi = (f"{v:+.0f}" for v in (min(dt), max(dt)))
        changes.append(f"temperature {lo} K" if lo == hi else f"temperature {lo} to {hi} K")
    gain = state.get("current_gain_ratio")
    if gain and any(v is not None for v in gain):
        changes.append("current gain x " + " / ".join(
            "-" if v is None else f"{v:.3f}" for v in gain) + " (joints 1-" + f"{len(gain)})")
    return line + (f" ({'; '.join(changes)})" if changes else "")
