"""Directional-valve identification (thesis 3.2.3, 4.1): CPR maps, new flow model, validation.

The simulator's ``model="new"`` valve is Eq 3.10–3.11 with maps known to the
test, so the fit can be checked against the truth; the default ISO valve is
the "real" plant the thesis's comparison of flow models is repeated on.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from app.cli import main
from app.engine import tables
from app.engine.constants import BAR, R_AIR
from app.engine.ident import dcv
from app.engine.ident.dcv import (
    CPRProcedure,
    DCVInputs,
    bobrow_flow,
    improved_flow,
    new_flow,
    standard_flow,
)
from app.engine.ident.runner import DCV_RATE_HZ, identify_dcv_sim, simulate
from app.engine.params import DCVParams, ParameterError, PlantParams, conductance_si
from app.engine.physics.flow import interp2_clip, interp_clip, new_model_flow
from app.engine.physics.plant import derive_new_model_maps_cached

P_ATM = 1.01325 * BAR
T = 293.15


# --------------------------------------------------------------------------- inputs and guards


@pytest.mark.parametrize(("kw", "msg"), [
    ({"chamber_volume_cm3": 0.0}, "Please enter a reasonable value!"),
    ({"ps_bar": (2.0, 9.0)}, "Working pressure can be min. 1 bar and max. 8 bar!"),
    ({"u_fill": (0.0, 11.0)}, "0–10 V"),
    ({"band_exh": (5.9, 4.5)}, "need 0 ≤ low < high"),
    ({"polytropic_n": 1.6}, "polytropic_n"),
])
def test_dcv_inputs_refused_with_a_specific_message(kw: dict[str, Any], msg: str) -> None:
    with pytest.raises(ParameterError, match=msg):
        DCVInputs(**kw)


def test_cpr_refuses_a_supply_sensor_that_is_not_at_the_valve() -> None:
    """On the interaction rig PS-0 reads the compressor (8 bar): the CPR set-up
    (Figure 3.10) needs it at the DCV's supply port, so the run fails, vented."""
    proc = CPRProcedure(DCVInputs(), cases=[("filling", 4.0, 3.0)])
    run = simulate(proc, PlantParams.linear_rig("C3"), DCV_RATE_HZ)
    assert run.summary.state == "failed"
    assert "PS-0 reads 8.00 bar" in proc.progress.message
    assert proc.data.tests == []


def test_cli_refuses_an_unknown_valve_model(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["identify", "dcv", "--dcv-model", "bogus"])
    assert e.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


# --------------------------------------------------------------------------- model invariants


pressures = st.floats(1.0, 8.0)


@settings(max_examples=200, deadline=None)
@given(ps=pressures, a=st.floats(0.15, 1.0), eps=st.floats(0.3, 2.0), p1=pressures, p2=pressures,
       mode=st.sampled_from(["filling", "exhausting"]))
def test_new_model_inflow_falls_as_the_chamber_pressure_rises(ps: float, a: float, eps: float, p1: float,
                                                              p2: float, mode: str) -> None:
    lo, hi = sorted((p1, p2))
    q = new_flow(mode, np.array([lo, hi]) * BAR, ps * BAR, P_ATM, a, eps, 1e-3, 1.0, T)
    assert q[1] <= q[0] + 1e-15


@settings(max_examples=200, deadline=None)
@given(ps=pressures, p1=pressures, p2=pressures, b=st.floats(0.0, 0.9), eps=st.floats(0.3, 2.0),
       mode=st.sampled_from(["filling", "exhausting"]))
def test_literature_models_monotonic_and_zero_at_equal_pressures(ps: float, p1: float, p2: float, b: float,
                                                                eps: float, mode: str) -> None:
    lo, hi = sorted((p1, p2))
    p = np.array([lo, hi]) * BAR
    for q in (standard_flow(mode, p, ps * BAR, P_ATM, 1e-6, T),
              improved_flow(mode, p, ps * BAR, P_ATM, 1e-6, b, eps, T),
              bobrow_flow(mode, p, ps * BAR, P_ATM, 4.0, (1e-3, 0.0), T)):
        assert q[1] <= q[0] + 1e-15
    at_rest = np.array([ps * BAR if mode == "filling" else P_ATM])
    assert standard_flow(mode, at_rest, ps * BAR, P_ATM, 1e-6, T)[0] == pytest.approx(0.0, abs=1e-12)


def test_new_model_flow_stops_at_the_cracking_pressure_ratio() -> None:
    """The point of Eq 3.10–3.11 (Figure 3.9): flow ends at P_d = a·P_u, not at P_d = P_u."""
    ps, a = 5.0 * BAR, 0.6
    assert new_flow("filling", np.array([a * ps]), ps, P_ATM, a, 0.8, 1e-3, 1.0, T)[0] == 0.0
    assert new_flow("filling", np.array([a * ps - 1e4]), ps, P_ATM, a, 0.8, 1e-3, 1.0, T)[0] > 0.0
    assert new_flow("filling", np.array([a * ps + 1e4]), ps, P_ATM, a, 0.8, 1e-3, 1.0, T)[0] < 0.0


def test_alpha1_alpha2_are_not_separable_at_one_signal() -> None:
    """Why we report g = α1·u + α2·u²: the two Jacobian columns are proportional."""
    p = np.linspace(1.2, 4.5, 50) * BAR
    u = 4.9
    s = new_flow("filling", p, 5 * BAR, P_ATM, 0.99, 0.7, 1.0, 1.0, T)
    jac = np.column_stack([u * s, u * u * s])  # ∂ṁ/∂α1, ∂ṁ/∂α2
    sv = np.linalg.svd(jac, compute_uv=False)
    assert sv[1] / sv[0] < 1e-12


def test_flow_fit_recovers_known_parameters_from_exact_data() -> None:
    """Round trip without the rig: noise-free transient of a known model → ε, g."""
    eps, g, a, ps = 0.8, 0.02, 0.95, 5.0 * BAR
    inp = DCVInputs()
    c = R_AIR * T / inp.volume_m3  # Ṗ = c·ṁ (Eq 4.1, isothermal)
    dt = 0.005
    p = [P_ATM]
    for _ in range(3000):
        q = new_flow("filling", np.array([p[-1]]), ps, P_ATM, a, eps, g, 1.0, T)[0]
        p.append(p[-1] + dt * c * q)
    pa = np.array(p)
    m = np.gradient(pa, dt) / c
    fit = dcv.DCVFlowEstimator._fit_signal("filling", 5.0, a, pa, m, np.full(pa.size, ps), P_ATM, T)
    assert fit.eps == pytest.approx(eps, rel=0.02)
    assert fit.g == pytest.approx(g, rel=0.15)  # g trades off against ε: |d|^ε spans decades
    assert fit.r2 > 0.999


# --------------------------------------------------------------------------- on the simulator


@pytest.fixture(scope="module")
def new_valve() -> Any:
    """The full thesis procedure on the simulated C3 set-up with a known new-model valve."""
    est, run, _, cases = identify_dcv_sim("new", seed=0)
    p = run.params
    d = p.dcv
    maps = derive_new_model_maps_cached(conductance_si(d.c), d.b, d.underlap_fill_v, d.underlap_exh_v,
                                        p.p_atm, p.t_atm, d.null_leak_fraction, d.null_width_v)
    return est, run, cases, maps


def _true_inflow(maps: Any, u: float, ps_meas: np.ndarray, ps_bar: float, p: np.ndarray) -> np.ndarray:
    """The simulator's own Eq 3.10–3.11 (kernel branch chosen by u, as in plant.pneumatic_flows)."""
    fill = u < maps.u_switch
    a = interp2_clip(u, ps_bar, maps.u_grid, maps.ps_grid_bar, maps.a_fill if fill else maps.a_exh)
    eps = interp_clip(u, maps.u_grid, maps.eps_fill if fill else maps.eps_exh)
    g = interp_clip(u, maps.u_grid, maps.g_fill if fill else maps.g_exh)
    k = float(np.polyval(tables.K_FILL_POLY if fill else tables.K_EXH_POLY, ps_bar))
    out = np.empty(p.size)
    for i, (pi, si) in enumerate(zip(p, ps_meas, strict=True)):
        if fill:
            out[i] = new_model_flow(si, pi, 1.0, ps_bar, a, eps, g, 0.0, k, T)[0]
        else:
            out[i] = -new_model_flow(pi, P_ATM, 1.0, ps_bar, a, eps, g, 0.0, k, T)[0]
    return out


@pytest.mark.slow
def test_cpr_maps_match_the_simulated_valve(new_valve: Any) -> None:
    _, run, _, maps = new_valve
    data = run.procedure.data
    assert len(data.tests) == data.inputs.n_tests == 6 * (60 + 61)
    # the exhaust branch's ε > 1 closes the last gap algebraically, which the end criterion reads
    # conservatively: 30 tests at 5.2–5.5 V run to the cap (their a is still within 0.011, below)
    assert all(t.settled or t.p_bar.size * t.dt >= dcv.MAX_TEST_S - 0.01 for t in data.tests)
    worst = 0.0
    for t in data.tests:
        truth_map = maps.a_fill if t.mode == "filling" else maps.a_exh
        fill_branch = t.u < maps.u_switch
        if t.mode == "filling" and not fill_branch:
            # equilibrium reached through the exhaust branch: P = P_atm / a_exh
            truth = P_ATM / interp2_clip(t.u, t.ps_mean, maps.u_grid, maps.ps_grid_bar, maps.a_exh) / (t.ps_mean * BAR)
        elif t.mode == "exhausting" and fill_branch:
            truth = P_ATM / (interp2_clip(t.u, t.ps_mean, maps.u_grid, maps.ps_grid_bar, maps.a_fill) * t.ps_mean * BAR)
        else:
            truth = interp2_clip(t.u, t.ps_mean, maps.u_grid, maps.ps_grid_bar, truth_map)
        worst = max(worst, abs(t.a - min(truth, 1.0)))
    # worst: 5.5 V filling at 4 bar (0.024), whose tiny flow through the exhaust branch moves
    # P_a by 0.1 bar over minutes, below what 2 s of noisy samples resolve
    assert worst < 0.03
    # thesis 4.1.1: a spans 0.145–1 (P_atm / 7 bar is the floor)
    a_all = np.array([t.a for t in data.tests])
    assert a_all.min() == pytest.approx(P_ATM / (7 * BAR), abs=0.01)


@pytest.mark.slow
def test_flow_fit_recovers_the_simulated_new_model(new_valve: Any) -> None:
    est, run, _, maps = new_valve
    data = run.procedure.data
    checked = 0
    for mode in ("filling", "exhausting"):
        mm = est.params_[mode]
        for s in mm.signals:
            fill_branch = s.u < maps.u_switch
            if fill_branch != (mode == "filling"):
                continue  # the simulated valve's other branch carries this test's flow
            i = int(round(s.u * 10))
            eps_true = (maps.eps_fill if fill_branch else maps.eps_exh)[i]
            assert s.eps == pytest.approx(eps_true, rel=0.10), (mode, s.u)
            test = next(t for t in data.select(mode, 5.0) if abs(t.u - s.u) < 1e-9)
            p, ps, _ = dcv.measured_flow(test, data.inputs)
            fitted = mm.flow("new", p, s.u, test.ps_mean, est.p_atm_, T, ps)
            truth = _true_inflow(maps, s.u, ps, test.ps_mean, p)
            rel = float(np.linalg.norm(fitted - truth) / np.linalg.norm(truth))
            assert rel < 0.10, (mode, s.u, rel)
            checked += 1
    assert checked >= 10
    # k(P_s)/k(5 bar) of Eq 4.2 / 4.3 (P_s = 3–7 bar; at 2 bar the exhaust swings are small)
    for mode, poly in (("filling", tables.K_FILL_POLY), ("exhausting", tables.K_EXH_POLY)):
        mm = est.params_[mode]
        truth = np.polyval(poly, mm.k_ps) / np.polyval(poly, 5.0)
        sel = mm.k_ps >= 3.0
        np.testing.assert_allclose(mm.k_val[sel], truth[sel], rtol=0.07)
    # Table 4.1's "-": no flow left to fit where the filling port has closed
    assert est.params_["filling"].skipped == [5.6, 5.7]


@pytest.mark.slow
def test_new_model_predicts_held_out_points_better_than_the_literature(new_valve: Any) -> None:
    """Held out (u, P_s) off both grids: the new model's mean error is under half the best
    literature model's; at the thesis's validation points (Figures 4.6–4.11) every error is
    inside the thesis's own range on its rig (0.004–8.8 %, 4.1.3) and the mean is below 1 %.

    Between the signals the simulated valve interpolates g and ε as separate lookups (the
    thesis's Simulink model) where the estimator interpolates the flow at 1 bar
    (``ModeModel.signal_params``), and at 5.15 V the simulated valve switches branch
    (u_switch = 5.2 V), so no test shows the filling branch it uses there: the held-out mean
    is ≈ 7 % where the literature models reach 15–21 %."""
    _, _, cases, _ = new_valve
    held = cases[len(dcv.THESIS_VALIDATION):]
    assert len(held) == len(dcv.HELD_OUT)
    mean = {m: float(np.mean([c.mape_pct[m] for c in held])) for m in dcv.MODELS}
    for m in ("standard", "improved", "bobrow"):
        assert mean["new"] < 0.5 * mean[m], mean
    thesis = cases[: len(dcv.THESIS_VALIDATION)]
    assert max(c.mape_pct["new"] for c in thesis) < 8.8
    assert float(np.mean([c.mape_pct["new"] for c in thesis])) < 1.0
    assert all(math.isfinite(c.final_pct["new"]) for c in cases)


@pytest.mark.slow
def test_identify_dcv_cli_on_the_iso_valve_writes_plots(tmp_path: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """The thesis's comparison on the "real" (ISO 6358, underlapped) valve, through the CLI."""
    import json

    assert main(["identify", "dcv", "--dcv-model", "iso", "--out", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    held = out["validation"]["mean_mape_pct"]["held_out"]
    assert held["new"] < held["standard"] and held["new"] < held["improved"] and held["new"] < held["bobrow"]
    assert len(out["fit"]["filling"]["table_4_1"]) >= 8
    for name in ("cpr.png", "flow_fit.png", "validation_thesis.png", "validation_held_out.png", "dcv.json"):
        assert (tmp_path / name).stat().st_size > 1000


# --------------------------------------------------------------------------- end of a CPR test (Ṗ_a ≈ 0)


@settings(max_examples=80, deadline=None)
@given(shape=st.sampled_from(("exponential", "algebraic")), tau=st.floats(0.2, 80.0), k=st.floats(0.5, 4.0),
       dp=st.floats(0.3, 5.0), sign=st.sampled_from((-1.0, 1.0)), t_end=st.floats(2.0, 300.0),
       seed=st.integers(0, 2**16))
# found by a random draw: 2 s of a slow algebraic creep, each window step inside the noise band
# but their sum outside it, had been called settled with 0.31 bar to go
@example(shape="algebraic", tau=54.0, k=0.5, dp=0.3125, sign=-1.0, t_end=2.0, seed=0)
def test_remaining_change_never_calls_an_unfinished_approach_settled(
        shape: str, tau: float, k: float, dp: float, sign: float, t_end: float, seed: int) -> None:
    """A CPR step of ≥ 0.3 bar closing as P∞ − Δp·e^(−t/τ) (τ from 0.2 to 80 s) or algebraically,
    P∞ − Δp·(τ/(t + τ))^k (a valve with ε > 1), + 0.003 bar noise at 200 Hz: never called settled
    while more than twice the tolerance is still to come; an exponential's projection is an upper
    bound of what is truly left, to within the noise."""
    dt = 0.005
    t = np.arange(1, int(t_end / dt) + 1) * dt
    rng = np.random.default_rng(seed)
    gap = dp * (np.exp(-t / tau) if shape == "exponential" else (tau / (t + tau)) ** k)
    p = 4.0 - sign * gap + rng.normal(0.0, 0.003, t.size)
    est = dcv.remaining_change(p, dt)
    truth = float(gap[-1])
    if shape == "exponential":
        assert est >= 0.8 * truth - dcv.SETTLED_REMAINING_BAR, (truth, est)
    if est < dcv.SETTLED_REMAINING_BAR:
        assert truth < 2 * dcv.SETTLED_REMAINING_BAR, (truth, est)


def test_remaining_change_waits_for_a_creep_that_a_flat_slope_would_call_settled() -> None:
    """The old criterion (2 s slope < 0.002 bar/s) ends a τ = 60 s approach with 0.12 bar to go."""
    dt, tau, dp = 0.005, 60.0, 3.0
    t_slope = tau * math.log(dp / (tau * 0.002))  # when the slope falls to 0.002 bar/s
    t = np.arange(1, int(t_slope / dt) + 1) * dt
    p = 4.0 - dp * np.exp(-t / tau)
    assert dp * math.exp(-t[-1] / tau) > 0.1
    # noise-free, the exponential reading is exact; the algebraic one only adds to it
    assert dcv.remaining_change(p, dt) >= 0.99 * dp * math.exp(-t[-1] / tau)
    assert dcv.remaining_change(np.full(400, 2.0), dt) == 0.0
    assert dcv.remaining_change(np.linspace(1.0, 2.0, 400), dt) == math.inf  # no convergence seen


# --------------------------------------------------------------------------- null zone (thesis 2.1, 3.2.4)


@settings(max_examples=60, deadline=None)
@given(u=st.floats(0.0, 10.0), s0=st.floats(0.01, 1.0), w=st.floats(0.05, 3.0))
def test_null_zone_scales_both_paths_alike(u: float, s0: float, w: float) -> None:
    """The attenuation multiplies fill and exhaust openings by one factor in (0, 1], largest far from 5 V."""
    from app.engine.physics.dcv_maps import openings
    from app.engine.physics.flow import null_scale

    f0, e0 = openings(u, 0.7, 0.3)
    f, e = openings(u, 0.7, 0.3, s0, w)
    s = null_scale(u, s0, w)
    assert s0 - 1e-12 <= s <= 1.0
    assert f == pytest.approx(s * f0) and e == pytest.approx(s * e0)
    assert null_scale(5.0 + 1.01 * w, s0, w) == 1.0
    assert null_scale(u, s0, w) <= null_scale(5.0 + (abs(u - 5.0) + 0.1) * (1 if u >= 5 else -1), s0, w) + 1e-12


def test_null_zone_leaves_the_cpr_maps_unchanged() -> None:
    """CPR is a ratio of the two paths' flows, so a common scale must not move it (it only slows the approach)."""
    from app.engine.physics.dcv_maps import derive_new_model_maps

    d = DCVParams()
    assert d.null_leak_fraction < 1.0 and d.null_width_v > 0.0  # the default valve has its null zone
    args = (conductance_si(d.c), d.b, d.underlap_fill_v, d.underlap_exh_v, 101325.0, 293.15)
    plain = derive_new_model_maps(*args)
    nz = derive_new_model_maps(*args, d.null_leak_fraction, d.null_width_v)
    assert np.allclose(nz.a_fill, plain.a_fill, atol=1e-4) and np.allclose(nz.a_exh, plain.a_exh, atol=1e-4)
    i5 = int(np.argmin(np.abs(nz.u_grid - 5.0)))
    assert nz.g_fill[i5] == pytest.approx(d.null_leak_fraction * plain.g_fill[i5], rel=1e-6)
