"""Command line: ``jaxinertia <command> ...``.

Every command raises :class:`jaxinertia.errors.JaxinertiaError` for what the user can fix;
:func:`main` catches it once, prints one line (``jaxinertia <command>: error: ...``) and
exits with the error's code (2 for bad input, 3 for the bus and the hardware); Ctrl-C ends
a command with one line and exit code 130. The commands live in
:mod:`jaxinertia.app.commands` (the paper's), :mod:`jaxinertia.app.sim_commands`,
:mod:`jaxinertia.app.estimate_commands`,
:mod:`jaxinertia.app.hardware_commands` and :mod:`jaxinertia.app.vision_commands`.

Fast to start: :func:`main` imports only the module of the command asked for, and the
command modules import JAX (flax, optax, orbax, matplotlib) only when a command's work
starts, so ``jaxinertia --help`` and every ``jaxinertia <command> --help`` answer without
loading any of them.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

from jaxinertia import _xla_workarounds  # (light: the environment only, no JAX)
from jaxinertia.app.options import Parser, flag_wording
from jaxinertia.errors import JaxinertiaError
from jaxinertia.fileio import command_locks

__all__ = ["COMMANDS", "build_parser", "main"]

#: Each command, the module (of ``jaxinertia.app``) that registers it, and its line in
#: ``jaxinertia --help`` (which lists them without importing the modules; a test checks
#: that each module registers exactly its commands).
COMMANDS = {
    "lbipe-benchmark": ("commands", "evaluate the authors' ten released model pairs on real "
                        "data (Tables I and III)"),
    "simulate": ("sim_commands", "generate samples from the simulated OpenMANIPULATOR-X"),
    "calibrate": ("sim_commands", "fit the simulator's link gravity, servo and friction to real "
                  "samples"),
    "train": ("commands", "train torque and attention models (K seeds) and fit the baselines"),
    "evaluate": ("commands", "Tables I-III of trained models on real (default) or simulated "
                 "data"),
    "reproduce": ("commands", "simulate, train, evaluate, switching loads, sim-to-real, "
                  "report"),
    "models-real": ("draws", "models_real from several reproduce runs (training draws) on "
                    "the same real files"),
    "estimate": ("estimate_commands", "mass and COM of an unknown object from a sample file"),
    "plan-poses": ("estimate_commands", "choose the N most informative poses (D-optimal) for "
                   "an estimate"),
    "virtual-robot": ("hardware_commands", "the simulated arm's servos (DYNAMIXEL, or Feetech "
                      "STS) on a pseudo-terminal"),
    "collect": ("hardware_commands", "collect samples on the arm (or a virtual robot) into a "
                "native sample file"),
    "tag-image": ("vision_commands", "write an official AprilTag image to print"),
    "tag-pose": ("vision_commands", "pose of an AprilTag in one image (camera frame, and base "
                 "frame)"),
    "camera-calibrate": ("vision_commands", "camera pose in the robot base from images of the "
                         "end-effector tag"),
}

#: Exit status after Ctrl-C (128 + SIGINT), as a shell reports it.
EXIT_INTERRUPTED = 130


def _new_parser() -> tuple[Parser, argparse._SubParsersAction]:
    p = Parser(
        prog="jaxinertia",
        description="Mass and centre of mass of a held object from servo encoder discrepancies.",
    )
    return p, p.add_subparsers(dest="command", required=True)


def _register(sub, module: str) -> None:
    importlib.import_module(f"jaxinertia.app.{module}").register(sub)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command (importing every command module), or with ``command``
    the parser that ``main`` uses: that command's module only, the others listed by name."""
    p, sub = _new_parser()
    owner = COMMANDS[command][0] if command in COMMANDS else None
    registered = set()
    for name, (module, help_line) in COMMANDS.items():
        if command is None or module == owner:
            if module not in registered:
                _register(sub, module)
                registered.add(module)
        elif name not in sub.choices:
            sub.add_parser(name, help=help_line)
    if command in COMMANDS:  # an option no parser knows: the command's help lists them
        p.help_hint = f"jaxinertia {command}"
    return p


def _command_of(argv: list[str]) -> str:
    """The command named in ``argv`` ('' when none is: ``--help`` lists them all)."""
    return next((a for a in argv if not a.startswith("-")), "")


#: Commands whose compiled programs are kept however quick they were to compile
#: (:func:`jaxinertia.compilation_cache.enable`'s ``keep_small``): those a user runs again
#: and again on new files, made of many small programs.
KEEP_SMALL_PROGRAMS = frozenset({"estimate", "evaluate", "lbipe-benchmark"})


def _compilation_cache(command: str = "") -> None:
    """Compiled programs persist between runs (the simulator's stream and the training
    steps take seconds to compile): in ``~/.cache/jaxinertia/xla``, or
    ``JAXINERTIA_CACHE_DIR``; ``JAXINERTIA_CACHE_DIR=off`` turns it off. Set by the
    command line only: importing the library leaves the cache setting to its host program."""
    where = os.environ.get("JAXINERTIA_CACHE_DIR",
                           str(Path.home() / ".cache" / "jaxinertia" / "xla"))
    if where.lower() != "off":
        from jaxinertia import compilation_cache  # JAX: only when a command runs

        # LRU beyond compilation_cache.MAX_BYTES
        compilation_cache.enable(where, keep_small=command in KEEP_SMALL_PROGRAMS)


def _quiet_closed_loops(unraisable) -> None:
    """``sys.unraisablehook`` without orbax's "Event loop is closed": its asyncio objects,
    collected at exit after a command's error or Ctrl-C, report their closed loop as an
    unraisable exception, noise after the one-line message. Everything else goes to the
    default hook."""
    exc = unraisable.exc_value
    if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
        return
    sys.__unraisablehook__(unraisable)


def main(argv: list[str] | None = None) -> int:
    _xla_workarounds.apply()  # before any command starts JAX's backend
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_of(argv)
    try:
        args = build_parser(command).parse_args(argv)
    except SystemExit as e:  # --help (0) or a bad option (2, one line printed)
        return int(e.code or 0)
    from jaxinertia.app import progress  # (light) bars on a terminal, lines in a log

    progress.configure()  # each bar looks at its own stream
    try:
        _compilation_cache(args.command)
        with command_locks():
            return int(args.func(args) or 0)
    except JaxinertiaError as e:
        print(f"jaxinertia {args.command}: error: {flag_wording(str(e), args.command)}",
              file=sys.stderr, flush=True)
        sys.unraisablehook = _quiet_closed_loops
        return e.exit_code
    except KeyboardInterrupt:
        print(f"jaxinertia {args.command}: interrupted (Ctrl-C); no output was left "
              "half-written", file=sys.stderr, flush=True)
        sys.unraisablehook = _quiet_closed_loops
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
