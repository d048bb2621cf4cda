"""Pressure-dependent Coulomb + viscous friction from constant-speed strokes in logs recorded elsewhere.

Built for (and tested on) the real pneumatic seal-friction measurements of
E. Zillen (TU Delft, 2021, CC0) in ``refdata/seal_friction/`` (SPEC §7):
whitespace-separated, no header, 100 Hz, columns t [ms], laser [V],
pressure [V], force [V], x [mm], p [bar gauge], F [N]; one chamber held at
1–7 bar while an external drive moves the piston back and forth at
≈ 5–14 mm/s; friction = p·A − F with A from a 25 mm bore (25.7 mm for files
named ``*257``).

Per file (one seal at one pressure) the constant-speed samples — away from
the reversals, where the speed has settled — are fitted by least squares to

    f = −sign(v)·F_c − B·v + f_0

(friction opposes motion; f_0 absorbs the load-cell/pressure offset that
makes the two directions' levels unequal). Per seal, F_c and B are then
regressed on pressure: F_c(p) = F_c0 + k_c·p, B(p) = B0 + k_b·p. The
strokes run at nearly one speed per direction, so B is weakly determined
(bounded at 0) while F_c — the half-difference of the two directions'
levels — is robust.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import lsq_linear
from scipy.signal import savgol_filter

from app.engine.params import ParameterError

_NAME = re.compile(r"^(?P<seal>.+?)_(?P<p>\d+(?:\.\d+)?)bar(?P<rest>.*)$")


@dataclass
class SealFit:
    """Coulomb + viscous friction of one seal at one pressure.

    Attributes:
        file: Source file name.
        seal: Seal type (from the file name).
        p_bar: Mean chamber pressure over the fitted samples [bar gauge].
        fc: Coulomb friction [N].
        b: Viscous coefficient [N·s/m].
        offset: Direction-independent offset f_0 [N].
        n: Samples used.
        rmse: Fit residual RMS [N].
        speed_range: (min, max) |v| of the samples [m/s].
        bore_mm: Bore used for p·A [mm].
    """

    file: str
    seal: str
    p_bar: float
    fc: float
    b: float
    offset: float
    n: int
    rmse: float
    speed_range: tuple[float, float]
    bore_mm: float


def load_zillen(path: str | Path) -> np.ndarray:
    """Read one file (7 numeric columns); refuses anything else with a clear message."""
    path = Path(path)
    try:
        a = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise ParameterError(f"{path.name}: not a whitespace-separated numeric table ({exc})") from exc
    if a.shape[1] != 7:
        raise ParameterError(f"{path.name}: expected 7 columns (t, laser, pressure V, force V, x, p, F), "
                             f"found {a.shape[1]}")
    if a.shape[0] < 50:
        raise ParameterError(f"{path.name}: only {a.shape[0]} rows; need a few strokes")
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"{path.name}: contains NaN or infinite values")
    if np.any(np.diff(a[:, 0]) <= 0):
        raise ParameterError(f"{path.name}: time column is not strictly increasing")
    return a


def fit_seal_file(path: str | Path, bore_mm: float | None = None, min_speed: float = 3e-3,
                  settle_s: float = 0.3) -> SealFit:
    """Fit one file.

    Args:
        path: The file.
        bore_mm: Bore [mm]; default from the name (25.7 for ``*257``, else 25).
        min_speed: Samples slower than this are dropped [m/s].
        settle_s: Samples this close to a reversal are dropped [s].
    """
    path = Path(path)
    m = _NAME.match(path.stem)
    seal = m.group("seal") if m else path.stem
    if bore_mm is None:
        bore_mm = 25.7 if "257" in path.stem else 25.0
    a = load_zillen(path)
    t = a[:, 0] * 1e-3
    x = a[:, 4] * 1e-3
    p = a[:, 5]
    f_load = a[:, 6]
    dt = float(np.median(np.diff(t)))
    v = savgol_filter(x, 11, 2, deriv=1, delta=dt)
    area = math.pi * (bore_mm * 1e-3) ** 2 / 4.0
    fr = p * 1e5 * area - f_load
    s = np.sign(v)
    s[np.abs(v) < min_speed] = 0.0
    # distance (in samples) from the nearest change of direction/standstill
    change = np.nonzero(np.diff(s) != 0)[0]
    near = np.zeros(s.size, dtype=bool)
    k = int(round(settle_s / dt))
    for c in change:
        near[max(0, c - k): c + k + 1] = True
    keep = (s != 0) & ~near
    if keep.sum() < 20 or len(set(s[keep].tolist())) < 2:
        raise ParameterError(f"{path.name}: fewer than 20 constant-speed samples in both directions")
    vk = v[keep]
    a_mat = np.column_stack([-np.sign(vk), -vk, np.ones(vk.size)])
    # F_c ≥ 0 and B ≥ 0: within one file the speed barely varies, so an
    # unbounded fit trades B against F_c and f_0 and can return B < 0
    coef = lsq_linear(a_mat, fr[keep], bounds=([0.0, 0.0, -np.inf], [np.inf, np.inf, np.inf])).x
    res = a_mat @ coef - fr[keep]
    return SealFit(path.name, seal, float(np.mean(p[keep])), float(coef[0]), float(coef[1]), float(coef[2]),
                   int(keep.sum()), float(np.sqrt(np.mean(res**2))),
                   (float(np.abs(vk).min()), float(np.abs(vk).max())), bore_mm)


def fit_seals(paths: list[Path]) -> dict[str, Any]:
    """Fit every file, then F_c(p) and B(p) per seal (linear in pressure)."""
    fits = [fit_seal_file(p) for p in sorted(paths)]
    by_seal: dict[str, list[SealFit]] = {}
    for f in fits:
        by_seal.setdefault(f.seal, []).append(f)
    summary = {}
    for seal, fs in sorted(by_seal.items()):
        pr = np.array([f.p_bar for f in fs])
        fc = np.array([f.fc for f in fs])
        b = np.array([f.b for f in fs])
        if len(fs) >= 2 and np.ptp(pr) > 0.5:
            kc, c0 = np.polyfit(pr, fc, 1)
            kb, b0 = np.polyfit(pr, b, 1)
        else:
            kc, c0, kb, b0 = 0.0, float(fc.mean()), 0.0, float(b.mean())
        summary[seal] = {"p_bar": pr.tolist(), "fc": fc.tolist(), "b": b.tolist(),
                         "fc0": float(c0), "fc_per_bar": float(kc), "b0": float(b0), "b_per_bar": float(kb)}
    return {"files": [asdict(f) for f in fits], "seals": summary}


def seal_plot(result: dict[str, Any], path: str | Path) -> Path:
    """F_c and B against pressure, one line per seal."""
    from app.engine.ident.plots import pyplot

    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for seal, s in result["seals"].items():
        order = np.argsort(s["p_bar"])
        pr = np.asarray(s["p_bar"])[order]
        a1.plot(pr, np.asarray(s["fc"])[order], "o-", ms=4, label=seal)
        a2.plot(pr, np.asarray(s["b"])[order], "o-", ms=4, label=seal)
    a1.set_xlabel("chamber pressure [bar gauge]")
    a1.set_ylabel("Coulomb friction F_c [N]")
    a2.set_xlabel("chamber pressure [bar gauge]")
    a2.set_ylabel("viscous coefficient B [N·s/m]")
    for ax in (a1, a2):
        ax.grid(True, alpha=0.3)
    a1.legend(fontsize=7, ncol=2)
    fig.suptitle("Seal friction (Zillen, TU Delft 2021): friction = p·A − F")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
