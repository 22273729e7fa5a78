"""Rim points after the chain's corrections against the true rim: by rim size, along the rim, beside the wall.

The rims' Type B (:mod:`partinspect.vision.rim_errors`) states what the
shading correction leaves at each point as the shading bound over sqrt(3),
correlated along the rim over ``EDGE_BIAS_CORR_ANGLE`` of the ellipse.
This benchmark sets that model against the points' own errors. A sample
part is rendered in bench_views' turntable views (noise-free, cached), each
view's pair measured (:func:`partinspect.vision.stereo.measure_stereo`) with
``--noise`` grey levels over ``--seeds`` draws; every rim seen in both
images is matched to its true circle, and each of its points, moved as
:func:`~partinspect.vision.stereo.feature_views` moves it (the shading
shift times ``BACKGROUND_CORRECTION``, then the curvature bias), is set
against the true rim's image along the outward normal (ideal px, + out);
the points and their Type B are the fit's views
(:func:`~partinspect.vision.stereo.feature_views`).

Printed per noise level:

- per rim image, binned by its semi-major axis: the RMS over rims of the
  points' mean error against the standard deviation of that mean the Type
  B states (its Gram over the points with the model's correlation), and
  with the correlation taken over the shading reading's footprint along
  the edge (``hypot(BACKGROUND_SMOOTHING, filter scale)``, 2.24 px)
  instead;
- the autocorrelation of the points' errors along the rim at lags in px,
  pooled, beside the model's at the median rim;
- the points' mean error binned by the width of the wall's band beside
  them, predicted from the hole's depth (its other rim in the CAD) and the
  true pose: the image distance, inwards, from a rim point to the image of
  the point a depth below it (negative where the wall is hidden behind the
  rim);
- the points' error binned by their distance along the rim image from its
  nearest end (a gap of more than ``END_GAP`` px between neighbouring
  points, after the segmentation's own trim): where the rim image stops,
  beside a limb or where its contrast turns.

Run: ``python benchmarks/bench_rim_geometry.py [--part plate] [--size 816x683]
[--noise 0,2] [--seeds 3] [--work DIR]``. The figures are in
docs/validation.md ("The rims' Type B against the image scale"; the ends'
table in "The wall holes' rims: crowding, the two-step model, the arc's
ends, the edge-on stretches").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_views import ROOT, TURNS, radiance  # noqa: E402

LAGS = (1, 2, 4, 8, 16, 32)
"""px along the rim at which the errors' autocorrelation is printed."""
SEMI_BINS = (0.0, 20.0, 40.0, 80.0, np.inf)
BAND_BINS = (-np.inf, -24.0, -6.0, 0.0, 6.0, 12.0, 24.0, np.inf)
END_BINS = (0.0, 1.5, 3.0, 5.0, 8.0, 15.0, np.inf)
END_GAP = 3.0
"""px: neighbouring points of a rim image (in the order of their angle about
the points' mean) farther apart than this mark an end."""


def project(P, X):
    x = np.c_[X, np.ones(len(X))] @ P.T
    return x[:, :2] / x[:, 2:]


def true_rims(truth):
    """Rims seen in both images with the hole's depth: ``[(id, centre, normal, radius, depth)]``, part frame, mm.

    The depth is the distance along the axis to the other circle of the
    same axis and radius (the hole's other rim).
    """
    circles = [f for f in truth["features"] if f["kind"] == "circle"]
    out = []
    for f in circles:
        if not f["visible_both"]:
            continue
        c, n, r = (np.asarray(f["rendered"][k], float) for k in ("center", "normal", "radius"))
        depths = [abs((np.asarray(g["rendered"]["center"]) - c) @ n) for g in circles if g is not f
                  and abs(g["rendered"]["radius"] - r) < 1e-6
                  and np.linalg.norm(np.cross(np.asarray(g["rendered"]["center"]) - c, n)) < 1e-6]
        if depths:
            out.append((f["id"], c, n, float(r), min(depths)))
    return out


def point_errors(xy, P, centre, normal, radius, depth, eye):
    """Each point's error along the true rim's outward normal and the wall band's width beside it, px.

    ``centre``, ``normal`` in the camera's frame (mm); ``eye`` the camera
    centre in it.
    """
    from scipy.spatial import cKDTree

    u = np.cross(normal, [1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.cross(normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    phi = np.linspace(0.0, 2.0 * np.pi, 7200, endpoint=False)
    X = centre + radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    rim = project(P, X)
    _, k = cKDTree(rim).query(xy)
    t = np.gradient(rim, axis=0)[k]
    t /= np.linalg.norm(t, axis=1)[:, None]
    out = np.c_[t[:, 1], -t[:, 0]]
    out[np.einsum("ni,ni->n", out, rim[k] - project(P, centre[None])[0]) < 0] *= -1
    down = -normal if normal @ (eye - centre) > 0 else normal
    band = -np.einsum("ni,ni->n", project(P, X[k] + depth * down) - rim[k], out)
    return np.einsum("ni,ni->n", xy - rim[k], out), band


def from_end(xy):
    """Each point's distance along the rim image from its nearest end, px (inf for a closed one)."""
    from partinspect.vision.contours import arc_length

    order = np.argsort(np.arctan2(*(xy - xy.mean(axis=0)).T[::-1]))
    p = xy[order]
    step = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)  # to the next point, round the rim
    s = arc_length(p)
    total = step.sum()
    dist = np.full(len(p), np.inf)
    for g in np.flatnonzero(step > END_GAP):
        for end in (s[g], s[(g + 1) % len(p)]):
            d = np.abs(s - end)
            dist = np.minimum(dist, np.minimum(d, total - d))
    out = np.empty(len(p))
    out[order] = dist
    return out


def mean_std(d2, type_b, length):
    """Standard deviation of the points' mean error the Type B states, correlated as ``exp(-d^2 / 4 l^2)``.

    ``d2``: the points' squared distances, (N, N) px^2.
    """
    return float(np.sqrt(type_b @ np.exp(-d2 / (4.0 * length * length)) @ type_b) / len(type_b))


def rim_images(part, size, noise, seed, work):
    """Per rim image of the three views: its records (semi-axis, errors, Type B, band widths, stated stds)."""
    from partinspect.simulate.render import sensor
    from partinspect.vision.ideal import camera_matrices
    from partinspect.vision.rim_errors import BACKGROUND_SMOOTHING, EDGE_BIAS_CORR_ANGLE
    from partinspect.vision.stereo import feature_views, measure_stereo

    out = []
    for k, turn in enumerate(TURNS, 1):
        left, right, rig, truth = radiance(part, k, turn, size, work)
        rng = np.random.default_rng([seed, k, 5151])
        res = measure_stereo(sensor(left, noise, rng), sensor(right, noise, rng), rig)
        T = np.asarray(truth["part_to_camera"], float)
        cams = camera_matrices(rig)
        eyes = (np.zeros(3), -rig.R.T @ np.ravel(rig.T))
        for cid, c, n, r, depth in true_rims(truth):
            c3, n3 = T[:3, :3] @ c + T[:3, 3], T[:3, :3] @ n
            hit = [f for f in res.features if f.kind == "circle" and np.linalg.norm(f.center - c3) < 1.0
                   and abs(f.radius - r) < 0.3]
            for f in hit[:1]:
                fl, fr = res.left.features[f.left], res.right.features[f.right]
                # The points as the 3D fit takes them: both corrections made, their Type B.
                views = feature_views(fl, fr, res.left.edges.sigma, rig)
                footprint = float(np.hypot(BACKGROUND_SMOOTHING, res.left.edges.sigma))
                for side, (fe, view) in enumerate(zip((fl, fr), views)):
                    err, band = point_errors(view.xy, cams[side], c3, n3, r, depth, eyes[side])
                    semi = float(max(fe.fit.params[2:4]))
                    d2 = np.sum((view.xy[:, None, :] - view.xy[None, :, :]) ** 2, axis=-1)
                    out.append(dict(view=k, id=cid, side=side, semi=semi, d=np.sqrt(d2), err=err, band=band,
                                    end=from_end(view.xy),
                                    type_b=view.bias, stated=mean_std(d2, view.bias, EDGE_BIAS_CORR_ANGLE * semi),
                                    footprint=mean_std(d2, view.bias, footprint)))
    return out


def by_size(records):
    rows = []
    for lo, hi in zip(SEMI_BINS[:-1], SEMI_BINS[1:]):
        rs = [r for r in records if lo <= r["semi"] < hi]
        if not rs:
            continue
        m = np.sqrt(np.mean([np.mean(r["err"]) ** 2 for r in rs]))
        s = np.sqrt(np.mean([r["stated"] ** 2 for r in rs]))
        f = np.sqrt(np.mean([r["footprint"] ** 2 for r in rs]))
        rows.append(f"  semi {lo:3.0f}-{hi:<4.0f} px: {len(rs):3d} rim images, RMS mean error {m:.4f} px, stated "
                    f"{s:.4f} (ratio {m / s:.2f}), over the footprint {f:.4f} (ratio {m / f:.2f})")
    return rows


def autocorrelation(records):
    """Pooled autocorrelation of the errors at ``LAGS`` px (pairs of points that far apart along the rim, +-25 %)."""
    out = []
    for lag in LAGS:
        num = den = 0.0
        for r in records:
            pair = np.abs(r["d"] - lag) <= 0.25 * lag
            num += float(np.sum(np.outer(r["err"], r["err"])[pair]))
            den += float(np.sum(r["err"] ** 2)) * pair.sum() / len(r["err"])
        out.append(num / den if den > 0 else np.nan)
    return out


def binned(records, key, bins, label):
    """Rows of the points' error binned by the records' ``key``; ``label(lo, hi)`` names a bin."""
    value, err, tb = (np.concatenate([r[k] for r in records]) for k in (key, "err", "type_b"))
    rows = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = (value >= lo) & (value < hi)
        if m.sum() >= 5:
            rows.append(f"  {label(lo, hi)}: {m.sum():5d} points, mean error {err[m].mean():+.4f} px, "
                        f"RMS {np.sqrt(np.mean(err[m] ** 2)):.4f}, mean Type B {tb[m].mean():.4f}")
    return rows


def by_band(records):
    return binned(records, "band", BAND_BINS, lambda lo, hi: f"band {lo:>5.0f} .. {hi:<5.0f} px")


def by_end(records):
    return binned(records, "end", END_BINS, lambda lo, hi: f"{lo:4.1f} .. {hi:<4.1f} px from an end")


def main(argv=None):
    from partinspect.vision.rim_errors import EDGE_BIAS_CORR_ANGLE

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="plate")
    ap.add_argument("--size", default="816x683")
    ap.add_argument("--noise", default="0,2")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_rim_geometry"))
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    args.work.mkdir(parents=True, exist_ok=True)
    if not (ROOT / "examples" / args.part).is_dir():
        ap.error(f"no sample part {args.part!r} in examples/")
    for noise in (float(v) for v in args.noise.split(",")):
        seeds = range(1 if noise == 0 else args.seeds)
        records = [r for s in seeds for r in rim_images(args.part, size, noise, s, args.work)]
        print(f"\n== {args.part}, {size[0]}x{size[1]}, noise {noise:g}, {len(seeds)} draw(s) of 3 views: "
              f"{len(records)} rim images, {sum(len(r['err']) for r in records)} points")
        print("The points' mean error per rim image against the std of that mean the Type B states:")
        print("\n".join(by_size(records)))
        semi = float(np.median([r["semi"] for r in records]))
        model = [np.exp(-lag**2 / (4.0 * (EDGE_BIAS_CORR_ANGLE * semi) ** 2)) for lag in LAGS]
        print("Autocorrelation of the errors along the rim (lag px: measured / the model at the median "
              f"rim, semi {semi:.0f} px):")
        print("  " + "  ".join(f"{lag}: {a:+.2f} / {b:.2f}" for lag, a, b in zip(LAGS, autocorrelation(records), model)))
        print("The points' error against the wall band's width beside them (negative: wall hidden):")
        print("\n".join(by_band(records)))
        print("The points' error against their distance along the rim image from its nearest end:")
        print("\n".join(by_end(records)))


if __name__ == "__main__":
    main()
