"""PID autotuner (thesis 3.6.2): estimator and design checked against python-control, then on the rig."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from app.engine.ident.pid_tune import (
    THESIS_TUNED,
    AutotuneSpec,
    FrequencyResponse,
    autotune_sim,
    estimate_frf,
    loop_margins,
    loop_response,
    tune_pid,
)
from app.engine.params import ParameterError

W = 2.0 * np.array([0.1, 1 / 3, 1.0, 3.0, 10.0])


def _fopdt(tau: float = 0.3, delay: float = 0.2) -> control.TransferFunction:
    num, den = control.pade(delay, 6)
    return control.tf([1.0], [tau, 1.0]) * control.tf(num, den)


def test_frequency_response_estimate_matches_python_control() -> None:
    g = _fopdt()
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 3 * 2 * math.pi / W.min(), 0.005)
    u = sum(0.05 * np.sin(w * t + ph) for w, ph in zip(W, rng.uniform(0, 6.28, W.size), strict=True))
    y = control.forced_response(g, t, u).outputs
    keep = t >= 2 * math.pi / W.min()  # the first slow period settles the transient
    frf = estimate_frf(t[keep], u[keep], y[keep], W)
    exact = control.frequency_response(g, W).complex
    np.testing.assert_allclose(np.abs(frf.g), np.abs(exact), rtol=0.01)
    np.testing.assert_allclose(np.angle(frf.g), np.angle(exact), atol=0.01)
    assert frf.coherence.min() > 0.99


def test_a_record_of_exactly_one_slow_period_is_enough() -> None:
    # periods=1: after the settling period the record holds N samples of one period,
    # whose first-to-last span is one sample short of it
    dt = 0.005
    n = int(round(2 * math.pi / W.min() / dt))
    t = np.arange(n) * dt
    u = sum(0.05 * np.sin(w * t) for w in W)
    frf = estimate_frf(t, u, 0.5 * u, W)
    np.testing.assert_allclose(frf.g, 0.5, rtol=1e-9)
    with pytest.raises(ParameterError, match="shorter than one period"):
        estimate_frf(t[: n // 2], u[: n // 2], u[: n // 2], W)


def test_tuner_meets_bandwidth_and_phase_margin_when_feasible() -> None:
    """A plant lagging > 30° at ω_c: both targets are reachable with gains ≥ 0 (python-control as oracle)."""
    g = _fopdt()
    frf = FrequencyResponse(W, control.frequency_response(g, W).complex, np.ones(W.size))
    tun = tune_pid(frf, 2.0, 60.0, 100.0)
    assert tun.exact and tun.kp > 0
    s = control.tf("s")
    c = tun.kp + tun.ki / s + tun.kd * s / (1 + s / 100.0)
    _, pm, _, wc = control.margin(c * g)
    assert wc == pytest.approx(2.0, rel=0.03)
    assert pm == pytest.approx(60.0, abs=2.0)


def test_the_loop_drawn_is_the_loop_the_margins_are_read_from() -> None:
    """The tuning's Bode chart (``loop_response``): python-control's C·G at the band's ends, where the
    estimate is the measured point, and crossing 0 dB where ``loop_margins`` says, with its margin."""
    g = _fopdt()
    frf = FrequencyResponse(W, control.frequency_response(g, W).complex, np.ones(W.size))
    tun = tune_pid(frf, 2.0, 60.0, 100.0)
    drawn = loop_response(frf, tun.kp, tun.ki, tun.kd, 100.0, points=400)
    w, gain, phase = (np.asarray(drawn[k]) for k in ("w_rad_s", "gain_db", "phase_deg"))
    assert w[0] == pytest.approx(W.min()) and w[-1] == pytest.approx(W.max()) and np.all(np.diff(w) > 0)
    s = control.tf("s")
    exact = control.frequency_response((tun.kp + tun.ki / s + tun.kd * s / (1 + s / 100.0)) * g, W[[0, -1]]).complex
    np.testing.assert_allclose(gain[[0, -1]], 20 * np.log10(np.abs(exact)), atol=1e-6)
    np.testing.assert_allclose(np.exp(1j * np.radians(phase[[0, -1]])), exact / np.abs(exact), atol=1e-6)
    i = int(np.nonzero((gain[:-1] >= 0.0) & (gain[1:] < 0.0))[0][0])
    wc = math.exp(np.interp(0.0, [gain[i + 1], gain[i]], np.log([w[i + 1], w[i]])))
    wc_m, pm_m = loop_margins(frf, tun.kp, tun.ki, tun.kd, 100.0)
    assert wc == pytest.approx(wc_m, rel=0.01)
    assert 180.0 + np.interp(math.log(wc), np.log(w), phase) == pytest.approx(pm_m, abs=0.5)


def test_tuner_puts_kp_on_zero_when_the_plant_barely_lags() -> None:
    """The thesis's finding: a PRV loop that is nearly static at 2 rad/s gives K_p = 0, K_i ≈ ω_c."""
    frf = FrequencyResponse(W, np.exp(-1j * 0.002 * W) / (1 + 0.01j * W), np.ones(W.size))
    tun = tune_pid(frf, 2.0, 60.0, 100.0)
    assert tun.kp == pytest.approx(0.0, abs=1e-6)
    assert tun.ki == pytest.approx(2.0, rel=0.02)
    assert tun.crossover_rad_s == pytest.approx(2.0, rel=0.01)
    assert tun.phase_margin_deg > 80 and not tun.exact
    assert "K_p < 0" in tun.note
    assert "try these gains in SC-4 before exercising with them" in tun.note  # docs/controllers.md


@pytest.mark.parametrize(("kw", "msg"), [({"side": "c"}, "side"), ({"pw_bar": 9.0}, "min. 1 bar and max. 8 bar"),
                                         ({"bandwidth_rad_s": 0.0}, "bandwidth"), ({"initial": (-1, 1, 0)}, "gains")])
def test_autotune_spec_refuses_bad_input(kw: dict[str, object], msg: str) -> None:
    with pytest.raises(ParameterError, match=msg):
        AutotuneSpec(**kw)  # type: ignore[arg-type]


def test_target_bandwidth_must_lie_inside_the_measured_band() -> None:
    frf = FrequencyResponse(W, np.ones(W.size, dtype=complex), np.ones(W.size))
    with pytest.raises(ParameterError, match="outside the measured"):
        tune_pid(frf, 50.0)


@pytest.mark.slow
@pytest.mark.parametrize("side", ["a", "b"])
def test_autotune_on_the_simulated_rig_reproduces_the_thesis_result(side: str) -> None:
    r = autotune_sim(AutotuneSpec(side=side))
    tun = r["tuning"]
    kp_t, ki_t, _ = THESIS_TUNED[side]
    assert tun.kp == pytest.approx(kp_t, abs=1e-6)  # the thesis: "every time zero K_p"
    assert tun.ki == pytest.approx(ki_t, rel=0.10)
    assert tun.crossover_rad_s == pytest.approx(2.0, rel=0.02)
    # the thesis's own autotuner gains cross over at ≈ 2 rad/s on the simulated plant too
    wc, pm = loop_margins(r["frf"], *THESIS_TUNED[side], 100.0)
    assert wc == pytest.approx(2.0, rel=0.05) and pm > 80
    steps = {s.label: s for s in r["steps"]}
    assert steps["tuned"].iae < steps["initial"].iae  # the testing stage: tuning improved the loop
