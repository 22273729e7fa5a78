import json

import pytest

from tests.cad.conftest import EXAMPLES


@pytest.fixture(scope="module")
def plate():
    """The sample plate's inventory, its default pose and the ids of the features both cameras see."""
    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.poses import default_pose
    from partinspect.simulate.rig import default_rig

    shape = load_step(EXAMPLES / "plate" / "part.step")
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    ids = [f["id"] for f in json.loads((EXAMPLES / "plate" / "truth.json").read_text())["features"] if f["visible_both"]]
    return inv, T, ids
