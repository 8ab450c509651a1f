"""The contacts between muscles in the quasi-static solve's preconditioner.

The L-BFGS iterations start each direction from an initial inverse Hessian. The one of
:mod:`.preconditioner` knows the springs, the connective tissue and the volume, not the contact
penalties: where muscles press on each other its steps overshoot, the line search cuts them to
a fraction (a median 0.2 at the flexed thigh) and the contacts set the iteration count. Here
each overlapping pair of muscle spheres adds its Gauss-Newton stiffness ``w n n^T`` (``n`` the
unit vector between the centres, ``w`` the pair's contact stiffness) on each of its two
particles, each side against the other held still (so the preconditioner stays one block per
muscle), and the sum is inverted by the Woodbury identity against the banded factors::

    (A0 + U U^T)^-1 = A0^-1 - A0^-1 U (I + U^T A0^-1 U)^-1 U^T A0^-1

``A0`` the :class:`~.preconditioner.InitialInverseHessian`'s matrix (springs, tissue, volume),
``U`` the pairs' columns ``sqrt(w) n`` merged particle by particle: a particle's summed
stiffness along its stiffest direction (:data:`RANK_SHARE`; its pairs push it along nearly one
normal, and the capacitance's cost grows with the cube of its columns). The capacitance ``I +
U^T A0^-1 U`` is one small dense matrix per muscle, built and factorised at every iteration from
the pairs of that iteration; its entries need ``A^-1`` between contact particles, the columns of
``A^-1`` at those particles, computed once per topology as contacts first reach a particle
(:class:`InverseColumns`; a column is a pure function of its particle, so a frame's answer does
not depend on which columns earlier frames left). Applying the result costs the small triangular
solves and a sum of the kept columns (``A0^-1 U t``: ``U t`` is zero but at the contacts'
particles), not a second banded solve. The contacts with the bones stay out: in the
preconditioner they sent the arm's brachialis at 130 degrees around a bone into an equilibrium
of 14 % more energy (docs/solver-notes.md, "Contacts in the preconditioner").
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

# Memory for the columns of A^-1 kept between solves (bytes); past it the columns are dropped
# and computed again as contacts need them.
COLUMN_BYTES = 512 * 2**20
# A particle's contacts enter as the principal directions of their summed stiffness whose
# stiffness is at least this share of the particle's largest (1: its stiffest direction alone).
RANK_SHARE = 1.0
RANK_ROUNDING = 1e-12          # a smaller share of the largest is a zero eigenvalue's rounding
JACOBI_SWEEPS = 16              # the 3 x 3 eigenproblems' rotation sweeps, at most


@njit(cache=True, parallel=True)
def inverse_columns(factors, factor_ptr, widths, rows_ptr, blocks, places, out):
    """Row ``c`` of ``out`` (c, K): the column of ``A^-1`` at the particle in place
    ``places[c]`` of block ``blocks[c]``, within that block (factor order, its first
    ``rows_ptr[b + 1] - rows_ptr[b]`` entries; the factors as
    :func:`~.preconditioner.solve_banded_blocks` takes them). Each row alone (no sum across
    rows): a column's values do not depend on the others computed with it."""
    for c in prange(blocks.shape[0]):
        b = blocks[c]
        w = widths[b]
        k = rows_ptr[b + 1] - rows_ptr[b]
        base = factor_ptr[b]
        y = out[c]
        for j in range(k):
            y[j] = 0.0
        y[places[c]] = 1.0
        for j in range(places[c], k):               # L y = e (zero above the unit)
            value = y[j] / factors[base + j * (w + 1)]
            y[j] = value
            top = min(w, k - 1 - j)
            for t in range(1, top + 1):
                y[j + t] -= factors[base + j * (w + 1) + t] * value
        for j in range(k - 1, -1, -1):              # L^T x = y
            top = min(w, k - 1 - j)
            total = 0.0
            for t in range(1, top + 1):
                total += factors[base + j * (w + 1) + t] * y[j + t]
            y[j] = (y[j] - total) / factors[base + j * (w + 1)]


def inverse_columns_of(pre) -> "InverseColumns":
    """The :class:`InverseColumns` of the :class:`~.preconditioner.Preconditioner` ``pre``,
    kept on it (its ``inverse_columns``) for the solves of the same topology."""
    if pre.inverse_columns is None:
        pre.inverse_columns = InverseColumns(pre)
    return pre.inverse_columns


class InverseColumns:
    """The columns of a :class:`~.preconditioner.Preconditioner`'s ``A^-1`` at free particles,
    each within its muscle's block, computed as they are first asked for and kept (up to
    :data:`COLUMN_BYTES`). ``block_of`` and ``place_of`` (f,): each free particle's block and
    its place in that block's factor order."""

    def __init__(self, pre):
        self.pre = pre
        f = len(pre.free)
        sizes = np.diff(pre.rows_ptr)
        self.block_of = np.empty(f, dtype=np.int64)
        self.block_of[pre.rows] = np.repeat(np.arange(len(sizes)), sizes)
        self.place_of = np.empty(f, dtype=np.int64)
        self.place_of[pre.rows] = np.arange(f) - np.repeat(pre.rows_ptr[:-1], sizes)
        self.width = int(sizes.max(initial=1))
        self.slot = np.full(f, -1, dtype=np.int64)
        self.columns = np.zeros((0, self.width))
        self.count = 0
        self.scratch = np.empty((3, f))     # :func:`_subtract_solved`'s

    def slots(self, particles: np.ndarray) -> np.ndarray:
        """(k,) the rows of :attr:`columns` holding the columns at the free ``particles``
        (k,), those missing computed first."""
        missing = np.unique(particles[self.slot[particles] < 0])
        if len(missing):
            if (self.count + len(missing)) * self.width * 8 > COLUMN_BYTES:
                self.slot[:] = -1
                self.count = 0
                missing = np.unique(particles)
            need = self.count + len(missing)
            if need > len(self.columns):
                grown = np.zeros((max(need, 2 * len(self.columns)), self.width))
                grown[:self.count] = self.columns[:self.count]
                self.columns = grown
            pre = self.pre
            inverse_columns(pre.factors, pre.factor_ptr, pre.widths, pre.rows_ptr,
                            self.block_of[missing], self.place_of[missing],
                            self.columns[self.count:need])
            self.slot[missing] = np.arange(self.count, need)
            self.count = need
        return self.slot[particles]


@njit(cache=True, parallel=True)
def _muscle_contacts(x, weight, particle, radius, fixed, begin, end, idx, start, at, column):
    """Sphere ``i``'s overlapping partners in its candidate list ``idx[begin[i]:end[i]]``
    (another muscle's spheres): their count into ``start[i + 1]`` when ``at`` is empty, else
    its columns from ``start[i]`` into ``at`` (its particle) and ``column`` (``sqrt(w) n``, ``n``
    the unit vector from the partner's centre to its own)."""
    fill = at.shape[0] > 0
    for i in prange(particle.shape[0]):
        if fixed[i]:
            if not fill:
                start[i + 1] = 0
            continue
        p = particle[i]
        c = start[i] if fill else 0
        for k in range(begin[i], end[i]):
            j = idx[k]
            q = particle[j]
            dx, dy, dz = x[0, p] - x[0, q], x[1, p] - x[1, q], x[2, p] - x[2, q]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            if d < radius[i] + radius[j] and d > 0.0:
                if fill:
                    s = np.sqrt(0.5 * (weight[p] + weight[q])) / d
                    at[c] = p
                    column[c, 0], column[c, 1], column[c, 2] = s * dx, s * dy, s * dz
                c += 1
        if not fill:
            start[i + 1] = c


def muscle_contact_columns(x, weight, spheres, lists):
    """The overlapping pairs of muscle spheres at ``x`` (3, n) mm as columns of ``U``:
    ``(particles (k,) solver order, columns (k, 3) sqrt(w) n)``, one per pair and free side;
    ``weight`` (n,) g/s^2 each particle's contact stiffness (a pair's the mean of its two, as
    :func:`~.energy.sphere_contact_energy`), ``lists`` the muscle candidate lists of
    :class:`~.energy.ContactEnergy`."""
    start = np.zeros(spheres.count + 1, dtype=np.int64)
    args = (x, weight, spheres.particle, spheres.radius, spheres.fixed, *lists)
    _muscle_contacts(*args, start, np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    start = np.cumsum(start)
    at = np.empty(start[-1], dtype=np.int64)
    column = np.empty((start[-1], 3))
    if len(at):
        _muscle_contacts(*args, start, at, column)
    return at, column


@njit(cache=True)
def _symmetric_eigen(a, values, vectors):
    """The eigenvalues ``values`` (3,) and eigenvectors (the columns of ``vectors`` (3, 3)) of
    the symmetric ``a`` (3, 3, overwritten) by cyclic Jacobi rotations."""
    for i in range(3):
        for j in range(3):
            vectors[i, j] = 1.0 if i == j else 0.0
    for _ in range(JACOBI_SWEEPS):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        scale = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-30 * scale or off == 0.0:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                if a[p, q] == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):          # a <- a J
                    akp, akq = a[k, p], a[k, q]
                    a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
                for k in range(3):          # a <- J^T a
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(3):
                    vkp, vkq = vectors[k, p], vectors[k, q]
                    vectors[k, p], vectors[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    for i in range(3):
        values[i] = a[i, i]


@njit(cache=True, parallel=True)
def _merged_columns(at, column, group_ptr, share, out_at, out_column, kept, stiffness, values):
    """Particle ``g``'s contacts ``group_ptr[g]:group_ptr[g + 1]`` of ``at``/``column`` (sorted
    by particle) as the eigenvectors of their stiffness ``sum u u^T`` scaled by the square
    roots of the eigenvalues, those of at least ``share`` times the largest, in slots ``3 g ..
    3 g + 2`` of ``out_at``/``out_column``, ``kept`` (3 g,) True where a slot is used;
    ``stiffness`` (G, 3, 3) and ``values`` (G, 3) scratch."""
    for g in prange(group_ptr.shape[0] - 1):
        a, value = stiffness[g], values[g]
        vectors = out_column[3 * g:3 * g + 3]           # the eigenvectors as its columns
        for i in range(3):
            for j in range(3):
                a[i, j] = 0.0
        for c in range(group_ptr[g], group_ptr[g + 1]):
            for i in range(3):
                for j in range(3):
                    a[i, j] += column[c, i] * column[c, j]
        _symmetric_eigen(a, value, vectors)
        largest = max(value[0], max(value[1], value[2]))
        for i in range(3):
            kept[3 * g + i] = value[i] > 0.0 and value[i] >= max(share, RANK_ROUNDING) * largest
            out_at[3 * g + i] = at[group_ptr[g]]
        for i in range(3):                  # eigenvector i into row i (slot 3 g + i), scaled
            for j in range(i + 1, 3):
                vectors[i, j], vectors[j, i] = vectors[j, i], vectors[i, j]
        for i in range(3):
            root = np.sqrt(max(value[i], 0.0))
            for j in range(3):
                vectors[i, j] *= root


def particle_columns(at, column, share):
    """The contacts' columns ``at`` (k,) / ``column`` (k, 3) merged particle by particle: each
    particle's stiffness ``sum_j u_j u_j^T`` (a 3 x 3 block of rank up to 3) along its
    principal directions, kept where their stiffness is at least ``share`` times the
    particle's largest (:data:`RANK_SHARE`; 0 keeps the block exactly). ``(at (k',), column
    (k', 3))``, sorted by particle."""
    if not len(at):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    order = np.argsort(at, kind="stable")
    at, column = at[order], np.ascontiguousarray(column[order])
    group_ptr = np.flatnonzero(np.r_[True, at[1:] != at[:-1], True]).astype(np.int64)
    groups = len(group_ptr) - 1
    out_at = np.empty(3 * groups, dtype=np.int64)
    out_column = np.empty((3 * groups, 3))
    kept = np.empty(3 * groups, dtype=np.bool_)
    if groups:
        _merged_columns(at, column, group_ptr, float(share), out_at, out_column, kept,
                        np.empty((groups, 3, 3)), np.empty((groups, 3)))
    return out_at[kept], out_column[kept]


@njit(cache=True, parallel=True)
def _capacitance(ptr, at, column, slot, columns, place, along_volume, beta, cap_ptr, cap):
    """Each muscle's capacitance ``I + U^T A0^-1 U`` (dense, row major from ``cap_ptr[m]``),
    for the contacts ``ptr[m]:ptr[m + 1]`` (particles ``at``, columns ``column``; ``slot`` of
    each particle's row of ``columns``, the columns of ``A^-1`` in factor order, ``place`` of
    each free particle in it) and the volume's ``A0^-1 = A^-1 - beta_m a a^T``:
    ``along_volume`` (k,) each column's ``u . a`` at its particle."""
    for m in prange(ptr.shape[0] - 1):
        first, k = ptr[m], ptr[m + 1] - ptr[m]
        s = cap[cap_ptr[m]:cap_ptr[m] + k * k]
        for a in range(k):
            ca = first + a
            va = along_volume[ca]
            for b in range(a + 1):
                cb = first + b
                dot = (column[ca, 0] * column[cb, 0] + column[ca, 1] * column[cb, 1]
                       + column[ca, 2] * column[cb, 2])
                value = (columns[slot[ca], place[at[cb]]] * dot
                         - beta[m] * va * along_volume[cb])
                if a == b:
                    value += 1.0
                s[a * k + b] = value
                s[b * k + a] = value


@njit(cache=True, parallel=True, fastmath={"reassoc"})
def _factorise(ptr, cap_ptr, cap):
    """The capacitances of :func:`_capacitance` replaced by their lower Cholesky factors, one
    muscle per thread (compiled here rather than LAPACK's: a BLAS call's threads spin after it
    and take the cores from the parallel kernels that follow, as in
    :func:`~.lbfgs.inner`)."""
    for m in prange(ptr.shape[0] - 1):
        k = ptr[m + 1] - ptr[m]
        s = cap[cap_ptr[m]:cap_ptr[m] + k * k]
        for j in range(k):
            total = s[j * k + j]
            for t in range(j):
                total -= s[j * k + t] * s[j * k + t]
            d = np.sqrt(total)
            s[j * k + j] = d
            for i in range(j + 1, k):
                total = s[i * k + j]
                for t in range(j):
                    total -= s[i * k + t] * s[j * k + t]
                s[i * k + j] = total / d


@njit(cache=True, parallel=True, fastmath={"reassoc"})
def _capacitance_solve(ptr, at, column, cap_ptr, cap, y, t):
    """``t`` (k,) = ``(I + U^T A0^-1 U)^-1 U^T y`` per muscle, ``y`` (f, 3)."""
    for m in prange(ptr.shape[0] - 1):
        first, k = ptr[m], ptr[m + 1] - ptr[m]
        s = cap[cap_ptr[m]:cap_ptr[m] + k * k]
        u = t[first:first + k]
        for a in range(k):
            c = first + a
            p = at[c]
            u[a] = column[c, 0] * y[p, 0] + column[c, 1] * y[p, 1] + column[c, 2] * y[p, 2]
        for a in range(k):                  # L v = u
            total = u[a]
            for b in range(a):
                total -= s[a * k + b] * u[b]
            u[a] = total / s[a * k + a]
        for a in range(k - 1, -1, -1):      # L^T t = v, row by row of L
            u[a] /= s[a * k + a]
            for b in range(a):
                u[b] -= s[a * k + b] * u[a]


@njit(cache=True, parallel=True, fastmath={"reassoc"})
def _subtract_solved(ptr, at, column, t, slot, columns, block_of, rows, rows_ptr,
                     volume_solved, beta, along_volume, out, work):
    """``out`` (f, 3) ``-= A0^-1 U t`` muscle by muscle, from the kept columns of ``A^-1`` (``U
    t`` is zero but at the contacts' particles, so no banded solve is needed; a particle's
    columns are adjacent) and the volume's ``- beta_m a (a^T U t)``. ``work`` (3, f)
    scratch."""
    for m in prange(ptr.shape[0] - 1):
        first, last = ptr[m], ptr[m + 1]
        if first == last:
            continue
        b = block_of[at[first]]
        start, size = rows_ptr[b], rows_ptr[b + 1] - rows_ptr[b]
        wx, wy, wz = (work[0, start:start + size], work[1, start:start + size],
                      work[2, start:start + size])
        for j in range(size):
            wx[j], wy[j], wz[j] = 0.0, 0.0, 0.0
        along = 0.0
        c = first
        while c < last:
            ux, uy, uz = 0.0, 0.0, 0.0
            p = at[c]
            row = columns[slot[c]]
            while c < last and at[c] == p:
                ux += column[c, 0] * t[c]
                uy += column[c, 1] * t[c]
                uz += column[c, 2] * t[c]
                along += along_volume[c] * t[c]
                c += 1
            for j in range(size):
                wx[j] += row[j] * ux
                wy[j] += row[j] * uy
                wz[j] += row[j] * uz
        scale = beta[m] * along
        for j in range(size):
            p = rows[start + j]
            out[p, 0] -= wx[j] - scale * volume_solved[p, 0]
            out[p, 1] -= wy[j] - scale * volume_solved[p, 1]
            out[p, 2] -= wz[j] - scale * volume_solved[p, 2]


class ContactInverseHessian:
    """``(A0 + U U^T)^-1`` (module docstring): ``h0`` applies ``A0^-1`` (an
    :class:`~.preconditioner.InitialInverseHessian`, its volume gradient solved), ``at`` (k,)
    the contacts' free particles, ``column`` (k, 3) their ``sqrt(w) n`` (merged particle by
    particle, :func:`particle_columns` with ``share``), ``muscle_of`` (f,) each free
    particle's muscle, ``inverse`` the :class:`InverseColumns`."""

    def __init__(self, h0, at, column, muscle_of, inverse: InverseColumns,
                 share: float = RANK_SHARE):
        self.h0, self.inverse = h0, inverse
        at, column = particle_columns(at, column, share)
        order = np.argsort(muscle_of[at], kind="stable")
        self.at, self.column = at[order], np.ascontiguousarray(column[order])
        n_muscles = len(h0.c)
        self.ptr = np.searchsorted(muscle_of[self.at], np.arange(n_muscles + 1)).astype(np.int64)
        sizes = np.diff(self.ptr)
        self.cap_ptr = np.concatenate([[0], np.cumsum(sizes * sizes)]).astype(np.int64)
        self.cap = np.empty(self.cap_ptr[-1])
        self.t = np.empty(len(self.at))
        if not len(self.at):
            return
        self.slot = inverse.slots(self.at)
        self.volume_solved, self.beta = h0.volume_terms()
        self.along_volume = np.einsum("ij,ij->i", self.column, self.volume_solved[self.at])
        _capacitance(self.ptr, self.at, self.column, self.slot, inverse.columns,
                     inverse.place_of, self.along_volume, self.beta, self.cap_ptr, self.cap)
        _factorise(self.ptr, self.cap_ptr, self.cap)

    def __call__(self, rhs):
        y = self.h0(rhs)
        if not len(self.at):
            return y
        inverse, pre = self.inverse, self.h0.pre
        _capacitance_solve(self.ptr, self.at, self.column, self.cap_ptr, self.cap, y, self.t)
        _subtract_solved(self.ptr, self.at, self.column, self.t, self.slot, inverse.columns,
                         inverse.block_of, pre.rows, pre.rows_ptr, self.volume_solved,
                         self.beta, self.along_volume, y, inverse.scratch)
        return y
