"""Shared geometry of the demo scenes (DESIGN §4): implicit solids and muscles built around a limb
axis.

The thigh (:mod:`.demo.scene`) and the elbow (:mod:`.demo.arm`) are made the same way, so the
machinery lives here once:

* implicit primitives (negative inside, roughly the signed distance in mm near the surface) and
  their smooth union, from which the bones are composed (and meshed by :mod:`.implicit_meshing`);
* muscles: a fusiform envelope (elliptic cross-section in horizontal slices) around a centreline
  through anatomical way-points, oriented by the limb's axis. Neighbouring envelopes overlap; where
  they do, each keeps the part where its own normalised elliptic distance is the smaller (a
  weighted Voronoi split), so that neighbours meet along a shared face instead of
  interpenetrating, and envelopes reaching into a bone are cut at its surface so that deep muscles
  lie against it. The surface is found by marching rays outward from the centreline in each slice
  to the first point outside; the fibres of the ``fibre_grid`` are placed along the same rays, the
  outer ring just beneath the surface.

Everything is built from closed formulas: no random numbers, no files.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from ..errors import MuscleMSSError
from .implicit_meshing import mesh_sampled
from ..scene import FibreSet, Scene, Surface


@dataclass(frozen=True)
class Size:
    """How finely a demo scene is built."""

    bone_spacing: float   # marching-tetrahedra grid step (mm)
    grid: int             # fibres per side of the fibre_grid
    fibre_vertices: int   # vertices per fibre polyline
    refine: int           # muscle surface rings per interval between fibre vertices
    ring_vertices: int    # vertices per muscle surface ring


# ---- rigid transforms ----------------------------------------------------------------------

def rotation_about(axis, centre, angle_deg) -> np.ndarray:
    """The 3x4 rigid transform rotating by ``angle_deg`` about the line through ``centre`` (mm)
    along ``axis`` (right-hand rule)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    a = np.radians(angle_deg)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    r = np.eye(3) + np.sin(a) * cross + (1.0 - np.cos(a)) * (cross @ cross)
    centre = np.asarray(centre, dtype=np.float64)
    return np.hstack([r, (centre - r @ centre)[:, None]])


def compose(outer, inner) -> np.ndarray:
    """3x4 transform of ``x -> outer(inner(x))``."""
    return np.hstack([outer[:, :3] @ inner[:, :3], (outer[:, :3] @ inner[:, 3] + outer[:, 3])[:, None]])



# ---- implicit primitives (negative inside, roughly the distance in mm near the surface) -----

def v(*xyz):
    return np.array(xyz, dtype=np.float64)


def sphere(p, centre, radius):
    return np.linalg.norm(p - centre, axis=1) - radius


def ellipsoid(p, centre, radii, frame=None):
    """``frame`` (3, 3): rows are the unit axes of the semi-axes ``radii``; None = x, y, z."""
    q = p - centre
    if frame is not None:
        q = q @ np.asarray(frame).T
    return (np.linalg.norm(q / radii, axis=1) - 1.0) * np.min(radii)


def round_cone(p, a, b, radius_a, radius_b):
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - (radius_a + t * (radius_b - radius_a))


def smooth_union(k, *fields):
    """Smooth union of signed fields; ``k`` (mm) is the width of the fillet between parts."""
    out = fields[0]
    for f in fields[1:]:
        h = np.clip(0.5 + 0.5 * (f - out) / k, 0.0, 1.0)
        out = f + (out - f) * h - k * h * (1.0 - h)
    return out


def frame(long_axis, towards):
    """Orthonormal rows (long axis, second axis in the plane of ``towards``, normal)."""
    e0 = np.asarray(long_axis, dtype=np.float64)
    e0 = e0 / np.linalg.norm(e0)
    e1 = np.asarray(towards, dtype=np.float64) - (np.dot(towards, e0)) * e0
    e1 = e1 / np.linalg.norm(e1)
    return np.array([e0, e1, np.cross(e0, e1)])


# ---- muscles -------------------------------------------------------------------------------

def around(axis, z, theta_deg, rho) -> np.ndarray:
    """The point at height ``z``, ``rho`` mm from the limb ``axis`` (as in :class:`Envelope`) in
    direction ``theta_deg`` (0 lateral, 90 anterior, 180 medial, 270 posterior)."""
    a = np.radians(theta_deg)
    return axis(np.array([z]))[0] + rho * np.array([np.cos(a), np.sin(a), 0.0])


@dataclass(frozen=True)
class MuscleSpec:
    """One demo muscle: attachments, centreline way-points and belly shape."""

    origin_bone: str
    origin: np.ndarray          # landmark near the origin (projected onto the bone)
    insertion_bone: str
    insertion: np.ndarray
    waypoints: tuple            # interior centreline points (mm), z decreasing
    radial: float               # belly semi-axis away from the limb axis (mm)
    tangential: float           # belly semi-axis around the limb axis (mm)
    peak: float = 0.5           # where along the muscle (0 origin, 1 insertion) the belly peaks
    fullness: float = 0.6       # exponent of the belly profile: small = long full belly


_TENDON = 2.5        # semi-axis of the muscle's cross-section at origin and insertion (mm)
_CAP = 3.0           # length of the rounded end cap beyond origin and insertion (mm)
_FIBRE_DEPTH = 0.92  # the outer ring of fibres lies at this fraction of the way to the surface
_OVERLAP = 0.03      # neighbours overlap by this fraction of their semi-axes along a shared face
_BONE_CONTACT = 0.3  # muscles press this far (mm) into the bones they lie against
_ATTACHMENT_DEPTH = 5.0  # ...and up to this far (mm) at their attachments
_ATTACHMENT_REACH = 15.0  # over this distance (mm) around the attachment point


class Envelope:
    """A muscle's centreline and elliptic fusiform cross-section as functions of height z.

    ``axis``: callable, heights (k,) mm -> points (k, 3) of the limb's axis; the cross-section's
    radial semi-axis points away from it.
    """

    def __init__(self, origin, insertion, waypoints, spec, axis):
        knots = np.vstack([origin, *waypoints, insertion])
        if (np.diff(knots[:, 2]) >= 0).any():
            raise MuscleMSSError("demo muscle way-points must descend from origin to insertion")
        self.z_origin, self.z_insertion = origin[2], insertion[2]
        self.length = self.z_origin - self.z_insertion
        self.spec = spec
        self.z_top, self.z_bottom = self.z_origin + _CAP, self.z_insertion - _CAP
        # Tabulated finely once: every field evaluation interpolates these instead of the spline.
        self._z = np.linspace(self.z_bottom, self.z_top, int(np.ceil((self.z_top - self.z_bottom) / 0.25)) + 1)
        xy = PchipInterpolator(knots[::-1, 2], knots[::-1, :2], extrapolate=True)(self._z)
        radial = xy - axis(self._z)[:, :2]
        a, b = self._profile(self._z)
        self._table = np.column_stack([xy, radial / np.linalg.norm(radial, axis=1)[:, None], a, b])
        reach = np.maximum(a, b)
        self._box = (np.min(xy - reach[:, None], axis=0), np.max(xy + reach[:, None], axis=0))

    def _lookup(self, z, column):
        return np.interp(z, self._z, self._table[:, column])

    def centre(self, z):
        z = np.asarray(z, dtype=np.float64)
        return np.column_stack([self._lookup(z, 0), self._lookup(z, 1), z])

    def radial_direction(self, z):
        d = np.column_stack([self._lookup(z, 2), self._lookup(z, 3)])
        return d / np.linalg.norm(d, axis=1)[:, None]

    def semi_axes(self, z):
        """(radial, tangential) semi-axes (mm) at heights z; 0 outside the muscle."""
        return self._lookup(z, 4), self._lookup(z, 5)

    def _profile(self, z):
        u = (self.z_origin - z) / self.length
        inner = np.clip(u, 0.0, 1.0) ** (np.log(0.5) / np.log(self.spec.peak))
        bell = np.sin(np.pi * inner) ** self.spec.fullness
        beyond = np.maximum(np.maximum(z - self.z_origin, self.z_insertion - z), 0.0)
        cap = np.sqrt(np.clip(1.0 - (beyond / _CAP) ** 2, 0.0, 1.0))
        radial = (_TENDON + (self.spec.radial - _TENDON) * bell) * cap
        tangential = (_TENDON + (self.spec.tangential - _TENDON) * bell) * cap
        return radial, tangential

    def elliptic_distance(self, points):
        """Normalised elliptic distance of ``points`` (n, 3) from the centreline in their own
        horizontal slice: 1 on the envelope; inf above or below the muscle."""
        z = points[:, 2]
        within = ((z < self.z_top) & (z > self.z_bottom)
                  & (points[:, :2] > self._box[0]).all(axis=1)
                  & (points[:, :2] < self._box[1]).all(axis=1))
        out = np.full(len(points), np.inf)
        if within.any():
            zw = z[within]
            offset = points[within, :2] - self.centre(zw)[:, :2]
            radial_dir = self.radial_direction(zw)
            a, b = self.semi_axes(zw)
            along = np.einsum("ij,ij->i", offset, radial_dir)
            across = offset[:, 1] * radial_dir[:, 0] - offset[:, 0] * radial_dir[:, 1]
            out[within] = np.hypot(along / a, across / b)
        return out


def muscle_field(name, envelopes, spec, bones):
    """Implicit function of one muscle: inside its envelope, on its side of every neighbour,
    outside the ``bones`` (name -> :class:`.implicit_meshing.SampledField`) except near its
    attachments."""
    own = envelopes[name]
    others = [e for n, e in envelopes.items() if n != name]
    attachments = {}
    for bone, point in ((spec.origin_bone, own.centre(np.array([own.z_origin]))[0]),
                        (spec.insertion_bone, own.centre(np.array([own.z_insertion]))[0])):
        attachments.setdefault(bone, []).append(point)

    def field(points):
        mine = own.elliptic_distance(points)
        f = mine - 1.0
        if others:
            nearest_other = np.min([e.elliptic_distance(points) for e in others], axis=0)
            # Above or below this muscle (mine = inf) f is inf already; avoid inf - inf.
            split = np.where(np.isfinite(mine), mine - np.minimum(nearest_other, 1e9), np.inf)
            f = np.maximum(f, split - _OVERLAP)
        for bone, sampled in bones.items():
            allowed = np.full(len(points), _BONE_CONTACT)
            for a in attachments.get(bone, ()):
                closeness = np.clip(1.0 - np.linalg.norm(points - a, axis=1) / _ATTACHMENT_REACH,
                                    0.0, 1.0)
                allowed = np.maximum(allowed, _ATTACHMENT_DEPTH * closeness)
            f = np.maximum(f, -sampled.interpolate(points) - allowed)
        return f

    return field


def cast_to_surface(field, origins, directions, reach, samples=16, halvings=13):
    """Distance (mm) along each ray from ``origins`` (r, 3) in unit ``directions`` (r, 3) to the
    first point where ``field`` >= 0; ``reach`` (r,) must lie beyond that point."""
    steps = reach[:, None] * (np.arange(1, samples + 1) / samples)[None, :]
    values = field((origins[:, None, :] + steps[..., None] * directions[:, None, :]).reshape(-1, 3))
    outside = values.reshape(steps.shape) >= 0.0
    first = np.argmax(outside, axis=1)
    rows = np.arange(len(origins))
    hi = steps[rows, first]
    lo = np.where(first > 0, steps[rows, np.maximum(first - 1, 0)], 0.0)
    for _ in range(halvings):
        mid = 0.5 * (lo + hi)
        below = field(origins + mid[:, None] * directions) < 0.0
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def slice_rays(envelope, z, guide):
    """Rays in the horizontal slices at heights ``z`` (k,) from the centreline, one per guide
    point (m, 2) on the unit circle, spread like the envelope's ellipse.

    Returns origins (k*m, 3), unit directions (k*m, 3) and the envelope radius along each
    direction (k*m,), all in mm.
    """
    centre = envelope.centre(z)
    radial = envelope.radial_direction(z)
    tangential = np.column_stack([-radial[:, 1], radial[:, 0]])
    a, b = envelope.semi_axes(z)
    a, b = np.maximum(a, 1e-3), np.maximum(b, 1e-3)
    d = (guide[None, :, 0, None] * a[:, None, None] * radial[:, None, :]
         + guide[None, :, 1, None] * b[:, None, None] * tangential[:, None, :])
    d = d / np.linalg.norm(d, axis=2, keepdims=True)
    along = np.einsum("kmj,kj->km", d, radial)
    across = np.einsum("kmj,kj->km", d, tangential)
    reach = 1.0 / np.hypot(along / a[:, None], across / b[:, None])
    directions = np.concatenate([d, np.zeros(d.shape[:2] + (1,))], axis=2).reshape(-1, 3)
    origins = np.repeat(centre, guide.shape[0], axis=0)
    return origins, directions, reach.reshape(-1)


def tube_triangles(rings, ring_vertices):
    """Triangles (outward for rings stacked top to bottom, counter-clockwise seen from above)
    of a tube of ``rings`` rings capped by a top pole (index 0) and a bottom pole (last)."""
    m = ring_vertices
    k = np.arange(m)
    ring = lambda r: 1 + r * m + k                          # noqa: E731
    top = np.column_stack([np.zeros(m, dtype=np.int64), ring(0), ring(0)[(k + 1) % m]])
    bottom_pole = 1 + rings * m
    bottom = np.column_stack([np.full(m, bottom_pole), ring(rings - 1)[(k + 1) % m], ring(rings - 1)])
    sides = []
    for r in range(rings - 1):
        a, b = ring(r), ring(r + 1)
        a1, b1 = a[(k + 1) % m], b[(k + 1) % m]
        sides.append(np.column_stack([a, b1, a1]))
        sides.append(np.column_stack([a, b, b1]))
    return np.vstack([top, *sides, bottom]).astype(np.int64)


def square_to_disc(sx, sy):
    """Map the square [-1, 1]^2 onto the unit disc (keeps the grid's rows and columns apart)."""
    return sx * np.sqrt(1.0 - sy ** 2 / 2.0), sy * np.sqrt(1.0 - sx ** 2 / 2.0)


def build_muscle(name, spec, envelopes, bones, size):
    """Surface and fibres of muscle ``name`` (its :class:`MuscleSpec` ``spec``) among
    ``envelopes`` (name -> :class:`Envelope`), cut at ``bones`` (name ->
    :class:`.implicit_meshing.SampledField`), built at :class:`Size` ``size``: ``(Surface,
    FibreSet)``."""
    envelope = envelopes[name]
    field = muscle_field(name, envelopes, spec, bones)

    # Surface: rings in horizontal slices through every fibre vertex: the surface's cross-section
    # there is exactly the ring polygon, which holds the fibre vertices of that slice.
    u = np.linspace(0.0, 1.0, size.refine * (size.fibre_vertices - 1) + 1)
    cap_u = np.array([0.45, 0.8]) * _CAP / envelope.length
    u = np.concatenate([-cap_u[::-1], u, 1.0 + cap_u])
    z = envelope.z_origin - u * envelope.length
    angles = 2.0 * np.pi * np.arange(size.ring_vertices) / size.ring_vertices
    # Counter-clockwise seen from above, as tube_triangles expects.
    guide = np.column_stack([np.cos(angles), np.sin(angles)])
    origins, directions, reach = slice_rays(envelope, z, guide)
    distance = cast_to_surface(field, origins, directions, 1.02 * reach)
    poles = envelope.centre(np.array([envelope.z_top, envelope.z_bottom]))
    points = np.vstack([poles[:1], origins + distance[:, None] * directions, poles[1:]])
    triangles = tube_triangles(len(z), size.ring_vertices)

    # Fibres: a grid (row across the limb, column around it) mapped onto the cross-section and
    # carried along the slices from origin (u = 0) to insertion (u = 1).
    g = size.grid
    rows, cols = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    sx, sy = square_to_disc((2.0 * rows.ravel() + 1.0) / g - 1.0, (2.0 * cols.ravel() + 1.0) / g - 1.0)
    fraction = np.hypot(sx, sy)
    # The centre fibre of an odd grid may take any direction: its fraction is zero.
    fibre_guide = np.where(fraction[:, None] > 0.0, np.column_stack([sx, sy]), [1.0, 0.0])
    fibre_guide = fibre_guide / np.linalg.norm(fibre_guide, axis=1)[:, None]
    fibre_u = np.linspace(0.0, 1.0, size.fibre_vertices)
    fibre_z = envelope.z_origin - fibre_u * envelope.length
    f_origins, f_dirs, f_reach = slice_rays(envelope, fibre_z, fibre_guide)
    f_distance = cast_to_surface(field, f_origins, f_dirs, 1.02 * f_reach)
    # Fibres gather towards the tendons so that their ends stay on the attachment area.
    gather = 1.0 - 0.5 * np.exp(-(fibre_u / 0.04) ** 2) - 0.5 * np.exp(-((1.0 - fibre_u) / 0.04) ** 2)
    depth = _FIBRE_DEPTH * fraction[None, :] * gather[:, None]
    fibre_points = f_origins + (depth.reshape(-1) * f_distance)[:, None] * f_dirs
    # (vertex along the fibre, fibre) -> fibre-major polylines.
    polylines = fibre_points.reshape(size.fibre_vertices, g * g, 3).transpose(1, 0, 2)
    fibres = FibreSet.from_polylines(list(polylines), np.column_stack([rows.ravel(), cols.ravel()]))
    fibres.origin_bone, fibres.insertion_bone = spec.origin_bone, spec.insertion_bone
    return Surface(points, triangles), fibres


def make_envelopes(specs, names, project, axis):
    """``{name: Envelope}`` of the muscles ``names`` of ``specs`` (name -> :class:`MuscleSpec`);
    ``project(bone, point)`` puts an attachment landmark onto its bone's surface, ``axis`` is
    the limb axis of :class:`Envelope`."""
    envelopes = {}
    for name in names:
        spec = specs[name]
        origin = project(spec.origin_bone, spec.origin)
        insertion = project(spec.insertion_bone, spec.insertion)
        envelopes[name] = Envelope(origin, insertion, spec.waypoints, spec, axis)
    return envelopes


def size_named(size: str, sizes: dict) -> Size:
    """The :class:`Size` called ``size`` among ``sizes`` (name -> Size)."""
    if size not in sizes:
        raise MuscleMSSError(f"demo scene size '{size}' is unknown; choose one of: "
                             f"{', '.join(sizes)}")
    return sizes[size]


def assemble_scene(motion, bones, specs, names, project, axis, size) -> Scene:
    """A demo scene of ``motion``, the ``bones`` (name -> :class:`.implicit_meshing.SampledField`)
    meshed, and the muscles ``names`` of ``specs`` built around them at :class:`Size` ``size``
    (:func:`make_envelopes` with ``project`` and ``axis``, :func:`build_muscle`)."""
    scene = Scene(motion=motion)
    for bone, sampled in bones.items():
        scene.bones[bone] = mesh_sampled(sampled)
    envelopes = make_envelopes(specs, names, project, axis)
    for name in names:
        scene.muscles[name], scene.fibres[name] = build_muscle(name, specs[name], envelopes,
                                                               bones, size)
    return scene
