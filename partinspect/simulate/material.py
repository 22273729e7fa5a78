"""Machined metal: a microfacet highlight and directional machining marks.

A matte face (:func:`partinspect.cad.raycast.shade`) has the same grey from
every viewpoint. Metal does not: it reflects the light mostly about the
mirror direction, in a lobe whose width is the surface's roughness, so the
left and right cameras see a highlight in different places, and it moves
when the light does. The grey of a surface point is

    grey = ambient + albedo * (rho_d * m * (n.l) + pi * f_s * (n.l)),

``albedo`` the light's scale of :class:`~partinspect.cad.raycast.Shading`
(the grey of a white Lambertian face lit head-on), ``rho_d`` the diffuse
fraction, ``m`` the marks' albedo modulation, and ``f_s`` the Cook-Torrance
microfacet BRDF

    f_s = D(h) F(v.h) G(l, v) / (4 (n.l) (n.v)),

``h`` the half vector of light ``l`` and view ``v``, with the GGX
(Trowbridge-Reitz) distribution ``D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)``
of roughness ``a``, the separable Smith masking-shadowing of GGX
``G = G1(n.l) G1(n.v)``, ``G1(x) = 2 x / (x + sqrt(a^2 + (1 - a^2) x^2))``,
and Schlick's Fresnel ``F = F0 + (1 - F0) (1 - v.h)^5`` with the metal's
normal-incidence reflectance ``F0``. Highlights brighter than the sensor's
range saturate, as on a real camera.

Machining marks are parallel grooves of height ``A sin(2 pi s / p)``
across each face, ``s`` the position along the face's *groove normal*
``g``: a cylinder's axis (a bored or turned wall's marks run round it), or
on a plane a seeded direction in the plane (the tool's feed); any other
face takes the direction its normals spread least along, as for a cylinder.
The grooves tilt the normal by their slope, ``slope cos(2 pi s / p)``
towards ``g``, and modulate the diffuse albedo by ``1 + albedo_mod sin(2 pi
s / p)``. Grooves finer than a pixel would alias at one ray per pixel, so
both amplitudes are multiplied by the pixel's box filter response at the
grooves' frequency, ``sinc(w / p)`` with ``w`` the pixel's footprint on the
surface (clamping, [4]_).

References
----------
.. [1] Cook, R. L., Torrance, K. E. (1982). A reflectance model for
       computer graphics. ACM Trans. Graph. 1(1), 7-24.
.. [2] Walter, B., Marschner, S. R., Li, H., Torrance, K. E. (2007).
       Microfacet models for refraction through rough surfaces. Proc.
       Eurographics Symposium on Rendering, 195-206 (GGX, its Smith G1).
.. [3] Schlick, C. (1994). An inexpensive BRDF model for physically-based
       rendering. Computer Graphics Forum 13(3), 233-246.
.. [4] Norton, A., Rockwood, A. P., Skolmoski, P. T. (1982). Clamping: a
       method of antialiasing textured surfaces by bandwidth limiting in
       object space. Computer Graphics 16(3), 1-8 (SIGGRAPH '82).
"""

from dataclasses import asdict, dataclass

import numpy as np

from partinspect.cad.raycast import MISS, surface_normals

__all__ = ["Material", "MATERIALS", "Finish", "parse_material", "finish", "shade_material"]


@dataclass(frozen=True)
class Material:
    """Reflection and machining marks of a metal.

    Attributes
    ----------
    name : str
    diffuse : float
        Diffuse fraction rho_d (the scattered part of a rough metal's light).
    f0 : float
        Fresnel reflectance at normal incidence (Schlick's F0).
    roughness : float
        GGX roughness a (the microfacet slopes' width).
    mark_period : float
        Period p of the grooves, mm.
    mark_slope : float
        Amplitude of the grooves' slope, radians (a groove height of
        ``slope * p / (2 pi)``).
    mark_albedo : float
        Relative amplitude of the diffuse albedo's modulation by the grooves.
    """

    name: str
    diffuse: float
    f0: float
    roughness: float
    mark_period: float
    mark_slope: float
    mark_albedo: float


# F0: the metals' normal-incidence reflectance at 550 nm (aluminium 0.91,
# iron 0.56). Milled aluminium: face-milling feed marks 0.15 mm apart, about
# 1.2 um high (Ra ~ 0.8 um); ground steel: grinding scratches 0.03 mm apart,
# about 0.4 um high (Ra ~ 0.25 um), a narrower lobe.
MATERIALS = {
    "aluminium": Material("aluminium", diffuse=0.45, f0=0.91, roughness=0.30, mark_period=0.15, mark_slope=0.05,
                          mark_albedo=0.04),
    "steel": Material("steel", diffuse=0.35, f0=0.56, roughness=0.18, mark_period=0.03, mark_slope=0.08,
                      mark_albedo=0.03),
}


@dataclass(frozen=True, eq=False)
class Finish:
    """A material laid on a scene's faces.

    Attributes
    ----------
    material : Material
    seed : int
    grooves : ndarray, shape (L, 3)
        Unit groove normal ``g`` of every CAD face label, part frame.
    phase : ndarray, shape (L,)
        Offset of each face's grooves, mm.
    """

    material: Material
    seed: int
    grooves: np.ndarray
    phase: np.ndarray

    def to_dict(self):
        d = asdict(self.material)
        d.update(seed=int(self.seed), model="lambertian diffuse + Cook-Torrance microfacet (GGX D, separable Smith G, "
                 "Schlick F), grooves of period mark_period mm and slope amplitude mark_slope rad along each face's "
                 "groove normal, amplitudes clamped by sinc(pixel footprint / period)")
        return d


def parse_material(text):
    """``NAME[:SEED]`` as (Material or None for matte, seed).

    Raises
    ------
    ValueError
        Unknown name or a seed that is not an integer.
    """
    name, _, seed = str(text).partition(":")
    names = ["matte", *MATERIALS]
    if name not in names:
        raise ValueError(f"unknown material {name!r}; one of {', '.join(names)}")
    try:
        seed = int(seed) if seed else 0
    except ValueError:
        raise ValueError(f"the marks' seed must be an integer, got {text!r}") from None
    return (None if name == "matte" else MATERIALS[name]), seed


def finish(rs, material, seed=0):
    """Lay a material on every face of a scene, with its grooves' directions.

    Parameters
    ----------
    rs : RaycastScene
    material : Material
    seed : int
        Seeds the planes' feed directions and every face's groove phase.

    Returns
    -------
    Finish
    """
    L = int(rs.labels.max()) + 1
    area = np.linalg.norm(np.cross(rs.vertices[rs.triangles[:, 1]] - rs.vertices[rs.triangles[:, 0]],
                                   rs.vertices[rs.triangles[:, 2]] - rs.vertices[rs.triangles[:, 0]]), axis=1)
    scatter = np.zeros((L, 3, 3))
    np.add.at(scatter, rs.labels, area[:, None, None] * rs.flat_normals[:, :, None] * rs.flat_normals[:, None, :])
    rng = np.random.default_rng([int(seed), 5527])
    angle = rng.uniform(0.0, np.pi, L)
    phase = rng.uniform(0.0, material.mark_period, L)
    grooves = np.zeros((L, 3))
    for k in range(L):
        trace = np.trace(scatter[k])
        if trace <= 0:
            grooves[k] = (1.0, 0.0, 0.0)
            continue
        w, e = np.linalg.eigh(scatter[k] / trace)
        # Normals confined to a plane (a cylinder, a cone): the least spread
        # direction is the axis. All alike (a plane): a seeded feed direction
        # within the plane.
        if w[1] - w[0] > 0.05:
            grooves[k] = e[:, 0]
        else:
            grooves[k] = np.cos(angle[k]) * e[:, 0] + np.sin(angle[k]) * e[:, 1]
    return Finish(material, int(seed), grooves, phase)


def _ggx_g1(x, a2):
    return 2.0 * x / (x + np.sqrt(a2 + (1.0 - a2) * x * x))


def shade_material(rs, hits, origin, directions, light, shading, fin, pixel_angle, marks=True):
    """Grey of every ray on a machined metal part.

    Parameters
    ----------
    rs : RaycastScene
    hits : Hits
    origin : ndarray, shape (3,)
        The camera centre, part frame, mm.
    directions : ndarray, shape (N, 3)
        Unit ray directions, part frame.
    light : ndarray, shape (3,)
        Unit direction towards the light, part frame.
    shading : Shading
        Its ``ambient``, ``albedo`` (the light's scale) and ``background``.
    fin : Finish
    pixel_angle : float
        Angle one pixel subtends, radians (``1 / f`` px).
    marks : bool
        False leaves the grooves out (the smooth surface's grey).

    Returns
    -------
    grey : ndarray of float32, shape (N,)
    """
    m = fin.material
    hit = hits.label != MISS
    grey = np.full(len(hits.label), shading.background, np.float32)
    if not hit.any():
        return grey
    n = surface_normals(rs, hits, directions)
    v = -directions[hit]
    albedo = np.full(len(n), m.diffuse)
    if marks and m.mark_slope > 0:
        label = hits.label[hit]
        dist = hits.distance[hit]
        g = fin.grooves[label]
        point = origin + dist[:, None] * directions[hit]
        s = np.einsum("ij,ij->i", point, g) + fin.phase[label]
        nv = np.abs(np.einsum("ij,ij->i", n, v))
        footprint = dist * pixel_angle / np.maximum(nv, 0.1)
        clamp = np.sinc(footprint / m.mark_period)
        phi = 2.0 * np.pi * s / m.mark_period
        gt = g - np.einsum("ij,ij->i", g, n)[:, None] * n  # g within the tangent plane
        gt_norm = np.linalg.norm(gt, axis=1)
        gt /= np.where(gt_norm > 1e-9, gt_norm, np.inf)[:, None]
        n = n - (m.mark_slope * clamp * np.cos(phi))[:, None] * gt
        n /= np.linalg.norm(n, axis=1)[:, None]
        albedo = albedo * (1.0 + m.mark_albedo * clamp * np.sin(phi))
    nl = np.maximum(0.0, n @ light)
    nv = np.maximum(np.einsum("ij,ij->i", n, v), 1e-4)
    h = v + light
    h /= np.linalg.norm(h, axis=1)[:, None]
    nh = np.clip(np.einsum("ij,ij->i", n, h), 0.0, 1.0)
    vh = np.clip(np.einsum("ij,ij->i", v, h), 0.0, 1.0)
    a2 = m.roughness ** 2
    D = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    F = m.f0 + (1.0 - m.f0) * (1.0 - vh) ** 5
    G = _ggx_g1(nl, a2) * _ggx_g1(nv, a2)
    # pi f_s (n.l) = pi D F G / (4 n.v); zero where the light is behind the face
    specular = np.where(nl > 0, np.pi * D * F * G / (4.0 * nv), 0.0)
    grey[hit] = shading.ambient + shading.albedo * (albedo * nl + specular)
    return grey
