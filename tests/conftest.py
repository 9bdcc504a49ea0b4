"""Shared test helpers."""
import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
FULL = os.environ.get("SAFESYSID_FULL") == "1"


def n_trials(small, full):
    """Monte-Carlo sample size: small in CI, full with SAFESYSID_FULL=1."""
    return full if FULL else small


def shared_path(*parts):
    """A file under ../shared, or skip the test when the shared data is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path
