"""Tables I-III as text: one table builder per table, one renderer (markdown for reports,
aligned plain text for the terminal)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from jaxinertia.evaluation import METHODS, average
from jaxinertia.sim.real_fit import baseline_statistics

__all__ = ["sim_fit_report", "coverage_table", "format_folds", "recipe_table", "render",
           "reproduce_report", "reproduce_section_new_object", "table1", "table2", "table3"]

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
    :func:`jaxinertia.uncertainty.interval_coverage` gives them (``{name: {method: ...}}``)."""
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


def sim_fit_report(real: dict, sim: dict, *, source: str | os.PathLike, iterations: int,
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


def format_folds(res: dict) -> str:
    """The held-out results as markdown: per fold, Table I on the held-out objects (ours,
    session-adapted and not, beside the released models on the same sets), the replayed
    baseline statistics; then the recipe they choose for the models of a new object."""
    lines = []
    if res.get("draws"):
        d = res["draws"]
        lines += [f"The folds of {len(d)} training draws (seeds "
                  f"{', '.join(str(x['seed']) for x in d)}): each draw's calibrations, "
                  "simulated data and trainings drawn with its own seed, every draw judged "
                  f"on the same sets. The tables below are the first draw's (`folds/`), the "
                  "others' are in tables.json (`held_out.draws`) and their folders under "
                  f"`folds/seed<s>/`; the recipe is ranked over all {len(d) * len(d[0]['folds'])} "
                  "folds.", ""]
    for fit_on, f in res["folds"].items():
        held = ", ".join(f["held_out"])
        ratio = "; ".join(f"{o} {np.round(r, 3).tolist()}" for o, r in
                          (f.get("session_ratio") or {}).items())
        lines += [f"### Calibrated and trained with {fit_on} only, judged on {held}", "",
                  table1(f["ours"], f"Models trained on the simulator calibrated on {fit_on}"),
                  ""]
        if "0.0" in (f.get("by_strength") or {}):
            lines += [table1(f["by_strength"]["0.0"], "The same, without session adaptation"),
                      "", f"Session ratio (held-out discrepancy per joint): {ratio}.", ""]
        if f.get("randomized"):
            r = f["randomized"]
            lines += [table1(r["objects"], f"Trained on domain-randomized data ({r['draws']} "
                             "simulated arms; spread of gain and offset measured on "
                             f"{fit_on})"), ""]
        if f.get("physical"):
            lines += [table1(f["physical"]["objects"], "The physics-structured torque model "
                             "trained on the same simulated data"), ""]
        for key, what in (("", ""), ("_current", " with the current input")):
            if f.get("physical" + key) and key:
                lines += [table1(f["physical" + key]["objects"], "The physics-structured "
                                 f"torque model{what}, on the same simulated data"), ""]
            for ft in (f.get("fine_tuned" + key) or {}).values():
                lines += [table1(ft["objects"], f"It{what} fine-tuned (servo part) on "
                                 f"{_finetuning_samples(ft, fit_on)}; baselines refitted on "
                                 "them"), ""]
        lines += [table1(f["released"], "The authors' released models, same sets"), ""]
        r, s = f["replay"]["real"], f["replay"]["sim"]
        rows = [[label, str(j + 1), f"{r[key][j] * scale:.{nd}f}", f"{s[key][j] * scale:.{nd}f}",
                 f"{(s[key][j] - r[key][j]) * scale:+.{nd}f}"]
                for label, key, scale, nd in (("PE gain k [N m/rad]", "k", 1, 2),
                                              ("PE intercept c [N mm]", "c", 1e3, 1),
                                              ("PE MAE [N mm]", "pe_mae", 1e3, 1))
                for j in range(len(r[key]))]
        lines += [render(f"{held}'s real plan replayed in the simulator calibrated on {fit_on}",
                         ["statistic", "joint", "real", "simulated", "sim - real"], rows,
                         n_left=2), ""]
    if res.get("recipe"):
        lines += [recipe_table(res["recipe"]), ""]
    return "\n".join(lines)


def recipe_table(recipe: dict) -> str:
    """The candidates for a new object's models, ranked by their held-out score."""
    rows = [[c["candidate"], "on (T-A)" if c.get("attention", True) else "off (T)",
             f"{c['session_strength']:g}", f"{c['score']:.3f}"] for c in recipe["scores"]]
    part = recipe.get("by_part")
    apart = ("" if not part else
             f". Judged apart, the mass is best from {part['mass']['candidate']} (session "
             f"strength {part['mass']['session_strength']:g}, {_attention(part['mass'])}, "
             f"mass score {part['mass']['score']:.3f}) and the COM from "
             f"{part['com']['candidate']} (strength {part['com']['session_strength']:g}, "
             f"{_attention(part['com'])}, COM score {part['com']['score']:.3f}): "
             f"{part['score']:.3f} for both")
    return render("Recipes ranked on the held-out sessions (mass and COM NMAE over the "
                  f"released models' {recipe['method']}, mean of every fold; lower is better). "
                  f"Best single candidate: {recipe['candidate']}, session adaptation "
                  f"{'on' if recipe['session_strength'] > 0 else 'off'}, "
                  f"{_attention(recipe)}{apart}",
                  ["candidate", "attention", "session strength", "score"], rows, n_left=2)


def _attention(recipe: dict) -> str:
    return ("attention on (T-A)" if recipe.get("attention", True) else
            "attention off (T: every joint weighted alike)")


def reproduce_report(results: dict, figs: dict, *, full: bool, seed: int, scale,
                     continuous: dict, real_note: str | None, lbipe_dir) -> str:
    """``jaxinertia reproduce``'s report.md, from the run's results (tables.json) alone."""
    t, tr = results["timings_s"], results["training"]
    sim, cov = results["simulated"], results["coverage"]
    lines = [
        "# jaxinertia reproduce", "",
        f"{'Full (paper-scale)' if full else 'Quick'} run of the "
        f"{results.get('arm', 'open_manipulator_x')}, seed {seed}, on "
        f"{results['machine']}.",
        f"Total {t['total']:.0f} s: " + ", ".join(
            f"{k} {v:.0f} s" for k, v in t.items() if k != "total") + ".", "",
        f"Training samples: {tr['samples']['train']} (+{tr['samples']['validation']} "
        f"validation), {scale.train.n_models} model pairs; test: {scale.test_per_object} "
        f"samples per object, {scale.n_sets} sets of {scale.train.set_size} per object and "
        "model.", "",
        "## Simulated test objects", "",
        table1(sim["objects"], "Table I: mass and COM"), "",
        # A baseline the arm's servos cannot give (the Koch's XL430s: no current sensor).
        *(line for m, why in sim.get("unavailable", {}).items()
          for line in (f"{m} baseline {why}.", "")),
        table2(sim["torque"], "Table II: joint torque (all test samples)"), "",
        table3(sim["objects"], "Table III: mean attention weights"), "",
        f"![Table I]({figs['table1'].name})", "",
        "## How sure: coverage of the intervals", "",
        "Per set, the covariance of x = [m, m p] from the residual scatter (floored at the "
        "torque models' validation error: " + cov["floor"]["source"] + ") and the spread "
        "over the model pairs; delta-method intervals for mass and COM. Coverage: the share "
        "of sets whose interval holds the truth (COM: mean over x, y, z; region: the joint "
        "3-D ellipsoid).", "",
        coverage_table(cov["simulated"], "Simulated test objects"), "",
        *([coverage_table(cov["real"], "Real files, models trained on the simulator"), ""]
          if "real" in cov else []),
        f"![coverage]({figs['coverage'].name})", "",
        "## Switching loads (continuous run)", "",
        f"{continuous['n']} consecutive samples, held object switching every "
        f"{scale.switch_every} samples ({' -> '.join(dict.fromkeys(continuous['objects']))}); "
        "windows of 128 samples, 128-wide mean filter. MAE of the vertical force: " + ", ".join(
            f"{m} {v:.3f} N" for m, v in results["continuous"].items()) + ".", "",
        f"![continuous]({figs['continuous'].name})", "",
        "## Sim-to-real", "",
    ]
    real = results["real"]
    if real is None and results.get("real_skipped"):
        lines += [f"Skipped: {results['real_skipped']}"]
    elif real is None:
        lines += [f"Skipped: no real data at {lbipe_dir} (see README: shared/lbipe)."]
    else:
        lines += [real_note or "", "",
                  "**These objects are not held out:** the shipped simulator calibration was "
                  "fitted on every real file (cube and white), so the numbers below are on "
                  "objects the fit saw. The held-out folds below are the honest numbers.", "",
                  table1(real["ours"]["objects"], "Models trained on the simulator, "
                         "real test files (calibration saw them)"), ""]
        if real.get("released"):
            lines += [table1(real["released"], "The authors' released models, same "
                             "files and sets"), ""]
        lines += [f"![real]({figs['real'].name})", ""]
    lines += _new_object_section(results["real_finetuned"])
    lines += ["## Held-out real objects (fit on one, judge on the other)", ""]
    if results["held_out"] is None:
        lines += ["Not run: it needs at least two real objects in the lbipe folder (and "
                  "scale.fold_calibration_iterations > 0).", ""]
    else:
        lines += ["Per fold, the simulator is calibrated from the datasheet on one real "
                  "object's samples only (link gravity, servo, friction, joint torque "
                  "offsets), models are trained on data simulated with it, and they are judged "
                  "on the other real object, beside the released models on the same sets.", "",
                  format_folds(results["held_out"]), ""]
    lines += ["## Training", "", f"Best epochs: torque {tr['best_epoch']['torque']}, "
              f"attention {tr['best_epoch']['attention']}.", "",
              f"![training]({figs['training'].name})", ""]
    return "\n".join(lines)


def _finetuning_samples(ft: dict, fit_on: str) -> str:
    """What a fold's fine-tuning saw: its real samples and, with the anchor
    (``FoldScale.finetune_anchor``), its start's simulated ones."""
    used = ft["samples"]
    split = f"{used['train']} + {used['validation']} (validation)"
    if not ft.get("anchor"):  # (a run before the anchor records no real_samples)
        return f"{split} real samples of {fit_on}"
    return (f"{ft['real_samples']} real samples of {fit_on} and as many of each load of its "
            f"start's simulated {', '.join(ft['anchor'])} ({split} in all)")


def _new_object_section(ft: dict | None) -> list[str]:
    if ft is None:
        return []
    names = ", ".join(ft["objects"])
    recipe = ft["recipe"]
    used = ("" if ft["samples"] is None else f" on {ft['samples']['train']} + "
            f"{ft['samples']['validation']} (validation) real samples of {names}")
    if ft["samples"] is not None and ft.get("anchor"):  # (models_real.models_real)
        used = (f" on {ft['real_samples']} real samples of each of {names} and as many of "
                f"each load of the run's simulated {', '.join(ft['anchor'])} "
                f"({ft['samples']['train']} + {ft['samples']['validation']} (validation) "
                "in all)")
    com = recipe.get("com")
    com_text = ("" if not com else
                f"; the COM of T and T-A from `{ft['models']}/com`: {com['candidate']}, "
                f"session adaptation {'on' if com['session_strength'] > 0 else 'off'}, "
                f"{_attention(com)}")
    made = ("the models were made as the folds made what they judged (trained and "
            "fine-tuned at the folds' training strength, then read at the strength chosen)")
    if recipe.get("members"):
        used = (" (" + "; ".join(m["candidate"] for m in recipe["members"]) + "; each made "
                f"as one candidate, the fine-tuned ones on every real file of {names}, the "
                f"first in `{ft['models']}`, the others in `{ft['models']}/members/`)")
    if ft.get("from_folds"):  # the folds' own folders (models_real.models_from_folds)
        n = {part: len(v) for part, v in ft["from_folds"].items()}
        draws = (ft.get("held_out") or {}).get("draws", 1)
        used = (f" ({'; '.join(m['candidate'] for m in recipe['members'])})"
                if recipe.get("members") else "")
        made = ("the models are the held-out folds' own, the very folders they judged: each "
                "calibrated, trained and fine-tuned on one real file and judged on the "
                f"others; the mass's {n['mass']} folders (every candidate named, from every "
                f"fold{f' of every one of {draws} training draws' if draws > 1 else ''}) "
                f"answer with their mean (the first in `{ft['models']}`, "
                "the others in "
                f"`{ft['models']}/members/`)"
                + (f", the COM's {n['com']} likewise in `{ft['models']}/com`"
                   if "com" in n else ""))
    return ["## Models for a new real object", "",
            f"`{ft['models']}`: {recipe['candidate']}{used}, session adaptation "
            f"{'on' if recipe['session_strength'] > 0 else 'off'}, {_attention(recipe)}"
            + ("" if recipe.get("attention", True) else
               " (the attention models' last layer zeroed: T-A answers as T)")
            + f"{com_text}; the recipe was "
            "chosen by "
            f"{recipe.get('chosen_by', 'the held-out folds')} (table in the held-out section), "
            f"and {made}. "
            "Use it (`jaxinertia estimate --models ...`) on objects none of the models saw; "
            "how well such models do on an object they did not see is what the held-out "
            "folds below measure.", "",
            table1(ft["objects"], f"On {names}: **not held out** (" + (
                "each file was seen by the members its own fold made" if ft.get("from_folds")
                else "the models saw these files") + ")"), ""] + _judged(
                    ft.get("held_out"), ft["models"]) + _with_released(
                    ft.get("with_released"), ft["models"])


def reproduce_section_new_object(ft: dict | None) -> str:
    """The report's section on the models for a new real object (``real_finetuned`` of
    ``tables.json``)."""
    return "\n".join(_new_object_section(ft))


def _held_out_rows(h: dict) -> list[str]:
    """A held-out judgement's (:func:`jaxinertia.app.with_released.judge_draws`) table."""
    return ["| fit on | judged on | T-A mass NMAE [%] | T-A COM NMAE [%] |",
            "| --- | --- | ---: | ---: |",
            *(f"| {fit} | {held} | {r['mass_NMAE_pct']:.2f} | {r['com_NMAE_pct']:.2f} |"
              for fit, f in h["folds"].items() for held, r in f.items()), ""]


def _judged(h: dict | None, models: str) -> list[str]:
    """``models_real`` judged held out (:func:`jaxinertia.app.with_released.judge_draws`)."""
    if h is None:
        return []
    each = h.get("each_draw") or []  # each draw's own score, beside the draws' mean
    alone = "" if len(each) < 2 else "; each training draw alone, the same recipe: " + \
        ", ".join(f"seed {d['seed']} {d['score']:.3f}" for d in each)
    return [f"`{models}` judged held out: on each real file, the members that did not see it "
            f"(those of the folds fitted on the other file, of {h['draws']} training "
            f"draw{'s' if h['draws'] > 1 else ''}), averaged as `{models}` averages them: "
            f"score over the released models' T-A **{h['score']:.3f}** (mass "
            f"{h['mass_score']:.3f}, COM {h['com_score']:.3f}){alone}.", "",
            *_held_out_rows(h)]


def _with_released(w: dict | None, models: str) -> list[str]:
    """``models_real_with_released`` (:mod:`jaxinertia.app.with_released`)."""
    if w is None:
        return []
    h = w["held_out"]
    return [f"`{w['models']}`: `{models}` averaged with the authors' released models, "
            f"{w['released_share']:g} each per model pair and set (T and T-A; the share "
            "fixed beforehand), a second folder beside it, never a candidate of the recipe. "
            "Judged by the same folds (each fold's own models of the recipe's parts, the "
            "released models on the same sets): score over the released models' T-A "
            f"{h['score']:.3f} (mass {h['mass_score']:.3f}, COM {h['com_score']:.3f}).", "",
            *_held_out_rows(h),
            table1(w["objects"], f"`{w['models']}` on the real files: **not held out** "
                   "(each file was seen by the members of `models_real` its own fold made)"),
            ""]
