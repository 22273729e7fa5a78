"""The PMI of a STEP file as text: a listing of its items and an editable spec file.

The listing is what ``inspect features PART.step --pmi`` prints; the spec
text is what ``inspect spec`` writes: `partinspect.tolerances.spec.dump_spec`'s
YAML, headed by comments naming each limit's PMI item and every item not
evaluated, so that `load_spec` reads it back to the same spec.
"""

import math

from partinspect.tolerances.resolve import GENERAL_GAP

__all__ = ["describe_item", "general_gaps_line", "pmi_listing", "pmi_problems_line", "spec_yaml"]


def describe_item(item):
    """``diameter 35 +0/-0.2 mm`` or ``position 0.75 mm | A | B | C``."""
    if item.kind == "datum":
        return f"datum {item.name}"
    if item.value is None:
        return f"{item.type} (no value)"
    rad = item.kind == "dimension" and item.type == "angle"
    conv, unit = (math.degrees, "deg") if rad else (float, "mm")
    text = f"{item.type} {conv(item.value):.6g}"
    if item.upper is not None:
        text += f" {conv(item.upper):+.6g}/{conv(item.lower):+.6g}"
    text += f" {unit}"
    extra = [m for m in item.modifiers if m in ("MMC", "LMC")]
    if item.datums and item.kind == "tolerance":
        marks = {"MMB": "(M)", "LMB": "(L)"}
        text += " | " + " | ".join(d + "".join(marks[b] for b in marks if f"datum_{d}_{b}" in item.modifiers)
                                   for d in item.datums)
        if any(m.startswith("datum_") for m in item.modifiers):
            extra.append("datum shift")
    return text + (f" ({', '.join(extra)})" if extra else "")


def pmi_listing(pmi, pmi_spec, path=None):
    """A text table of the PMI items and the features each applies to.

    Parameters
    ----------
    pmi : partinspect.cad.pmi.Pmi
    pmi_spec : PmiSpec
    path : str or os.PathLike, optional
        The STEP file, named in the heading.

    Returns
    -------
    str
    """
    from pathlib import Path

    name = Path(path).name if path else "the STEP file"
    if not pmi and not pmi.unread:
        return f"{name}: no semantic PMI (the ISO 2768 general tolerances or a spec file apply)"
    skipped = {n.item: n.reason for n in pmi_spec.not_evaluated}
    rows = []
    for item in pmi.items:
        applies = pmi_spec.applies_to.get(item.id)
        target = ", ".join(_compact(applies)) if applies else "not evaluated: " + skipped.get(item.id, "")
        rows.append((item.id, describe_item(item), item.name if item.kind != "datum" else "", target))
    for n in pmi_spec.not_evaluated:
        if n.item not in {i.id for i in pmi.items}:
            rows.append(("-", n.type, n.item, "not evaluated: " + n.reason))
    widths = [max(len(r[k]) for r in rows + [("id", "PMI", "name", "")]) for k in range(3)]
    lines = [f"{name}: {len(pmi.of_kind('dimension'))} dimensions, {len(pmi.of_kind('tolerance'))} geometric "
             f"tolerances, {len(pmi.of_kind('datum'))} datums; {len(pmi_spec.applies_to)} items on edges, "
             f"{len(pmi_spec.not_evaluated)} not evaluated",
             "  ".join(h.ljust(w) for h, w in zip(("id", "PMI", "name"), widths)) + "  applies to"]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r[:3], widths)) + "  " + r[3] for r in rows]
    return "\n".join(lines)


def pmi_problems_line(part_name, not_evaluated, where="report.json"):
    """One line summing up the PMI items a run does not check, or None when there are none.

    Parameters
    ----------
    part_name : str
        The STEP file's name.
    not_evaluated : sequence of NotEvaluated or of their dicts
        ``item``, ``type``, ``reason`` each.
    where : str
        Where the reasons are listed in full.

    Returns
    -------
    str or None
        E.g. ``part.stp PMI: 16 items not evaluated (1 not read by OCCT;
        7 profile of surface, 4 datum, ...); reasons in report.json``; a PMI
        that could not be used at all says so and that ISO 2768 applies.
    """
    items = [n if isinstance(n, dict) else n.to_dict() for n in not_evaluated]
    items = [n for n in items if n["type"] != GENERAL_GAP]
    if not items:
        return None
    broken = [n for n in items if n["type"] == "PMI"]
    if broken:
        return f"{part_name}: {broken[0]['reason']}"
    unread = sum("not read by OCCT" in n["reason"] for n in items)
    counts = {}
    for n in items:
        if "not read by OCCT" not in n["reason"]:
            kind = n["type"].replace("_", " ")
            counts[kind] = counts.get(kind, 0) + 1
    parts = ([f"{unread} not read by OCCT"] if unread else []) + [
        ", ".join(f"{c} {k}" for k, c in sorted(counts.items(), key=lambda kc: (-kc[1], kc[0])))]
    return (f"{part_name} PMI: {len(items)} item{'s' if len(items) != 1 else ''} not evaluated "
            f"({'; '.join(p for p in parts if p)}); reasons in {where}")


def _compact(ids, limit=8):
    ids = list(ids)
    return ids if len(ids) <= limit else ids[:limit] + [f"... ({len(ids)} features)"]


def spec_yaml(pmi_spec, pmi, part_name):
    """The PMI's spec as YAML text to edit, its sources and omissions as comments.

    The comments name, for every characteristic, the PMI item it comes
    from, and list what is not evaluated with the reason; the YAML itself is
    `partinspect.tolerances.spec.dump_spec`'s, so `load_spec` reads it back
    to the same spec.
    """
    from partinspect.tolerances.spec import dump_spec, format_loc

    by_id = {i.id: i for i in pmi.items}
    head = [f"# Tolerance spec from the semantic PMI of {part_name} (written by `inspect spec`).",
            "# Edit freely: a spec file overrides the PMI item by item.", "#", "# source of each limit:"]
    for loc, item_id in pmi_spec.sources.items():
        item = by_id.get(item_id)
        what = describe_item(item) if item else item_id
        head.append(f"#   {format_loc(loc)}: PMI {item_id} ({what}{', ' + repr(item.name) if item and item.name else ''})")
    if pmi_spec.data.get("datums"):
        letters = [i.name for i in pmi.items if i.kind == "datum" and i.id in pmi_spec.applies_to]
        head += ["#", f"# datums: the edges of PMI datum(s) {', '.join(letters)}. They alone drive the alignment, so",
                 "# they must be in view; delete the key to align on every feature."]
    shifted = sorted({d[0] for body in pmi_spec.data.get("features", {}).values()
                      for d in (body.get("position") or {}).get("datums", ()) if d.endswith(("(M)", "(L)"))})
    unknown = [d for d in shifted if d not in pmi_spec.data.get("datum_features", {})]
    if unknown:
        head += ["#", f"# datum(s) {', '.join(unknown)} at MMB/LMB: the file attaches them to no face. Name their",
                 "# features under datum_features (e.g. B: [circle-5, circle-6]) for the datum shift to apply."]
    if pmi_spec.not_evaluated:
        head += ["#", "# not evaluated by edge measurement:"]
        head += [f"#   {n.item} ({n.type}): {n.reason}" for n in pmi_spec.not_evaluated]
    return "\n".join(head) + "\n" + dump_spec(pmi_spec.spec())


def general_gaps_line(part_name, not_evaluated, where="report.json"):
    """One line naming the characteristics no tolerance covers, or None when there are none.

    E.g. ``part.stp: 3 characteristics without a tolerance (ISO 2768 sets
    none for them: circle-7.radius, ...; give one in the spec); not
    evaluated, listed in report.json``.
    """
    items = [n if isinstance(n, dict) else n.to_dict() for n in not_evaluated]
    ids = [n["item"] for n in items if n["type"] == GENERAL_GAP]
    if not ids:
        return None
    return (f"{part_name}: {len(ids)} characteristic{'s' if len(ids) != 1 else ''} without a tolerance (ISO 2768 "
            f"sets none for {'them' if len(ids) != 1 else 'it'}: {', '.join(_compact(ids, 4))}; give one in the spec); "
            f"not evaluated, listed in {where}")
