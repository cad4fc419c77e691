"""Benchmark: the batched lbipe evaluation against the authors' per-set loop, same run.

    python experiments/bench_lbipe.py [--lbipe-dir DIR] [--repeats 20] [--json OUT]

Measures, on whatever device JAX uses:
  * ``jaxinertia``: every object present x 10 released model pairs x 1000 sets (T and T-A)
    in one jitted call: compile time, first call, and the median of ``--repeats`` calls;
  * the same for four objects (the two real ones twice over, as a stand-in for the paper's
    four; the arrays are the same size a four-object run would have);
  * ``reference``: a faithful per-set loop of the authors' test procedure (numpy, explicit
    ``(A^T W A)^-1 A^T W y`` with dense W per set, as in the paper's eq. 15), per object;
and prints the ratios. Results go in docs/benchmarks.md with the machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxinertia import apply_xla_workarounds

jax.config.update("jax_enable_x64", True)

from jaxinertia.app.pipeline import load_real  # noqa: E402
from jaxinertia.estimation import estimate_sets  # noqa: E402
from jaxinertia.evaluation import stack  # noqa: E402
from jaxinertia.features import LBIPE_FEATURES  # noqa: E402
from jaxinertia.lbipe import default_lbipe_dir, load_released_models  # noqa: E402

# The per-set numpy reference lives with the tests (tests/support/reference.py).
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from support.reference import reference_loop  # noqa: E402


def _time_batched(pair, feats, A, tau_g, sets, repeats):
    args = (pair, feats, A, tau_g, sets)
    t0 = time.perf_counter()
    compiled = estimate_sets.lower(*args).compile()
    t1 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    t2 = time.perf_counter()
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t)
    return {"compile_s": t1 - t0, "first_call_s": t2 - t1, "median_s": statistics.median(runs),
            "min_s": min(runs), "incl_compile_s": t2 - t0}


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lbipe-dir", default=default_lbipe_dir())
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--reference-objects", type=int, default=None,
                    help="run the per-set loop on only this many objects (default: all)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()

    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({dev.platform}); jax {jax.__version__}; "
          f"{platform.processor() or platform.machine()}")
    t = time.perf_counter()
    real = load_real(args.lbipe_dir)
    pair = load_released_models(real.layout.weights_dir, prefer=real.layout.prefer)
    inputs = stack(real.objects, real.sets, LBIPE_FEATURES)
    load_s = time.perf_counter() - t
    names = [o.name for o in real.objects]
    O = len(names)
    K, B, M = pair.n_models, inputs.sets.shape[1], inputs.sets.shape[2]
    print(f"objects {names}, {K} model pairs x {B} sets of {M}; load {load_s:.2f} s")

    res = {"device": f"{dev.device_kind} ({dev.platform})", "jax": jax.__version__,
           "objects": names, "models": K, "sets": B, "set_size": M}
    res["batched"] = _time_batched(pair, *inputs, args.repeats)
    reps = -(-4 // O)  # four objects: repeat the present ones
    four = [jnp.concatenate([a] * reps)[:4] for a in inputs]
    res["batched_4_objects"] = _time_batched(pair, *four, args.repeats)

    n_ref = O if args.reference_objects is None else min(O, args.reference_objects)
    ref_times = []
    for o in range(n_ref):
        S = real.objects[o].n_samples
        t = time.perf_counter()
        reference_loop(pair, inputs.features[o][:S], inputs.A[o][:S], inputs.tau_g[o][:S],
                       real.sets[o])
        ref_times.append(time.perf_counter() - t)
        print(f"reference loop, {names[o]}: {ref_times[-1]:.2f} s")
    ref_per_object = float(np.mean(ref_times))
    res["reference_per_object_s"] = ref_per_object

    b, b4 = res["batched"], res["batched_4_objects"]
    ratio = ref_per_object * O / b["median_s"]
    ratio4 = ref_per_object * 4 / b4["median_s"]
    res["speedup_after_compile"] = ratio
    res["speedup_4_objects_after_compile"] = ratio4
    print()
    print(f"{'':34}{'objects':>8}{'compile':>10}{'first':>10}{'median':>10}{'speed-up':>10}")
    print(f"{'reference loop (per object x O)':34}{O:>8}{'':>10}{'':>10}"
          f"{ref_per_object * O:>9.3f}s{1.0:>9.1f}x")
    print(f"{'jaxinertia batched':34}{O:>8}{b['compile_s']:>9.2f}s{b['first_call_s']:>9.3f}s"
          f"{b['median_s']:>9.4f}s{ratio:>9.0f}x")
    print(f"{'jaxinertia batched':34}{4:>8}{b4['compile_s']:>9.2f}s{b4['first_call_s']:>9.3f}s"
          f"{b4['median_s']:>9.4f}s{ratio4:>9.0f}x")
    print(f"four objects including compilation: {b4['incl_compile_s']:.2f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
