"""Each optional effect switches on a recognisable physical signature."""

from __future__ import annotations

import numpy as np

from app.engine.params import (
    DCVParams,
    HeatTransferEffect,
    LeakageEffect,
    PlantParams,
    PreslidingEffect,
    TubeEffect,
)
from app.engine.physics import plant as pl

SEALED = PlantParams(dcv=DCVParams(underlap_fill_v=0.0, underlap_exh_v=0.0))
HOLD = np.array([0.0, 0.0, 5.0, 5.0, 0.0, 0.0])
NOPROG = (np.zeros(0), np.zeros(0))


def _run(p: PlantParams, x: np.ndarray, cmd: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros(pl.NO)
    pl.advance(0.0, x, cmd, pl.build_kernel(p), n, *NOPROG, out)
    return x


def test_external_leakage_decays_a_closed_chamber() -> None:
    p = SEALED.with_effects(external_leakage=LeakageEffect(c=0.005))
    x = _run(p, pl.initial_state(p, 0.0, 6.0, 6.0), HOLD, 4000)
    pa, pb = pl.chamber_pressures(x, pl.build_kernel(p))
    assert pa < 5.0e5 and abs(pa - pb) < 1e3


def test_vane_leakage_equalises_the_chambers() -> None:
    p = SEALED.with_effects(vane_leakage=LeakageEffect(c=0.01))
    p_held = PlantParams(vane=p.vane.__class__(inertia=10.0), dcv=p.dcv, effects=p.effects)
    x = _run(p_held, pl.initial_state(p_held, 0.0, 5.0, 2.0), HOLD, 4000)
    pa, pb = pl.chamber_pressures(x, pl.build_kernel(p_held))
    assert abs(pa - pb) < 0.3e5


def test_heat_transfer_heats_on_fast_filling_then_relaxes() -> None:
    p = PlantParams().with_effects(heat_transfer=HeatTransferEffect(h_a=0.15))
    x = pl.initial_state(p, 0.0, 1.01325, 1.01325)
    cmd = np.array([6.0, 0.0, 0.0, 10.0, 0.0, 0.0])
    _run(p, x, cmd, 100)
    t_hot = x[pl.I_TCA]
    assert t_hot > p.t_atm + 20.0  # near-adiabatic compression of the charge
    _run(p, x, cmd, 20000)
    assert abs(x[pl.I_TCA] - p.t_atm) < 0.3 * (t_hot - p.t_atm)


def test_tube_slows_the_chamber_response() -> None:
    base = PlantParams(vane=PlantParams().vane.__class__(inertia=10.0))
    tube = base.with_effects(tube_dynamics=TubeEffect(length=3.0, diameter=0.002))
    cmd = np.array([4.0, 0.0, 0.0, 10.0, 0.0, 0.0])
    res = []
    for p in (base, tube):
        x = _run(p, pl.initial_state(p), cmd, 40)
        res.append(pl.chamber_pressures(x, pl.build_kernel(p))[0])
    assert res[1] < res[0] - 0.2e5


def test_presliding_gives_micro_motion_below_breakaway() -> None:
    p = PlantParams(vane=PlantParams().vane.__class__(inertia=2.5e-3)).with_effects(
        presliding_friction=PreslidingEffect(sigma0=150.0, sigma1=0.5))
    k = pl.build_kernel(p)
    x = np.zeros(pl.NX)
    drive = 0.6  # below the ≈1.3 N·m breakaway
    for _ in range(4000):
        pl._lugre_mech(x, drive, 3.0, k.fr, k.fr_j, k.inertia, -2.0, 2.0, k.sigma0, k.sigma1, k.h)
    assert 0.0 < x[pl.I_POS] < 0.02  # elastic bristle deflection, no sliding
    assert abs(x[pl.I_VEL]) < 1e-3
