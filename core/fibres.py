"""Resampling muscle fibres into particles (the paper's §3.1, DESIGN §6 "Fibres").

A fibre is a polyline from origin to insertion. It becomes ``n`` particles: the two end
particles sit exactly on the fibre's end points and are *fixed* (tendon attachment, §3.2).
The fibre's arc length ``L`` is cut into ``n - 1`` equal intervals of length ``h = L / (n - 1)``,
numbered ``0 .. n - 2``; interval ``k`` is ``[k h, (k + 1) h]``. Particle ``k``
(``0 <= k <= n - 2``) lies in interval ``k``: the origin particle at its start, every free
particle ``1 .. n - 2`` at a uniformly random arc-length place ``(k + u) h``, ``u`` in ``[0, 1)``;
the insertion particle ``n - 1`` closes the last interval. With randomisation off ``u = 0``,
i.e. the particles are the interval end points ``k h``. The paper randomises because fibres of
about equal length would otherwise put their particles in clusters across the muscle, with gaps
between them that the sphere-based collision detection (§3.3) sees as holes.

Randomness comes from ``numpy.random.default_rng(seed)``; the same fibres, ``n`` and seed give
the same particles.
"""
from __future__ import annotations

import numba
import numpy as np

from .errors import MuscleMSSError


@numba.njit(parallel=True, cache=True)
def _place_particles(points, offsets, arc, fractions, out):
    """Particles at arc-length fractions of each fibre.

    points (v, 3) float64 mm, offsets (F + 1,) int64, arc (v,) float64 mm (arc length of each
    vertex from its fibre's origin), fractions (F, n) float64 ascending in [0, 1],
    out (F * n, 3) float64 mm, written.
    """
    n_fibres, n = fractions.shape
    for f in numba.prange(n_fibres):
        start = offsets[f]
        last = offsets[f + 1] - 1
        length = arc[last]
        seg = start
        for j in range(n):
            s = fractions[f, j] * length
            # the fractions ascend, so the segment holding s only ever moves forward
            while seg < last - 1 and arc[seg + 1] < s:
                seg += 1
            a = arc[seg]
            b = arc[seg + 1]
            t = (s - a) / (b - a) if b > a else 0.0
            t = min(max(t, 0.0), 1.0)
            # (1 - t) p + t q is exact at both ends, so end particles equal the end points
            for d in range(3):
                out[f * n + j, d] = (1.0 - t) * points[seg, d] + t * points[seg + 1, d]


def check_fibres(points, offsets, where: str = "fibres") -> None:
    """Raise :class:`MuscleMSSError` unless the fibres can be resampled.

    Rules: at least one fibre; every fibre has at least 2 points, finite coordinates and a
    non-zero length. ``where`` names the block in messages, e.g. ``"fibres.vtm block 'gracilis'"``.

    Parameters
    ----------
    points : (v, 3) float64, mm
        All fibre vertices, fibre by fibre.
    offsets : (F + 1,) int
        Fibre ``f`` is ``points[offsets[f]:offsets[f + 1]]``.
    """
    points = np.asarray(points)
    offsets = np.asarray(offsets)
    if len(offsets) < 2:
        raise MuscleMSSError(f"{where} has no fibres; a muscle needs at least one fibre polyline")
    if offsets[0] != 0 or offsets[-1] != len(points) or (np.diff(offsets) < 0).any():
        raise MuscleMSSError(f"{where}: fibre offsets do not describe the {len(points)} points")
    counts = np.diff(offsets)
    short = np.flatnonzero(counts < 2)
    if len(short):
        f = int(short[0])
        raise MuscleMSSError(f"{where}: fibre {f} has {int(counts[f])} point"
                             f"{'' if counts[f] == 1 else 's'}; a fibre needs at least 2")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        f = int(np.searchsorted(offsets, np.flatnonzero(bad)[0], side="right") - 1)
        raise MuscleMSSError(f"{where}: fibre {f} has a NaN or infinite coordinate; "
                             "every coordinate must be finite")
    lengths = fibre_lengths(points, offsets)
    flat = np.flatnonzero(lengths <= 0.0)
    if len(flat):
        raise MuscleMSSError(f"{where}: fibre {int(flat[0])} has zero length; "
                             "a fibre's end points must differ")


def _vertex_arc_lengths(points, offsets):
    """(v,) float64 mm: arc length of every vertex measured from its fibre's origin."""
    step = np.zeros(len(points))
    step[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1)
    step[offsets[:-1]] = 0.0        # no step from the previous fibre's insertion
    total = np.cumsum(step)
    return total - np.repeat(total[offsets[:-1]], np.diff(offsets))


def fibre_lengths(points, offsets) -> np.ndarray:
    """(F,) float64 mm: the arc length of every fibre (CSR layout as in :func:`check_fibres`)."""
    points = np.asarray(points, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    return _vertex_arc_lengths(points, offsets)[offsets[1:] - 1]


def interval_fractions(n_fibres: int, n: int, randomise: bool, seed=0) -> np.ndarray:
    """(F, n) float64: arc-length fraction of each particle of each fibre (see the module doc).

    ``seed`` is anything ``numpy.random.default_rng`` takes (an int or a sequence of ints).
    """
    k = np.arange(n, dtype=np.float64)
    fractions = np.broadcast_to(k, (n_fibres, n)).copy()
    if randomise and n > 2:
        fractions[:, 1:-1] += np.random.default_rng(seed).random((n_fibres, n - 2))
    fractions /= n - 1
    return fractions


def resample_fibres(points, offsets, n: int, randomise: bool = True, seed=0,
                    where: str = "fibres"):
    """Sample every fibre into ``n`` particles (paper §3.1).

    Parameters
    ----------
    points : (v, 3) float64, mm
        All fibre vertices, fibre by fibre, each fibre from origin to insertion.
    offsets : (F + 1,) int
        Fibre ``f`` is ``points[offsets[f]:offsets[f + 1]]``.
    n : int
        Particles per fibre, at least 2.
    randomise : bool
        Free particles at a uniformly random place inside their interval (True) or at the
        interval end points (False).
    seed : int or sequence of int
        Seed of the random placement.
    where : str
        Names the block in error messages.

    Returns
    -------
    particles : (F * n, 3) float64, mm
        Fibre by fibre, origin to insertion: particle ``f * n + j`` is fibre ``f``'s ``j``-th.
    fibre_id : (F * n,) int32
    fibre_index : (F * n,) int32
        0 at the origin, ``n - 1`` at the insertion.
    fixed : (F * n,) uint8
        1 for the two end particles of every fibre.

    Raises
    ------
    MuscleMSSError
        ``n < 2``, no fibres, a fibre with fewer than 2 points, zero length or non-finite points.
    """
    if int(n) != n or n < 2:
        raise MuscleMSSError(f"{where}: {n} particles per fibre asked; a fibre needs at least 2 "
                             "(its two fixed end particles)")
    n = int(n)
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    check_fibres(points, offsets, where)
    n_fibres = len(offsets) - 1
    fractions = interval_fractions(n_fibres, n, randomise, seed)
    particles = np.empty((n_fibres * n, 3))
    _place_particles(points, offsets, _vertex_arc_lengths(points, offsets), fractions, particles)
    fibre_id = np.repeat(np.arange(n_fibres, dtype=np.int32), n)
    fibre_index = np.tile(np.arange(n, dtype=np.int32), n_fibres)
    fixed = ((fibre_index == 0) | (fibre_index == n - 1)).astype(np.uint8)
    return particles, fibre_id, fibre_index, fixed
