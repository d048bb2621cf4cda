"""Shared fixtures."""

from __future__ import annotations

import numpy as np
import pytest

from app.engine.params import DCVParams, PlantParams


@pytest.fixture(scope="session")
def params() -> PlantParams:
    """Default rotary rig (SPEC §1)."""
    return PlantParams()


@pytest.fixture(scope="session")
def sealed() -> PlantParams:
    """A rig whose DCVs close perfectly at 5 V (no underlap leakage)."""
    return PlantParams(dcv=DCVParams(underlap_fill_v=0.0, underlap_exh_v=0.0))


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
