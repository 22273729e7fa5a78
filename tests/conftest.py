"""Shared fixtures: where the repository and the external test data are."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# The real external data (NIST STEP files, OpenCV's stereo chessboards),
# with their sources and licences in tests/data/SOURCES.md.
TEST_DATA = REPO / "tests" / "data"

# The tests compare the forked and the in-process paths and must take the
# forked one whatever else the machine is doing: the load rule
# (vision.forked.MIN_IDLE_CPUS) only decides whether forking pays.
from partinspect.vision import forked as _forked  # noqa: E402

_forked.MIN_IDLE_CPUS = float("-inf")


@pytest.fixture(scope="session", autouse=True)
def cad_cache(tmp_path_factory):
    """A CAD model cache of this session's own, for the runs in-process and the CLI's child processes."""
    import os

    folder = tmp_path_factory.mktemp("cad-cache")
    old = os.environ.get("PARTINSPECT_CACHE")
    os.environ["PARTINSPECT_CACHE"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("PARTINSPECT_CACHE", None)
    else:
        os.environ["PARTINSPECT_CACHE"] = old


@pytest.fixture(scope="session")
def repo():
    return REPO


@pytest.fixture(scope="session")
def test_data():
    return TEST_DATA
