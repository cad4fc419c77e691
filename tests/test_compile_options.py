"""Programs compiled otherwise than XLA's defaults (:mod:`jaxinertia.compile_options`): the
options reach the program called, not one it is part of, and the simulator's stepping
programs compile with theirs."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxinertia import compile_options, objects
from jaxinertia.open_manipulator_x import ARM as OMX
from jaxinertia.plans import random_plan
from jaxinertia.sim import stream
from jaxinertia.sim.params import default_sim_params

#: A compiler option no XLA knows: a program compiled with it fails (the CPU's compiler, like
#: the GPU's, checks every option's name), which shows where options are applied.
MISSPELT = {"xla_no_such_option": 0}


def _f(x):
    return jnp.sin(x) @ x


def test_options_reach_the_program_called_and_not_one_it_is_part_of():
    x = jnp.linspace(0.0, 1.0, 9).reshape(3, 3)
    seen = []
    bad = compile_options.jit_for_backend(_f, lambda backend: seen.append(backend) or MISSPELT)
    with pytest.raises(Exception, match="No such compile option"):
        bad(x)
    assert seen == [jax.default_backend()], "built for the backend it ran on"
    # Inside another program it is part of that one, which compiles with its own options.
    np.testing.assert_allclose(jax.jit(lambda x: bad(x) + 1.0)(x), _f(x) + 1.0, rtol=1e-12)
    # Built once per backend; none for it: the plain jit, the same numbers.
    seen.clear()
    plain = compile_options.jit_for_backend(_f, lambda backend: seen.append(backend) or {})
    for _ in range(2):
        np.testing.assert_array_equal(plain(x), jax.jit(_f)(x))
    assert seen == [jax.default_backend()]


def test_the_simulators_stepping_compiles_with_its_own_options(monkeypatch):
    assert compile_options.stepping_options("cpu") == {
        "xla_backend_optimization_level": compile_options.CPU_STEPPING_LEVEL}
    assert compile_options.stepping_options("gpu") == {}
    assert compile_options.CPU_STEPPING_LEVEL >= 1  # never the test suite's level 0
    # The stream's programs (stepping, refill, finish) compile with them.
    monkeypatch.setattr(stream, "stepping_options", lambda: dict(MISSPELT))
    p, tag = default_sim_params(), dict(tag_in_ee=OMX.tag_in_ee)
    plan = stream.LanePlan(objects.paper_object("cube", **tag),
                           *random_plan(9, 2, workspace=OMX.workspace_deg), jax.random.key(1))
    args, sizes = stream._assemble(p, [plan], 3, keys=False)
    table, carry = jax.eval_shape(partial(stream._prepare, sizes=sizes, lanes=3), *args)
    with stream.StreamPrograms() as programs:
        made = programs.programs(p, table, carry, 0, 32, True)
        for program in (*made["main"], made["finish"]):
            with pytest.raises(Exception, match="No such compile option"):
                programs.result([program])
