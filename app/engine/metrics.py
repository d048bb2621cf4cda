"""The thesis's six tracking metrics (4.4–4.7) as pure functions.

All take the sample times ``t`` [s] and the tracking error ``e`` = target −
measured interaction torque [N·m] over the evaluation window. Integrals use
the trapezoidal rule on the samples; ITAE weights by the time since the start
of the window (the thesis evaluates "from convergence, or from t_d").
Beside them, what a run tells a therapist besides how well the torque was
tracked: a pressure loop's chatter and how far the arm went.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

METRICS: tuple[str, ...] = ("mae", "iae", "itae", "evar", "rmse", "maxae")
METRIC_LABELS: dict[str, str] = {
    "mae": "MAE [N·m]", "iae": "IAE [N·m·s]", "itae": "ITAE [N·m·s²]",
    "evar": "e_var [N²·m²]", "rmse": "RMSE [N·m]", "maxae": "Max AE [N·m]",
}


def _check(t: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float)
    e = np.asarray(e, dtype=float)
    if t.ndim != 1 or t.shape != e.shape:
        raise ValueError(f"t and e must be 1-D arrays of equal length, got {t.shape} and {e.shape}")
    if t.size < 2:
        raise ValueError("an evaluation window needs at least two samples")
    if np.any(np.diff(t) <= 0):
        raise ValueError("sample times must be strictly increasing")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(e))):
        raise ValueError("t and e must be finite")
    return t, e


def mae(t: np.ndarray, e: np.ndarray) -> float:
    """Mean absolute error [N·m]."""
    _, e = _check(t, e)
    return float(np.mean(np.abs(e)))


def iae(t: np.ndarray, e: np.ndarray) -> float:
    """Integral of absolute error ∫|e|dt [N·m·s]."""
    t, e = _check(t, e)
    return float(np.trapezoid(np.abs(e), t))


def itae(t: np.ndarray, e: np.ndarray) -> float:
    """Integral of time-weighted absolute error ∫(t − t₀)|e|dt [N·m·s²]."""
    t, e = _check(t, e)
    return float(np.trapezoid((t - t[0]) * np.abs(e), t))


def evar(t: np.ndarray, e: np.ndarray) -> float:
    """Error variance (population, ddof = 0) [N²·m²]."""
    _, e = _check(t, e)
    return float(np.var(e))


def rmse(t: np.ndarray, e: np.ndarray) -> float:
    """Root-mean-square error [N·m]."""
    _, e = _check(t, e)
    return float(np.sqrt(np.mean(e * e)))


def maxae(t: np.ndarray, e: np.ndarray) -> float:
    """Maximum absolute error [N·m]."""
    _, e = _check(t, e)
    return float(np.max(np.abs(e)))


def all_metrics(t: np.ndarray, e: np.ndarray) -> dict[str, float]:
    """All six, keyed as in :data:`METRICS`."""
    return {"mae": mae(t, e), "iae": iae(t, e), "itae": itae(t, e), "evar": evar(t, e),
            "rmse": rmse(t, e), "maxae": maxae(t, e)}


TOGGLE_WARN_BAR = 0.02
"""Period-2 toggle of a chamber pressure [bar, median over the scored window] past which a run says so.

On the simulated rig, Default and Fuzzy leave ≤ 0.0053 bar in every main case (the sensors' noise alone gives
≈ 0.0012), and the Cascade PID with the thesis's Eq 3.26 gains 0.07–0.38 bar in its counter chamber
(docs/controllers.md, "With a plant that answers within one 5 ms tick")."""


def toggle_amplitude(p: np.ndarray) -> np.ndarray:
    """Period-2 amplitude of a sampled pressure at each inner sample [bar]: |P[k+1] − 2P[k] + P[k−1]| / 4.

    A ±A square wave at the sample rate has second differences of ±4A; a slow change has none.

    Args:
        p: Pressure samples, one per control period [bar].
    """
    p = np.asarray(p, dtype=float)
    return np.abs(p[2:] - 2.0 * p[1:-1] + p[:-2]) / 4.0


def pressure_toggle(t: np.ndarray, p: np.ndarray, window: tuple[float, float]) -> float | None:
    """Median period-2 toggle of ``p`` [bar] over the samples of ``t`` [s] inside ``window`` [s].

    None when no sample with a neighbour on each side lies in the window.
    """
    t, amp = np.asarray(t, dtype=float), toggle_amplitude(p)
    inside = (t[1:-1] >= window[0]) & (t[1:-1] <= window[1])
    return float(np.median(amp[inside])) if inside.any() else None


def toggle_report(t: np.ndarray, p_a: np.ndarray, p_b: np.ndarray, window: tuple[float, float]) -> dict[str, Any]:
    """Each chamber's period-2 toggle over the scored window [bar] and, past :data:`TOGGLE_WARN_BAR`, a warning.

    A pressure loop whose gains are too high for the rig's valves toggles its chamber every control period:
    the arm feels a buzz at half the control rate and the metrics carry it. Said in the run's result, where
    the therapist (the dashboard, viser), a script and ``cwrr sim`` read it.

    Args:
        t: Sample times, one per control period [s].
        p_a: Chamber a's measured pressure [bar abs].
        p_b: Chamber b's measured pressure [bar abs].
        window: The scored window [s], on ``t``'s clock.

    Returns:
        ``pressure_toggle_bar`` per chamber (None when the window holds no inner sample) and, when either is past
        the threshold, ``warnings``: one sentence per such chamber.
    """
    toggles = {"p_a": pressure_toggle(t, p_a, window), "p_b": pressure_toggle(t, p_b, window)}
    out: dict[str, Any] = {"pressure_toggle_bar": toggles}
    loud = [(c, v) for c, v in toggles.items() if v is not None and v > TOGGLE_WARN_BAR]
    if loud:
        out["warnings"] = [f"Chamber {c[-1]}'s pressure toggled every control period (±{v:.2f} bar, median over "
                           "the scored window): the pressure-loop gains are too high for this rig's valves, and "
                           "the metrics include that chatter." for c, v in loud]
    return out


def angle_range_deg(theta: np.ndarray) -> list[float] | None:
    """The range of motion an exercise reached: the lowest and highest measured angle [deg].

    A therapist follows a person's active range from session to session; the
    six metrics say how well the torque was tracked, not how far the arm went.

    Args:
        theta: The vane angle over the exercise's program, one sample per period
            [rad, positive: pronation].

    Returns:
        ``[lowest, highest]`` [deg, positive: pronation], or None with no finite sample.
    """
    th = theta[np.isfinite(theta)]
    if th.size == 0:
        return None
    return [math.degrees(float(th.min())), math.degrees(float(th.max()))]
