"""Fixtures shared by the tests (plain helpers are in helpers.py). A module that defines a
fixture of the same name uses its own."""

import pytest
from helpers import FULL, n_trials, params_with_spheres, shared_path  # noqa: F401 (test_gap.py still imports them from here)


@pytest.fixture(scope="module")
def robot():
    """The Gen3 model with the scenarios' Coulomb smoothing (0.01 rad/s)."""
    from safesysid.systems.robot_model import load_robot

    return load_robot(coulomb_smoothing=0.01)


@pytest.fixture(scope="module")
def dumbbells():
    from safesysid.systems.payload import load_dumbbells
    from safesysid.systems.robot_model import MODELS_DIR

    return load_dumbbells(MODELS_DIR / "dumbbells.yaml")
