"""Every error the library raises on purpose, under one base.

``jaxinertia.app.cli.main`` catches :class:`JaxinertiaError` once, prints its one-line
message and exits with its ``exit_code``: 2 for bad input (files, options, requests), 3 for
the servo bus and the hardware. Anything else is a bug and keeps its traceback.

Each class also derives from the built-in exception a caller would expect
(``FileFormatError`` is a ``ValueError``, ``TagNotFoundError`` a ``LookupError``), so
``except ValueError`` keeps working for library users.

A message speaks of the caller's arguments, never of command-line flags: it names an
argument in back-quotes, as Python spells it (`` `step_deg` ``, `` `overwrite` ``); the
command line shows the flag instead (:func:`jaxinertia.app.options.flag_wording`:
``--step-deg``, ``--overwrite``).
"""

from __future__ import annotations

import os

__all__ = [
    "CameraError",
    "ConfigError",
    "FileFormatError",
    "HardwareError",
    "JaxinertiaError",
    "ModelFolderError",
    "RobotMismatchError",
    "SimulationError",
    "TagNotFoundError",
    "TrainingError",
    "UsageError",
    "WeightsError",
]

EXIT_BAD_INPUT = 2
EXIT_HARDWARE = 3


class JaxinertiaError(Exception):
    """Base of the library's errors; ``str(e)`` is a complete one-line message."""

    exit_code: int = EXIT_BAD_INPUT


class UsageError(JaxinertiaError, ValueError):
    """A request that cannot be carried out as given (an option, an object name, a plan)."""


class FileFormatError(JaxinertiaError, ValueError):
    """A file that is missing, unreadable or malformed; names the file and the field."""

    def __init__(self, path: str | os.PathLike, field: str | None, message: str):
        self.path, self.field = str(path), field
        where = f"{path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {message}")


class RobotMismatchError(JaxinertiaError, ValueError):
    """Data, models or parameters made for another robot than the one asked for."""


class ModelFolderError(JaxinertiaError, ValueError):
    """A model folder (orbax checkpoint + ``config.json``) that cannot be used; the message
    names the folder or file."""


class WeightsError(JaxinertiaError, ValueError):
    """Network weights (``.npz`` or PyTorch ``.pt``) that cannot be used; the message names
    the file."""


class ConfigError(FileFormatError):
    """A parameter file (simulator fit, camera pose, intrinsics) that cannot be used."""


class TrainingError(JaxinertiaError, ArithmeticError):
    """Training that diverged (a loss went non-finite): no model folder is written."""


class SimulationError(JaxinertiaError, ValueError):
    """A plan that cannot be simulated, or a simulation that diverged."""


class CameraError(JaxinertiaError, ValueError):
    """A camera calibration or pose that cannot be computed from the images given."""


class TagNotFoundError(JaxinertiaError, LookupError):
    """The AprilTag asked for is not in the image."""


class HardwareError(JaxinertiaError, RuntimeError):
    """A device failed: the servo bus or a servo (communication, hardware error status), or
    a camera that cannot be opened or gives no frame."""

    exit_code = EXIT_HARDWARE
