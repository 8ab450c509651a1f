"""The MSS Collision Solver's PosedModel input read block by block into checked arrays: each
muscle block's particles (points and the point data the solver needs) and springs (two-point
line cells and their cell data), every rule checked with the block and the rule named."""
import numpy as np

from muscle_mss.core.cage import fibre_polylines
from muscle_mss.core.errors import MuscleMSSError

from . import array_names as A
from . import vtk_arrays as V

MODEL = "PosedModel"
MODEL_BLOCK = "a model block of particles and spring lines"
POINT_ARRAYS = (A.REST_POSITION, A.FIBRE_ID, A.FIBRE_INDEX, A.FIXED, A.BOUNDARY, A.RADIUS, A.MASS)
CELL_ARRAYS = (A.REST_LENGTH, A.STIFFNESS, A.DAMPING)


def muscle_block(name, block, known: dict | None = None):
    """Arrays of one muscle block, checked. ``known``: this function's answer for a block with
    the same arrays (:func:`~muscle_mss.filters.vtk_arrays.arrays_identity`), whose arrays other
    than the coordinates are then taken as they are (checked then)."""
    where = f"{MODEL} block '{name}'"
    V.require_polydata(block, where, MODEL_BLOCK)
    n = block.GetNumberOfPoints()
    if n == 0:
        raise MuscleMSSError(f"{where} has no particles")
    points = V.points_of(block)
    if not np.isfinite(points).all():
        bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise MuscleMSSError(f"{where}: particle {bad} has a NaN or infinite position")
    if known is not None:
        return {**known, "points": points}
    data = {key: V.point_array(block, key, where) for key in POINT_ARRAYS}
    grid = V.point_array(block, A.FIBRE_GRID, where, required=False)
    in_bone = V.point_array(block, A.IN_BONE_AT_REST, where, required=False)
    if in_bone is not None and in_bone.size != n:
        raise MuscleMSSError(f"{where}: array '{A.IN_BONE_AT_REST}' must have one value per "
                             "particle")
    offsets, connectivity = V.lines_of(block)
    sizes = np.diff(offsets)
    if (sizes != 2).any():
        bad = int(np.flatnonzero(sizes != 2)[0])
        raise MuscleMSSError(f"{where}: line cell {bad} has {int(sizes[bad])} points; springs "
                             "must be two-point lines")
    rest = data[A.REST_POSITION].reshape(n, -1)
    if rest.shape[1] != 3 or not np.isfinite(rest).all():
        raise MuscleMSSError(f"{where}: array '{A.REST_POSITION}' must have 3 finite components "
                             "per particle")
    springs = connectivity.reshape(-1, 2)
    cells = {key: V.cell_array(block, key, where) for key in CELL_ARRAYS}
    for key in (A.FIBRE_ID, A.FIBRE_INDEX, A.FIXED, A.BOUNDARY, A.RADIUS, A.MASS):
        data[key] = data[key].reshape(-1)
        if data[key].shape != (n,):
            raise MuscleMSSError(f"{where}: array '{key}' must have one value per particle")
    # each fibre's particles numbered 0..k-1 (the particle ordering and the volume cage rely
    # on it; a cage that cannot be built would silently drop the muscle's volume term)
    fibre_polylines(data[A.FIBRE_ID], data[A.FIBRE_INDEX], where)
    for key in (A.RADIUS, A.MASS):
        if not np.isfinite(data[key]).all() or (data[key] < 0).any():
            raise MuscleMSSError(f"{where}: array '{key}' has a negative, NaN or infinite value")
    free = data[A.FIXED] == 0
    if (data[A.MASS][free] <= 0).any():
        bad = int(np.flatnonzero(free & (data[A.MASS] <= 0))[0])
        raise MuscleMSSError(f"{where}: particle {bad} is free with mass "
                             f"{data[A.MASS][bad]}; a free particle needs a positive mass")
    if len(springs) and (springs.min() < 0 or springs.max() >= n):
        raise MuscleMSSError(f"{where}: a spring refers to a particle that does not exist")
    for key in CELL_ARRAYS:
        cells[key] = cells[key].reshape(-1)
        if cells[key].shape != (len(springs),):
            raise MuscleMSSError(f"{where}: cell array '{key}' must have one value per spring")
        if not np.isfinite(cells[key]).all() or (cells[key] < 0).any():
            bad = int(np.flatnonzero(~np.isfinite(cells[key]) | (cells[key] < 0))[0])
            raise MuscleMSSError(f"{where}: spring {bad} has {key} {cells[key][bad]}; it must "
                                 "be finite and 0 or more")
    if len(springs) and (springs[:, 0] == springs[:, 1]).any():
        bad = int(np.flatnonzero(springs[:, 0] == springs[:, 1])[0])
        raise MuscleMSSError(f"{where}: spring {bad} joins particle {springs[bad, 0]} to itself")
    return {"points": points, "springs": springs, "grid": grid, "in_bone": in_bone, **data,
            **cells}
