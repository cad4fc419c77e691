"""The attention's training sets drawn a set at a time (``Generator.choice`` per set, the
code before session 45) or every set of an object at once (``training_setup.draw_sets``),
by T threads side by side, with B busy Python threads beside them (the GPU folds: 24
attention trainings drawing their sets while other threads trace and dispatch).

    python experiments/draw_sets_threads.py [--threads 1 8] [--busy 0 2] [--repeats 3]

Each thread draws what a fold's attention training from scratch draws: 1,000 sets of 64
of each of four training loads of 10,000 samples. Prints the wall time of all threads'
draws (best of ``--repeats``) each way and the ratio, both measured in this run.
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import numpy as np

from jaxinertia.training_setup import draw_sets

LOADS, PER_LOAD, SETS, SET_SIZE = 4, 10_000, 1_000, 64


def per_set(object_id: np.ndarray, per_object: int, set_size: int, seed: int) -> np.ndarray:
    """The reference: the code before session 45, one ``Generator.choice`` per set."""
    rng = np.random.default_rng(seed)
    out = []
    for o in np.unique(object_id):
        idx = np.flatnonzero(object_id == o)
        out += [rng.choice(idx, set_size, replace=len(idx) < set_size)
                for _ in range(per_object)]
    return np.stack(out)


def timed(draw, n_threads: int, n_busy: int) -> float:
    """Seconds until ``n_threads`` threads have each drawn their sets, beside ``n_busy``
    threads that run Python without pause."""
    object_id = np.repeat(np.arange(LOADS), PER_LOAD)
    stop = threading.Event()

    def busy():
        x = 0
        while not stop.is_set():
            x += 1

    spinners = [threading.Thread(target=busy, daemon=True) for _ in range(n_busy)]
    for s in spinners:
        s.start()
    workers = [threading.Thread(target=draw, args=(object_id, SETS, SET_SIZE, seed))
               for seed in range(n_threads)]
    t = time.perf_counter()
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    seconds = time.perf_counter() - t
    stop.set()
    for s in spinners:
        s.join()
    return seconds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 8])
    p.add_argument("--busy", type=int, nargs="+", default=[0, 2])
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args()
    print(f"{os.cpu_count()} CPU cores; each thread: {SETS} sets of {SET_SIZE} of each of "
          f"{LOADS} loads of {PER_LOAD} samples")
    print("| threads | busy threads | a set at a time [s] | all at once [s] | ratio |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for n_threads in a.threads:
        for n_busy in a.busy:
            old, new = (min(timed(draw, n_threads, n_busy) for _ in range(a.repeats))
                        for draw in (per_set, draw_sets))
            print(f"| {n_threads} | {n_busy} | {old:.3f} | {new:.3f} | {old / new:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
