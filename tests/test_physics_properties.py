"""Physics invariants as hypothesis properties."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from app.engine.constants import BAR, CP_AIR
from app.engine.params import PlantParams
from app.engine.physics import plant as pl
from app.engine.physics.flow import iso6358_flow, iso6358_signed, new_model_flow

P = st.floats(min_value=1.0, max_value=9.0)
FAST = settings(max_examples=60, deadline=None)


@FAST
@given(pu=P, r1=st.floats(0.0, 1.0), r2=st.floats(0.0, 1.0), b=st.floats(0.05, 0.6))
def test_iso_flow_is_monotonic_in_pressure_ratio(pu: float, r1: float, r2: float, b: float) -> None:
    lo, hi = sorted((r1, r2))
    q_lo = iso6358_flow(pu * BAR, lo * pu * BAR, 3.1e-8, b, 293.15)[0]
    q_hi = iso6358_flow(pu * BAR, hi * pu * BAR, 3.1e-8, b, 293.15)[0]
    assert q_lo >= q_hi - 1e-15
    assert q_hi >= 0.0


@FAST
@given(p=P, b=st.floats(0.05, 0.6))
def test_iso_flow_is_zero_at_equal_pressures(p: float, b: float) -> None:
    assert iso6358_signed(p * BAR, p * BAR, 3.1e-8, b, 293.15, 293.15)[0] == 0.0


@FAST
@given(p1=P, p2=P)
def test_signed_flow_is_antisymmetric(p1: float, p2: float) -> None:
    q12 = iso6358_signed(p1 * BAR, p2 * BAR, 3.1e-8, 0.26, 293.15, 293.15)[0]
    q21 = iso6358_signed(p2 * BAR, p1 * BAR, 3.1e-8, 0.26, 293.15, 293.15)[0]
    assert q12 == -q21
    assert np.sign(q12) == np.sign(p1 - p2)


@FAST
@given(pu=P, r1=st.floats(0.0, 1.0), r2=st.floats(0.0, 1.0), a=st.floats(0.15, 1.0), eps=st.floats(0.5, 1.8))
def test_new_model_flow_monotonic_and_zero_at_cracking_point(
    pu: float, r1: float, r2: float, a: float, eps: float
) -> None:
    lo, hi = sorted((r1, r2))
    g = 40.0 * CP_AIR

    def q(r: float) -> float:
        return new_model_flow(pu * BAR, r * pu * BAR, 1.0, 5.0, a, eps, g, 0.0, 1.0, 293.15)[0]

    assert q(lo) >= q(hi) - 1e-15
    q_crack = new_model_flow(pu * BAR, a * pu * BAR, 1.0, 5.0, a, eps, g, 0.0, 1.0, 293.15)[0]
    assert abs(q_crack) <= 1e-9 * abs(q(0.0))


@FAST
@given(pa=P, theta=st.floats(-2.0, 2.0))
def test_zero_pneumatic_torque_at_equal_pressures(pa: float, theta: float) -> None:
    p = PlantParams()
    k = pl.build_kernel(p)
    x = pl.initial_state(p, theta, pa, pa)
    a, b = pl.chamber_pressures(x, k)
    assert a == b or abs(a - b) < 1e-9 * a
    assert abs(a * k.area_a - b * k.area_b - k.p_atm * k.area_rod) < 1e-12


@FAST
@given(pa=P, pb=P, theta=st.floats(-2.0, 2.0), omega=st.floats(-3.0, 3.0))
def test_closed_chambers_conserve_gas_mass(pa: float, pb: float, theta: float, omega: float) -> None:
    from app.engine.params import DCVParams

    p = PlantParams(dcv=DCVParams(underlap_fill_v=0.0, underlap_exh_v=0.0))
    k = pl.build_kernel(p)
    x = pl.initial_state(p, theta, pa, pb)
    x[pl.I_VEL] = omega
    m0 = x[pl.I_M0 + pl.N_CA], x[pl.I_M0 + pl.N_CB]
    cmd = np.array([0.0, 0.0, 5.0, 5.0, 0.0, 0.0])
    out = np.zeros(pl.NO)
    pl.advance(0.0, x, cmd, k, 400, np.zeros(0), np.zeros(0), out)
    assert (x[pl.I_M0 + pl.N_CA], x[pl.I_M0 + pl.N_CB]) == m0  # exactly: masses are the states


@FAST
@given(omega=st.floats(0.05, 5.0), sign=st.sampled_from([-1.0, 1.0]), pw=st.floats(1.0, 6.0))
def test_friction_opposes_motion_and_never_reverses_it(omega: float, sign: float, pw: float) -> None:
    p = PlantParams()
    k = pl.build_kernel(p)
    x = np.zeros(pl.NX)
    x[pl.I_VEL] = sign * omega
    speeds = []
    for _ in range(2000):
        tf = pl._moreau_mech(x, 0.0, pw, k.fr, k.fr_j, k.inertia, -10.0, 10.0, 5e-4)
        assert tf * sign >= 0.0  # friction torque acts against the motion
        speeds.append(x[pl.I_VEL] * sign)
    s = np.array(speeds)
    assert np.all(s >= 0.0)  # never reverses
    assert np.all(np.diff(s) <= 1e-15)  # only slows down
    assert s[-1] == 0.0  # and comes to rest exactly


@FAST
@given(frac=st.floats(-0.99, 0.99), pw=st.floats(1.0, 6.0))
def test_static_friction_holds_below_breakaway(frac: float, pw: float) -> None:
    p = PlantParams()
    k = pl.build_kernel(p)
    ts_ccw = float(np.interp(pw, k.fr[0], k.fr[1]))
    ts_cw = float(np.interp(pw, k.fr[0], k.fr[5]))
    drive = frac * (ts_ccw if frac > 0 else ts_cw)
    x = np.zeros(pl.NX)
    for _ in range(200):
        pl._moreau_mech(x, drive, pw, k.fr, k.fr_j, k.inertia, -10.0, 10.0, 5e-4)
    assert x[pl.I_VEL] == 0.0 and x[pl.I_POS] == 0.0


def test_breakaway_above_static_friction() -> None:
    p = PlantParams()
    k = pl.build_kernel(p)
    x = np.zeros(pl.NX)
    ts = float(np.interp(3.0, k.fr[0], k.fr[1]))
    pl._moreau_mech(x, 1.05 * ts, 3.0, k.fr, k.fr_j, k.inertia, -10.0, 10.0, 5e-4)
    assert x[pl.I_VEL] > 0.0


def _dense_elimination(a: np.ndarray, b: np.ndarray) -> None:
    """Solve a·x = b in place (b ← x): Gaussian elimination without pivoting over every entry, zero
    multipliers skipped (the implicit step's solver before it kept to the network's pattern)."""
    n = b.shape[0]
    for c in range(n):
        for r in range(c + 1, n):
            m = a[r, c]
            if m != 0.0:
                m /= a[c, c]
                for j in range(c + 1, n):
                    a[r, j] -= m * a[c, j]
                b[r] -= m * b[c]
    for c in range(n - 1, -1, -1):
        s = b[c]
        for j in range(c + 1, n):
            s -= a[c, j] * b[j]
        b[c] = s / a[c, c]


@FAST
@given(p=st.lists(P, min_size=6, max_size=6), spools=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)),
       u=st.tuples(st.floats(0.0, 10.0), st.floats(0.0, 10.0)), tube=st.booleans(), vane=st.booleans(),
       leak=st.booleans(), dpdm=st.lists(st.floats(1e7, 1e11), min_size=6, max_size=6), h=st.floats(1e-4, 2e-3))
def test_the_network_solve_is_the_dense_elimination_to_the_bit(
    p: list[float], spools: tuple[float, float], u: tuple[float, float], tube: bool, vane: bool, leak: bool,
    dpdm: list[float], h: float,
) -> None:
    # the implicit step solves only the entries the network's edges can fill; a new edge outside
    # that pattern (or a changed order of operations) shows here as a different mass change
    k = pl.build_kernel(PlantParams())._replace(
        tube_on=tube, tube_vol=1e-5, tube_g=1e-9, vl_c=2e-9 if vane else 0.0, el_c=1e-9 if leak else 0.0)
    x = np.zeros(pl.NX)
    x[pl.I_XA], x[pl.I_XB] = spools
    x[pl.I_UA], x[pl.I_UB] = u
    x[pl.I_PS] = 7.0 * BAR
    f, jac = np.empty(pl.NN), np.empty((pl.NN, pl.NN))
    pl.pneumatic_flows(np.array(p) * BAR, np.full(pl.NN, 293.15), x, k, f, jac)
    d = np.array(dpdm)
    dm = np.empty(pl.NN)
    pl._solve_network(jac, d, h, f, dm)
    a = jac * (-h * d)[None, :]
    a[np.diag_indices(pl.NN)] += 1.0
    b = h * f
    _dense_elimination(a, b)
    assert np.array_equal(dm, b)
    assert np.isfinite(dm).all()


@FAST
@given(h_a=st.floats(1e-3, 1e5), dt0=st.floats(-80.0, 120.0), pa=P, h=st.sampled_from([1e-4, 5e-4, 1e-3]),
       side=st.sampled_from([-1.0, 1.0]))
def test_a_closed_chambers_gas_relaxes_to_the_wall_without_overshoot(h_a: float, dt0: float, pa: float, h: float,
                                                                     side: float) -> None:
    # at any h·A, however stiff against the substep (the diagnosis replays at up to 1 ms, and fits
    # h·A up to where the exchange is the isothermal baseline), the wall only ever pulls the gas
    # towards its own temperature: an explicit Euler step overshot where h·A·h > 2·m·c_v
    from app.engine.params import DCVParams, HeatTransferEffect

    p = PlantParams(dcv=DCVParams(underlap_fill_v=0.0, underlap_exh_v=0.0)
                    ).with_effects(heat_transfer=HeatTransferEffect())
    k = pl.build_kernel(p)._replace(heat_ha=h_a, h=h, inertia=1e12)  # the vane held: no work on the gas
    x = pl.initial_state(p, side * 0.95 * k.pos_max, pa, pa)  # one chamber near its dead volume
    x[pl.I_TCA] = x[pl.I_TCB] = p.t_atm + dt0
    cmd = np.array([0.0, 0.0, 5.0, 5.0, 0.0, 0.0])
    out = np.zeros(pl.NO)
    gaps = [[dt0, dt0]]
    for _ in range(50):
        pl.advance(0.0, x, cmd, k, 2, np.zeros(0), np.zeros(0), out)
        gaps.append([x[pl.I_TCA] - p.t_atm, x[pl.I_TCB] - p.t_atm])
    g = np.array(gaps) * np.sign(dt0)
    assert np.all(g >= -1e-9)  # never past the wall's temperature
    assert np.all(np.diff(g, axis=0) <= 1e-9)  # only ever nearer


def test_loops_compiled_without_reference_counting_give_the_counted_builds_bits() -> None:
    """``NO_REFCOUNT`` drops only Numba's bookkeeping (``app/engine/physics/jit.py``).

    The plant's step (every effect on, the user pushing, commands changing) and
    the gap diagnosis's log replay (vane leak, tubes and heat exchange on) are
    built again as they were before it, with reference counting, and must give
    the same state and pressures to the bit.
    """
    from numba import njit

    from app.engine.diagnosis.rotary import _replay_pneumatics
    from app.engine.diagnosis.suite import MAGNITUDES
    from app.engine.human import isotonic

    params = PlantParams().with_effects(**{name: big for name, (_small, big) in MAGNITUDES.items()})
    k = pl.build_kernel(params)
    program = isotonic(+1, repetitions=1)
    rng = np.random.default_rng(3)
    n = 4000
    cmds = np.column_stack([rng.uniform(0.0, 6.0, (n, 2)), rng.uniform(0.0, 10.0, (n, 2)), np.zeros((n, 2))])
    cmds = np.repeat(cmds[::200], 200, axis=0)  # held commands, as the engine writes them
    counted_step = njit(error_model="numpy")(pl.step.py_func)
    states = []
    for step in (pl.step, counted_step):
        x = pl.initial_state(params, 0.0, 3.0, 3.0)
        out, work, jac = np.zeros(pl.NO), np.empty(pl.NWORK), np.empty((pl.NN, pl.NN))
        trace = np.empty((n, pl.NX))
        for i in range(n):
            step(i * k.h, x, cmds[i], k, program.t, program.pos, out, work, jac)
            trace[i] = x
        states.append(trace)
    assert np.ptp(states[0][:, pl.I_POS]) > 0.1  # the vane moved: the mechanics ran
    assert np.array_equal(states[0], states[1])

    theta = states[0][::5, pl.I_POS].copy()
    omega = states[0][::5, pl.I_VEL].copy()
    samples = np.ascontiguousarray(cmds[::5, :4])
    pressures = []
    for replay in (_replay_pneumatics, njit(error_model="numpy")(_replay_pneumatics.py_func)):
        out = np.empty((theta.shape[0], 3))
        replay(k, samples, theta, omega, pl.initial_state(params, theta[0], 3.0, 3.0), 5, 1, out,
               np.empty(pl.NWORK), np.empty((pl.NN, pl.NN)), np.zeros(pl.NU))
        pressures.append(out)
    assert np.ptp(pressures[0][:, 0]) > 0.5  # the chambers filled and emptied
    assert np.array_equal(pressures[0], pressures[1])
