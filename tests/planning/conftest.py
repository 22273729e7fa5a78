"""Fixtures of the planning tests: the sample plate loaded once, a small rig, its spec characteristics."""

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
SIZE = (816, 683)  # the default rig's field of view at a third of its resolution


@pytest.fixture(scope="session")
def plate():
    from tests.simulate.scenes import Part

    return Part("plate")


@pytest.fixture(scope="session")
def rig():
    from partinspect.simulate.rig import default_rig

    return default_rig(SIZE)


@pytest.fixture(scope="session")
def spec_characteristics(plate):
    """The five characteristics plate/part.tol.yaml tolerances (no general ones: fast)."""
    from partinspect.tolerances.resolve import resolve_spec
    from partinspect.tolerances.spec import load_spec

    path = REPO / "examples" / "plate" / "part.tol.yaml"
    return list(resolve_spec(load_spec(path), plate.inv, path).characteristics)


def view_pose(plate, rig, elevation, azimuth, roll):
    """The plate's bounding-box centre at the fixation point, seen from (elevation, azimuth, roll) degrees."""
    from partinspect.poses import bounds_of, view_rotation
    from partinspect.poses import fixation_point

    b = bounds_of(plate.shape)
    R = view_rotation(*np.deg2rad([elevation, azimuth, roll]))
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = fixation_point(rig) - R @ (0.5 * (b[0] + b[1]))
    return P
