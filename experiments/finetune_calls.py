"""A fine-tuning's epochs one program call each, or several per call (a ``lax.scan`` over
them: ``training_group.epochs_per_call``): seconds for the whole fine-tuning, the first
(compiling) and a second (compiled), alone and in a group, with and without busy Python
threads beside it (the held-out folds run a dozen threads: judges, other trainings).

    python experiments/finetune_calls.py [--samples 64 250 1000] [--group 4] [--busy 4]

The folds' fine-tunings: the physical model's servo part, 200 epochs, batch 64, K = 10
models, on 64, 250 or 1000 samples of one real object (a tenth for validation). Synthetic
inputs of those shapes (``bench_train.synthetic``): the time does not depend on the values.
Both ways train the same models (tests/test_training_group.py checks it bit for bit on a
CPU); the script checks their validation losses agree.
"""

from __future__ import annotations

import argparse
import threading
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from bench_train import synthetic  # noqa: E402 - the sibling's inputs

from jaxinertia import training_group  # noqa: E402
from jaxinertia.app.programs import side_by_side  # noqa: E402
from jaxinertia.training import (  # noqa: E402
    FINETUNE_DEFAULTS,
    TrainConfig,
    feature_config_from,
    split_validation,
    train_torque_models,
)

K = 10


def _busy(stop: threading.Event) -> None:
    while not stop.is_set():  # pure Python: holds the GIL in turns with the trainings
        sum(i * i for i in range(2000))


def finetunings(n: int, group: int, steps_per_call: int) -> tuple[float, float, np.ndarray]:
    """Seconds of a first and a second fine-tuning (of ``group`` trainings side by side as
    one program when > 1) on ``n`` samples, and the first training's validation history."""
    data = synthetic(n, seed=n)
    train, val = split_validation(data, 0.1, 0)
    fc = feature_config_from(train)
    start = train_torque_models(TrainConfig(n_models=K, torque_epochs=1,
                                            torque_model="physical"),
                                fc, train, val, jax.random.key(0), progress=False).variables
    cfg = TrainConfig(n_models=K, torque_model="physical", trainable="servo",
                      **FINETUNE_DEFAULTS)
    training_group.STEPS_PER_CALL = steps_per_call

    def one(g: int):
        return train_torque_models(cfg.replace(seed=g), fc, train, val, jax.random.key(g),
                                   init=start, progress=False)

    def run():
        if group == 1:
            return [one(0)]
        tg = training_group.TrainingGroup([str(g) for g in range(group)])

        def member(g):
            with tg.member(str(g)):
                return one(g)
        return side_by_side([lambda g=g: member(g) for g in range(group)], workers=group)

    times, first = [], None
    for _ in range(2):
        t = time.perf_counter()
        out = run()
        jax.block_until_ready([o.variables for o in out])
        times.append(time.perf_counter() - t)
        first = first if first is not None else out[0].history
    return times[0], times[1], first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[64, 250, 1000])
    ap.add_argument("--group", type=int, default=4)
    ap.add_argument("--busy", type=int, default=4, help="busy Python threads beside")
    args = ap.parse_args()
    default = training_group.STEPS_PER_CALL
    print(f"device: {jax.devices()[0].device_kind}, K = {K}, "
          f"{FINETUNE_DEFAULTS['torque_epochs']} epochs, batch {FINETUNE_DEFAULTS['torque_batch']}")
    for busy in sorted({0, args.busy}):
        stop = threading.Event()
        threads = [threading.Thread(target=_busy, args=(stop,), daemon=True)
                   for _ in range(busy)]
        for th in threads:
            th.start()
        try:
            for n in args.samples:
                steps = (n - int(round(0.1 * n))) // min(64, n)
                for g in sorted({1, args.group}):
                    one = finetunings(n, g, 0)
                    several = finetunings(n, g, default)
                    np.testing.assert_allclose(several[2], one[2], rtol=1e-4)
                    per = training_group.epochs_per_call(
                        FINETUNE_DEFAULTS["torque_epochs"], max(steps, 1))
                    print(f"busy {busy}, {n} samples, G = {g}: one epoch a call "
                          f"{one[0]:.2f} s first / {one[1]:.2f} s second; {per} a call "
                          f"{several[0]:.2f} / {several[1]:.2f} s "
                          f"({several[0] / one[0]:.2f} x / {several[1] / one[1]:.2f} x)",
                          flush=True)
        finally:
            stop.set()
            for th in threads:
                th.join()


if __name__ == "__main__":
    main()
