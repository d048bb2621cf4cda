"""The identification GUIs' plots (Figures 3.19, 3.27, 4.2–4.4, 4.6–4.12, 4.20–4.21), as files.

Matplotlib with the Agg backend: PNG for reports and the dashboard.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (files only: a server has no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def friction_curve_plot(data: Any, result: Any, path: str | Path) -> Path:
    """Friction vs speed: static tests (▲ at zero speed), their mean (●),
    dynamic tests (✱) and the fitted curve per direction (Appendix 1–2 plot).

    Args:
        data: :class:`RotaryFrictionData` or :class:`LinearFrictionData`.
        result: The matching fitted result.
        path: Output PNG.
    """
    plt = pyplot()
    rotary = hasattr(result, "ccw")
    pairs = ((("ccw", result.ccw), ("cw", result.cw)) if rotary
             else (("extension", result.extension), ("retraction", result.retraction)))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for d, fit in pairs:
        st, v, f = data.arrays(d)
        st = st[np.isfinite(st)]
        ok = np.isfinite(v) & np.isfinite(f)
        first = d in ("ccw", "extension")
        ax.plot(np.zeros_like(st), st, "k^", ms=4, alpha=0.5, label="static tests" if first else None)
        ax.plot([0.0], [fit.fs], "ko", ms=7, mfc="w", label="static mean" if first else None)
        ax.plot(v[ok], f[ok], "k*", ms=5, label="dynamic tests" if first else None)
        vmax = float(np.max(np.abs(v[ok]))) if ok.any() else 1.0
        grid = np.linspace(0.0, vmax, 300) * (1.0 if fit.direction == "positive" else -1.0)
        ax.plot(grid, fit.curve(grid), "-", lw=1.4, label=f"fit {d}")
    unit_v, unit_f = ("rad/s", "N·m") if rotary else ("m/s", "N")
    ax.set_xlabel(f"speed [{unit_v}]")
    ax.set_ylabel(f"friction [{unit_f}]")
    ax.grid(True, alpha=0.3)
    ax.axhline(0, color="k", lw=0.5)
    ax.axvline(0, color="k", lw=0.5)
    ax.legend(fontsize=8)
    title = f"Rotary friction at P_w = {result.pw_bar:g} bar" if rotary else "Linear friction"
    ax.set_title(title)
    return save_figure(fig, plt, path)


def friction_surface_plot(table: Any, path: str | Path) -> Path:
    """Friction torque surfaces T_f(ω, P_w) for CCW and CW (Figure 4.12)."""
    from app.engine.ident.fitting import stribeck

    plt = pyplot()
    pw = np.asarray(table.pw_bar)
    fig = plt.figure(figsize=(10, 4.2))
    for i, (name, sgn) in enumerate((("CCW", 1.0), ("CW", -1.0))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        w = np.linspace(0.0, 10.0, 60) * sgn
        pp = np.linspace(pw.min(), pw.max(), 30)
        W, P = np.meshgrid(w, pp)
        sfx = "ccw" if sgn > 0 else "cw"
        par = {k: np.interp(pp, pw, np.asarray(getattr(table, f"{k}_{sfx}"))) for k in ("ts", "tc", "ws", "b")}
        Z = np.vstack([stribeck(w, par["ts"][j], par["tc"][j], par["ws"][j], par["b"][j]) for j in range(pp.size)])
        ax.plot_surface(W, P, Z, cmap="viridis", linewidth=0, antialiased=True)
        ax.set_xlabel("ω [rad/s]")
        ax.set_ylabel("P_w [bar]")
        ax.set_zlabel("T_f [N·m]")
        ax.set_title(f"{name}")
    return save_figure(fig, plt, path)


def cpr_plot(estimator: Any, path: str | Path) -> Path:
    """CPR a(u) per supply pressure for filling and exhausting (Figure 4.2)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, mode in zip(axes, ("filling", "exhausting"), strict=True):
        mm = estimator.params_.get(mode)
        if mm is None:
            continue
        for j, ps in enumerate(mm.ps_cpr):
            ax.plot(mm.u_cpr, mm.a[:, j], ".-", ms=3, lw=1, label=f"P_s = {ps:g} bar")
        ax.set_xlabel("u [V]")
        ax.set_ylabel("CPR a [-]")
        ax.set_title(f"Port 2, {mode}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, plt, path)


def flow_fit_plot(estimator: Any, data: Any, path: str | Path, signals: tuple[float, ...] = (4.7, 5.0, 5.3)) -> Path:
    """Measured mass flow against chamber pressure with the fitted new model (Figures 4.3–4.4)."""
    from app.engine.ident.dcv import measured_flow

    plt = pyplot()
    fig, axes = plt.subplots(2, len(signals), figsize=(4 * len(signals), 7), squeeze=False)
    for r, mode in enumerate(("filling", "exhausting")):
        mm = estimator.params_.get(mode)
        for c, u in enumerate(signals):
            ax = axes[r][c]
            tests = [t for t in data.select(mode, estimator.fit_ps_bar) if abs(t.u - u) < 1e-6]
            if mm is None or not tests:
                ax.set_visible(False)
                continue
            p, ps, m = measured_flow(tests[0], data.inputs)
            ax.plot(p / 1e5, m * 1e3, "k.", ms=2, alpha=0.4, label="measured (Eq 4.1)")
            order = np.argsort(p)
            ax.plot(p[order] / 1e5, mm.flow("new", p[order], u, tests[0].ps_mean, estimator.p_atm_,
                                            data.inputs.temperature_k, ps[order]) * 1e3,
                    "r-", lw=1.2, label="new model fit")
            ax.set_title(f"{mode}, u = {u:g} V, P_s = {estimator.fit_ps_bar:g} bar")
            ax.set_xlabel("P_a [bar abs]")
            ax.set_ylabel("ṁ [g/s]")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7)
    return save_figure(fig, plt, path)


def validation_plot(cases: list[Any], path: str | Path, models: tuple[str, ...] = ("new", "standard")) -> Path:
    """Measured vs predicted P_a for each validation run (Figures 4.6–4.11)."""
    plt = pyplot()
    n = len(cases)
    cols = 3
    rows = max(1, (n + cols - 1) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
    for i, c in enumerate(cases):
        ax = axes[i // cols][i % cols]
        ax.plot(c.t, c.measured, "k-", lw=1.4, label="measured")
        for m in models:
            ax.plot(c.t, c.predicted[m], "--", lw=1, label=f"{m} ({c.mape_pct[m]:.2f} %)")
        ax.set_title(f"{c.mode} u = {c.u:g} V, P_s = {c.ps_bar:g} bar", fontsize=8)
        ax.set_xlabel("t [s]", fontsize=7)
        ax.set_ylabel("P_a [bar]", fontsize=7)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].set_visible(False)
    return save_figure(fig, plt, path)


def save_figure(fig: Any, plt: Any, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (PNG, 110 dpi) and close it."""
    path = Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def autotune_plot(result: dict[str, Any], path: str | Path) -> Path:
    """Estimated plant response with the tuned loop, and the testing stage's steps (Figure 3.40)."""
    from app.engine.ident.pid_tune import pidf

    plt = pyplot()
    frf, tun = result["frf"], result["tuning"]
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 4))
    w = np.exp(np.linspace(np.log(frf.w.min()), np.log(frf.w.max()), 300))
    g = np.array([frf.at(float(x)) for x in w])
    lg = g * pidf(w, tun.kp, tun.ki, tun.kd, tun.n_filter)
    a1.semilogx(frf.w, 20 * np.log10(np.abs(frf.g)), "ko", label="G measured")
    a1.semilogx(w, 20 * np.log10(np.abs(lg)), "r-", label="L = C·G tuned")
    a1.axhline(0, color="k", lw=0.5)
    a1.set_ylabel("gain [dB]")
    a2.semilogx(frf.w, np.degrees(np.unwrap(np.angle(frf.g))), "ko", label="G measured")
    a2.semilogx(w, np.degrees(np.unwrap(np.angle(lg))), "r-", label="L tuned")
    a2.axhline(-180 + result["spec"]["phase_margin_deg"], color="b", ls=":", label="target PM")
    a2.set_ylabel("phase [deg]")
    for ax in (a1, a2):
        ax.set_xlabel("ω [rad/s]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for s in result["steps"]:
        a3.plot(s.t, s.p, lw=1, label=f"{s.label} ({s.gains[0]:.2f}, {s.gains[1]:.2f}, {s.gains[2]:.4f})")
    a3.set_xlabel("t [s]")
    a3.set_ylabel(f"P_{result['spec']['side']} [bar abs]")
    a3.set_title("pressure step, testing stage")
    a3.grid(True, alpha=0.3)
    a3.legend(fontsize=7)
    return save_figure(fig, plt, path)
