"""The identification GUIs' plots (Figures 3.19, 3.27, 4.12, 4.20–4.21), as files.

Matplotlib with the Agg backend: PNG for reports and the dashboard.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _plt() -> Any:
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
    plt = _plt()
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
    path = Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def friction_surface_plot(table: Any, path: str | Path) -> Path:
    """Friction torque surfaces T_f(ω, P_w) for CCW and CW (Figure 4.12)."""
    from app.engine.ident.fitting import stribeck

    plt = _plt()
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
    path = Path(path)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
