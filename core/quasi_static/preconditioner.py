"""The constant part of the quasi-static solve's Hessian: the spring Laplacian on the free
particles, factorised muscle by muscle once per topology (banded Cholesky), and the initial
inverse Hessian of the L-BFGS iterations, that factor corrected by each muscle's rank-one volume
stiffness (Sherman-Morrison). The muscles' triangular solves run in one parallel kernel
(:func:`solve_banded_blocks`)."""
from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
import scipy.linalg as linalg
import scipy.sparse as sparse
from scipy.sparse.csgraph import reverse_cuthill_mckee

from numba import njit, prange

from ..connective_tissue import tissue_stiffness
from ..errors import MuscleMSSError
from ..model import MSSModel, PreparedModel


@njit(cache=True, parallel=True, fastmath={"reassoc"})
def solve_banded_blocks(factors, factor_ptr, widths, rows, rows_ptr, rhs, out, work):
    """``out = A^-1 rhs`` for ``rhs`` (f, c), ``c`` a multiple of 3, ``A`` block diagonal,
    block ``k`` the rows ``rows[rows_ptr[k]:rows_ptr[k + 1]]`` (in its factor's order) with the
    lower Cholesky factor of bandwidth ``widths[k]`` stored column by column from
    ``factors[factor_ptr[k]]`` (column ``j``'s diagonal then its ``widths[k]`` entries below;
    the transpose of LAPACK's lower banded layout). ``work`` (f, 3) scratch. One thread per
    block, so the result does not depend on the number of threads. The right-hand sides go
    three at a time (a particle's x, y, z side by side): each factor entry read once serves
    the three, and the three running values stay in registers (1.7x faster than one side at a
    time on the demo thigh; ``fastmath`` lets the sums over a column reassociate)."""
    for block in prange(widths.shape[0]):
        w = widths[block]
        first = rows_ptr[block]
        k = rows_ptr[block + 1] - first
        base = factor_ptr[block]
        y = work[first:first + k]
        for group in range(0, rhs.shape[1], 3):
            for j in range(k):
                for col in range(3):
                    y[j, col] = rhs[rows[first + j], group + col]
            for j in range(k):                  # L y = b, column by column
                at = base + j * (w + 1)
                diagonal = factors[at]
                v0, v1, v2 = y[j, 0] / diagonal, y[j, 1] / diagonal, y[j, 2] / diagonal
                y[j, 0], y[j, 1], y[j, 2] = v0, v1, v2
                for t in range(1, min(w, k - 1 - j) + 1):
                    entry = factors[at + t]
                    y[j + t, 0] -= entry * v0
                    y[j + t, 1] -= entry * v1
                    y[j + t, 2] -= entry * v2
            for j in range(k - 1, -1, -1):      # L^T x = y
                at = base + j * (w + 1)
                s0 = s1 = s2 = 0.0
                for t in range(1, min(w, k - 1 - j) + 1):
                    entry = factors[at + t]
                    s0 += entry * y[j + t, 0]
                    s1 += entry * y[j + t, 1]
                    s2 += entry * y[j + t, 2]
                diagonal = factors[at]
                y[j, 0] = (y[j, 0] - s0) / diagonal
                y[j, 1] = (y[j, 1] - s1) / diagonal
                y[j, 2] = (y[j, 2] - s2) / diagonal
            for j in range(k):
                for col in range(3):
                    out[rows[first + j], group + col] = y[j, col]


@dataclass
class Preconditioner:
    """The spring Laplacian ``L`` on the free particles, factorised muscle by muscle.

    ``free`` (f,) the free particles (solver order); the factors as
    :func:`solve_banded_blocks` takes them: ``rows`` (f,) positions in ``free`` muscle by
    muscle, each in its factor's order (the smaller bandwidth of the particles ordered slice by
    slice along the fibres and of reverse Cuthill-McKee), ``rows_ptr`` (B + 1,), ``widths``
    (B,) bandwidths, ``factors`` the lower banded Cholesky factors column by column, from
    ``factor_ptr`` (B,); ``stiffest`` (g/s^2) the largest sum of one particle's spring
    stiffnesses (the contact stiffness's unit); ``bandwidth`` the largest block's; ``tissue``
    (n,) g/s^2 every particle's connective tissue stiffness (solver order,
    :func:`~muscle_mss.core.connective_tissue.tissue_stiffness`), on ``L``'s diagonal."""

    free: np.ndarray
    rows: np.ndarray
    rows_ptr: np.ndarray
    widths: np.ndarray
    factors: np.ndarray
    factor_ptr: np.ndarray
    stiffest: float
    bandwidth: int
    tissue: np.ndarray
    inverse_columns: object = None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` for ``rhs`` (f, c), ``c`` a multiple of 3 (each particle's x, y, z)."""
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        if rhs.shape[1] % 3:
            raise ValueError(f"the banded solve takes columns three at a time, not {rhs.shape[1]}")
        out = np.empty_like(rhs)
        solve_banded_blocks(self.factors, self.factor_ptr, self.widths, self.rows,
                            self.rows_ptr, rhs, out, np.empty((len(rhs), 3)))
        return out


def _solver_ends(model: MSSModel, prep: PreparedModel) -> np.ndarray:
    """(S, 2) every spring's ends in the solver's particle order (the model's spring order)."""
    rank = np.empty(len(prep.order), dtype=np.int64)
    rank[prep.order] = np.arange(len(prep.order))
    return rank[np.asarray(model.springs, dtype=np.int64).reshape(-1, 2)]


def spring_order(model: MSSModel, prep: PreparedModel) -> np.ndarray:
    """(S,) the model's springs in :func:`spring_table`'s order (grouped by muscle)."""
    return np.argsort(prep.muscle[_solver_ends(model, prep)[:, 0]], kind="stable")


SpringTable = namedtuple("SpringTable", "ends rest stiffness ptr")
SpringTable.__doc__ = """Every spring's ends (solver order) ``(S, 2)``, rest length (mm) and
stiffness (g/s^2) ``(S,)``, grouped by muscle (:func:`spring_order`), muscle ``m``'s springs
at ``ptr[m]:ptr[m + 1]`` ``(M + 1,)``."""


def spring_table(model: MSSModel, prep: PreparedModel) -> SpringTable:
    """The model's :class:`SpringTable`."""
    ends = _solver_ends(model, prep)
    muscle = prep.muscle[ends[:, 0]]
    order = spring_order(model, prep)
    ptr = np.searchsorted(muscle[order], np.arange(len(prep.offsets))).astype(np.int64)
    return SpringTable(np.ascontiguousarray(ends[order]),
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
    for ``prep``'s topology, cached on ``prep`` (its ``factorisations``: ``L`` does not depend on
    the springs' rest lengths). Without tissue, a muscle whose free particles
    are not all joined to a fixed particle through springs would float: the solve refuses
    it."""
    key = float(tissue_ratio)
    if key in prep.factorisations:
        return prep.factorisations[key]
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
        blocks.append((rows[order], np.ascontiguousarray(factor_.T).ravel(), width))
        widest = max(widest, width)
    result = Preconditioner(free, *_packed(blocks), stiffest, widest, tissue)
    prep.factorisations[key] = result
    return result


def _packed(blocks):
    """``(rows, rows_ptr, widths, factors, factor_ptr)`` of :class:`Preconditioner` from the
    blocks ``(rows (k,), factor column by column (k (w + 1),), w)``."""
    def joined(arrays, dtype):
        return np.concatenate([np.zeros(0, dtype)] + [np.asarray(a, dtype) for a in arrays])

    def starts(sizes):
        return np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).astype(np.int64)

    return (joined([r for r, _, _ in blocks], np.int64), starts([len(r) for r, _, _ in blocks]),
            np.array([w for _, _, w in blocks], dtype=np.int64),
            joined([f for _, f, _ in blocks], np.float64),
            starts([len(f) for _, f, _ in blocks])[:-1])


def model_springs(model: MSSModel, prep: PreparedModel) -> SpringTable:
    """:func:`spring_table`, cached on ``prep`` (its ``spring_table``)."""
    if prep.spring_table is None:
        prep.spring_table = spring_table(model, prep)
    return prep.spring_table


class InitialInverseHessian:
    """``(A + K)^-1`` at one state: ``A`` the :class:`Preconditioner`, ``K`` each muscle's
    rank-one volume stiffness ``(B / V0) g g^T`` for the volume gradient ``g`` (f, 3) of that
    state (Sherman-Morrison per muscle, ``A`` being block diagonal). ``A`` alone leaves the
    volume term's stiff whole-cage mode out: at BulkModulus 50 its steps overshoot that mode
    many times."""

    def __init__(self, pre: Preconditioner, free_muscle, volume_stiffness, volume_gradient):
        self.pre, self.free_muscle, self.c = pre, free_muscle, volume_stiffness
        self.g = np.ascontiguousarray(volume_gradient, dtype=np.float64)
        self.solved_g = None
        self.self_term = None

    def volume_terms(self):
        """``(A^-1 g (f, 3), beta (M,))`` with ``(A + K)^-1 = A^-1 - beta_m (A^-1 g)(A^-1 g)^T``
        muscle by muscle (zero where a muscle has no volume term)."""
        if not self.c.any():
            return np.zeros_like(self.g), np.zeros_like(self.c)
        if self.solved_g is None:
            self(np.zeros((len(self.g), 3)))
        return self.solved_g, self.c / (1.0 + self.c * self.self_term)

    def __call__(self, rhs):
        if not self.c.any():
            return self.pre.solve(rhs)
        if self.solved_g is None:
            both = self.pre.solve(np.concatenate([rhs, self.g], axis=1))
            # contiguous, as the plain solve's: one signature of _remove_volume_mode
            out = np.ascontiguousarray(both[:, :3])
            self.solved_g = np.ascontiguousarray(both[:, 3:])
            self.self_term = np.bincount(self.free_muscle, np.einsum(
                "ij,ij->i", self.g, self.solved_g), minlength=len(self.c))
        else:
            out = self.pre.solve(rhs)
        _remove_volume_mode(out, self.g, self.solved_g, self.free_muscle, self.c,
                            self.self_term, np.empty(len(self.c)))
        return out


@njit(cache=True)
def _remove_volume_mode(out, g, solved_g, muscle, c, self_term, along):
    """``out`` (f, 3) ``-= beta_m (g^T out)_m A^-1 g`` particle by particle (Sherman-Morrison:
    ``A^-1 rhs`` in, ``(A + K)^-1 rhs`` out), ``g`` (f, 3) the volume gradient, ``solved_g``
    ``A^-1 g``, ``muscle`` (f,) each row's muscle, ``c`` (M,) the volume stiffness and
    ``self_term`` (M,) ``g^T A^-1 g`` per muscle; ``along`` (M,) scratch. Serial: a few
    microseconds, less than NumPy's temporaries or waking a thread."""
    for m in range(along.shape[0]):
        along[m] = 0.0
    for i in range(out.shape[0]):
        along[muscle[i]] += g[i, 0] * out[i, 0] + g[i, 1] * out[i, 1] + g[i, 2] * out[i, 2]
    for m in range(along.shape[0]):
        along[m] = c[m] * along[m] / (1.0 + c[m] * self_term[m])
    for i in range(out.shape[0]):
        scale = along[muscle[i]]
        for axis in range(3):
            out[i, axis] -= solved_g[i, axis] * scale
