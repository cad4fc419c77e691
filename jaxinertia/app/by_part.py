"""Models for the mass and models for the COM: a model folder whose ``config.json`` names a
folder inside it (``com_models``, written by :func:`attach_com_models`) answers the mass
from its own models and the COM from that folder's.

Why: the held-out folds judge the mass and the COM of every candidate apart
(:func:`jaxinertia.app.recipe.choose_recipe`'s ``by_part``), and the best of each need not
be one model: at full scale the mass is best from a torque model fine-tuned on real
samples, the COM from one trained on drawn recording sessions alone (docs/results.md,
"Sessions"). Each folder estimates ``x = [m, m p]`` by its own WLS; the answer takes ``m``
(and its spread, standard error and intervals) from the mass folder and ``p`` (likewise)
from the COM folder, for the network methods (T, T-A). The baselines (Sensor, PE) are the
mass folder's, whole. The covariance of ``x`` across two folders' estimates is not known,
so a merged answer gives none (it says so) rather than a wrong one.
"""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np

from jaxinertia.checkpoints import CONFIG
from jaxinertia.fileio import write_json

__all__ = ["COM_MODELS", "NETWORK_METHODS", "attach_com_models", "com_models_of",
           "merge_answers", "merge_evaluations"]

#: The ``config.json`` key naming the COM folder (relative to the folder).
COM_MODELS = "com_models"
#: The methods whose COM comes from the COM folder.
NETWORK_METHODS = ("T", "T-A")
#: Answer fields of one method that are the COM's (:func:`jaxinertia.app.estimate`).
_COVARIANCE = ("covariance_x", "covariance_mass_com", "covariance_terms")


def com_models_of(models: str | os.PathLike, config: dict) -> Path | None:
    """The COM folder that a model folder (its ``config``) names, or None."""
    name = config.get(COM_MODELS)
    return None if name is None else Path(models) / name


def attach_com_models(models: str | os.PathLike, name: str = "com") -> None:
    """Records in ``models/config.json`` that the COM comes from ``models/name`` (a model
    folder already written there)."""
    path = Path(models) / CONFIG
    config = json.loads(path.read_text())
    if not (Path(models) / name / CONFIG).is_file():
        raise FileNotFoundError(f"{Path(models) / name}: no model folder to take the COM from")
    write_json(path, {**config, COM_MODELS: name})


def _is_com_key(key: str) -> bool:
    return key.startswith("com_")


def merge_evaluations(mass: dict, com: dict) -> dict:
    """An evaluation (:func:`jaxinertia.evaluation.evaluate` or ``evaluate_models``) with the
    network methods' COM metrics and estimates of ``com``'s."""
    out = copy.deepcopy(mass)
    for name, methods in out["objects"].items():
        for m in NETWORK_METHODS:
            if m in methods and m in com["objects"][name]:
                methods[m].update({k: v for k, v in com["objects"][name][m].items()
                                   if _is_com_key(k)})
    for m in NETWORK_METHODS:
        if m in out.get("estimates", {}):
            xm, xc = np.asarray(out["estimates"][m]), np.asarray(com["estimates"][m])
            p = xc[..., 1:] / xc[..., :1]
            out["estimates"][m] = np.concatenate([xm[..., :1], xm[..., :1] * p], axis=-1)
    return out


def merge_answers(mass: dict, com: dict) -> dict:
    """An ``estimate`` answer with the network methods' COM (value, spread, standard error,
    intervals) of ``com``'s; a method is an answer only where both folders give one."""
    out = copy.deepcopy(mass)
    for name, obj in out["objects"].items():
        for m in NETWORK_METHODS:
            a, b = obj["methods"].get(m), com["objects"][name]["methods"].get(m)
            if a is None or b is None:
                continue
            if not (a["ok"] and b["ok"]):
                why = [f"{part}: {r['reason']}" for part, r in (("mass models", a),
                                                                  ("COM models", b))
                       if not r["ok"]]
                obj["methods"][m] = {"ok": False, "reason": "; ".join(why)}
                continue
            a.update({k: v for k, v in b.items() if _is_com_key(k)})
            for k, v in b.items():
                if k.startswith("interval_"):
                    a[k]["com_tag_m"] = v["com_tag_m"]
                elif k == "servo_state_sensitivity":  # the mass's from a, the COM's from b
                    a[k] = {**a[k], "com_m": v["com_m"]}
            for k in _COVARIANCE:
                a.pop(k, None)
            a["covariance_note"] = ("mass and COM from two model folders: their joint "
                                    "covariance is not known")
        obj["com_session_ratio"] = com["objects"][name]["session_ratio"]
    return out
