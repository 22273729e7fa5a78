"""The rig's refinement from the part as the reports state it (report.json's ``rig_refinement``, one line).

Angles are reported in degrees, ``T`` in mm, principal points in px: the
refinement itself works in rad (:mod:`partinspect.vision.rig_refinement`).
A refinement is never silent: the line names what was refined and what
was held, and the entry gives every correction beside the stated value
with both standard uncertainties (GUM, JCGM 100, 7.2).

References
----------
.. [1] JCGM 100:2008 (GUM), 7.2 (reporting standard uncertainty).
"""

import numpy as np

__all__ = ["refinement_entry", "refinement_summary"]


def refinement_entry(r):
    """report.json's ``rig_refinement`` of a refinement: rotation in degrees, T in mm, principal points in px.

    Parameters
    ----------
    r : partinspect.vision.rig_refinement.RigRefinement

    Returns
    -------
    dict
        Each refined parameter's stated and refined value, correction,
        posterior and prior standard uncertainty and significance; the
        parameters held and why; the rotation's correction, the baseline
        kept, the joint chi-square against the stated calibration.
    """
    rows = []
    for k, name in enumerate(r.names):
        f = np.degrees(1.0) if name.startswith("r") else 1.0
        rows.append({
            "name": name, "unit": "deg" if name.startswith("r") else ("mm" if name.startswith("t") else "px"),
            "stated": round(float(r.stated[k] * f), 7), "refined": round(float(r.refined[k] * f), 7),
            "correction": round(float(r.correction[k] * f), 7),
            "standard_uncertainty": round(float(r.std[k] * f), 7),
            "prior_standard_uncertainty": round(float(r.prior_std[k] * f), 7) if r.prior_std[k] > 0 else None,
            "prior": ("none stated" if r.prior_std[k] == 0
                      else "stated, widened by the drift" if r.widened[k] else "stated"),
            "significance": round(float(r.z[k]), 3)})
    return {
        "method": ("bundle adjustment of the rig's relative orientation to the edge points of the registered "
                   "circles, each circle's centre, normal and radius free (the CAD model gives only which "
                   "circles are the part's); the stated calibration as prior (MAP); the baseline's length kept"),
        "circles": r.circles,
        "parameters": rows,
        "fixed": [{"name": k, "reason": v} for k, v in r.fixed.items()],
        "rotation_correction_deg": round(r.rotation_deg(), 6),
        "baseline_mm": round(r.baseline, 6),
        "baseline_standard_uncertainty_mm": round(r.baseline_std, 6),
        "chi_square": round(r.chi2, 3), "dof": r.dof, "p_value": round(r.p_value, 6),
        "significant": r.significant,
        "weighted_rms": round(r.rms, 4),
    }


def refinement_summary(r):
    """One line for the terminal and the report: what was refined, the turn, its significance, what was held."""
    word = "significant" if r.significant else "not significant"
    return (f"rig refined from {r.circles} circles ({', '.join(r.names)}): right camera turned "
            f"{r.rotation_deg():.5f} deg, {word} against the stated calibration "
            f"(chi-square {r.chi2:.1f} on {r.dof}); baseline kept at {r.baseline:.3f} mm"
            + (f"; held: {', '.join(r.fixed)}" if r.fixed else ""))
