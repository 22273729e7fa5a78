"""The CAD model cache: the same model from the cache as from the file, and never a stale or broken one."""

import shutil

import numpy as np
import pytest

from partinspect.cad import model as model_mod
from partinspect.cad.model import build_model, cache_dir, load_model


@pytest.fixture(scope="module")
def plate_step(repo, tmp_path_factory):
    path = tmp_path_factory.mktemp("part") / "plate.step"
    shutil.copy(repo / "examples" / "plate" / "part.step", path)
    return path


@pytest.fixture(scope="module")
def built(plate_step):
    return build_model(plate_step)


def _same(a, b):
    assert a.inventory.to_dict() == b.inventory.to_dict()
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    np.testing.assert_array_equal(a.mesh.face_attributes["cad_face"], b.mesh.face_attributes["cad_face"])
    np.testing.assert_array_equal(a.bounds, b.bounds)
    assert (a.pmi is None) == (b.pmi is None)


def test_a_second_load_comes_from_the_cache_and_equals_the_first(plate_step, built, tmp_path, monkeypatch):
    first = load_model(plate_step, cache=tmp_path)
    assert len(list(tmp_path.glob("*.pickle"))) == 1
    _same(first, built)

    def no_build(path):
        raise AssertionError("built again although cached")

    monkeypatch.setattr(model_mod, "build_model", no_build)
    again = load_model(plate_step, cache=tmp_path)
    _same(again, built)
    assert again._shape is None  # the OCCT shape is not read unless asked for
    assert again.shape.isValid()  # and is read when it is


def test_another_file_content_is_another_entry(plate_step, tmp_path):
    load_model(plate_step, cache=tmp_path)
    other = tmp_path / "other.step"
    other.write_bytes(plate_step.read_bytes().replace(b"ENDSEC;", b"ENDSEC;\n", 1))
    load_model(other, cache=tmp_path)
    assert len(list(tmp_path.glob("*.pickle"))) == 2


def test_a_corrupt_entry_is_rebuilt_not_trusted(plate_step, built, tmp_path):
    load_model(plate_step, cache=tmp_path)
    (entry,) = tmp_path.glob("*.pickle")
    entry.write_bytes(entry.read_bytes()[:100])
    _same(load_model(plate_step, cache=tmp_path), built)
    entry.write_bytes(b"not a cache file")
    _same(load_model(plate_step, cache=tmp_path), built)
    assert entry.read_bytes().startswith(b"partinspect-cad-model/")


def test_an_unwritable_cache_costs_time_not_the_run(plate_step, built, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would be")
    _same(load_model(plate_step, cache=blocker / "cache"), built)


def test_cache_folder_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("PARTINSPECT_CACHE", str(tmp_path))
    assert cache_dir() == tmp_path
    monkeypatch.setenv("PARTINSPECT_CACHE", "off")
    assert cache_dir() is None
    monkeypatch.delenv("PARTINSPECT_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "partinspect"
