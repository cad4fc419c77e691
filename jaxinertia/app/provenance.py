"""Which real files a model folder was fitted on, so that a number on such a file is never
taken for a held-out one.

A folder was fitted on a file when it was trained or fine-tuned on it (its record's
``data``, whose ``sha256`` is the file's, and its start's) or when its simulator was
calibrated on it (the held-out folds' folders copied into ``models_real``:
:data:`FITTED_ON`, written by :func:`jaxinertia.app.models_real.models_from_folds`; a
folder trained on simulated data records no calibration otherwise). ``evaluate`` and
``estimate`` count, per part (the mass's folders, the COM's), how many of the folders
answering were fitted on the file they read, and say so."""

from __future__ import annotations

import os
from pathlib import Path

from jaxinertia.app.by_part import com_models_of
from jaxinertia.app.ensemble import members_of
from jaxinertia.checkpoints import CONFIG, read_config
from jaxinertia.fileio import write_json

__all__ = ["FITTED_ON", "fitted_on", "not_held_out_line", "record_fitted_on", "seen_by"]

#: A folder's record of the real files its simulator was calibrated on (and it trained or
#: fine-tuned on): ``[{"file": name, "sha256": ...}, ...]``.
FITTED_ON = "fitted_on_real"


def fitted_on(config: dict) -> set[str]:
    """The SHA-256 of every file a folder (its ``config``) was fitted on, as far as its
    record tells: :data:`FITTED_ON` (a fine-tuning carries its start's there), its
    training data, and that of the folder it was fine-tuned from (``fine_tuned_from``)."""
    def entries(key, within=config) -> list:  # a hand-edited record may hold anything
        v = within.get(key) if isinstance(within, dict) else None
        return [f for f in v if isinstance(f, dict)] if isinstance(v, list) else []

    start = config.get("fine_tuned_from")
    files = entries(FITTED_ON) + entries("data") + entries("data", start)
    return {f["sha256"] for f in files if isinstance(f.get("sha256"), str)}


def record_fitted_on(models: str | os.PathLike, files: list[dict]) -> None:
    """Adds ``files`` (``{"file": name, "sha256": ...}``) to a written folder's
    :data:`FITTED_ON` record."""
    config = read_config(models)
    new = {f.get("sha256"): f for f in files}  # one entry per file, the fuller one
    config[FITTED_ON] = [f for f in config.get(FITTED_ON) or ()
                         if not isinstance(f, dict) or f.get("sha256") not in new] + list(
        new.values())
    write_json(Path(models) / CONFIG, config)


def _answering(models: Path) -> list[dict]:
    """The configs of the folders that answer with ``models``: itself and its members."""
    config = read_config(models)
    return [config] + [read_config(m) for m in members_of(models, config)]


def seen_by(models: str | os.PathLike, sha256: str | None) -> dict[str, tuple[int, int]]:
    """Per part (``mass``, and ``com`` where the folder takes the COM from other models),
    how many of the folders answering it were fitted on the file of ``sha256``, of how
    many: ``{"mass": (k, n), ...}``; empty when none was (or the file's digest is unknown)."""
    if not sha256:
        return {}
    models = Path(models)
    parts = {"mass": models}
    com = com_models_of(models, read_config(models))
    if com is not None:
        parts["com"] = com
    out = {}
    for part, folder in parts.items():
        configs = _answering(folder)
        k = sum(sha256 in fitted_on(c) for c in configs)
        if k:
            out[part] = (k, len(configs))
    return out


def not_held_out_line(name: str, seen: dict[str, tuple[int, int]]) -> str | None:
    """The line ``evaluate`` and ``estimate`` print for an object whose file the models
    were fitted on (None: none was)."""
    if not seen:
        return None
    what = " and ".join(f"{k} of {n} folder(s) answering the {'COM' if part == 'com' else part}"
                        for part, (k, n) in seen.items())
    return (f"{name}: NOT HELD OUT: {what} were calibrated, trained or fine-tuned on this "
            "file; judge models on files they did not see")
