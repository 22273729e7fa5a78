"""Fixtures of tests/cad: the sample parts and the NIST STEP files, loaded once."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
STEP_DIR = DATA / "step"
EXAMPLES = REPO / "examples"

# Files whose load + inventory takes over a second or two each (measured on
# the 2-core CI machine): tested in their own slow parametrisations.
BIG_NIST = {"nist_ctc_02_asme1_ap242-e2.stp", "nist_ctc_04_asme1_ap242-e1.stp", "nist_ftc_10_asme1_ap242-e2.stp"}


def nist_files():
    """pytest params over every NIST STEP file; the big ones marked slow."""
    return [
        pytest.param(p.name, id=p.stem, marks=[pytest.mark.slow] if p.name in BIG_NIST else [])
        for p in sorted(STEP_DIR.glob("*.stp"))
    ]


def load_example_module(name):
    """examples/<name>/make_part.py as a module (its parameters and build())."""
    path = EXAMPLES / name / "make_part.py"
    spec = importlib.util.spec_from_file_location(f"make_part_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Cache:
    """Load each STEP file (and make its inventory) at most once per session."""

    def __init__(self):
        self.shapes, self.inventories = {}, {}

    def shape(self, path):
        from partinspect.cad.step import load_step

        path = Path(path)
        if path not in self.shapes:
            self.shapes[path] = load_step(path)
        return self.shapes[path]

    def inventory(self, path):
        from partinspect.cad.features import inventory

        path = Path(path)
        if path not in self.inventories:
            self.inventories[path] = inventory(self.shape(path))
        return self.inventories[path]


@pytest.fixture(scope="session")
def cad_cache():
    return _Cache()


@pytest.fixture(scope="session")
def step_dir():
    return STEP_DIR


@pytest.fixture(scope="session")
def plate_module():
    return load_example_module("plate")


@pytest.fixture(scope="session")
def bracket_module():
    return load_example_module("bracket")


@pytest.fixture(scope="session")
def plate_path():
    return EXAMPLES / "plate" / "part.step"


@pytest.fixture(scope="session")
def bracket_path():
    return EXAMPLES / "bracket" / "part.step"


@pytest.fixture(scope="module", params=["plate", "bracket"])
def scene(request):
    """(inventory, true pose, visible ids) of a sample part at the renderer's default pose."""
    import json

    import numpy as np

    from partinspect.cad.features import inventory
    from partinspect.cad.step import load_step
    from partinspect.poses import default_pose
    from partinspect.simulate.rig import default_rig

    shape = load_step(EXAMPLES / request.param / "part.step")
    inv = inventory(shape)
    T = default_pose(shape, default_rig())
    truth = json.loads((EXAMPLES / request.param / "truth.json").read_text())
    # the rendered truth was made at the same default pose; its visibility is the renderer's
    assert np.allclose(T, truth["part_to_camera"], atol=1e-6)
    ids = [f["id"] for f in truth["features"] if f["visible_both"]]
    return request.param, inv, T, ids
