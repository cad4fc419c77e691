"""Command line: ``jaxinertia <command> ...``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _enable_x64():
    # Identification is float64 (see jaxinertia.identification); networks stay float32.
    import jax

    jax.config.update("jax_enable_x64", True)


def _parse_l_max(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        try:
            metres = float(value)
        except ValueError:
            metres = float("nan")
        if not sep or not name or not metres > 0:
            raise SystemExit(f"jaxinertia: --l-max expects NAME=METRES (positive), got {item!r}")
        out[name] = metres
    return out


def cmd_lbipe_benchmark(args) -> int:
    _enable_x64()
    from jaxinertia.lbipe import LbipeFormatError
    from jaxinertia.lbipe_benchmark import format_tables, run_lbipe_benchmark, write_json
    from jaxinertia.networks import WeightsError

    try:
        res = run_lbipe_benchmark(args.lbipe_dir, seed=args.seed, l_max=_parse_l_max(args.l_max))
    except (LbipeFormatError, WeightsError, ValueError) as e:
        print(f"jaxinertia lbipe-benchmark: error: {e}", file=sys.stderr)
        return 2
    print(format_tables(res["metrics"]))
    print()
    for name, src in res["set_source"].items():
        diag = res["diagnostics"][name]
        flags = ", ".join(
            f"{k}: {d['rank_deficient']} rank-deficient, {d['ill_conditioned']} ill-conditioned "
            f"of {d['n_solves']} (max cond {d['max_condition']:.1f})"
            for k, d in diag.items()
        )
        print(f"{name}: sets from {src}; {flags}")
    t = res["timing_s"]
    print(f"load {t['load']:.2f} s, batched evaluation incl. compilation "
          f"{t['evaluate_incl_compile']:.2f} s")
    if args.json:
        write_json(args.json, res["metrics"])
        print(f"wrote {args.json}")
    if args.plot:
        from jaxinertia.plots import plot_lbipe_estimates

        plot_lbipe_estimates(res, args.plot)
        print(f"wrote {args.plot}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from jaxinertia.lbipe import default_lbipe_dir

    p = argparse.ArgumentParser(
        prog="jaxinertia",
        description="Mass and centre of mass of a held object from servo encoder discrepancies.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    b = sub.add_parser(
        "lbipe-benchmark",
        help="evaluate the authors' ten released model pairs on real data (Tables I and III)",
        description="Evaluates every data/data_test_<name>.npz in DIR with the ten released "
        "model pairs (weights/*.npz|.pt or dicts/*.pt) in one batched call.",
    )
    b.add_argument("--lbipe-dir", type=Path, default=default_lbipe_dir(),
                   help="shared/lbipe layout or a checkout of ChirikjianLab/lbipe "
                   "(default: %(default)s)")
    b.add_argument("--json", type=Path, help="write the metrics here (reference_metrics schema)")
    b.add_argument("--seed", type=int, default=0,
                   help="seed of the 1000 random 64-sample sets when no golden sets exist")
    b.add_argument("--l-max", action="append", metavar="NAME=METRES",
                   help="bounding-box diagonal of an object without a built-in one")
    b.add_argument("--plot", type=Path, help="write a PNG of the per-set estimates here")
    b.set_defaults(func=cmd_lbipe_benchmark)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
