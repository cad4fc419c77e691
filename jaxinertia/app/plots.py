"""Figures (matplotlib, headless Agg backend)."""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxinertia.baselines import fit_pe_law, pe_rows
from jaxinertia.fileio import replacing
from jaxinertia.samples import Samples

__all__ = ["plot_sim_fit", "plot_continuous", "plot_lbipe_estimates", "plot_table1",
           "plot_training", "pyplot"]


@functools.cache
def pyplot():
    """``matplotlib.pyplot`` on the headless Agg backend (files only), imported at the first
    figure: a third of a second that every command drawing nothing would pay at start."""
    import matplotlib  # here, not at start: see the docstring

    matplotlib.use("Agg")  # before pyplot is imported
    import matplotlib.pyplot as plt  # after the backend is chosen

    return plt


def _save(fig, path: str | os.PathLike, dpi: int) -> Path:
    """Lays out, writes (creating the folder) and closes a figure."""
    plt = pyplot()
    fig.tight_layout()
    with replacing(path, suffix=Path(path).suffix) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return Path(path)


def plot_lbipe_estimates(objects: Sequence[Samples], estimates: dict, path: str | os.PathLike,
                         ) -> Path:
    """Per object: the distribution of mass estimates and of COM errors over every model
    pair and set, T beside T-A, with the truth marked. ``estimates``: ``{"T": (O, K, B, 4),
    "T-A": ...}`` as :func:`jaxinertia.evaluation.evaluate` returns them."""
    plt = pyplot()
    n = len(objects)
    fig, axes = plt.subplots(2, n, figsize=(4.2 * n, 6.4), squeeze=False)
    colors = {"T": "tab:orange", "T-A": "tab:blue"}
    for o, obj in enumerate(objects):
        name, x_true = obj.name, np.asarray(obj.x[0])
        m_true, p_true = x_true[0], x_true[1:] / x_true[0]
        for key in ("T", "T-A"):
            x = np.asarray(estimates[key][o]).reshape(-1, 4)
            x = x[np.all(np.isfinite(x), axis=-1)]
            m = x[:, 0]
            com_err = np.linalg.norm(x[:, 1:] / x[:, :1] - p_true, axis=-1)
            kw = dict(bins=60, histtype="step", lw=1.5, color=colors[key])
            axes[0, o].hist(m * 1e3, label=f"{key}: MAE {np.mean(np.abs(m - m_true)) * 1e3:.1f} g",
                            **kw)
            axes[1, o].hist(com_err * 1e3, label=f"{key}: MAE {np.mean(com_err) * 1e3:.1f} mm",
                            **kw)
        axes[0, o].axvline(m_true * 1e3, color="k", ls="--", lw=1, label="true")
        axes[0, o].set(title=f"{name} ({m_true * 1e3:.1f} g)", xlabel="estimated mass [g]",
                       ylabel="sets x models")
        axes[1, o].set(xlabel="COM error [mm]", ylabel="sets x models")
        for ax in axes[:, o]:
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
    K, B = np.shape(estimates["T"])[1:3]
    fig.suptitle(f"Released lbipe models on the real OpenMANIPULATOR-X data ({K} model pairs "
                 f"x {B} sets)")
    return _save(fig, path, dpi=120)


def plot_sim_fit(real: dict, sim: dict, path: str | os.PathLike) -> Path:
    """Per joint: q_d - q against tau by direction, real beside simulated, and the
    residual histograms of the position-error baseline fit on each."""
    plt = pyplot()
    n = real["q"].shape[1]
    fig, axes = plt.subplots(3, n, figsize=(3.6 * n, 9.6), squeeze=False)
    for col, (label, d) in enumerate((("real", real), ("simulated", sim))):
        qe_ticks = (d["q_d"] - d["q"]) / (2 * np.pi / 4096)
        for j in range(n):
            ax = axes[col, j]
            for s, c in ((1.0, "tab:red"), (-1.0, "tab:blue")):
                m = d["direction"][:, j] == s
                ax.scatter(qe_ticks[m, j], d["tau"][m, j], s=3, alpha=0.4, color=c,
                           label=f"s = {s:+.0f}")
            ax.set(title=f"{label}: joint {j + 1}", xlabel="q_d - q [ticks]", ylabel="tau [N m]")
            ax.grid(alpha=0.3)
            if j == 0:
                ax.legend(fontsize=8, markerscale=3)
    for j in range(n):
        ax = axes[2, j]
        for label, d, c in (("real", real, "k"), ("simulated", sim, "tab:green")):
            qe = d["q_d"][:, j] - d["q"][:, j]
            coef = fit_pe_law(qe, d["direction"][:, j], d["tau"][:, j])
            r = (pe_rows(qe, d["direction"][:, j]) @ coef - d["tau"][:, j]) * 1e3
            ax.hist(r, bins=50, histtype="step", color=c, lw=1.5,
                    label=f"{label}: MAE {np.mean(np.abs(r)):.0f}")
        ax.set(title=f"PE-fit residual, joint {j + 1}", xlabel="[N mm]")
        ax.legend(fontsize=8)
    return _save(fig, path, dpi=110)


_METHOD_COLORS = {"Sensor": "tab:gray", "PE": "tab:green", "T": "tab:orange", "T-A": "tab:blue",
                  "truth": "black"}


def plot_training(history: dict, path: str | os.PathLike) -> Path:
    """Validation loss per epoch of every model (torque MSE; attention loss)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, (name, label) in zip(axes, (("torque", "torque model: MSE (normalised)"),
                                        ("attention", "attention model: loss [SI]"))):
        h = np.asarray(history[name])  # (epochs, 2, K)
        ep = np.arange(1, h.shape[0] + 1)
        ax.semilogy(ep, h[:, 0], color="tab:gray", lw=0.8, alpha=0.6)
        ax.semilogy(ep, h[:, 1], color="tab:blue", lw=1.0)
        ax.set_title(label)
        ax.set_xlabel("epoch")
        ax.plot([], [], color="tab:gray", label="training")
        ax.plot([], [], color="tab:blue", label="validation")
        ax.legend()
    return _save(fig, path, 120)


def plot_table1(objects: dict, path: str | os.PathLike, title: str = "") -> Path:
    """Mass and COM NMAE per object and method (Table I as bars)."""
    plt = pyplot()
    names = list(objects)
    methods = [m for m in ("Sensor", "PE", "T", "T-A") if m in objects[names[0]]]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    width = 0.8 / len(methods)
    x = np.arange(len(names))
    for ax, key, label in ((axes[0], "mass_NMAE_pct", "mass NMAE [%]"),
                           (axes[1], "com_NMAE_pct", "COM NMAE [%]")):
        for i, m in enumerate(methods):
            ax.bar(x + (i - (len(methods) - 1) / 2) * width,
                   [objects[n][m][key] for n in names], width, label=m,
                   color=_METHOD_COLORS[m])
        ax.set_xticks(x, names)
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend()
    if title:
        fig.suptitle(title)
    return _save(fig, path, 120)


def plot_continuous(res: dict, path: str | os.PathLike, joints=(0, 1, 2, 3)) -> Path:
    """Switching-load run: filtered vertical force per method against the truth, and the
    joint torques along the trajectory."""
    plt = pyplot()
    n_j = len(joints)
    fig, axes = plt.subplots(1 + n_j, 1, figsize=(10, 2.4 * (1 + n_j)), sharex=True)
    ax = axes[0]
    ax.plot(res["sample"], res["truth_N"], color="black", lw=1.5, label="truth")
    for m, r in res["methods"].items():
        ax.plot(res["sample"], r["force_N"], color=_METHOD_COLORS[m], lw=1.0,
                label=f"{m} (MAE {r['MAE_N']:.3f} N)")
    ax.set_ylabel("vertical force [N]")
    ax.legend(fontsize=8, ncol=3)
    tq = res["torques"]
    s = np.arange(len(tq["truth"]))
    for ax, j in zip(axes[1:], joints):
        for m in ("truth", "Sensor", "PE", "T"):
            if m in tq:
                ax.plot(s, tq[m][:, j], color=_METHOD_COLORS[m], lw=0.8 if m != "truth" else 1.2,
                        label=m)
        ax.set_ylabel(f"joint {j + 1} [N m]")
    axes[1].legend(fontsize=8, ncol=4)
    axes[-1].set_xlabel("sample")
    return _save(fig, path, 110)
