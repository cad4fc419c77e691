"""Every local device: a batch axis spread over all of them, with JAX's own machinery.

One 1-D :class:`jax.sharding.Mesh` over ``jax.local_devices()`` (axis ``"batch"``);
:func:`shard` places arrays with a :class:`jax.sharding.NamedSharding` that splits one
axis over it, and ``jit`` then runs the computation where the data is (GSPMD partitions
the program; outputs keep the split). One device is the same code on a mesh of one.

Where it is used:

* the batched evaluation (:func:`jaxinertia.evaluation.evaluate`): the sample sets
  (O, B, M) split along B, so each device solves its share of the 1000 sets per object;
* K-pair training (:func:`jaxinertia.training_group.run_epochs`): the stacked models' state
  and their own data split along K, so each device trains its share of the pairs.

An axis whose length the device count does not divide is left whole on every device
(replicated): correct, only not spread. Across several hosts the same placements apply
to a mesh over ``jax.devices()`` after ``jax.distributed.initialize()`` (docs/benchmarks.md,
"Every device of a host, and several hosts").
"""

from __future__ import annotations

from functools import cache

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["AXIS", "local_mesh", "replicate", "shard"]

AXIS = "batch"


@cache
def local_mesh() -> Mesh:
    """The 1-D mesh over this process's devices (of the default backend)."""
    return Mesh(np.asarray(jax.local_devices()), (AXIS,))


def shard(tree, axis: int | None = 0):
    """``tree``'s arrays placed with ``axis`` split over :func:`local_mesh` (arrays without
    that axis, or whose length there the device count does not divide: replicated; every
    array when ``axis`` is None). ``None`` leaves stay ``None``."""
    mesh = local_mesh()
    n = mesh.devices.size

    def place(a):
        a = jax.numpy.asarray(a) if isinstance(a, np.ndarray) else a
        if axis is not None and np.ndim(a) > axis and np.shape(a)[axis] % n == 0:
            spec = PartitionSpec(*([None] * axis), AXIS)
        else:
            spec = PartitionSpec()
        return jax.device_put(a, NamedSharding(mesh, spec))

    return jax.tree_util.tree_map(place, tree)


def replicate(tree):
    """``tree``'s arrays whole on every device of :func:`local_mesh` (committed there, as
    :func:`shard` commits: a program's inputs then have one placement wherever the arrays
    came from, and so one compiled program)."""
    return shard(tree, None)
