"""Fixtures shared by the tests (plain helpers are in helpers.py). A module that defines a
fixture of the same name uses its own."""

import os
import sys
from pathlib import Path

# One BLAS/OpenMP/numba thread per xdist worker: CI has 2 cores and runs 2 workers, and a second
# thread in each only oversubscribes them (serial runs keep the libraries' defaults). Set before
# numpy or Drake is imported (helpers.py below) and inherited by the tests' subprocesses.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import pytest

# The experiment scripts (experiments/, not installed) import as top-level modules, as when run
# with `python experiments/NAME.py`.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

from helpers import FULL, n_trials, params_with_spheres, shared_path  # noqa: F401 (test_gap.py still imports them from here)


@pytest.fixture(autouse=True)
def _outputs_match_their_schemas(request):
    """Every summary.json, diagnosis.json and aggregate.json a test writes under its tmp_path must
    match its published JSON Schema (docs/schemas)."""
    yield
    folder = request.node.funcargs.get("tmp_path") if hasattr(request.node, "funcargs") else None
    if folder is not None:
        from helpers import validate_outputs

        validate_outputs(folder)


@pytest.fixture(scope="module")
def robot():
    """The Gen3 model with the scenarios' Coulomb smoothing (0.01 rad/s)."""
    from safesysid.systems.model.robot_model import load_robot

    return load_robot(coulomb_smoothing=0.01)


@pytest.fixture(scope="module")
def dumbbells():
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.model.robot_model import MODELS_DIR

    return load_dumbbells(MODELS_DIR / "dumbbells.yaml")
