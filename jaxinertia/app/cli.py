"""Command line: ``jaxinertia <command> ...``.

Every command raises :class:`jaxinertia.errors.JaxinertiaError` for what the user can fix;
:func:`main` catches it once, prints one line (``jaxinertia <command>: error: ...``) and
exits with the error's code (2 for bad input, 3 for the bus and the hardware). The commands
live in :mod:`jaxinertia.app.commands` (the paper's), :mod:`jaxinertia.app.estimate_commands`,
:mod:`jaxinertia.app.hardware_commands` and :mod:`jaxinertia.app.vision_commands`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from jaxinertia import _xla_workarounds, compilation_cache
from jaxinertia.app import commands, estimate_commands, hardware_commands, vision_commands
from jaxinertia.app.options import Parser
from jaxinertia.errors import JaxinertiaError

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="jaxinertia",
        description="Mass and centre of mass of a held object from servo encoder discrepancies.",
    )
    sub = p.add_subparsers(dest="command", required=True)
    commands.register(sub)
    estimate_commands.register(sub)  # an unknown object: estimate, plan-poses
    hardware_commands.register(sub)  # DYNAMIXEL bus, virtual robot, collection
    vision_commands.register(sub)  # camera: tag pose, camera-in-base calibration
    return p


def _compilation_cache() -> None:
    """Compiled programs persist between runs (the simulator's stream and the training
    steps take seconds to compile): in ``~/.cache/jaxinertia/xla``, or
    ``JAXINERTIA_CACHE_DIR``; ``JAXINERTIA_CACHE_DIR=off`` turns it off. Set by the
    command line only: importing the library leaves the cache setting to its host program."""
    where = os.environ.get("JAXINERTIA_CACHE_DIR",
                           str(Path.home() / ".cache" / "jaxinertia" / "xla"))
    if where.lower() != "off":
        compilation_cache.enable(where)  # LRU beyond compilation_cache.MAX_BYTES


def main(argv: list[str] | None = None) -> int:
    _xla_workarounds.apply()  # before any command starts JAX's backend
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a bad option (2, one line printed)
        return int(e.code or 0)
    _compilation_cache()
    try:
        return int(args.func(args) or 0)
    except JaxinertiaError as e:
        print(f"jaxinertia {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code


if __name__ == "__main__":
    sys.exit(main())
