"""Benchmark: simulated arm-steps per second, jaxinertia's JAX chain beside MJX.

    python experiments/bench_sim.py [--batches 1024 8192] [--steps 1000] [--mjx-steps 100]

Same arm (the embedded OpenMANIPULATOR-X MJCF), same joint-space PD law applied as joint
torques, 1 ms Euler steps, vmapped over a batch of arms with random start states:
  * mjx:          mujoco.mjx.step (frictionless; MJX has no sticking friction);
  * jax-rigid:    jaxinertia.dynamics.euler_step (the same physics as MJX here);
  * jax-servo:    jaxinertia.sim.simulator.step: the XM430 servo law from registers and
                  the sticking-friction solve (what the simulator actually runs).
  * jax-servo-batched: the same step, same law, written batch-last without vmap
                  (jaxinertia.sim.batched.step_batched; the scan carries (N, B) arrays,
                  converted from and to (B, N) outside the scan).
Reports compile time and arm-steps/s (batch x steps / wall time after compilation), and
the ratio of each to MJX measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import apply_xla_workarounds


def _timed(fn, *args, repeats=3):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t)
    return compile_s, best


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1024, 8192])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--mjx-steps", type=int, default=100)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                    help="float32 is what a GPU run would use; float64 is the library default")
    ap.add_argument("--json")
    args = ap.parse_args()
    # One precision for everything, MJX included (its arrays follow jax_enable_x64).
    jax.config.update("jax_enable_x64", args.dtype == "float64")

    # Imported once the precision is set (module-level arrays follow jax_enable_x64).
    import mujoco
    from mujoco import mjx

    from jaxinertia.dynamics import euler_step
    from jaxinertia.robot import compile_mujoco, data_path, open_manipulator_x
    from jaxinertia.sim.batched import state_batch_first, state_batch_last, step_batched
    from jaxinertia.sim.params import default_sim_params
    from jaxinertia.sim.servo import goal_ticks
    from jaxinertia.sim.simulator import SimState, step

    dtype = jnp.float32 if args.dtype == "float32" else jnp.float64
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, {args.dtype}")
    model = compile_mujoco(data_path("open_manipulator_x.xml"))
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    # The bare chain: no contacts, no joint-limit constraints (as the JAX paths).
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    mx = mjx.put_model(model)
    robot = open_manipulator_x().astype(dtype)
    sim = default_sim_params()
    sim = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), sim)
    kp, kd, dt = 16.0, 0.5, 1e-3
    rows = []
    for B in args.batches:
        rng = np.random.default_rng(0)
        q0 = jnp.asarray(rng.uniform(-0.5, 0.5, (B, 4)), dtype)
        goal = jnp.asarray(rng.uniform(-0.5, 0.5, (B, 4)), dtype)

        def pd(q, qd, g):
            return kp * (g - q) - kd * qd

        @jax.jit
        def run_mjx(q0, goal):
            d = jax.vmap(lambda q: mjx.make_data(mx).replace(qpos=q))(q0)

            def body(d, _):
                d = d.replace(qfrc_applied=pd(d.qpos, d.qvel, goal))
                return jax.vmap(mjx.step, (None, 0))(mx, d), None

            return jax.lax.scan(body, d, None, length=args.mjx_steps)[0].qpos

        @jax.jit
        def run_rigid(q0, goal):
            def body(carry, _):
                q, qd = carry
                return jax.vmap(euler_step, (None, 0, 0, 0, None))(
                    robot, q, qd, pd(q, qd, goal), dt), None

            return jax.lax.scan(body, (q0, jnp.zeros_like(q0)), None, length=args.steps)[0][0]

        @jax.jit
        def run_servo(q0, goal):
            s0 = jax.vmap(SimState.at_rest)(q0)
            g = goal_ticks(goal)

            def body(s, _):
                return jax.vmap(step, (None, 0, 0))(sim, s, g), None

            return jax.lax.scan(body, s0, None, length=args.steps)[0].q

        @jax.jit
        def run_servo_batched(q0, goal):
            s0 = state_batch_last(jax.vmap(SimState.at_rest)(q0))
            g = goal_ticks(goal).T

            def body(s, _):
                return step_batched(sim, s, g), None

            return state_batch_first(jax.lax.scan(body, s0, None, length=args.steps)[0]).q

        res = {"batch": B}
        for name, fn, n in (("mjx", run_mjx, args.mjx_steps), ("jax-rigid", run_rigid, args.steps),
                            ("jax-servo", run_servo, args.steps),
                            ("jax-servo-batched", run_servo_batched, args.steps)):
            c, t = _timed(fn, q0, goal)
            res[name] = {"compile_s": c, "steps": n, "arm_steps_per_s": B * n / t}
        for name in ("jax-rigid", "jax-servo", "jax-servo-batched"):
            res[name]["vs_mjx"] = res[name]["arm_steps_per_s"] / res["mjx"]["arm_steps_per_s"]
        rows.append(res)
        print(f"batch {B}: " + ", ".join(
            f"{k} {res[k]['arm_steps_per_s']:.3g} arm-steps/s (compile {res[k]['compile_s']:.1f} s"
            + (f", {res[k]['vs_mjx']:.1f}x MJX)" if k != "mjx" else ")")
            for k in ("mjx", "jax-rigid", "jax-servo", "jax-servo-batched")))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": f"{dev.device_kind} ({dev.platform})", "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
