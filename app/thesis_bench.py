"""``cwrr bench thesis``: the full SC-1–SC-4 matrix, radar charts, tracking
plots and a markdown table (thesis 4.4–4.7)."""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.metrics import METRIC_LABELS, METRICS
from app.engine.runlog import atomic_write_text
from app.engine.scenarios import CONTROLLERS, CaseRun, ScenarioSettings, iter_matrix

COLORS = {"default": "#d62728", "pid": "#1f77b4", "fuzzy": "#2ca02c"}
STYLES = {"default": "--", "pid": ":", "fuzzy": "-"}
NAMES = {"default": "Default", "pid": "Cascade PID", "fuzzy": "Cascade Fuzzy Adaptive PID"}


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def radar_figure(title: str, values: dict[str, dict[str, float]], figsize: tuple[float, float] = (6.4, 6.0),
                 fontsize: float = 8.0) -> Any:
    """Radar chart of the six metrics per controller (thesis Fig 4.26) as a matplotlib figure.

    Each axis is scaled by the largest value among the controllers, so the
    worst controller touches the rim; the raw maxima are in the tick labels.

    Args:
        title: Figure title (empty: none).
        values: Metrics per controller, keyed as in :data:`~app.engine.metrics.METRICS`.
        figsize: Figure size [in].
        fontsize: Labels' and legend's font size [pt] (the title's is 2 pt larger).
    """
    plt = _plt()
    ang = np.linspace(0.0, 2.0 * np.pi, len(METRICS), endpoint=False)
    fig = plt.figure(figsize=figsize)
    ax = fig.add_subplot(111, polar=True)
    scale = {m: max(v[m] for v in values.values()) or 1.0 for m in METRICS}
    for ctl, met in values.items():
        r = [met[m] / scale[m] for m in METRICS]
        ax.plot(np.r_[ang, ang[0]], np.r_[r, r[0]], STYLES[ctl], color=COLORS[ctl], lw=2, label=NAMES[ctl])
        ax.fill(np.r_[ang, ang[0]], np.r_[r, r[0]], color=COLORS[ctl], alpha=0.06)
    ax.set_xticks(ang)
    ax.set_xticklabels([f"{METRIC_LABELS[m]}\nmax {scale[m]:.3g}" for m in METRICS], fontsize=fontsize)
    ax.set_ylim(0, 1.05)
    ax.set_yticklabels([])
    if title:
        ax.set_title(title, fontsize=fontsize + 2)
    if figsize[0] >= 5.0:
        ax.legend(loc="lower center", bbox_to_anchor=(0.5, -0.18), ncol=3, fontsize=fontsize)
        fig.tight_layout()
    else:  # narrow: the legend in one column below, and room beside the polar axes for the labels
        fig.subplots_adjust(left=0.24, right=0.76, top=0.86, bottom=0.32)
        ax.tick_params(axis="x", pad=fontsize)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=1, fontsize=fontsize, frameon=False)
    return fig


def radar_chart(title: str, values: dict[str, dict[str, float]], path_stem: Path) -> list[Path]:
    """:func:`radar_figure` saved as PNG and SVG, the table embedded as JSON in the
    files' metadata (PNG text chunk ``cwrr:metrics``, SVG ``Description``).

    Returns:
        The PNG and SVG paths.
    """
    plt = _plt()
    fig = radar_figure(title, values)
    payload = json.dumps(values, sort_keys=True)
    png = path_stem.with_suffix(".png")
    svg = path_stem.with_suffix(".svg")
    fig.savefig(png, dpi=110, metadata={"Title": title, "cwrr:metrics": payload})
    fig.savefig(svg, metadata={"Title": title, "Description": payload})
    plt.close(fig)
    return [png, svg]


def tracking_plot(runs: list[CaseRun], path: Path) -> Path:
    """Target and measured torque, error %, and for SC-4 the chamber pressures,
    one column per controller (like thesis Figs 4.24–4.50)."""
    plt = _plt()
    sc4 = runs[0].case.scenario == "SC-4"
    nrow = 3 if sc4 else 2
    fig, axs = plt.subplots(nrow, len(runs), figsize=(4.2 * len(runs), 2.4 * nrow), sharex=True, squeeze=False)
    for j, run in enumerate(runs):
        res = run.result
        t = res.column("t")
        tq = res.column("torque")
        tgt = run.case.target
        on = res.column("mode") > 0
        ax = axs[0, j]
        ax.plot(t, np.where(on, tgt, 0.0), "k--", lw=1, label="target")
        ax.plot(t, tq, color=COLORS[run.controller], lw=0.8, label="T_i measured")
        ax.axvspan(run.window[0], run.window[1], color="0.9", zorder=-1)
        if run.t_d is not None:
            ax.axvline(run.t_d, color="k", lw=0.6)
        ax.set_title(f"{NAMES[run.controller]}  RMSE {run.metrics['rmse']:.3f} N·m", fontsize=9)
        ax.set_ylabel("T_i [N·m]")
        if j == 0:
            ax.legend(fontsize=7, loc="lower right")
        ax = axs[1, j]
        w = (t >= run.window[0]) & (t <= run.window[1])
        ax.plot(t[w], 100.0 * (tgt - tq[w]) / abs(tgt), color=COLORS[run.controller], lw=0.8)
        ax.set_ylabel("e [%]")
        ax.set_ylim(-60, 60)
        if sc4:
            ax = axs[2, j]
            ax.plot(t, res.column("p_a"), lw=0.8, label="P_a")
            ax.plot(t, res.column("p_b"), lw=0.8, label="P_b")
            ax.set_ylabel("P [bar abs]")
            if j == 0:
                ax.legend(fontsize=7)
        axs[-1, j].set_xlabel("t [s]")
    c = runs[0].case
    fig.suptitle(f"{c.scenario} {c.direction} [T_i]^t = {c.target:+.1f} N·m "
                 f"(PDRA {'on' if c.pdra else 'off'}, TDRA {'on' if c.tdra else 'off'})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _markdown(records: list[dict[str, Any]]) -> str:
    main = [r for r in records if not r["ablation"]]
    by_case: dict[tuple[str, float], dict[str, float]] = defaultdict(dict)
    for r in main:
        by_case[(r["scenario"], r["target"])][r["controller"]] = r["metrics"]["rmse"]
    lines = ["| Case | Default | Cascade PID | Fuzzy | best | worst | thesis: Fuzzy best / Default worst |",
             "|---|---|---|---|---|---|---|"]
    fz_best = df_worst = 0
    for (sc, tg), v in by_case.items():
        best = min(v, key=lambda k: v[k])
        worst = max(v, key=lambda k: v[k])
        fz_best += best == "fuzzy"
        df_worst += worst == "default"
        agree = f"{'yes' if best == 'fuzzy' else 'no'} / {'yes' if worst == 'default' else 'no'}"
        lines.append(f"| {sc} {'FP' if tg > 0 else 'FS'} {tg:+.1f} | {v['default']:.3f} | {v['pid']:.3f} | "
                     f"{v['fuzzy']:.3f} | {best} | {worst} | {agree} |")
    lines.append("")
    lines.append(f"RMSE [N·m] on the evaluation window. Fuzzy lowest in {fz_best}/{len(by_case)} cases; "
                 f"Default highest in {df_worst}/{len(by_case)}.")
    lines.append("")
    lines.append("| Ablation | Controller | RMSE off | RMSE on | lowered |")
    lines.append("|---|---|---|---|---|")
    for r in [r for r in records if r["ablation"]]:
        flag = "TDRA" if r["scenario"] == "SC-3" else "PDRA"
        on = next(m for m in main if m["scenario"] == r["scenario"] and m["target"] == r["target"]
                  and m["controller"] == r["controller"])
        a, b = r["metrics"]["rmse"], on["metrics"]["rmse"]
        lines.append(f"| {r['scenario']} {r['target']:+.1f} {flag} | {r['controller']} | {a:.3f} | {b:.3f} | "
                     f"{'yes' if b < a else 'no'} |")
    return "\n".join(lines) + "\n"


def run_thesis_bench(out: Path, seed: int = 0, plots: bool = True,
                     settings: ScenarioSettings | None = None) -> list[dict[str, Any]]:
    """Run the matrix and write ``results.json``, ``results.md`` and figures to ``out``.

    Returns:
        The ``results.json`` records (36 main runs, then 12 ablation runs).
    """
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = list(iter_matrix(seed=seed, settings=settings))
    wall = time.perf_counter() - t0
    records = [r.record() for r in runs]
    atomic_write_text(out / "results.json", json.dumps(records, indent=1))
    atomic_write_text(out / "results.md", _markdown(records))
    if plots:
        groups: dict[str, list[CaseRun]] = defaultdict(list)
        for r in runs:
            groups[r.case.key].append(r)
        for key, grp in groups.items():
            grp.sort(key=lambda r: CONTROLLERS.index(r.controller))  # type: ignore[arg-type]
            tracking_plot(grp, out / f"tracking_{key}.png")
            if not grp[0].case.ablation:
                c = grp[0].case
                radar_chart(f"{c.scenario} {c.direction} [T_i]^t = {c.target:+.1f} N·m",
                            {r.controller: r.metrics for r in grp}, out / f"radar_{key}")
    atomic_write_text(out / "run_info.json", json.dumps({"seed": seed, "runs": len(runs), "wall_s": wall}))
    return records
