"""Parameter validation and golden values from the thesis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.engine import tables
from app.engine.params import (
    LinearCylinder,
    ParameterError,
    PlantParams,
    PRVParams,
    RotaryFriction,
    SupplyParams,
    VaneCylinder,
    check_working_pressure,
)


def test_torque_per_bar_matches_eq_3_4() -> None:
    # SPEC §1 / thesis 3.2.1: A_v = 15·57 mm², r = (31 + 15)/2 mm → ≈ 1.97 N·m/bar
    v = VaneCylinder()
    assert v.vane_area == pytest.approx(8.55e-4)
    assert v.radius == pytest.approx(0.023)
    assert v.torque_per_pa * 1e5 == pytest.approx(1.9665, abs=1e-4)


@pytest.mark.parametrize("i", range(6))
def test_table_4_2_interpolation_at_table_points(i: int) -> None:
    f = RotaryFriction()
    ccw, cw = f.at(float(tables.FRICTION_PW_BAR[i]))
    assert (ccw.fs, ccw.fc, ccw.vs, ccw.b) == pytest.approx(
        (tables.FRICTION_TS_CCW[i], tables.FRICTION_TC_CCW[i], tables.FRICTION_WS_CCW[i], tables.FRICTION_B_CCW[i]))
    assert (cw.fs, cw.fc, cw.vs, cw.b) == pytest.approx(
        (tables.FRICTION_TS_CW[i], tables.FRICTION_TC_CW[i], tables.FRICTION_WS_CW[i], tables.FRICTION_B_CW[i]))


def test_table_4_2_interpolates_between_points_and_clips() -> None:
    f = RotaryFriction()
    ccw, _ = f.at(3.5)
    assert ccw.fs == pytest.approx(0.5 * (1.296 + 1.334))
    assert f.at(0.5)[0].fs == pytest.approx(1.196)
    assert f.at(9.0)[0].fs == pytest.approx(1.320)


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        (lambda: VaneCylinder(rom_deg=400.0), "rom_deg = 400.0 deg is outside its allowed range (0, 360]"),
        (lambda: VaneCylinder(rom_deg=0.0), "rom_deg"),
        (lambda: VaneCylinder(dead_volume_a=-1e-6), "dead_volume_a"),
        (lambda: VaneCylinder(h=float("nan")), "h = nan"),
        (lambda: SupplyParams(p_supply_bar=-2.0), "p_supply_bar"),
        (lambda: PRVParams(deadband_off_bar=0.5), "deadband_off_bar"),
        (lambda: PlantParams(p_atm=-1.0), "p_atm"),
        (lambda: PlantParams(substep_hz=500.0), "substep_hz"),
        (lambda: LinearCylinder.catalogue("C1").__class__(
            "x", 0.02, 0.03, 0.2, LinearCylinder.catalogue("C1").extension,
            LinearCylinder.catalogue("C1").retraction), "rod"),
    ],
)
def test_impossible_parameters_are_rejected_with_name_and_range(make: object, fragment: str) -> None:
    with pytest.raises(ParameterError) as ei:
        make()  # type: ignore[operator]
    assert fragment in str(ei.value)


@pytest.mark.parametrize("pw", [0.5, 8.5, 9.0, float("nan")])
def test_working_pressure_rule_uses_the_gui_message(pw: float) -> None:
    with pytest.raises(ParameterError, match=r"^Working pressure can be min\. 1 bar and max\. 8 bar!$"):
        check_working_pressure(pw)


def test_working_pressure_bounds_accepted() -> None:
    check_working_pressure(1.0)
    check_working_pressure(8.0)


def test_unknown_effect_is_rejected() -> None:
    with pytest.raises(ParameterError, match="unknown effect 'gremlins'"):
        PlantParams().with_effects(gremlins=None)


def test_end_stops_are_symmetric_about_neutral() -> None:
    v = VaneCylinder()
    assert v.theta_max == pytest.approx(math.radians(135.0))
    assert v.theta_min == -v.theta_max
    assert np.isfinite(v.torque_per_pa)
