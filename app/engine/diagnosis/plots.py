"""A gap diagnosis's figures as files (``cwrr diagnose LOGDIR --plots DIR``).

How far the gap shrinks per channel, and where in time it lies along each
held-out log: the pictures the diagnosis page draws from the same report,
for a researcher working from the command line.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.ident.plots import pyplot, save_figure

UNITS = {"p_a": "bar", "p_b": "bar", "p_s": "bar", "p": "bar", "torque": "N·m", "force": "N"}
"""A channel's unit (its errors' unit: a pressure difference has no "abs")."""


def how_far_plot(report: dict[str, Any], path: str | Path) -> Path:
    """Each channel's held-out NRMSE before and after the verdict's effects, as a multiple of its noise floor.

    Args:
        report: A diagnosis report (one family's).
        path: Output PNG.
    """
    plt = pyplot()
    hf, floor = report["how_far"], report["noise_floor"]["nrmse"]
    chans = list(hf["before"])
    before = [hf["before"][c] / max(floor[c], 1e-12) for c in chans]
    after = [hf["after"][c] / max(floor[c], 1e-12) for c in chans]
    x = np.arange(len(chans))
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(chans), 3.6))
    model = " + ".join(hf.get("model") or report["verdict"]["effects"])
    ax.bar(x - 0.2, before, 0.4, color="#b3261e", label="before (the recalibrated baseline)")
    ax.bar(x + 0.2, after, 0.4, color="#0a7d32", label=f"after, with {model}" if model else "after (no effect)")
    ax.axhline(1.0, color="#7a8794", ls="--", lw=1, label="noise floor")
    ax.set_xticks(x, chans)
    ax.set_ylabel("held-out NRMSE / noise floor")
    ax.set_title("How far the gap shrinks")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return save_figure(fig, plt, path)


def trace_plot(report: dict[str, Any], log: dict[str, Any], path: str | Path) -> Path:
    """Each channel's prediction error along one held-out log, against the band its noise floor leaves.

    Args:
        report: A diagnosis report with ``traces``.
        log: One entry of ``report["traces"]["logs"]``.
        path: Output PNG.
    """
    plt = pyplot()
    floors = {w["channel"]: w.get("floor", w["noise"]) for w in report["where"]}
    model = " + ".join(report["traces"]["model"])
    chans = list(log["channels"])
    t = np.array(log["t"], dtype=float)
    fig, axes = plt.subplots(len(chans), 1, figsize=(8, 1.9 * len(chans) + 0.6), sharex=True, squeeze=False)
    for ax, c in zip(axes[:, 0], chans, strict=True):
        s = {k: np.array(v, dtype=float) for k, v in log["channels"][c].items() if k != "confusable"}
        fl = floors.get(c)
        if fl:
            ax.axhspan(-fl, fl, color="#9aa4ae", alpha=0.3, lw=0, label="± noise floor")
        ax.plot(t, s["baseline"] - s["measured"], color="#b3261e", lw=1.1, label="baseline")
        if "after" in s:
            ax.plot(t, s["after"] - s["measured"], color="#0a7d32", lw=1.1, label=f"with {model}")
        # an effect the verdict cannot tell from its own: where in time the two differ, if anywhere
        for k, (effect, ys) in enumerate(log["channels"][c].get("confusable", {}).items()):
            ax.plot(t, np.array(ys, dtype=float) - s["measured"], color=("#1f77b4", "#9467bd", "#ff7f0e")[k % 3],
                    lw=1.1, ls="--", label=f"with {effect} alone (confusable)")
        ax.set_ylabel(f"{c} [{UNITS.get(c, '-')}]")
        ax.grid(True, alpha=0.3)
    axes[0, 0].set_title(f"{log['log']}: prediction − measured")
    axes[0, 0].legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("t [s from the log's start]")
    return save_figure(fig, plt, path)


def diagnosis_plots(report: dict[str, Any], directory: str | Path) -> list[Path]:
    """How far, and one trace figure per held-out log (where the report has ``traces``), into ``directory``.

    A report of several objects (the closed chambers: ``reports``) gets each one's figures, named after it.

    Returns:
        The files written.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    parts = report["reports"].items() if "reports" in report else [("", report)]
    out: list[Path] = []
    for name, rep in parts:
        prefix = f"{_safe(name)}-" if name else ""
        out.append(how_far_plot(rep, d / f"{prefix}how_far.png"))
        for log in (rep.get("traces") or {}).get("logs", []):
            out.append(trace_plot(rep, log, d / f"{prefix}trace-{_safe(log['log'])}.png"))
    return out


def _safe(name: str) -> str:
    """A log's name as a file name (``Ultimaker_020[held-out]`` → ``Ultimaker_020_held-out_``)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)
