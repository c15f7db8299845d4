"""Fixtures of the env tests (helpers live in env_helpers.py)."""

import pytest
from error_helpers import warmed_up
from highway_env.vehicle.behavior import IDMVehicle

IDM_CONSTANTS = {
    name: getattr(IDMVehicle, name)
    for name in ("COMFORT_ACC_MAX", "COMFORT_ACC_MIN", "DISTANCE_WANTED")
}


@pytest.fixture(autouse=True)
def pristine_idm_constants(monkeypatch):
    """Every test starts from highway-env's IDM constants and leaves them as it found them."""
    for name, value in IDM_CONSTANTS.items():
        monkeypatch.setattr(IDMVehicle, name, value)


@pytest.fixture
def env_and_twin():
    """Two envs built and driven identically: one gets the bad input, the other does not."""
    return warmed_up(), warmed_up()
