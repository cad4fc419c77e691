"""Trained models on disk: an orbax checkpoint plus a JSON sidecar.

A model folder holds ``checkpoint/`` (orbax: the K stacked torque and attention model
parameters) and ``config.json`` (architecture, feature normalisation, baselines, training
hyperparameters, seeds, the robot and its arm, the simulator fit and the training data's
SHA-256). Everything needed to use the models is in the folder.

``config.json`` records the SHA-256 of every file of ``checkpoint/`` (``checksums``);
:func:`load_models` verifies them before restoring, so a flipped bit, a truncated or a
swapped shard is a one-line :class:`ModelFolderError` naming the file, never weights that
load silently wrong. Folders written before the checksums (none recorded) still load,
unverified, with a note on stderr saying so; ``jaxinertia train --init OLD --out NEW``
(or retraining) writes a verified one.

A folder may be written anew from another with only its record changed
(:func:`copy_folder`: the checkpoint's files copied as they are, with their checksums); a
folder whose record says ``uniform_attention`` answers with its attention's last layer
zeroed (:func:`jaxinertia.networks.uniform_attention`), whatever its checkpoint holds.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia.baselines import Baselines
from jaxinertia.errors import ModelFolderError, RobotMismatchError
from jaxinertia.estimation import ModelPair
from jaxinertia.features import FeatureConfig
from jaxinertia.fileio import replacing_dir
from jaxinertia.networks import (
    TORQUE_MODELS,
    AttentionModel,
    parameter_shapes,
    torque_model_kind,
    uniform_attention,
)

__all__ = ["UNIFORM_ATTENTION", "ModelFolder", "copy_folder", "file_sha256", "load_models",
           "read_config", "save_models"]

CONFIG = "config.json"
#: The ``config.json`` key of a folder whose attention weights every joint alike: its
#: attention's last layer is zeroed when loaded (T-A then answers as T).
UNIFORM_ATTENTION = "uniform_attention"
FORMAT = "jaxinertia-models"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class ModelFolder:
    """A model folder as :func:`load_models` read it (verified, every weight finite).

    Attributes:
      pair: the K torque and attention models (:class:`~jaxinertia.estimation.ModelPair`).
      baselines: the baseline methods' fitted values (PE law, current-to-torque).
      features: the feature normalisation the models were trained with.
      config: ``config.json`` as a dict (architecture, training record, session, the
        torque models' validation error, checksums, ...).
      directory: the folder's absolute path.
    """

    pair: ModelPair
    baselines: Baselines
    features: FeatureConfig
    config: dict
    directory: Path


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _arch(model) -> dict:
    """A network's architecture as config.json records it. ``stacked_joints`` is how a
    program computes it (a GPU's training epochs), not what it is: left out, so a folder
    reads the same wherever it was trained."""
    return {k: list(v) if isinstance(v, tuple) else v
            for k, v in model.__dict__.items() if k in model.__dataclass_fields__
            and k not in ("parent", "name", "stacked_joints")}


#: One orbax save or restore at a time in this process: orbax's checkpointers are not safe
#: side by side in threads (their background operations share process-wide ids; two saves
#: at once in different folders failed on an H100 with "File exists" in one of them).
_ORBAX = threading.Lock()


def save_models(directory: str | os.PathLike, pair: ModelPair, baselines: Baselines,
                features: FeatureConfig, *, robot: str, extra: dict | None = None,
                arm: str | None = None) -> Path:
    """Writes ``directory/checkpoint`` (orbax) and ``directory/config.json`` (``arm``: the
    arm record's name, default the robot's: an arm's robot is named after it)."""
    import orbax.checkpoint as ocp  # heavy (~1 s): only when models are written or read

    _check_finite(pair, directory)
    state = {"torque": jax.device_get(pair.torque_vars),
             "attention": jax.device_get(pair.attention_vars)}
    config = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "robot": robot,
        "arm": arm or robot, "n_models": pair.n_models,
        "torque_model": {"kind": torque_model_kind(pair.torque_model),
                         **_arch(pair.torque_model)},
        "attention_model": _arch(pair.attention_model),
        "features": features.to_dict(),
        "baselines": baselines.to_dict(),
        **(extra or {}),
    }
    json.dumps(config, allow_nan=False)  # no bare NaN in the config (checked before writing)
    # Checkpoint and config appear together (a folder renamed into place) or not at all.
    with replacing_dir(directory) as tmp:
        with _ORBAX, ocp.StandardCheckpointer() as saver:
            saver.save(tmp / "checkpoint", state, force=True)
        config["checksums"] = _checksums(tmp / "checkpoint")
        text = json.dumps(config, indent=2, allow_nan=False) + "\n"
        (tmp / CONFIG).write_text(text)
    return Path(directory).absolute()


def _checksums(checkpoint: Path) -> dict[str, str]:
    """SHA-256 of every file under ``checkpoint``, by its path relative to the folder."""
    return {p.relative_to(checkpoint).as_posix(): file_sha256(p)
            for p in sorted(checkpoint.rglob("*")) if p.is_file()}


def _verify(directory: Path, config: dict) -> None:
    """Every file of ``checkpoint/`` as ``config.json`` recorded it (none missing, none
    added, none changed); a folder without checksums is loaded with a note."""
    recorded = config.get("checksums")
    checkpoint = directory / "checkpoint"
    if recorded is None:
        print(f"note: {directory} has no checksums (written before jaxinertia recorded "
              "them): its files are not verified", file=sys.stderr)
        return
    if not isinstance(recorded, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in recorded.items()):
        raise ModelFolderError(f"{directory / CONFIG}: checksums must map file names to "
                               "SHA-256 digests")
    found = _checksums(checkpoint) if checkpoint.is_dir() else {}
    for name in sorted(set(recorded) | set(found)):
        if name not in found:
            raise ModelFolderError(f"{checkpoint / name}: missing (config.json records it)")
        if name not in recorded:
            raise ModelFolderError(f"{checkpoint / name}: not recorded in config.json's "
                                   "checksums (a file added to the folder)")
        if found[name] != recorded[name]:
            raise ModelFolderError(f"{checkpoint / name}: checksum mismatch (the file changed "
                                   "after it was written: corrupt or edited)")


def read_config(directory: str | os.PathLike) -> dict:
    """A model folder's ``config.json``, checked to be one this version reads (the
    checkpoint is neither read nor verified: :func:`load_models` does both)."""
    directory = Path(directory).absolute()
    cfg_path = directory / CONFIG
    if not cfg_path.is_file():
        raise ModelFolderError(f"{directory}: no {CONFIG}: not a jaxinertia model folder "
                              "(make one with `jaxinertia train`)")
    try:
        config = json.loads(cfg_path.read_text())
    except (OSError, ValueError) as e:  # ValueError: not UTF-8, not JSON
        raise ModelFolderError(f"{cfg_path}: unreadable ({e})") from None
    if not isinstance(config, dict):
        raise ModelFolderError(f"{cfg_path}: not a jaxinertia model config (a JSON object "
                               f"expected, got {type(config).__name__})")
    if config.get("format") != FORMAT:
        raise ModelFolderError(f"{cfg_path}: not a jaxinertia model config")
    if config.get("format_version") != FORMAT_VERSION:
        raise ModelFolderError(f"{cfg_path}: format_version {config.get('format_version')!r}; "
                               f"this version of jaxinertia reads {FORMAT_VERSION}")
    return config


def copy_folder(src: str | os.PathLike, dst: str | os.PathLike, config: dict) -> Path:
    """Writes the model folder ``dst`` (atomically, replacing one there) with ``src``'s
    checkpoint files as they are and ``config`` as its record (the caller's: ``src``'s
    :func:`read_config` with changes; its ``checksums`` are ``src``'s). ``src``'s files are
    verified first, so a corrupt source is the error :func:`load_models` gives; a source
    without checksums gets them (as :func:`save_models` writes). The same weights bit
    for bit, without restoring and saving them (orbax: a tenth of a second a folder, and
    ``models_real`` copies 28 of them)."""
    src = Path(src).absolute()
    source = read_config(src)
    _verify(src, source)  # a corrupt source: load_models' one-line error, before any write
    config = {k: v for k, v in config.items() if k != "checksums"}
    json.dumps(config, allow_nan=False)  # no bare NaN in the config (checked before writing)
    with replacing_dir(dst) as tmp:
        shutil.copytree(src / "checkpoint", tmp / "checkpoint")
        config["checksums"] = source.get("checksums") or _checksums(tmp / "checkpoint")
        (tmp / CONFIG).write_text(json.dumps(config, indent=2, allow_nan=False) + "\n")
    return Path(dst).absolute()


def load_models(directory: str | os.PathLike, *, robot: str | None = None,
                arm: str | None = None) -> ModelFolder:
    """Reads and verifies a model folder -> :class:`ModelFolder`.

    ``robot`` / ``arm``: the robot and the arm the caller's samples come from; models of
    another are an error (:class:`RobotMismatchError`, one line). A folder that records no
    arm (trained on files that record none) is taken for any.
    """
    import orbax.checkpoint as ocp  # heavy (~1 s): only when models are written or read

    directory = Path(directory).absolute()
    cfg_path = directory / CONFIG
    config = read_config(directory)
    trained = config.get("arm") or config.get("robot")
    if (robot is not None and config.get("robot") != robot) or (
            arm is not None and trained not in (None, arm)):
        theirs = arm or robot
        raise RobotMismatchError(
            f"{directory}: models trained for robot {config.get('robot')!r} (arm {trained!r}), "
            f"the samples come from the arm {theirs!r} (as their file, or else `arm`, says): "
            f"use models trained on that arm's samples (train with `arm` {theirs})")
    try:
        arch = dict(config["torque_model"])
        kind = arch.pop("kind", "paper")  # folders before the option: the paper's network
        if kind not in TORQUE_MODELS:
            raise ValueError(f"unknown torque model kind {kind!r}")
        tm = TORQUE_MODELS[kind](**{k: tuple(v) if isinstance(v, list) else v
                                    for k, v in arch.items()})
        am = AttentionModel(**{k: tuple(v) if isinstance(v, list) else v
                               for k, v in config["attention_model"].items()})
    except (KeyError, TypeError, ValueError) as e:
        raise ModelFolderError(f"{cfg_path}: malformed model architecture "
                               f"({type(e).__name__}: {e})") from None
    try:
        features = FeatureConfig.from_dict(config["features"])
        baselines = Baselines.from_dict(config["baselines"])
        K = int(config["n_models"])
    except (KeyError, TypeError, ValueError) as e:
        raise ModelFolderError(f"{cfg_path}: malformed ({type(e).__name__}: {e})") from None
    if K < 1:
        raise ModelFolderError(f"{cfg_path}: n_models {K} must be at least 1")
    _verify(directory, config)
    n_in = features.n_inputs  # 4: the paper's inputs; 5 with the current torque
    target = {"torque": parameter_shapes(tm, tm.n_joints, K, n_inputs=n_in),
              "attention": parameter_shapes(am, tm.n_joints, K, n_inputs=n_in)}
    try:
        with _ORBAX, ocp.StandardCheckpointer() as loader:
            state = loader.restore(directory / "checkpoint", target)
    except Exception as e:  # orbax raises many types for missing or mismatched files
        raise ModelFolderError(f"{directory / 'checkpoint'}: cannot restore the models "
                              f"({type(e).__name__}: {_first_line(e)})") from e
    for name, tree in state.items():  # orbax restores what is on disk, whatever the target
        want = {jax.tree_util.keystr(p): s.shape
                for p, s in jax.tree_util.tree_leaves_with_path(target[name])}
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            if np.shape(leaf)[:1] != (K,):
                raise ModelFolderError(
                    f"{directory}: {name} parameters {jax.tree_util.keystr(path)} have shape "
                    f"{np.shape(leaf)}: not the {K} models config.json's n_models says")
            if want.get(jax.tree_util.keystr(path), np.shape(leaf)) != np.shape(leaf):
                raise ModelFolderError(
                    f"{directory}: {name} parameters {jax.tree_util.keystr(path)} have shape "
                    f"{np.shape(leaf)}, the architecture in config.json needs "
                    f"{want[jax.tree_util.keystr(path)]}")
    if config.get(UNIFORM_ATTENTION):
        state["attention"] = uniform_attention(state["attention"])
    pair = ModelPair(torque_vars=state["torque"], attention_vars=state["attention"],
                     tau_scale=jnp.asarray(np.asarray(features.tau_scale), jnp.float32),
                     torque_model=tm, attention_model=am)
    _check_finite(pair, directory)
    for k, v in {**features.to_dict(), **config["baselines"]}.items():
        # null: the Sensor baseline's constants of a joint without a current sensor
        missing = [x is None for x in v] if k.startswith("sensor_") else False
        a = np.asarray([0.0 if m else x for m, x in zip(missing, v)] if missing else v,
                       np.float64)
        if not np.all(np.isfinite(a)):
            raise ModelFolderError(f"{cfg_path}: {k} holds non-finite values")
    return ModelFolder(pair=pair, baselines=baselines, features=features, config=config,
                       directory=directory)


def _first_line(e: Exception) -> str:
    """The first line of an orbax error, without its listing of every key."""
    text = (str(e).splitlines() or [""])[0]
    return text.split(" Metadata keys:")[0][:300]


def _check_finite(pair: ModelPair, directory) -> None:
    """Every weight finite, or an error naming the folder and the parameter."""
    for name, tree in (("torque", pair.torque_vars), ("attention", pair.attention_vars)):
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            if not np.all(np.isfinite(np.asarray(leaf))):
                raise ModelFolderError(f"{directory}: {name} parameters "
                                       f"{jax.tree_util.keystr(path)} hold non-finite values")
