"""Fibres that shorten with their muscle (the solver's fibre shortening).

The paper's springs keep their rest lengths whatever the pose, so a muscle whose attachments
come closer keeps its fibre length and folds (the demo arm's brachialis at 130 degrees: fibres
1.65 times their end-to-end distance), where a real one shortens and thickens. With this rule
the springs' rest lengths follow the pose: each fibre gets the factor

    s = min(1, |end now - start now| / |end at rest - start at rest|)

(its end particles' distance, posed, over that at rest: 1 for a fibre that lengthens, which
stretches as before), and a spring between particles of factors s_i and s_j, whose rest vector
makes the angle theta with the fibres' direction there (the mean of the two particles' fibre
tangents at rest), gets the rest length

    L' = L sqrt(cos^2(theta) s^2 + sin^2(theta) / s),     s = (s_i + s_j) / 2,

the rest shape contracted by s along the fibres and widened by 1 / sqrt(s) across them, which
keeps its volume (the muscle thickens as it shortens); of the rules measured in
docs/accuracy.md it changes the volume error least. A spring with both factors 1 keeps its rest
length bitwise, so a model that nowhere shortens is solved exactly as without the rule.

The connective tissue follows too (:func:`shortened_target`): it holds a particle toward its
posed position, where a shortening muscle's fibres keep their rest length and bend, so the
tissue would hold them bent and long (docs/accuracy.md, "The tissue's target shortens with the
muscle"). In a muscle whose ends come closer, by the factor

    s_m = |insertion centroid - origin centroid| posed / at rest

(the centroids of its fibres' last and first particles), the target is its rest shape
contracted by s_m along that origin-insertion line and widened by 1 / sqrt(s_m) across it
(volume kept), carried by the rigid motion that best fits its fibres' end particles; blended
with the posed positions by ``w = smoothstep((1 - s_m) / TARGET_BLEND)``, so that it is the
posed pose at s_m = 1 and leaves it smoothly.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .cage import polyline_lengths
from .errors import PoseError
from .model import MSSModel
from .rigid_fit import rigid_fit
from .solver_properties import ROW_OF_FIELD

TARGET_BLEND = 0.1
"""The muscle shortening (1 - s_m) over which the connective tissue's target passes from the
posed positions to the shortened rest shape (:func:`shortened_target`): with 0.2 the thigh's
walk followed less (adductor brevis 0.50 against 0.65, biceps femoris short head 0.91 against
0.96) and was no faster (424 iterations at most against 469)."""


SHORTEST = 0.5
"""The least end ratio (s of a fibre, s_m of a muscle) the rule accepts: a pose whose muscle
or fibre ends come closer than this fraction of their rest distance is refused
(:func:`check_ends`). The rest shape stretched by s along and 1 / sqrt(s) across has no limit
as s -> 0: with a muscle's origin and insertion on one point (the small demo thigh's tibia
posed onto the pelvis, s_m ~ 1e-17) the tissue target lay 1e8 times the muscle's width out and
the quasi-static solve ran its particles 16 m away. Measured on that pose (N = 8) with the
ratios clamped instead: at 0.5 it converges (336 iterations, volume errors 1.9-5.5 %), at 0.2
and 0.3 it does not in 2,000 iterations, with only s_m clamped (0.001-0.05, fibres 0.0007) the
rectus femoris swells by 100-470 %: a clamp gives a folded muscle between overlapping bones
for an impossible pose, so the pose is refused. The demo motions reach 0.69 at least (the
arm's brachioradialis at 130 degrees; the thigh's walk 0.86)."""


def fibre_order(model: MSSModel):
    """``(order (n,), starts (F,), ends (F,))``: the particles of each fibre in fibre order (a
    fibre is a muscle's ``fibre_id``), fibre f being ``order[starts[f]:ends[f] + 1]`` (its first
    particle ``order[starts[f]]``, its last ``order[ends[f]]``)."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    muscle = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    fibre_id = np.asarray(model.fibre_id, dtype=np.int64)
    order = np.lexsort((np.asarray(model.fibre_index), fibre_id, muscle))
    key_muscle, key_fibre = muscle[order], fibre_id[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (key_muscle[1:] != key_muscle[:-1]) | (key_fibre[1:] != key_fibre[:-1])
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], len(order)) - 1
    return order, starts, ends


def shortening_factors(model: MSSModel, fibres=None) -> np.ndarray:
    """(n,) per particle: its fibre's factor s = min(1, end-to-end distance posed / at rest)
    (``model.positions`` posed, ``model.rest_positions`` at rest, mm). ``fibres``: the
    model's :func:`fibre_order`, where the caller has it."""
    order, starts, ends = fibre_order(model) if fibres is None else fibres
    first, last = order[starts], order[ends]
    rest = np.asarray(model.rest_positions, dtype=np.float64).reshape(-1, 3)
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)
    rest_chord = np.linalg.norm(rest[last] - rest[first], axis=1)
    chord = np.linalg.norm(posed[last] - posed[first], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):     # a closed fibre has no chord
        factor = np.where(rest_chord > 0.0, np.minimum(1.0, chord / rest_chord), 1.0)
    per_particle = np.empty(len(order))
    per_particle[order] = np.repeat(factor, ends - starts + 1)
    return per_particle


def fibre_tangents(model: MSSModel, positions=None, fibres=None) -> np.ndarray:
    """(n, 3) unit vectors: each particle's fibre direction at ``positions`` (n, 3) mm (default
    the rest positions): from its predecessor to its successor along the fibre; at the ends,
    the end segment. ``fibres``: the model's :func:`fibre_order`, where the caller has it."""
    order, starts, ends = fibre_order(model) if fibres is None else fibres
    rest = np.asarray(model.rest_positions if positions is None else positions,
                      dtype=np.float64).reshape(-1, 3)
    following, preceding = np.empty(len(order), np.int64), np.empty(len(order), np.int64)
    following[order] = np.append(order[1:], order[-1])
    preceding[order] = np.insert(order[:-1], 0, order[0])
    following[order[ends]] = order[ends]
    preceding[order[starts]] = order[starts]
    tangent = rest[following] - rest[preceding]
    length = np.linalg.norm(tangent, axis=1, keepdims=True)
    return np.divide(tangent, length, out=np.zeros_like(tangent), where=length > 0.0)


def shortened_rest_lengths(model: MSSModel) -> np.ndarray:
    """(S,) mm: the springs' rest lengths under the rule of the module docstring for the pose
    ``model.positions``; ``model.rest_length`` itself (bitwise) where both ends' fibres do not
    shorten."""
    return shortened_springs(model).rest_length


def muscle_shortening(model: MSSModel, first, last) -> np.ndarray:
    """(M,): each muscle's s_m (module docstring), the distance between the centroids of its
    fibres' ``last`` and ``first`` particles (index arrays) posed over that at rest (1 where
    the rest distance is 0)."""
    offsets = np.asarray(model.offsets, dtype=np.int64)
    muscle = np.searchsorted(offsets, first, side="right") - 1
    count = np.maximum(np.bincount(muscle, minlength=len(offsets) - 1), 1)[:, None]
    chords = []
    for points in (model.rest_pose(), np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)):
        ends = [np.stack([np.bincount(muscle, points[k, axis], minlength=len(count))
                          for axis in range(3)], axis=1) / count for k in (first, last)]
        chords.append(np.linalg.norm(ends[1] - ends[0], axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(chords[0] > 0.0, chords[1] / chords[0], 1.0)


def volume_kept_stretch(axis, s: float) -> np.ndarray:
    """(3, 3): the linear map that stretches by ``s`` along the unit vector ``axis`` (3,) and by
    1 / sqrt(s) across it, keeping volumes (``s`` < 1 shortens and widens)."""
    along = np.outer(axis, axis)
    return s * along + (np.eye(3) - along) / np.sqrt(s)


def kept_shape_lengths(rest_positions, order, offsets, s: float) -> np.ndarray:
    """(F,) mm: the lengths of one muscle's fibres (``order``, ``offsets`` as from
    :func:`~muscle_mss.core.cage.fibre_polylines`) in its rest shape ``rest_positions`` (p, 3)
    mm stretched by :func:`volume_kept_stretch` with ``s`` along its origin-insertion line (the
    centroids of the fibres' first and last particles): the lengths the fibres would have if the
    muscle kept its rest shape and volume while its ends moved ``s`` times as far apart. A
    curved fibre of a muscle that thickens as it shortens (or thins as it lengthens) changes
    less than ``s``; a straight fibre along that line changes by ``s``. NaN where ``s`` is not
    positive (the ends on one point)."""
    rest = np.asarray(rest_positions, dtype=np.float64)
    if not s > 0.0:
        return np.full(len(offsets) - 1, np.nan)
    firsts, lasts = rest[order[offsets[:-1]]], rest[order[offsets[1:] - 1]]
    axis = lasts.mean(axis=0) - firsts.mean(axis=0)
    size = np.linalg.norm(axis)
    if size == 0.0:
        return polyline_lengths(rest, order, offsets)
    return polyline_lengths(rest @ volume_kept_stretch(axis / size, s).T, order, offsets)


def shortened_target(model: MSSModel, fibres=None) -> np.ndarray | None:
    """(n, 3) mm: the connective tissue's target with the shortened muscles' rest shapes
    (module docstring), or None where no muscle's ends come closer than at rest. ``fibres``:
    the model's :func:`fibre_order`, where the caller has it."""
    order, starts, ends = fibre_order(model) if fibres is None else fibres
    first, last = order[starts], order[ends]
    factor = muscle_shortening(model, first, last)
    if not (factor < 1.0).any():
        return None
    rest = model.rest_pose()
    target = np.array(model.positions, dtype=np.float64).reshape(-1, 3)
    offsets = np.asarray(model.offsets, dtype=np.int64)
    muscle = np.searchsorted(offsets, first, side="right") - 1
    for m in np.flatnonzero(factor < 1.0):
        s = float(factor[m])
        a, b = first[muscle == m], last[muscle == m]
        axis = rest[b].mean(axis=0) - rest[a].mean(axis=0)
        stretch = volume_kept_stretch(axis / np.linalg.norm(axis), s)
        tips = np.concatenate([a, b])
        rotation, translation, _, _ = rigid_fit(rest[tips] @ stretch.T, target[tips])
        lo, hi = offsets[m], offsets[m + 1]
        shaped = rest[lo:hi] @ stretch.T @ rotation.T + translation
        x = min(1.0, (1.0 - s) / TARGET_BLEND)
        w = x * x * (3.0 - 2.0 * x)
        target[lo:hi] += w * (shaped - target[lo:hi])
    return target


def check_ends(model: MSSModel, fibres=None) -> None:
    """Raise :class:`~muscle_mss.core.errors.PoseError` for the muscle whose origin and
    insertion (their centroids) or one of whose fibres' ends come closest, relative to their
    rest distance, when that is below :data:`SHORTEST`. ``fibres``: the model's
    :func:`fibre_order`, where the caller has it."""
    order, starts, ends = fibre_order(model) if fibres is None else fibres
    first, last = order[starts], order[ends]
    rest = model.rest_pose()
    posed = np.asarray(model.positions, dtype=np.float64).reshape(-1, 3)
    rest_chord = np.linalg.norm(rest[last] - rest[first], axis=1)
    chord = np.linalg.norm(posed[last] - posed[first], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(rest_chord > 0.0, chord / rest_chord, 1.0)
    muscle_ratio = muscle_shortening(model, first, last)
    offsets = np.asarray(model.offsets, dtype=np.int64)
    muscle = np.searchsorted(offsets, first, side="right") - 1
    f = int(np.argmin(ratio)) if len(ratio) else 0
    m = int(np.argmin(muscle_ratio)) if len(muscle_ratio) else 0
    if not (len(ratio) and min(ratio[f], muscle_ratio[m]) < SHORTEST):
        return
    row = ROW_OF_FIELD["fibre_shortening"]
    rule = (f"{row.name} gives no rest shape to a muscle or fibre whose ends come closer "
            f"than {SHORTEST:.0%} of their rest distance (its rest shape, shortened along and "
            "widened across to keep the volume, would grow without bound); check the motion "
            f"of the bones it is attached to at this time, or turn {row.name} off "
            f"(--no-{row.option.flag[2:]}) to let its fibres keep their lengths and fold")
    if muscle_ratio[m] <= ratio[f]:
        a, b = first[muscle == m], last[muscle == m]
        at_rest = np.linalg.norm(rest[b].mean(axis=0) - rest[a].mean(axis=0))
        now = np.linalg.norm(posed[b].mean(axis=0) - posed[a].mean(axis=0))
        raise PoseError(model.names[m], f": its origin and insertion (its fibres' end "
                        f"centroids) are {now:.3g} mm apart, {100 * muscle_ratio[m]:.3g} % of "
                        f"their {at_rest:.3g} mm at rest; {rule}")
    m = int(muscle[f])
    fibre = int(np.asarray(model.fibre_id)[first[f]])
    raise PoseError(model.names[m], f": the ends of its fibre {fibre} are {chord[f]:.3g} mm "
                    f"apart, {100 * ratio[f]:.3g} % of their {rest_chord[f]:.3g} mm at rest; "
                    f"{rule}")


def shortened_springs(model: MSSModel) -> MSSModel:
    """``model`` with the rest lengths of :func:`shortened_rest_lengths` and the rest vectors
    (``MSSModel.rest_vectors``) of that rest shape: each shortening spring's vector contracted
    by s along the fibres' direction and widened by 1 / sqrt(s) across it, then scaled to the
    new rest length (the co-rotational springs keep the shape, not only the lengths; with the
    rest pose's directions a slab brought 30 % closer shortened its fibres by 12 %); and the
    connective tissue's target of :func:`shortened_target`. ``model`` itself where no fibre
    and no muscle shortens. A pose that shortens a muscle or fibre below :data:`SHORTEST` is
    refused (:func:`check_ends`)."""
    rest_length = np.asarray(model.rest_length, dtype=np.float64)
    fibres = fibre_order(model)
    check_ends(model, fibres)
    factor = shortening_factors(model, fibres)
    springs = np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)
    i, j = springs[:, 0], springs[:, 1]
    s = 0.5 * (factor[i] + factor[j])
    shortening = s < 1.0
    target = shortened_target(model, fibres)
    if not shortening.any():
        return model if target is None else dataclasses.replace(model, tissue_target=target)
    i, j, s = i[shortening], j[shortening], s[shortening]
    tangents = fibre_tangents(model, fibres=fibres)
    direction = tangents[i] + tangents[j]
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    rest = np.asarray(model.rest_positions, dtype=np.float64).reshape(-1, 3)
    vector = rest[j] - rest[i]
    along = np.einsum("ij,ij->i", vector, direction)
    cos2 = (along / np.maximum(np.linalg.norm(vector, axis=1), 1e-300)) ** 2
    shortened = rest_length.copy()
    shortened[shortening] *= np.sqrt(cos2 * s * s + (1.0 - cos2) / s)
    vectors = model.spring_rest_vectors()
    shaped = vector / np.sqrt(s)[:, None] + ((s - 1.0 / np.sqrt(s)) * along)[:, None] * direction
    size = np.linalg.norm(shaped, axis=1)
    vectors[shortening] = shaped * np.divide(shortened[shortening], size, out=np.zeros_like(size),
                                             where=size > 0.0)[:, None]
    return dataclasses.replace(model, rest_length=shortened, rest_vectors=vectors,
                               tissue_target=target)
