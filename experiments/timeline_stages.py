"""A ``fold_timeline.py`` timeline summed up: the held-out folds' stages and their group
programs (docs/benchmarks.md's stage tables since session 42).

Each stage is the wall time from its first start to its last end, over every fold:

* calibrations: ``fit_simulators``;
* simulations: the folds' ``simulate_files`` (or, where a timeline has none, from the
  calibrations' end to the first fold training);
* trainings from scratch: from the first fold training's start to the last from-scratch
  training's end (the fine-tunings start with them and wait for their starts);
* fine-tunings: the ``models_finetuned*`` trainings;
* judges: ``Fold.judge``;

then the folds and the whole ``reproduce``. The group programs (``_run_stacked``, named
with what they train and how many members since session 43) are listed by kind: how many
programs, their members, and the wall time from the first's start to the last's end.

    python experiments/timeline_stages.py TIMELINE [TIMELINE ...]
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

_EVENT = re.compile(r"^\s*(?P<t>[\d.]+)\s+(?P<thread>\S+)\s+(?P<kind>start|end)\s+"
                    r"(?P<name>\S+)\s*(?P<arg>.*?)\s*$")


def events(path: Path) -> list[tuple[float, str, str, str]]:
    """``(seconds, start|end, name, argument)`` of every start and end in the timeline
    (an end's argument without its trailing duration)."""
    out = []
    for line in path.read_text().splitlines():
        m = _EVENT.match(line)
        if m:
            arg = m["arg"]
            if m["kind"] == "end":
                arg = re.sub(r"\s*[\d.]+$", "", arg)
            out.append((float(m["t"]), m["kind"], m["name"], arg))
    return out


def _span(ev, pred, after: float = float("-inf")) -> tuple[float, float] | None:
    starts = [t for t, k, n, a in ev if k == "start" and t >= after and pred(n, a)]
    ends = [t for t, k, n, a in ev if k == "end" and t >= after and pred(n, a)]
    return (min(starts), max(ends)) if starts and ends else None


def stages(ev) -> dict[str, float | None]:
    """Seconds of each stage (None: not in the timeline)."""
    cal = _span(ev, lambda n, a: n == "fit_simulators")
    after = cal[1] if cal else float("-inf")
    sim = _span(ev, lambda n, a: n == "simulate_files", after)
    first_train = min((t for t, k, n, a in ev if k == "start" and n == "train" and t >= after),
                      default=None)
    scratch_end = _span(ev, lambda n, a: n == "train" and "finetuned" not in a, after)
    if sim is None and cal and first_train is not None:
        sim = (cal[1], first_train)
    out = {"calibrations": cal, "simulations": sim,
           "trainings from scratch": (None if first_train is None or scratch_end is None
                                      else (first_train, scratch_end[1])),
           "fine-tunings": _span(ev, lambda n, a: n == "train" and "finetuned" in a, after),
           "judges": _span(ev, lambda n, a: n == "judge", after),
           "held-out folds": _span(ev, lambda n, a: n == "stage" and a == "held-out folds"),
           # the command in its process, from the timeline's start (imports not counted)
           "reproduce": next(((0.0, t) for t, k, n, a in ev
                              if k == "end" and n == "reproduce"), None)}
    return {k: None if v is None else v[1] - v[0] for k, v in out.items()}


def programs(ev, after: float) -> dict[str, tuple[list[int], float]]:
    """Per kind of group program after ``after``: the member counts and the seconds from
    the first start to the last end."""
    sizes, spans = defaultdict(list), defaultdict(list)
    for t, k, n, a in ev:
        if n != "_run_stacked" or t < after:
            continue
        m = re.match(r"(?P<what>.*?) x(?P<g>\d+)$", a)
        what = m["what"] if m else "(unnamed)"
        spans[what].append(t)
        if k == "start":
            sizes[what].append(int(m["g"]) if m else 0)
    return {w: (sorted(sizes[w], reverse=True), max(spans[w]) - min(spans[w])) for w in sizes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("timeline", nargs="+", type=Path)
    for path in ap.parse_args().timeline:
        ev = events(path)
        print(f"== {path}")
        for name, s in stages(ev).items():
            print(f"   {name:24s} {'-' if s is None else f'{s:7.1f} s'}")
        cal = _span(ev, lambda n, a: n == "fit_simulators")
        for what, (g, s) in programs(ev, cal[1] if cal else float("-inf")).items():
            members = ("members not recorded (a timeline before session 43)" if not any(g)
                       else f"of {', '.join(map(str, g))} members")
            print(f"   group programs: {what}: {len(g)}, {members}; {s:.1f} s")


if __name__ == "__main__":
    main()
