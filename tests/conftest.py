"""Shared fixtures: where the repository and the external test data are."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

# The tests compare the forked and the in-process paths and must take the
# forked one whatever else the machine is doing: the load rule
# (vision.forked.MIN_IDLE_CPUS) only decides whether forking pays.
from partinspect.vision import forked as _forked  # noqa: E402

_forked.MIN_IDLE_CPUS = float("-inf")


@pytest.fixture(scope="session")
def repo():
    return REPO


@pytest.fixture(scope="session")
def shared_data():
    if not SHARED_DATA.is_dir():
        pytest.skip(f"external test data not found at {SHARED_DATA} (see README: ../shared beside the clone)")
    return SHARED_DATA
