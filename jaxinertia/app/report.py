"""Tables I-III as text: one table builder per table, one renderer (markdown for reports,
aligned plain text for the terminal)."""

from __future__ import annotations

import os
from collections.abc import Sequence

from jaxinertia.evaluation import METHODS, average
from jaxinertia.sim.calibration import baseline_statistics

__all__ = ["calibration_report", "coverage_table", "render", "table1", "table2", "table3"]

_T1_COLS = (("mass_MAE_g", "mass MAE [g]"), ("mass_NMAE_pct", "mass NMAE [%]"),
            ("mass_NRMSE_pct", "mass NRMSE [%]"), ("com_MAE_mm", "COM MAE [mm]"),
            ("com_NMAE_pct", "COM NMAE [%]"), ("com_NRMSE_pct", "COM NRMSE [%]"))


def render(title: str, header: Sequence[str], rows: Sequence[Sequence[str]], *,
           style: str = "markdown", n_left: int = 1) -> str:
    """A table of strings; the first ``n_left`` columns are labels (left-aligned), the
    rest numbers (right-aligned)."""
    if style == "markdown":
        lines = [f"**{title}**", "", "| " + " | ".join(header) + " |",
                 "|" + " --- |" * n_left + " ---: |" * (len(header) - n_left)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    if style != "text":
        raise ValueError(f"unknown table style {style!r}")
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]

    def line(cells):
        return " ".join(c.ljust(w) if i < n_left else c.rjust(w)
                        for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    head = line(header)
    return "\n".join([title, "", head, "-" * len(head), *(line(r) for r in rows)])


def table1(objects: dict, title: str, *, style: str = "markdown",
           methods: Sequence[str] = METHODS) -> str:
    """Table I: mass and COM error per object and method (and their average)."""
    rows = dict(objects)
    if len(objects) > 1:
        rows["average"] = average(objects)
    body = [[name, m, *(f"{e[m][key]:.2f}" for key, _ in _T1_COLS)]
            for name, e in rows.items() for m in methods if m in e]
    return render(title, ["object", "method", *(label for _, label in _T1_COLS)], body,
                  style=style, n_left=2)


def table2(torque: dict, title: str, *, style: str = "markdown") -> str:
    """Table II: joint torque error per method."""
    n = len(next(iter(torque.values()))["MAE_Nmm"])
    body = [[m, label, *(f"{v:.2f}" for v in torque[m][key])]
            for m in METHODS if m in torque
            for key, label in (("MAE_Nmm", "MAE [N mm]"), ("NMAE_pct", "NMAE [%]"),
                               ("NRMSE_pct", "NRMSE [%]"))]
    return render(title, ["method", "metric", *(f"joint {j + 1}" for j in range(n))], body,
                  style=style, n_left=2)


def table3(objects: dict, title: str, *, style: str = "markdown") -> str:
    """Table III: mean attention weight per joint and object ("" without attention)."""
    have = {k: e for k, e in objects.items() if "mean_attention_weight" in e}
    if not have:
        return ""
    n = len(next(iter(have.values()))["mean_attention_weight"])
    body = [[name, *(f"{w:.4f}" for w in e["mean_attention_weight"])]
            for name, e in have.items()]
    return render(title, ["object", *(f"joint {j + 1}" for j in range(n))], body,
                  style=style)


def coverage_table(objects: dict, title: str, *, style: str = "markdown",
                   methods: Sequence[str] = ("T", "T-A")) -> str:
    """How often the 68 % and 95 % intervals hold the truth, per object and method (and
    their average), beside the median standard error and the RMS error: ``objects`` as
    :func:`jaxinertia.uncertainty.calibration` gives them (``{name: {method: ...}}``)."""
    def row(c):
        se, err = c["median_se"], c["rms_error"]
        return [f"{100 * c[0.68]['mass']:.1f}", f"{100 * c[0.95]['mass']:.1f}",
                f"{100 * c[0.68]['com']:.1f}", f"{100 * c[0.95]['com']:.1f}",
                f"{100 * c[0.95]['com_region']:.1f}", f"{se[0] * 1e3:.1f}",
                f"{err[0] * 1e3:.1f}", f"{sum(se[1:]) / 3 * 1e3:.1f}",
                f"{sum(err[1:]) / 3 * 1e3:.1f}"]

    body = [[name, m, *row(e[m])] for name, e in objects.items() for m in methods if m in e]
    for m in methods:
        rows = [e[m] for e in objects.values() if m in e]
        if len(rows) > 1:
            cells = [[float(v) for v in row(c)] for c in rows]
            body.append(["average", m, *(f"{v:.1f}" for v in
                                         [sum(col) / len(col) for col in zip(*cells)])])
    header = ["object", "method", "mass 68 %", "mass 95 %", "COM 68 %", "COM 95 %",
              "COM region 95 %", "mass SE [g]", "mass RMSE [g]", "COM SE [mm]",
              "COM RMSE [mm]"]
    return render(title, header, body, style=style, n_left=2)


_CAL_ROWS = (("k [N m/rad]", "k", 1, 1), ("c [N mm]", "c", 1e3, 0), ("f0 [N mm]", "f0", 1e3, 0),
             ("mu", "mu", 1, 2), ("PE MAE [N mm]", "pe_mae", 1e3, 0),
             ("current gain", "gain", 1, 2), ("current MAE [N mm]", "current_mae", 1e3, 0),
             ("max abs tau [N m]", "tau_max", 1, 3))


def calibration_report(real: dict, sim: dict, *, source: str | os.PathLike, iterations: int,
                       parameters: str | os.PathLike, figure: str) -> str:
    """``jaxinertia calibrate``'s report: the baseline statistics of the real and the
    simulated samples side by side (markdown)."""
    keys = ("q_d", "q", "direction", "tau", "current_tau")
    st_r = baseline_statistics(*(real[k] for k in keys))
    st_s = baseline_statistics(*(sim[k] for k in keys))
    rows = []
    for label, key, scale, nd in _CAL_ROWS:
        for j in range(len(st_r[key])):
            r, s_ = st_r[key][j] * scale, st_s[key][j] * scale
            ratio = f"{s_ / r:.2f}" if abs(r) > 1e-12 else "-"
            rows.append([label, str(j + 1), f"{r:.{nd}f}", f"{s_:.{nd}f}", ratio])
    table = render("Simulated against real", ["statistic", "joint", "real", "simulated", "ratio"],
                   rows, n_left=2)
    return "\n".join(["# Simulator calibration", "", f"Real data: {source}; {iterations} "
                      f"iterations; parameters in `{parameters}`.", "", table, "",
                      f"![calibration]({figure})", ""])
