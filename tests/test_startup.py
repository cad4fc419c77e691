"""The command line starts fast and logs cleanly (issue 32 item 7): ``--help`` of every
command imports none of JAX, flax, optax, orbax, matplotlib or OpenCV (the time is
measured by ``make bench-help``, never asserted here); the parsers' defaults are the
library's; progress bars become one line per stage when the output is not a terminal."""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys

import pytest

from jaxinertia.app import cli, defaults

HEAVY = ("jax", "flax", "optax", "orbax", "matplotlib", "cv2", "torch", "mujoco")


def test_help_of_every_command_imports_no_heavy_module():
    """One subprocess: ``--help``, then each command's (but the vision commands', whose
    module is not light yet), each from a fresh parser, JAX never imported."""
    commands = [c for c, (m, _) in cli.COMMANDS.items() if m != "vision_commands"]
    code = ("import contextlib, io, json, sys\n"
            "from jaxinertia.app.cli import main\n"
            "codes = {}\n"
            f"for c in [''] + {commands!r}:\n"
            "    with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            "        codes[c] = (main([c, '--help'] if c else ['--help']), len(out.getvalue()))\n"
            f"print(json.dumps({{'codes': codes, 'heavy': sorted(m for m in {HEAVY!r} "
            "if m in sys.modules)}))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["heavy"] == [], res
    assert all(code == 0 and n > 100 for code, n in res["codes"].values()), res["codes"]


def _choices(parser) -> dict[str, str]:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return {c.dest: c.help for c in a._choices_actions}
    raise AssertionError("no subcommands")


def test_the_command_table_is_what_the_modules_register():
    full = _choices(cli.build_parser())
    assert sorted(full) == sorted(cli.COMMANDS)
    for name, (module, line) in cli.COMMANDS.items():
        own = cli.build_parser(name)  # the parser main uses for this command
        sub = next(a for a in own._actions if isinstance(a, argparse._SubParsersAction))
        assert sub.choices[name].get_default("func").__module__ == f"jaxinertia.app.{module}"
        if module != "vision_commands":  # its help line is that module's to change
            assert full[name] == line, name
    listing = _choices(cli.build_parser(""))  # `jaxinertia --help`: every command, by name
    assert listing == {n: line for n, (_, line) in cli.COMMANDS.items()}


def test_the_parsers_defaults_are_the_librarys():
    from jaxinertia import arms, design, objects, open_manipulator_x, training, training_setup
    from jaxinertia.hardware.driver import ArmConfig

    assert defaults.TRAIN == training.TrainConfig().to_dict()
    assert defaults.FINETUNE == training.FINETUNE_DEFAULTS
    assert defaults.TRAINABLE == training_setup.TRAINABLE
    assert defaults.MARGIN_DEG == design.DEFAULT_MARGIN_DEG
    assert defaults.MOUNT_CLEARANCE_M == open_manipulator_x.MOUNT_CLEARANCE_M
    assert defaults.JOINT_IDS == open_manipulator_x.JOINT_IDS
    assert defaults.GRIPPER_ID == open_manipulator_x.GRIPPER_ID
    assert defaults.BUS_RETRIES == ArmConfig.retries
    assert list(defaults.OBJECT_NAMES) == objects.known_names()
    assert defaults.ARM_NAMES == tuple(arms.ARMS) and defaults.DEFAULT_ARM == arms.DEFAULT_ARM


@pytest.mark.parametrize("leave", [True, False])
def test_progress_is_one_line_per_stage_off_a_terminal(leave):
    from tqdm.auto import tqdm

    from jaxinertia.app import progress

    progress.configure()
    log = io.StringIO()
    with tqdm(total=40, desc="torque models", unit="epoch", file=log, mininterval=0,
              leave=leave) as bar:
        for _ in range(40):
            bar.update(1)
    text = log.getvalue()
    assert "\r" not in text
    if leave:
        assert text.count("\n") == 1 and text.startswith("torque models: 40/40 in "), text
    else:
        assert text == ""


def test_progress_stays_a_bar_on_a_terminal():
    from tqdm.auto import tqdm

    from jaxinertia.app import progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    progress.configure()
    term = Terminal()
    with tqdm(total=3, desc="x", file=term, mininterval=0) as bar:
        for _ in range(3):
            bar.update(1)
    assert term.getvalue().count("\r") >= 3
