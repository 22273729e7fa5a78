"""Synthetic *measured* 3D features: CAD edges posed in the rig, with realistic noise.

This stands in for the stereo chain when testing what comes after it
(registration, evaluation, decisions): each visible CAD circle, arc and line
is moved into the rig frame by a known ``part_to_camera`` and disturbed by
noise drawn from an anisotropic covariance aligned with the line of sight
(depth worse than lateral, as triangulation gives), and that covariance is
reported with it, so the downstream uncertainty can be checked against the
truth.

Records are plain frozen dataclasses with the fields of
:class:`partinspect.vision.fit3d.Circle3D` / ``Line3D`` that the downstream
code reads (duck-typed), plus the measured extent of lines and optional
edge points with their 3x3 covariances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from partinspect.frames import plane_basis

__all__ = [
    "MeasuredCircle",
    "MeasuredLine",
    "Measurement",
    "ray_covariance",
    "facing_feature_ids",
    "measure_features",
]


@dataclass(frozen=True, eq=False)
class MeasuredCircle:
    """A measured circle or arc, rig frame (mm).

    ``covariance`` is the centre's (3, 3); ``normal_cov`` (3, 3) of the unit
    normal (rank 2); ``points`` (M, 3) and ``point_covs`` (M, 3, 3) the
    edge points, or None.
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    covariance: np.ndarray
    normal_cov: np.ndarray
    radius_std: float
    points: np.ndarray | None = None
    point_covs: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class MeasuredLine:
    """A measured straight edge, rig frame (mm).

    ``point`` is the foot of the data centroid on the line, ``covariance``
    its (3, 3) covariance (zero along the line), ``direction_cov`` that of
    the unit direction; ``start``/``end`` the measured extent.
    """

    point: np.ndarray
    direction: np.ndarray
    covariance: np.ndarray
    direction_cov: np.ndarray
    start: np.ndarray
    end: np.ndarray
    points: np.ndarray | None = None
    point_covs: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Measurement:
    """Synthetic measured features and their truth.

    Attributes
    ----------
    circles, lines : tuple of MeasuredCircle / MeasuredLine
    circle_ids, line_ids : tuple of str
        The CAD id each measured feature was made from.
    part_to_camera : ndarray, shape (4, 4)
        The true pose.
    """

    circles: tuple
    lines: tuple
    circle_ids: tuple
    line_ids: tuple
    part_to_camera: np.ndarray


def ray_covariance(point, lateral, depth):
    """3x3 covariance with std ``depth`` along the ray from the rig origin to ``point`` and ``lateral`` across it."""
    z = np.asarray(point, float)
    z = z / np.linalg.norm(z)
    return lateral**2 * np.eye(3) + (depth**2 - lateral**2) * np.outer(z, z)


def facing_feature_ids(inventory, part_to_camera):
    """Ids of the non-smooth features with an adjacent plane face turned to the camera (no occlusion test)."""
    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    out = []
    for f in inventory.features:
        if f.smooth:
            continue
        mid = f.center if f.kind != "line" else 0.5 * (f.start + f.end)
        x = R @ mid + t
        for fid in f.faces:
            n = getattr(inventory[fid], "normal", None)
            if n is not None and (R @ n) @ (-x) > 0:
                out.append(f.id)
                break
    return tuple(out)


def _sqrt_psd(C):
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0, None))


def measure_features(
    inventory,
    part_to_camera,
    ids,
    rng,
    *,
    lateral=0.002,
    depth=0.008,
    point_lateral=0.005,
    point_depth=0.020,
    n_points=60,
    shifts=None,
    form=None,
    inset=0.05,
):
    """Measured versions of CAD features, posed and disturbed.

    Parameters
    ----------
    inventory : Inventory
    part_to_camera : ndarray, shape (4, 4)
    ids : sequence of str
        CAD features to measure (the visible ones).
    rng : numpy.random.Generator
    lateral, depth : float
        Standard uncertainties of a circle centre / line point across and
        along the line of sight, mm. Normals get ``depth / radius`` rad,
        radii ``lateral``, line directions ``sqrt(12) * std / length``.
    point_lateral, point_depth : float
        Per edge point, mm.
    n_points : int
        Edge points per feature (0 for none).
    shifts : dict, optional
        ``{cad_id: (3,) vector}``: the real feature sits this far from
        nominal, part frame, mm (a machining deviation).
    form : dict, optional
        ``{cad_id: amplitude}``: a true form deviation, a sine of this
        amplitude (mm) across the edge (lobing for circles, a bow for lines).
    inset : float
        Fraction of a line's length left unseen at each end.

    Returns
    -------
    Measurement
    """
    R, t = part_to_camera[:3, :3], part_to_camera[:3, 3]
    shifts, form = shifts or {}, form or {}
    circles, lines, cids, lids = [], [], [], []
    for fid in ids:
        f = inventory[fid]
        shift = np.asarray(shifts.get(fid, np.zeros(3)), float)
        amp = float(form.get(fid, 0.0))
        if f.kind in ("circle", "arc"):
            c = R @ (f.center + shift) + t
            n = R @ f.normal
            if n @ c > 0:
                n = -n  # oriented towards the camera, as the fitter reports it
            C = ray_covariance(c, lateral, depth)
            E = plane_basis(n)
            s_n = depth / f.radius
            Ncov = s_n**2 * E @ E.T
            cm = c + _sqrt_psd(C) @ rng.standard_normal(3)
            nm = n + E @ (s_n * rng.standard_normal(2))
            nm /= np.linalg.norm(nm)
            rm = f.radius + lateral * rng.standard_normal()
            pts = pcs = None
            if n_points:
                a0, a1 = (0.0, 2 * np.pi) if f.kind == "circle" else (f.angle_start, f.angle_end)
                th = a0 + (np.arange(n_points) + 0.5) / n_points * (a1 - a0)
                fr = f.frame()
                rad = f.radius + amp * np.cos(3 * th)
                P = f.center + shift + rad[:, None] * (np.cos(th)[:, None] * fr[0] + np.sin(th)[:, None] * fr[1])
                pts, pcs = _noisy_points(P @ R.T + t, point_lateral, point_depth, rng)
            circles.append(MeasuredCircle(cm, nm, float(rm), C, Ncov, lateral, pts, pcs))
            cids.append(fid)
        else:
            a, b = f.start + shift, f.end + shift
            L = np.linalg.norm(b - a)
            d = (b - a) / L
            a_v, b_v = a + inset * L * d, b - inset * L * d
            Lv = (1 - 2 * inset) * L
            mid = R @ (0.5 * (a_v + b_v)) + t
            dr = R @ d
            Pp = np.eye(3) - np.outer(dr, dr)
            C = Pp @ ray_covariance(mid, lateral, depth) @ Pp
            Dc = 12.0 / Lv**2 * C
            pm = mid + _sqrt_psd(C) @ rng.standard_normal(3)
            dm = dr + _sqrt_psd(Dc) @ rng.standard_normal(3)
            dm /= np.linalg.norm(dm)
            pm = pm - ((pm - mid) @ dm) * dm
            start = pm + ((R @ a_v + t) - pm) @ dm * dm
            end = pm + ((R @ b_v + t) - pm) @ dm * dm
            pts = pcs = None
            if n_points:
                s = (np.arange(n_points) + 0.5) / n_points
                P = a_v + s[:, None] * (b_v - a_v)
                if amp:
                    side = plane_basis(d)[:, 0]
                    P = P + amp * np.sin(np.pi * s)[:, None] * side
                pts, pcs = _noisy_points(P @ R.T + t, point_lateral, point_depth, rng)
            lines.append(MeasuredLine(pm, dm, C, Dc, start, end, pts, pcs))
            lids.append(fid)
    return Measurement(tuple(circles), tuple(lines), tuple(cids), tuple(lids), np.array(part_to_camera, float))


def _noisy_points(P, lat, dep, rng):
    covs = np.array([ray_covariance(p, lat, dep) for p in P])
    noise = np.einsum("nij,nj->ni", np.array([_sqrt_psd(c) for c in covs]), rng.standard_normal(P.shape))
    return P + noise, covs
