"""The plan's outputs: a table on the terminal, plan.html, plan.json and best_pose.json.

``plan.json`` (schema ``plan/1``) holds every number the page shows;
``best_pose.json`` holds the proposed pose as ``{"part_to_camera": [[4x4]]}``,
which ``inspect render --pose`` and ``inspect plan --pose`` read back.
Angles are in degrees in every output, lengths in mm (DESIGN.md).
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["SCHEMA", "plan_to_dict", "plan_table", "render_plan_html", "write_plan"]

SCHEMA = "plan/1"


def _num(x, digits=4):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}"


def _features_dict(pred):
    out = []
    for fp in pred.features.values():
        d = {"id": fp.id, "kind": fp.kind, "status": fp.status, "reason": fp.reason,
             "points": [len(fp.left) if fp.left is not None else 0, len(fp.right) if fp.right is not None else 0],
             "visible_fraction": round(fp.visible_fraction, 4)}
        if fp.epipolar_angle is not None:
            d["epipolar_angle_deg"] = round(math.degrees(fp.epipolar_angle), 3)
        if fp.view_angle is not None:
            d["view_angle_deg"] = round(math.degrees(fp.view_angle), 3)
        if fp.axis_ratio is not None:
            d["axis_ratio"] = round(fp.axis_ratio, 4)
        c = fp.median_contrast
        d["median_contrast"] = None if not math.isfinite(c) else round(c, 2)
        stds = [float(np.median(v.std)) for v in (fp.left, fp.right) if v is not None and len(v)]
        d["median_edge_std_px"] = round(max(stds), 5) if stds else None
        out.append(d)
    return out


def _pose_dict(pred, center):
    from partinspect.planning.search import pose_text

    return {
        "label": pred.label,
        "fixture": {"rotation_deg": pred.angles[0], "tilt_x_deg": pred.angles[1], "tilt_y_deg": pred.angles[2]}
        if pred.angles else None,
        "pose": pose_text(pred.part_to_camera, center),
        "part_to_camera": np.round(pred.part_to_camera, 12).tolist(),
        "decidable": pred.n_decidable,
        "registration_error": pred.registration_error,
        "ambiguity": pred.ambiguity or None,
        "characteristics": [c.to_dict() for c in pred.characteristics],
        "features": _features_dict(pred),
    }


def plan_to_dict(result):
    """The plan.json content (schema ``plan/1``)."""
    m = result.model
    d = {
        "schema": SCHEMA,
        "part": result.part.name,
        "rig": str(result.rig),
        "tolerances": None if result.tolerances is None else str(result.tolerances),
        "units": "mm",
        "image_size": list(result.calibration.image_size),
        "decidable_ratio": result.max_ratio,
        "coverage_factor": 2.0,
        "model": {"noise": m.noise, "blur": m.blur, "sigma": m.sigma, "contrast": m.contrast,
                  "end_trim": m.run_trim, "arc_end_trim": m.arc_trim, "min_points": m.min_points},
        "datums": None if result.datums is None else list(result.datums),
        "characteristics": len(result.characteristics),
        "not_evaluated": [n.to_dict() for n in result.not_evaluated],
        "start": _pose_dict(result.start, result.center),
        "best": _pose_dict(result.best, result.center),
        "all_decidable": result.all_decidable,
        "check": None if result.check is None else result.check.to_dict(),
    }
    if result.search is not None:
        d["poses"] = [{"label": p.label, "fixture": list(p.angles), "decidable": p.n_decidable,
                       "worst_ratio": _finite(max((c.ratio for c in p.characteristics if not math.isnan(c.ratio)),
                                                  default=0.0))}
                      for p in result.search.poses]
        d["out_of_view"] = list(result.search.out_of_view)
        d["never_decidable"] = [{"id": c.id, "reason": c.reason, "causes": summary,
                                 "best_ratio": _finite(c.ratio)} for c, summary in result.search.never]
    if result.views is not None:
        d["views"] = _views_dict(result)
    return d


def _views_dict(result):
    """plan.json's ``views``: the chosen views, what each decides, what none decides, and every candidate."""
    from partinspect.planning.search import pose_text
    from partinspect.planning.views import turns_text, view_turns

    vp = result.views
    turns = view_turns(vp.views)
    return {
        "complete": vp.complete,
        "pose": pose_text(result.start.part_to_camera, result.center),
        "render_views": turns_text(turns),
        "chosen": [{"label": v.label, "fixture": list(v.angles), "turn_deg": [float(a) for a in t],
                    "decides": [cid for cid, by in vp.decided_by.items() if k in by]}
                   for k, (v, t) in enumerate(zip(vp.views, turns))],
        "together": [{"id": cid, "views": [f"view-{k + 1}" for k in vp.decided_by[cid]],
                      "expanded_uncertainty": _finite(U)} for cid, U in vp.together.items()],
        "undecided": [{"id": c.id, "reason": c.reason, "causes": why, "best_ratio": _finite(c.ratio)}
                      for c, why in vp.undecided],
        "out_of_view": list(vp.out_of_view),
        "candidates": [{"label": p.label, "fixture": list(p.angles), "decidable": p.n_decidable,
                        "registration_error": p.registration_error} for p in vp.candidates],
    }


def _views_lines(result):
    """The terminal lines of a views plan."""
    from partinspect.planning.search import pose_text
    from partinspect.planning.views import turns_text, view_turns

    vp, n = result.views, len(result.characteristics)
    lines = ["", f"views: {len(vp.views)} of {len(vp.candidates)} candidates decide {len(vp.decided_by)} of {n}"
             + ("" if vp.complete else " (more views would decide more)")]
    for k, v in enumerate(vp.views):
        own = [cid for cid, by in vp.decided_by.items() if by == [k]]
        lines.append(f"  view-{k + 1}: {v.label}: decides {v.n_decidable}"
                     + (f", alone: {', '.join(own)}" if own else ""))
    for cid, U in vp.together.items():
        lines.append(f"  {cid}: decided by views {', '.join(str(k + 1) for k in vp.decided_by[cid])} together "
                     f"(U = {U:.4f})")
    if vp.views:
        lines.append(f"  render them: inspect render PART OUT --pose {pose_text(result.start.part_to_camera, result.center)} "
                     f"--views \"{turns_text(view_turns(vp.views))}\"")
    if vp.out_of_view:
        lines.append(f"  out of view in every candidate (general tolerances, not inspected): {', '.join(vp.out_of_view)}")
    if vp.undecided:
        lines += ["", f"undecided by any set of up to {len(vp.views) or 'the'} views:"]
        lines += [f"  {c.id}: {why}; closest: {c.reason}" for c, why in vp.undecided]
    return lines


def _finite(x):
    return None if x is None or not math.isfinite(x) else round(float(x), 6)


def _u_text(c):
    if not math.isfinite(c.U):
        return "–"
    v = math.degrees(c.U) if c.characteristic.unit == "rad" else c.U
    return f"{v:.4f}"


def _t_text(c):
    if c.tolerance is None:
        return "–"
    v = math.degrees(c.tolerance) if c.characteristic.unit == "rad" else c.tolerance
    return f"{v:.4f}"


def _r_text(c):
    return "–" if not math.isfinite(c.ratio) else f"{c.ratio:.2f}"


def _status(c):
    return "ok" if c.decidable else ("out of view" if not c.inspected else "NO")


def plan_table(result):
    """The terminal summary: one row per characteristic, then the proposal and the reasons."""
    start, best = result.start, result.best
    two = result.search is not None and best is not start
    head = ["characteristic", "type", "tolerance", "U start", "U/T", ""]
    if two:
        head += ["U best", "U/T", ""]
    rows = [head]
    for cs, cb in zip(start.characteristics, best.characteristics):
        row = [cs.id, cs.characteristic.type, _t_text(cs), _u_text(cs), _r_text(cs), _status(cs)]
        if two:
            row += [_u_text(cb), _r_text(cb), _status(cb)]
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    right = {2, 3, 4, 6, 7}
    lines = ["  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
             for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    unit = "U: expanded uncertainty (k = 2), mm (deg for angles); T: tolerance zone width"
    lines += ["", unit, f"decidable: U <= {result.max_ratio:g} T", ""]
    if result.check is not None:
        lines += _check_lines(result.check) + [""]
    n = len(result.characteristics)
    lines.append(f"start pose ({start.label or 'as given'}): {start.n_decidable} of {n} decidable"
                 + (f", {len(start.not_inspected())} general tolerances of edges out of view (not inspected)"
                    if start.not_inspected() else ""))
    if start.registration_error:
        lines.append(f"  {start.registration_error}")
    if start.ambiguity:
        lines.append(f"  pose ambiguous: {start.ambiguity}")
    for c in start.undecidable():
        lines.append(f"  {c.id}: {c.reason}")
    for c in start.characteristics:
        if c.warning and c.decidable:
            lines.append(f"  {c.id} (decidable, but): {c.warning}")
    if result.views is not None:
        lines += _views_lines(result)
    if result.search is not None:
        lines.append("")
        lines.append(f"best of {len(result.search.poses)} poses tried: {best.label}: {best.n_decidable} of {n} decidable")
        from partinspect.planning.search import pose_text

        lines.append(f"  --pose {pose_text(best.part_to_camera, result.center)}")
        if best.ambiguity:
            lines.append(f"  pose ambiguous: {best.ambiguity}")
        fixed = [cb.id for cs, cb in zip(start.characteristics, best.characteristics) if cb.decidable and not cs.decidable]
        if fixed:
            lines.append(f"  makes decidable: {', '.join(fixed)}")
        lost = [cb.id for cs, cb in zip(start.characteristics, best.characteristics) if cs.decidable and not cb.decidable]
        if lost:
            lines.append(f"  but loses: {', '.join(lost)}")
        if result.search.out_of_view:
            lines.append(f"  out of view in every pose (general tolerances, not inspected): "
                         f"{', '.join(result.search.out_of_view)}")
        if result.search.never:
            lines.append("")
            lines.append("undecidable in every pose tried:")
            for c, summary in result.search.never:
                lines.append(f"  {c.id}: {summary}; closest: {c.reason}")
    return "\n".join(lines)


def _check_lines(check):
    """The check's rows: predicted image-noise u beside the rendered spread, and U after the check."""
    head = ["characteristic", "u noise", "spread", "spread/u", "chance", "U checked", "U/T", "", "verdict"]
    rows = [head]
    for c in check.characteristics:
        deg = c.prediction.characteristic.unit == "rad"

        def num(x, digits=4):
            return _num(math.degrees(x) if deg and math.isfinite(x) else x, digits)

        r = c.spread / c.u_noise if math.isfinite(c.spread) and math.isfinite(c.u_noise) and c.u_noise > 0 else math.nan
        status = "ok" if c.decidable else ("out of view" if not c.prediction.inspected else "NO")
        chance = "-" if c.interval is None else f"{c.interval[0]:.2f}-{c.interval[1]:.2f}"
        rows.append([c.id, num(c.u_noise, 5), num(c.spread, 5), _num(r, 2), chance, num(c.U), _num(c.ratio, 2),
                     status, c.verdict])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    right = {1, 2, 3, 4, 5, 6}
    out = [f"check of the proposed pose on {check.draws} rendered noise draws (noise {check.noise:g}, seed {check.seed}; "
           f"a spread / u outside its 'chance' interval is beyond chance: for normal values "
           f"{check.interval[0]:.2f}-{check.interval[1]:.2f}, wider for heavier tails and, for a form value, "
           f"for the scene's fixed displacements):"]
    out += ["  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in rows]
    out.insert(2, "  ".join("-" * w for w in widths))
    if check.failed:
        out.append(f"draws the chain could not register: {len(check.failed)} ({check.failed[0]})")
    n = sum(c.decidable for c in check.characteristics)
    out.append(f"after the check: {n} of {len(check.characteristics)} decidable")
    return out


def _environment():
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("partinspect.reports", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    return env


def render_plan_html(result, created=None):
    """The plan.html text: self-contained (inline CSS, no network), user strings escaped."""
    data = plan_to_dict(result)
    rows = []
    for cs, cb in zip(result.start.characteristics, result.best.characteristics):
        rows.append({"id": cs.id, "type": cs.characteristic.type, "source": cs.characteristic.source,
                     "tolerance": _t_text(cs), "u_start": _u_text(cs), "r_start": cs.ratio, "ok_start": cs.decidable,
                     "reason_start": cs.reason, "u_best": _u_text(cb), "r_best": cb.ratio, "ok_best": cb.decidable,
                     "reason_best": cb.reason, "inspected_start": cs.inspected, "inspected_best": cb.inspected,
                     "warning": (cb if result.search is not None else cs).warning})
    return _environment().get_template("plan.html.j2").render(
        p=data, rows=rows, two=result.search is not None and result.best is not result.start,
        ratio=result.max_ratio, created=created or "", bar=_bar)


def _bar(r, limit):
    """Width (percent) of the U/T bar, the limit at 50 %."""
    if r is None or not math.isfinite(r):
        return 100.0
    return float(min(100.0, 50.0 * r / limit))


def write_plan(out_dir, result, created=None):
    """Write plan.html, plan.json and best_pose.json into ``out_dir`` (created if needed).

    Returns
    -------
    Path
        The folder.
    """
    from partinspect.atomic import prepare_output_dir, write_text_atomic

    out = prepare_output_dir(out_dir)
    data = plan_to_dict(result)
    # allow_nan=False: a non-finite number is a defect upstream, never written as invalid JSON.
    plan_json = json.dumps(data, indent=1, allow_nan=False) + "\n"
    pose_json = json.dumps({"part_to_camera": data["best"]["part_to_camera"]}, indent=1, allow_nan=False) + "\n"
    write_text_atomic(out / "plan.json", plan_json)
    write_text_atomic(out / "best_pose.json", pose_json)
    write_text_atomic(out / "plan.html", render_plan_html(result, created))
    return out
