"""The connective tissue around the muscles (DESIGN §6 "Connective tissue"): epimysium,
intermuscular septa and fascia tie every muscle to its neighbours and to the tissue around it,
which moves with the skeleton. Modelled as a spring of stiffness ``k_i`` holding each free
particle ``i`` toward its *target* ``t_i``, its rest position carried by the pose (the Rigid
Pose Transform's posed position; in a muscle that fibre shortening shortens, its rest shape
shortened between its attachments: :func:`~muscle_mss.core.fibre_shortening.shortened_target`):

    E_tissue = sum_i k_i |x_i - t_i|^2 / 2        (g mm^2 / s^2)

Without it the slack, slender muscles bend with about 1e-4 of a spring's stiffness, so their
equilibrium is not determined to a tenth of a millimetre and every solve's shape is set by its
iteration cap. ``k_i`` is ``ratio`` times the mean stiffness of the particle's muscle's springs,
scaled by ``((REFERENCE_PARTICLES - 1) / (N_m - 1))^2`` for a muscle of ``N_m`` particles per
fibre: a fibre's springs act in series, so its stretching and bending stiffness fall as
``1 / (N - 1)`` while the tissue along it grows as ``N - 1``; the square keeps their balance,
and so the shape, the same at every resolution (the ratio is the one at
:data:`REFERENCE_PARTICLES` particles per fibre). ``ratio = 0`` is the paper's model.

Weaker along the fibres (``along`` < 1, the fraction of the stiffness across that acts along the
particle's posed fibre direction ``f_i``)::

    E_tissue = sum_i k_i (|d_i|^2 - (1 - along) (d_i . f_i)^2) / 2,     d_i = x_i - t_i

so that a fibre lengthens and shortens, and a muscle slides along its neighbours, against a
tissue ``along`` times as stiff as the one holding it sideways. The kernels take it as
*targets* (6, n): rows 0-2 ``t_i``, rows 3-5 ``g_i = sqrt(1 - along) f_i`` (energy
``k_i (|d|^2 - (d . g)^2) / 2``); (3, n) targets, ``along = 1``, are the isotropic tissue,
computed without the along term.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .model import REFERENCE_PARTICLES
from .mss import along_part

__all__ = ["REFERENCE_PARTICLES", "add_tissue_energy", "tissue_share",
           "tissue_stiffness", "tissue_targets"]


def tissue_stiffness(model, order, fixed, ratio: float) -> np.ndarray:
    """(n,) g/s^2: each particle's tissue stiffness ``k_i`` (module docstring) in the order
    ``order`` (the solver's particle order, or ``np.arange(n)`` for the input's), 0 for the
    ``fixed`` (n,) particles (in that order) and everywhere when ``ratio`` is 0."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    n = int(offsets[-1])
    stiffness = np.zeros(n)
    if ratio == 0.0 or n == 0:
        return stiffness
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    spring_muscle = np.searchsorted(offsets, springs[:, 0], side="right") - 1
    m_count = len(offsets) - 1
    totals = np.bincount(spring_muscle, np.asarray(model.stiffness, dtype=np.float64),
                         minlength=m_count)
    counts = np.bincount(spring_muscle, minlength=m_count)
    mean_spring = totals / np.maximum(counts, 1)
    muscle = np.repeat(np.arange(m_count), np.diff(offsets))
    scale = model.resolution_scale() ** 2
    stiffness = (float(ratio) * mean_spring * scale)[muscle][order]
    stiffness[np.asarray(fixed, dtype=bool)] = 0.0
    return stiffness


def tissue_targets(model, order, along: float) -> np.ndarray:
    """The kernels' targets (module docstring): the targets ``t_i``
    (``model.tissue_target_positions()``) in the solver's ``order`` (3, n) mm, as they are for
    ``along`` 1; else stacked on ``sqrt(1 - along)`` times each particle's fibre direction
    there (6, n)."""
    target = model.tissue_target_positions()
    placed = np.ascontiguousarray(target[order].T)
    if along >= 1.0:
        return placed
    from .fibre_shortening import fibre_tangents
    direction = fibre_tangents(model, target)[order].T
    return np.ascontiguousarray(np.vstack([placed, np.sqrt(1.0 - along) * direction]))


@njit(cache=True, parallel=True)
def add_tissue_energy(x, target, stiffness, offsets, gradient, energy):
    """Add the tissue's energy of every muscle to ``energy`` (M,) and its gradient
    ``k_i (d_i - (d_i . g_i) g_i)`` (``k_i d_i`` isotropic) to ``gradient`` (3, n), at ``x``
    (3, n) mm with ``target`` (3 or 6, n) and stiffness ``stiffness`` (n,) g/s^2."""
    anisotropic = target.shape[0] == 6
    for m in prange(offsets.shape[0] - 1):
        e = 0.0
        for p in range(offsets[m], offsets[m + 1]):
            k = stiffness[p]
            if k == 0.0:
                continue
            dot = along_part(x, target, p)
            for axis in range(3):
                d = x[axis, p] - target[axis, p]
                e += 0.5 * k * d * d
                if anisotropic:
                    d -= dot * target[3 + axis, p]
                gradient[axis, p] += k * d
            if anisotropic:
                e -= 0.5 * k * dot * dot
        energy[m] += e


def tissue_share(model, positions, ratio: float, along: float, tension=None) -> np.ndarray:
    """(M,) %: per muscle, the tissue's force ``sum_i |f_i|`` (``k_i |x_i - t_i|`` isotropic)
    over the springs' ``sum_s |t_s|`` at the solved ``positions`` (n, 3) mm (input order),
    targets ``model.tissue_target_positions()``; how much of the load the tissue carries.
    ``tension`` (S,) g mm/s^2 each spring's force (omitted: Hooke's, ``k_s |l_s - l0_s|``). 0
    where ``ratio`` is 0 or nothing pulls, ``inf`` where only the tissue does."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    m_count = len(offsets) - 1
    if ratio == 0.0:
        return np.zeros(m_count)
    n = int(offsets[-1])
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    target = model.tissue_target_positions()
    k = tissue_stiffness(model, np.arange(n), model.fixed, ratio)
    muscle = np.repeat(np.arange(m_count), np.diff(offsets))
    d = x - target
    if along < 1.0:
        from .fibre_shortening import fibre_tangents
        g = np.sqrt(1.0 - along) * fibre_tangents(model, target)
        d = d - np.einsum("ij,ij->i", d, g)[:, None] * g
    tissue = np.bincount(muscle, k * np.linalg.norm(d, axis=1), minlength=m_count)
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    if tension is None:
        length = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
        tension = np.abs(np.asarray(model.stiffness, dtype=np.float64)
                         * (length - np.asarray(model.rest_length, dtype=np.float64)))
    spring = np.bincount(muscle[springs[:, 0]], tension, minlength=m_count)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(spring > 0.0, 100.0 * tissue / spring,
                        np.where(tissue > 0.0, np.inf, 0.0))
