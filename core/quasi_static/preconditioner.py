"""The constant part of the quasi-static solve's Hessian: the spring Laplacian on the free
particles, factorised muscle by muscle once per topology (banded Cholesky), and the initial
inverse Hessian of the L-BFGS iterations, that factor corrected by each muscle's rank-one volume
stiffness (Sherman-Morrison)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as linalg
import scipy.sparse as sparse
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..connective_tissue import tissue_stiffness
from ..errors import MuscleMSSError
from ..model import MSSModel, PreparedModel


@dataclass
class Preconditioner:
    """The spring Laplacian ``L`` on the free particles, factorised muscle by muscle.

    ``free`` (f,) the free particles (solver order); ``blocks`` per muscle ``(rows, factor)``:
    ``rows`` (k,) positions in ``free`` in the factor's order (the smaller bandwidth of the
    particles ordered slice by slice along the fibres and of reverse Cuthill-McKee), ``factor``
    the lower banded Cholesky factor (LAPACK layout); ``stiffest`` (g/s^2) the largest sum of
    one particle's spring stiffnesses (the contact stiffness's unit); ``bandwidth`` the largest
    block's; ``tissue`` (n,) g/s^2 every particle's connective tissue stiffness (solver order,
    :func:`~muscle_mss.core.connective_tissue.tissue_stiffness`), on ``L``'s diagonal."""

    free: np.ndarray
    blocks: list
    stiffest: float
    bandwidth: int
    tissue: np.ndarray

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` for ``rhs`` (f, c)."""
        out = np.empty_like(rhs)
        for rows, factor_ in self.blocks:
            out[rows] = linalg.cho_solve_banded((factor_, True), rhs[rows], check_finite=False)
        return out


def spring_table(model: MSSModel, prep: PreparedModel):
    """Every spring's ends (solver order), rest length and stiffness, grouped by muscle:
    ``(ends (S, 2), rest (S,), stiffness (S,), ptr (M + 1,))``."""
    rank = np.empty(len(prep.order), dtype=np.int64)
    rank[prep.order] = np.arange(len(prep.order))
    ends = rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]
    muscle = prep.muscle[ends[:, 0]]
    order = np.argsort(muscle, kind="stable")
    ptr = np.searchsorted(muscle[order], np.arange(len(prep.offsets))).astype(np.int64)
    return (np.ascontiguousarray(ends[order]),
            np.asarray(model.rest_length, dtype=np.float64)[order].copy(),
            np.asarray(model.stiffness, dtype=np.float64)[order].copy(), ptr)


def _bandwidth(matrix, order) -> int:
    coo = matrix.tocoo()
    place = np.empty(len(order), dtype=np.int64)
    place[order] = np.arange(len(order))
    return int(np.abs(place[coo.row] - place[coo.col]).max(initial=0))


def preconditioner(model: MSSModel, prep: PreparedModel,
                   tissue_ratio: float = 0.0) -> Preconditioner:
    """The factorised ``L`` plus the connective tissue of ``tissue_ratio`` on its diagonal,
    for ``prep``'s topology, cached on ``prep``. Without tissue, a muscle whose free particles
    are not all joined to a fixed particle through springs would float: the solve refuses
    it."""
    key = ("quasi-static preconditioner", float(tissue_ratio))
    if key in prep.cache:
        return prep.cache[key]
    ends, _, stiffness, _ = model_springs(model, prep)
    n = int(prep.offsets[-1])
    diagonal = np.bincount(ends.ravel(), np.repeat(stiffness, 2), minlength=n)
    stiffest = float(diagonal.max(initial=0.0) or 1.0)
    tissue = tissue_stiffness(model, prep.order, prep.fixed, tissue_ratio)
    a, b = ends[:, 0], ends[:, 1]
    lap = sparse.coo_matrix(
        (np.concatenate([stiffness, stiffness, -stiffness, -stiffness, tissue]),
         (np.concatenate([a, b, a, b, np.arange(n)]),
          np.concatenate([a, b, b, a, np.arange(n)]))), shape=(n, n)).tocsr()
    free = np.flatnonzero(~prep.fixed)
    matrix = lap[free][:, free].tocsr()
    along = np.asarray(model.fibre_index).ravel()[prep.order][free]
    free_muscle = prep.muscle[free]
    blocks, widest = [], 0
    for m in range(len(prep.offsets) - 1):
        rows = np.flatnonzero(free_muscle == m)
        if not len(rows):
            continue
        block = matrix[rows][:, rows]
        candidates = [np.lexsort((np.arange(len(rows)), along[rows])),
                      np.asarray(reverse_cuthill_mckee(block, symmetric_mode=True), np.int64)]
        widths = [_bandwidth(block, c) for c in candidates]
        order = candidates[int(np.argmin(widths))]
        width = min(widths)
        ordered = block[order][:, order].tocoo()
        keep = ordered.row >= ordered.col
        banded = np.zeros((width + 1, len(rows)))
        banded[(ordered.row - ordered.col)[keep], ordered.col[keep]] = ordered.data[keep]
        try:
            factor_ = linalg.cholesky_banded(banded, lower=True, check_finite=False)
        except linalg.LinAlgError:
            raise MuscleMSSError(
                f"the quasi-static solver cannot factorise the springs of muscle "
                f"'{model.names[m]}': some of its free particles are joined to no fixed "
                "particle through springs (they would float away); fix its tendon ends or use "
                "the paper relaxation") from None
        blocks.append((rows[order], factor_))
        widest = max(widest, width)
    result = Preconditioner(free, blocks, stiffest, widest, tissue)
    prep.cache[key] = result
    return result


def model_springs(model: MSSModel, prep: PreparedModel):
    """:func:`spring_table`, cached on ``prep`` (the topology's)."""
    key = "quasi-static springs"
    if key not in prep.cache:
        prep.cache[key] = spring_table(model, prep)
    return prep.cache[key]


class InitialInverseHessian:
    """``(A + K)^-1`` at one state: ``A`` the :class:`Preconditioner`, ``K`` each muscle's
    rank-one volume stiffness ``(B / V0) g g^T`` for the volume gradient ``g`` (f, 3) of that
    state (Sherman-Morrison per muscle, ``A`` being block diagonal). ``A`` alone leaves the
    volume term's stiff whole-cage mode out: at BulkModulus 50 its steps overshoot that mode
    many times."""

    def __init__(self, pre: Preconditioner, free_muscle, volume_stiffness, volume_gradient):
        self.pre, self.free_muscle, self.c = pre, free_muscle, volume_stiffness
        self.g = volume_gradient
        self.solved_g = None
        self.self_term = None

    def __call__(self, rhs):
        if not self.c.any():
            return self.pre.solve(rhs)
        if self.solved_g is None:
            both = self.pre.solve(np.concatenate([rhs, self.g], axis=1))
            out, self.solved_g = both[:, :3], both[:, 3:]
            self.self_term = np.bincount(self.free_muscle, np.einsum(
                "ij,ij->i", self.g, self.solved_g), minlength=len(self.c))
        else:
            out = self.pre.solve(rhs)
        along = np.bincount(self.free_muscle, np.einsum("ij,ij->i", self.g, out),
                            minlength=len(self.c))
        scale = self.c * along / (1.0 + self.c * self.self_term)
        out -= self.solved_g * scale[self.free_muscle, None]
        return out
