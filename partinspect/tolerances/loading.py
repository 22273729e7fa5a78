"""A part's tolerances: the spec file given or beside the STEP file, the STEP file's PMI, else ISO 2768-mK."""

from dataclasses import replace
from pathlib import Path

from partinspect.errors import InputError

__all__ = ["find_tolerances", "load_characteristics"]


def find_tolerances(part, tolerances=None):
    """The tolerance spec for ``part``: the given file, else PART.tol.yaml beside it, else None.

    ``part.step`` looks for ``part.tol.yaml`` (and ``part.tol.yml``).
    """
    if tolerances is not None:
        path = Path(tolerances)
        if not path.is_file():
            raise InputError(path, "tolerance file not found" if not path.exists() else "not a regular file")
        return path
    part = Path(part)
    for suffix in (".tol.yaml", ".tol.yml"):
        candidate = part.with_name(part.stem + suffix)
        if candidate.is_file():
            return candidate
    return None


def load_characteristics(inv, tol_path, part=None, pmi=None):
    """The resolved spec (or the ISO 2768-mK default) and every characteristic to evaluate.

    With ``part`` (the STEP file), its semantic PMI fills in what the spec
    does not tolerance itself, item by item, before the general tolerances
    take the rest (`partinspect.tolerances.from_pmi.merge_pmi`); ``pmi``, the
    file's PMI if already read (`partinspect.cad.pmi.read_pmi`), saves
    reading it again. A characteristic no general tolerance covers (a
    radius below 0.5 mm under ISO 2768) is listed as not evaluated, with
    the PMI items that are, rather than stopping the run.
    """
    from partinspect.tolerances import spec as spec_mod
    from partinspect.tolerances.resolve import (GENERAL_GAP, general_characteristics, resolve_spec, with_edge_breaks,
                                                with_material_sizes)

    spec = spec_mod.load_spec(tol_path) if tol_path is not None else spec_mod.default_spec()
    resolved = resolve_spec(spec, inv, tol_path)
    if part is not None:
        from partinspect.tolerances.from_pmi import merge_pmi

        resolved = merge_pmi(resolved, inv, part, pmi=pmi)
    gaps = []
    general = general_characteristics(inv, resolved, gaps=gaps)
    if gaps:
        from partinspect.tolerances.from_pmi import NotEvaluated

        resolved = replace(resolved, not_evaluated=tuple(resolved.not_evaluated) + tuple(
            NotEvaluated(item, GENERAL_GAP, why) for item, why in gaps))
    chars = with_edge_breaks(list(resolved.characteristics) + general, resolved)
    return resolved, with_material_sizes(chars, inv, tol_path)
