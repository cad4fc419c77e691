"""Shared fixtures. Identification is tested in float64 (the library's choice)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

import jaxinertia  # noqa: F401  (applies the XLA:CPU settings before JAX starts)

jax.config.update("jax_enable_x64", True)

# The command line keeps compiled programs in a persistent cache; tests point it at one
# folder per session (never the user's ~/.cache), shared with the CLI and virtual-robot
# subprocesses they start, so each program compiles once per session.
if "JAXINERTIA_CACHE_DIR" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="jaxinertia-test-xla-")
    os.environ["JAXINERTIA_CACHE_DIR"] = _CACHE

    def pytest_sessionfinish(session, exitstatus):  # noqa: ARG001
        shutil.rmtree(_CACHE, ignore_errors=True)

from jaxinertia.lbipe import default_lbipe_dir  # noqa: E402

ASSETS = Path(__file__).parent / "assets"

HOW_TO_GET_LBIPE = (
    "the real OpenMANIPULATOR-X data (lbipe) is not at {path}. Put the shared/lbipe folder "
    "beside the repository (../shared/lbipe) or point JAXINERTIA_LBIPE_DIR at it; the data, "
    "weights and golden files come from the project's shared/ folder (the authors' "
    "ChirikjianLab/lbipe repository plus golden outputs)."
)


@pytest.fixture(scope="session")
def lbipe_dir() -> Path:
    """The shared lbipe folder; skipped with instructions when absent, failing under CI."""
    path = default_lbipe_dir()
    if not (path / "data").is_dir():
        msg = HOW_TO_GET_LBIPE.format(path=path)
        if os.environ.get("CI"):
            pytest.fail("CI is set and " + msg)
        pytest.skip(msg)
    return path
