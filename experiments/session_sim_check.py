"""The simulated check of session adaptation (issue 30, item 5).

Recording sessions are drawn around the shipped simulator with the spread the two real
files show (:func:`jaxinertia.sim.randomize.session_spread`: per joint, the spread of the
current gain between sessions and of the torque gain beyond it). Models are trained

* ``one session``: on the nominal simulator alone (what ``reproduce`` does);
* ``sessions``: on ``--train-sessions`` drawn sessions (same total samples);

each once without session adaptation (``session_strength=0``) and once with it, and
judged on the four test objects simulated in ``--test-sessions`` further sessions that no
model saw (drawn with the spread times ``--test-scale``). Reported: T and T-A mass / COM
NMAE [%], mean over the test sessions.

    python experiments/session_sim_check.py --out runs/session_sim [--scale quick|full]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from jaxinertia import apply_xla_workarounds
from jaxinertia.app.pipeline import evaluate_samples, train
from jaxinertia.app.reproduce import FULL, QUICK
from jaxinertia.app.simdata import simulate_files
from jaxinertia.lbipe import default_lbipe_dir, find_layout, load_test_files
from jaxinertia.session import servo_session
from jaxinertia.sim.params import default_sim_params
from jaxinertia.sim.randomize import session_drawn, session_spread
from jaxinertia.sim.real_fit import baseline_statistics


def real_spread(lbipe_dir):
    files = load_test_files(find_layout(lbipe_dir))
    cur = [servo_session(o).current_gain for o in files]
    tor = [baseline_statistics(o.q_d, o.q, o.direction, o.tau, o.current_tau)["k"]
           for o in files]
    return session_spread(cur, tor), {o.name: (c.tolist(), t.tolist())
                                      for o, c, t in zip(files, cur, tor)}


def sessions_spread(lbipe_dir, torque_rel_scale: float = 1.0):
    """The spread sessions are drawn with (the real files', the torque-only part times
    ``torque_rel_scale``) and the real files' gains."""
    spread, real = real_spread(lbipe_dir or default_lbipe_dir())
    return dataclasses.replace(spread, torque_rel=spread.torque_rel * torque_rel_scale), real


def main():
    apply_xla_workarounds()  # XLA:CPU settings, before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="runs/session_sim")
    ap.add_argument("--scale", choices=["quick", "full"], default="quick")
    ap.add_argument("--train-sessions", type=int, default=4)
    ap.add_argument("--test-sessions", type=int, default=4)
    ap.add_argument("--test-scale", type=float, default=1.5)
    ap.add_argument("--torque-rel-scale", type=float, default=1.0,
                    help="times the torque-only spread (0: sessions differ electrically only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lbipe-dir", default=None)
    a = ap.parse_args()
    scale = FULL if a.scale == "full" else QUICK
    out = Path(a.out)
    t0 = time.perf_counter()
    spread, real = sessions_spread(a.lbipe_dir, a.torque_rel_scale)
    print("real sessions (current gain, torque gain):", real)
    print("session spread:", spread.to_dict())
    base = default_sim_params()
    key = jax.random.key(a.seed + 4242)
    k_train, k_test = jax.random.split(key)
    n = scale.random_per_load
    one = simulate_files(base, [(out / "data" / "one_session.npz", "random", n, a.seed)])
    sessions = []
    for s in range(a.train_sessions):
        p = session_drawn(base, jax.random.fold_in(k_train, s), spread)
        sessions += simulate_files(p, [(out / "data" / f"session_{s}.npz", "random",
                                        -(-n // a.train_sessions), a.seed + 101 * (s + 1))])
    tests = []
    for s in range(a.test_sessions):
        p = session_drawn(base, jax.random.fold_in(k_test, s), spread, scale=a.test_scale)
        tests += simulate_files(p, [(out / "data" / f"test_session_{s}.npz", "test",
                                     scale.test_per_object, a.seed + 1000 + s)])
    t_sim = time.perf_counter() - t0
    results = {"spread": spread.to_dict(), "real": real, "rows": {}, "args": vars(a)}
    cfg = scale.train.replace(seed=a.seed)
    for label, files in (("one session", one), ("sessions", sessions)):
        for adapt in (False, True):
            models = out / f"models_{label.replace(' ', '_')}_{'adapted' if adapt else 'plain'}"
            train(files, models, cfg.replace(session_strength=float(adapt)), overwrite=True,
                  progress=False)
            per = [evaluate_samples(models, f, n_sets=scale.n_sets, seed=a.seed)
                   for f in tests]
            row = {}
            for m in ("PE", "T", "T-A"):
                for q in ("mass_NMAE_pct", "com_NMAE_pct"):
                    v = [np.mean([r["objects"][o][m][q] for o in r["objects"]]) for r in per]
                    row[f"{m} {q}"] = float(np.mean(v))
            row["ratios"] = [r["session_ratio"] for r in per]
            name = f"{label}, {'adapted' if adapt else 'not adapted'}"
            results["rows"][name] = row
            print(f"{name:<28} " + "  ".join(f"{k.split('_')[0]} {v:6.2f}" for k, v in
                                             row.items() if k != "ratios"), flush=True)
    results["wall_time_s"] = {"simulate": t_sim, "total": time.perf_counter() - t0}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out / 'results.json'} ({results['wall_time_s']['total']:.0f} s)")


if __name__ == "__main__":
    main()
