"""Families for data from outside the station, accepted through the adapters in :mod:`.logs`.

* :class:`ChamberFamily` — a closed pneumatic chamber (``refdata/chamber_leak``):
  one channel, pressure. Baseline: mass conserved, isothermal (the thesis's
  assumptions), so the pressure stays at its initial value. Candidates:
  ``external_leakage`` (an ISO 6358 orifice to atmosphere, as a time
  constant), ``heat_transfer`` (the gas relaxing to wall temperature after
  filling), ``sensor_bias`` (an offset; it cannot be told from the initial
  pressure, which the identifiability report shows).
* :class:`DriveFamily` — a translational drive with a force input
  (``refdata/emps``): the force predicted from the measured motion.
  Baseline: Coulomb + viscous friction. Candidates: ``inertia`` (a mass),
  ``sensor_bias`` (a force offset), ``presliding_friction`` (a smooth
  transition through zero speed instead of a sign).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp
from scipy.signal import butter, filtfilt

from app.engine.constants import P_ATM_BAR
from app.engine.diagnosis.core import Param, white_noise_sd
from app.engine.diagnosis.logs import Experiment, on_uniform_grid, unscored_near_fills

B_CRIT = 0.528  # critical pressure ratio of an ideal orifice (Eq 2.3), for an unknown leak path
WORKING_PRESSURE_BAR = 3.0  # P_w of the thesis's HIL tests [bar abs] (SPEC §1)
LEAK_HORIZON_S = 60.0  # how long a chamber stays closed when a leak's effect on the rig is judged [s]


def split_time(exp: Experiment, frac: float = 0.6) -> tuple[Experiment, Experiment]:
    """The first ``frac`` of a record to calibrate on and the rest to hold out (times kept)."""
    k = int(len(exp.t) * frac)

    def part(sl: slice, tag: str) -> Experiment:
        return replace(exp, name=f"{exp.name}[{tag}]", t=exp.t[sl],
                       inputs={c: v[sl] for c, v in exp.inputs.items()},
                       channels={c: v[sl] for c, v in exp.channels.items()})

    return part(slice(0, k), "calibration"), part(slice(k, None), "held-out")


# --------------------------------------------------------------------------- closed chamber


@dataclass
class _ChamberPrep:
    t: np.ndarray
    p: np.ndarray
    noise: float
    p_atm: float


class ChamberFamily:
    """A closed chamber's pressure decay (channel ``p`` [bar abs]).

    Relevance: 0.01 bar, the PRV's rest deadband (``PRVParams.deadband_off_bar``):
    a smaller pressure error cannot be acted upon on the rig.
    """

    name: str = "chamber"
    channels: tuple[str, ...] = ("p",)
    candidates: tuple[str, ...] = ("external_leakage", "heat_transfer", "sensor_bias")

    def __init__(self) -> None:
        self.relevance: dict[str, float] = {"p": 0.01}

    def baseline(self) -> list[Param]:
        return [Param("p0", 5.0, 0.5, 15.0, "bar abs")]

    def effect(self, name: str) -> list[Param]:
        if name == "external_leakage":
            return [Param("external_leakage.tau", 1e4, 0.1, 1e8, "s", log=True)]
        if name == "heat_transfer":
            # a chamber's thermal time constant m·c_v/(h·A) is seconds to a minute or two
            # (Carneiro & de Almeida 2006); unbounded, a slow exponential would mimic any drift
            return [Param("heat_transfer.dp", 0.01, 0.0, 1.5, "bar"),
                    Param("heat_transfer.tau", 30.0, 0.5, 300.0, "s", log=True)]
        if name == "sensor_bias":
            return [Param("sensor_bias.p_bar", 0.0, -0.5, 0.5, "bar")]
        raise ValueError(f"chamber family: no effect {name!r}")

    def prepare(self, exp: Experiment) -> _ChamberPrep:
        p = exp.channels["p"]
        return _ChamberPrep(exp.t, p, white_noise_sd(p), float(exp.meta.get("p_atm_bar", P_ATM_BAR)))

    def measured(self, prep: _ChamberPrep) -> dict[str, np.ndarray]:
        return {"p": prep.p}

    def noise(self, prep: _ChamberPrep) -> dict[str, float]:
        return {"p": prep.noise}

    def times(self, prep: _ChamberPrep) -> np.ndarray:
        return prep.t - prep.t[0]

    def noise_shows(self, prep: _ChamberPrep) -> dict[str, np.ndarray]:
        return {}  # every prediction is the model's own: each sample carries the whole noise

    def regimes(self, prep: _ChamberPrep) -> dict[str, np.ndarray]:
        hi = prep.p > prep.p_atm / B_CRIT
        return {"choked (p > P_atm/b)": hi, "subsonic": ~hi}

    def inputs(self, prep: _ChamberPrep) -> dict[str, np.ndarray]:
        return {}

    @staticmethod
    def _leak_decay(p0: float, tau: float, p_atm: float, t: np.ndarray) -> np.ndarray:
        """Pressure [bar abs] at times ``t`` [s] of a chamber leaking through an orifice (choked above P_atm/b)."""

        def rhs(_t: float, y: np.ndarray) -> np.ndarray:
            r = p_atm / max(y[0], 1e-6)
            psi = 1.0 if r <= B_CRIT else math.sqrt(max(0.0, 1.0 - ((r - B_CRIT) / (1.0 - B_CRIT)) ** 2))
            return np.array([-y[0] / tau * psi if y[0] > p_atm else 0.0])

        sol = solve_ivp(rhs, (0.0, float(t[-1])), [p0], t_eval=t, rtol=1e-8, atol=1e-9, method="LSODA")
        return sol.y[0] if sol.success and sol.y.shape[1] == t.size else np.full(t.shape, np.nan)

    def leak_on_the_rig(self, report: dict[str, Any], working_pressure_bar: float = WORKING_PRESSURE_BAR,
                        horizon_s: float = LEAK_HORIZON_S, p_atm_bar: float = P_ATM_BAR) -> dict[str, Any] | None:
        """What a chamber's fitted leak would do on the rig: the pressure a closed chamber loses.

        A leak can be beyond doubt in a record taken at 7–8 bar over minutes and still be too
        slow to act on at the rig's working pressure; this says which, by the family's relevance.

        Args:
            report: The chamber's diagnosis report.
            working_pressure_bar: Pressure the chamber is closed at [bar abs] (the thesis's HIL
                tests' P_w, SPEC §1).
            horizon_s: How long it stays closed [s] (a minute of exercise).
            p_atm_bar: Atmospheric pressure [bar abs].

        Returns:
            ``None`` when the verdict names no leak (nor one it cannot tell from its
            effect); else ``tau_s`` [s], ``loss_bar`` [bar]
            over the horizon, the conditions, and ``on_the_rig``: ``negligible`` (a loss under the
            relevance, 0.01 bar), ``dominant`` (half the gauge pressure or more) or ``matters``.
        """
        v = report["verdict"]
        c = next((c for c in report["ranking"] if c["effect"] == "external_leakage"), None)
        if c is None or "external_leakage" not in (*v["effects"], *v["confusable_with"]):
            return None
        tau = float(c["params"]["external_leakage.tau"])
        end = self._leak_decay(working_pressure_bar, tau, p_atm_bar, np.array([0.0, horizon_s]))[-1]
        loss = float(working_pressure_bar - end)
        gauge = working_pressure_bar - p_atm_bar
        kind = ("negligible" if loss < self.relevance["p"] else "dominant" if loss >= 0.5 * gauge else "matters")
        return {"tau_s": tau, "working_pressure_bar": working_pressure_bar, "horizon_s": horizon_s,
                "loss_bar": loss, "on_the_rig": kind}

    def predict(self, prep: _ChamberPrep, x: dict[str, float], effects: tuple[str, ...]) -> dict[str, np.ndarray]:
        t = prep.t
        p = np.full(t.shape, x["p0"])
        if "external_leakage" in effects:
            p = self._leak_decay(x["p0"], x["external_leakage.tau"], prep.p_atm, t)
        if "heat_transfer" in effects:
            p = p - x["heat_transfer.dp"] * (1.0 - np.exp(-t / x["heat_transfer.tau"]))
        if "sensor_bias" in effects:
            p = p + x["sensor_bias.p_bar"]
        return {"p": p}


# --------------------------------------------------------------------------- translational drive


@dataclass
class _DrivePrep:
    v: np.ndarray
    a: np.ndarray
    force: np.ndarray
    q_ref: np.ndarray
    noise: float
    v_full: np.ndarray  # full-rate speed, for the nonlinear columns
    ba: tuple[np.ndarray, np.ndarray]
    keep: slice
    t: np.ndarray  # of the kept samples, from the log's start [s]


class DriveFamily:
    """A translational drive (EMPS): force [N] predicted from the measured position.

    Preparation follows the published inverse-model identification of the
    EMPS (Janot, Gautier, Brunot 2019): zero-phase Butterworth low-pass of the
    position and the force (``cutoff_hz``), speed and acceleration by central
    differences, then decimation. Relevance: 1 N (0.5 % of the drive's
    ≈ 200 N force span).

    Args:
        cutoff_hz: Low-pass cut-off [Hz].
        every: Decimation factor.
    """

    name: str = "drive"
    channels: tuple[str, ...] = ("force",)
    candidates: tuple[str, ...] = ("inertia", "sensor_bias", "presliding_friction")

    def __init__(self, cutoff_hz: float = 20.0, every: int = 10) -> None:
        self.relevance: dict[str, float] = {"force": 1.0}
        self.cutoff_hz = cutoff_hz
        self.every = every

    def baseline(self) -> list[Param]:
        return [Param("F_v", 100.0, 0.0, 1e4, "N·s/m"), Param("F_c", 10.0, 0.0, 1e3, "N")]

    def effect(self, name: str) -> list[Param]:
        if name == "inertia":
            return [Param("inertia.mass", 10.0, 0.0, 1e4, "kg")]
        if name == "sensor_bias":
            return [Param("sensor_bias.force", 0.0, -100.0, 100.0, "N")]
        if name == "presliding_friction":
            return [Param("presliding_friction.v_p", 1e-3, 1e-6, 0.1, "m/s", log=True)]
        raise ValueError(f"drive family: no effect {name!r}")

    def prepare(self, exp: Experiment) -> _DrivePrep:
        measured = exp.channels["force"]  # its noise as measured (interpolation averages it away)
        exp = on_uniform_grid(exp)
        dt = exp.dt
        b, a = butter(4, self.cutoff_hz / (0.5 / dt))
        q = filtfilt(b, a, exp.channels["q"])
        f_raw = exp.channels["force"]
        f = filtfilt(b, a, f_raw)
        # what a gap in the log made up is not scored, as far as the filter spreads it (1.5 periods
        # of the cut-off; see logs.on_uniform_grid)
        gap = unscored_near_fills(exp.filled, int(round(1.5 / (self.cutoff_hz * dt))))
        if gap is not None:
            f[gap] = np.nan
        v = np.gradient(q, dt)
        acc = np.gradient(v, dt)
        edge = int(round(0.2 / dt))
        k = slice(edge, len(q) - edge, self.every)
        # the floor: the raw force's white noise (robust estimate) passed through the same
        # zero-phase filter (measured on a fixed unit-variance sequence, not approximated)
        unit = filtfilt(b, a, np.random.default_rng(0).standard_normal(min(len(q), 20000)))
        noise = white_noise_sd(measured) * float(np.std(unit[edge:-edge]))
        return _DrivePrep(v[k], acc[k], f[k], exp.inputs.get("q_ref", q)[k], noise, v, (b, a), k,
                          np.arange(len(q))[k] * dt)

    def measured(self, prep: _DrivePrep) -> dict[str, np.ndarray]:
        return {"force": prep.force}

    def noise(self, prep: _DrivePrep) -> dict[str, float]:
        return {"force": prep.noise}

    def times(self, prep: _DrivePrep) -> np.ndarray:
        return prep.t

    def noise_shows(self, prep: _DrivePrep) -> dict[str, np.ndarray]:
        return {}  # every prediction is the model's own: each sample carries the whole noise

    def regimes(self, prep: _DrivePrep) -> dict[str, np.ndarray]:
        sp = np.abs(prep.v)
        vmax = float(sp.max()) or 1.0
        acc = np.abs(prep.a)
        return {"standstill": sp < 0.01 * vmax, "slow motion": (sp >= 0.01 * vmax) & (sp < 0.3 * vmax),
                "fast motion": sp >= 0.3 * vmax, "high acceleration": acc > np.percentile(acc, 90)}

    def inputs(self, prep: _DrivePrep) -> dict[str, np.ndarray]:
        return {"speed": prep.v, "acceleration": prep.a}

    def predict(self, prep: _DrivePrep, x: dict[str, float], effects: tuple[str, ...]) -> dict[str, np.ndarray]:
        v = prep.v
        # the force was low-passed, so a nonlinear column must pass the same filter
        # (IDIM's parallel filtering); unfiltered, sgn(v) would switch faster than the
        # measured force can and a smooth pre-sliding curve would win by the filter's lag
        vf = prep.v_full
        raw = np.tanh(vf / x["presliding_friction.v_p"]) if "presliding_friction" in effects else np.sign(vf)
        sgn = filtfilt(*prep.ba, raw)[prep.keep]
        f = x["F_v"] * v + x["F_c"] * sgn
        if "inertia" in effects:
            f = f + x["inertia.mass"] * prep.a
        if "sensor_bias" in effects:
            f = f + x["sensor_bias.force"]
        return {"force": f}

