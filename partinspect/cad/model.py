"""A part's CAD model as a run uses it, kept on disk by the STEP file's content.

Reading a STEP file, making its feature inventory, tessellating it for the
visibility test and reading its PMI take one to several seconds, and none
of it depends on anything but the file's bytes and this software: a
production line inspects the same part number hundreds of times. The
results are cached per SHA-256 of the file (and of the code that makes
them), so a second run on the same part number reads one file instead; the
OCCT shape itself is loaded only if a stage asks for it.

The cache folder is ``$PARTINSPECT_CACHE``, else
``$XDG_CACHE_HOME/partinspect``, else ``~/.cache/partinspect``;
``PARTINSPECT_CACHE=off`` turns it off. A cache that cannot be read or
written is passed over: the model is then built as without one.
"""

from __future__ import annotations

import hashlib
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from partinspect.atomic import write_bytes_atomic
from partinspect.digest import sha256_file

__all__ = ["CadModel", "TriangleArrays", "build_model", "load_model", "cache_dir"]

# The modules whose output is cached: a change to any of them is a new key.
_PRODUCERS = ("features.py", "mesh.py", "step.py", "pmi.py", "step_text.py", "model.py", "visibility.py")
_FORMAT = b"partinspect-cad-model/1"


@dataclass(frozen=True)
class TriangleArrays:
    """A triangle mesh as plain arrays: what the ray caster reads of a trimesh.Trimesh.

    Loading it needs no mesh library (importing trimesh alone takes longer
    than reading the whole cached model).

    Attributes
    ----------
    vertices : ndarray, shape (V, 3)
        Part frame, mm.
    faces : ndarray of int64, shape (F, 3)
    face_attributes : dict
        ``"cad_face"``: ndarray of int64, shape (F,), each triangle's face
        index in the inventory.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_attributes: dict


@dataclass
class CadModel:
    """What a run needs of the STEP file.

    Attributes
    ----------
    path : Path
        The STEP file.
    inventory : partinspect.cad.features.Inventory
    mesh : TriangleArrays
        The coarse tessellation the visibility test casts rays at
        (`partinspect.cad.visibility.visibility_mesh`), part frame, mm.
    bounds : ndarray, shape (2, 3)
        The shape's bounding box, part frame, mm.
    pmi : partinspect.cad.pmi.Pmi or None
        Its semantic PMI; None when it could not be read (the reader then
        runs again where the PMI is used, and says why).
    """

    path: Path
    inventory: object
    mesh: object
    bounds: object
    pmi: object = None
    _shape: object = field(default=None, repr=False, compare=False)

    @property
    def shape(self):
        """The OCCT shape (cadquery), loaded from ``path`` on first use."""
        if self._shape is None:
            from partinspect.cad.step import load_step

            self._shape = load_step(self.path)
        return self._shape

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_shape"] = None  # an OCCT shape does not pickle; it is re-read when needed
        return state


def build_model(path):
    """Load and analyse a STEP file (no cache).

    Raises
    ------
    partinspect.errors.InputError
        If the file is not a readable STEP file with a solid.
    """
    from partinspect.cad.features import inventory
    from partinspect.cad.pmi import read_pmi
    from partinspect.cad.step import load_step
    from partinspect.cad.visibility import visibility_mesh
    from partinspect.poses import bounds_of

    shape = load_step(path)
    inv = inventory(shape)
    try:
        pmi = read_pmi(path)
    except Exception:  # noqa: BLE001  the PMI is optional; merge_pmi reads it again and reports why it failed
        pmi = None
    mesh = visibility_mesh(shape, inv)
    arrays = TriangleArrays(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64),
                            {"cad_face": np.asarray(mesh.face_attributes["cad_face"], np.int64)})
    return CadModel(Path(path), inv, arrays, bounds_of(shape), pmi, shape)


def cache_dir():
    """The cache folder, or None when ``PARTINSPECT_CACHE=off``."""
    env = os.environ.get("PARTINSPECT_CACHE")
    if env is not None:
        return None if env.strip().lower() in ("off", "0", "") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "partinspect"


def load_model(path, cache=None):
    """A STEP file's CadModel, from the cache when it holds this content.

    Parameters
    ----------
    path : str or os.PathLike
    cache : Path, optional
        Cache folder; `cache_dir` by default.

    Returns
    -------
    CadModel
    """
    path = Path(path)
    cache = cache_dir() if cache is None else Path(cache)
    entry = None
    if cache is not None:
        try:
            entry = cache / f"{_key(path)}.pickle"
            model = _read(entry)
        except OSError:
            model = None
        if model is not None:
            model.path = path
            return model
    model = build_model(path)
    if entry is not None:
        try:
            entry.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(entry, _FORMAT + b"\n" + pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL))
        except OSError:
            pass  # a read-only or full cache costs only the next run's time
    return model


def _key(path):
    """SHA-256 of the file's bytes and of the code that analyses it."""
    h = hashlib.sha256(sha256_file(path).encode())
    here = Path(__file__).parent
    for name in _PRODUCERS:
        h.update((here / name).read_bytes())
    h.update(_library_versions().encode())
    return h.hexdigest()


def _library_versions():
    # OCCT's tessellation and analysis come with cadquery-ocp; trimesh holds the mesh.
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for dist in ("cadquery-ocp", "cadquery", "trimesh", "numpy"):
        try:
            out.append(f"{dist}={version(dist)}")
        except PackageNotFoundError:
            out.append(f"{dist}=-")
    return ";".join(out)


def _read(entry):
    """The cached model, or None if there is none or it is not one this code wrote."""
    try:
        data = entry.read_bytes()
    except FileNotFoundError:
        return None
    head, _, body = data.partition(b"\n")
    if head != _FORMAT:
        return None
    try:
        model = pickle.loads(body)
    except Exception:  # noqa: BLE001  a truncated or foreign file is a cache miss, not an error
        return None
    return model if isinstance(model, CadModel) else None
