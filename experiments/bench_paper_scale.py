"""Benchmark: wall time to simulate the paper-scale dataset, in a fresh process.

    python experiments/bench_paper_scale.py [--lanes L] [--tail-lanes T] [--dtype float32]
                                            [--cache DIR] [--trace] [--no-planning]
                                            [--batch-last {auto,on,off}] [--save-q FILE]
                                            [--compare-q FILE] [--no-jitter]

46,144 planning + 36,000 random (9,000 per training load) + 4,000 test samples (1,000 per
test object), the sets of ``jaxinertia reproduce --full``, in one stream of lanes. Prints
one JSON line: import time (Python + JAX + jaxinertia), simulate time (compilation
included: run it in a fresh process for a cold number; with ``--cache DIR`` a second run
reads the compiled programs from DIR, as the command line does by default), samples at
rest and settle-time percentiles.
"""

from __future__ import annotations

import time

T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxinertia import apply_xla_workarounds  # noqa: E402


def main() -> None:
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lanes", type=int, help="default: jaxinertia.sim.stream.default_lanes()")
    ap.add_argument("--tail-lanes", type=int,
                    help="lanes for the stream's end (0: off); default: default_tail_lanes()")
    ap.add_argument("--trace", action="store_true", help="log every stream call (stderr)")
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    ap.add_argument("--cache", help="persistent compilation cache directory (default: none)")
    ap.add_argument("--random-per-load", type=int, default=9000)
    ap.add_argument("--test-per-object", type=int, default=1000)
    ap.add_argument("--no-planning", action="store_true",
                    help="random and test sets only (--random-per-load 800 --test-per-object "
                    "300 --no-planning: the quick demo's sets)")
    ap.add_argument("--batch-last", choices=["auto", "on", "off"], default="auto",
                    help="lanes stepped batch-last or by vmap (auto: the library's default, "
                    "jaxinertia.sim.stream.batch_last_default())")
    ap.add_argument("--save-q", help="write every sample's Present Position (npz) here")
    ap.add_argument("--compare-q", help="count the samples whose ticks differ from this "
                    "--save-q file (e.g. of another --dtype or --batch-last)")
    ap.add_argument("--no-jitter", action="store_true",
                    help="friction jitter off: no random draws in the physics, so float32 "
                    "and float64 runs simulate the same samples")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", args.dtype == "float64")
    if args.cache:
        jax.config.update("jax_compilation_cache_dir", args.cache)
    if args.trace:
        logging.basicConfig(format="%(relativeCreated)8.0f ms %(message)s")
        logging.getLogger("jaxinertia.sim.stream").setLevel(logging.DEBUG)
    # Imported after the precision and cache settings, and timed (import_s).
    from jaxinertia.sim.params import default_sim_params
    from jaxinertia.sim.run import ScenarioRequest, simulate_scenarios

    params = default_sim_params()
    if args.no_jitter:
        params = params.replace(friction=params.friction.replace(jitter=0 * params.friction.jitter))
    t1 = time.perf_counter()
    requests = [ScenarioRequest("test", args.test_per_object, None, 1000),
                ScenarioRequest("random", args.random_per_load, None, 0)]
    if not args.no_planning:
        requests.append(ScenarioRequest("planning", None, None, 0))
    batch_last = {"auto": None, "on": True, "off": False}[args.batch_last]
    results = simulate_scenarios(params, requests, lanes=args.lanes,
                                 tail_lanes=args.tail_lanes, batch_last=batch_last)
    t2 = time.perf_counter()
    fields = [f for r in results for _, f in r.values()]
    if args.save_q:
        np.savez(args.save_q, q=np.concatenate([f["q"] for f in fields]))
    compare = {}
    if args.compare_q:
        q = np.concatenate([f["q"] for f in fields]).astype(np.float64)
        ticks = np.rint((q - np.load(args.compare_q)["q"]) / (2 * np.pi / 4096)).astype(int)
        compare = {"samples_differing": int((ticks != 0).any(axis=1).sum()),
                   "joint_values_differing_by_ticks": np.bincount(abs(ticks).ravel()).tolist()}
    settle = np.concatenate([f["settle_time"] for f in fields])
    print(json.dumps({
        "device": jax.devices()[0].device_kind, "dtype": args.dtype, "lanes": args.lanes,
        "tail_lanes": args.tail_lanes, "batch_last": args.batch_last,
        "samples": int(sum(len(f["q"]) for f in fields)),
        "at_rest": int(sum(f["at_rest"].sum() for f in fields)),
        "import_s": round(t1 - T0, 2), "simulate_s": round(t2 - t1, 2),
        "total_s": round(t2 - T0, 2),
        "settle_p50_p99_max_s": np.percentile(settle, [50, 99, 100]).round(3).tolist(),
        **compare}))


if __name__ == "__main__":
    main()
