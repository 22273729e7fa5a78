"""Fixtures of the simulator tests: the sample parts, loaded and rendered once per session."""

import pytest

from tests.simulate.scenes import Part

_PARTS = {}



@pytest.fixture(scope="session")
def parts():
    """``parts(name)`` -> the cached :class:`Part`."""

    def get(name):
        if name not in _PARTS:
            _PARTS[name] = Part(name)
        return _PARTS[name]

    return get


@pytest.fixture(scope="session")
def plate(parts):
    return parts("plate")


@pytest.fixture(scope="session")
def bracket(parts):
    return parts("bracket")
