"""Run by tests/test_sharding.py in a fresh interpreter (the device count is fixed when
JAX starts): the batched evaluation and K-pair training of tiny synthetic inputs; writes
the numbers and how many devices their arrays span to the npz named on the command line."""

from __future__ import annotations

import sys

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds

apply_xla_workarounds()  # an entry point: the XLA:CPU settings before JAX starts
jax.config.update("jax_enable_x64", True)

from jaxinertia.evaluation import evaluate  # noqa: E402
from jaxinertia.training import TrainConfig, train_torque_models  # noqa: E402
from support.synthetic import feature_config, synthetic_samples, tiny_pair  # noqa: E402


def main(out: str) -> None:
    rng = np.random.default_rng(0)
    objects = synthetic_samples(rng, n=120, n_obj=2).by_object()
    sets = [np.random.default_rng(o).integers(0, 60, (8, 16)) for o in range(2)]
    res = evaluate(objects, sets, pair=tiny_pair(K=2), fc=feature_config(), l_max=[0.1, 0.1])
    est = res["model_estimates"]  # two objects: gathered on the host, object by object
    # Each object's call is one program over every device: its own results span them.
    one = evaluate(objects[:1], sets[:1], pair=tiny_pair(K=2), fc=feature_config(),
                   l_max=[0.1])["model_estimates"]
    train = synthetic_samples(np.random.default_rng(1), n=96, n_obj=2)
    val = synthetic_samples(np.random.default_rng(2), n=32, n_obj=2)
    cfg = TrainConfig(n_models=2, torque_epochs=2, torque_batch=16)
    trained = train_torque_models(cfg, feature_config(), train, val, jax.random.key(0),
                                  progress=False)
    leaves = jax.tree_util.tree_leaves(trained.variables)
    np.savez(out, x_T=np.asarray(est.T.x), x_TA=np.asarray(est.TA.x),
             history=trained.history,
             weights=np.concatenate([np.ravel(np.asarray(a)) for a in leaves]),
             devices=len(jax.local_devices()),
             eval_devices=len(one.TA.x.sharding.device_set),
             train_devices=min(len(a.sharding.device_set) for a in leaves))


if __name__ == "__main__":
    main(sys.argv[1])
