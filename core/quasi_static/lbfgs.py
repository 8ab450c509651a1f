"""The quasi-Newton direction of the quasi-static solve (L-BFGS, two-loop recursion, on an
initial inverse Hessian) and its stopping estimate: how far the particles still have to go."""
from __future__ import annotations

import numpy as np
from numba import njit

# The iterations over which the residual's decay is measured. With 10, the walking pose of the full
# demo thigh (N = 20) stopped as converged after 1,292 iterations 0.020 / 1.14 mm (mean / max)
# from a solve to 1e-5 mm: the last ten steps shrank faster than the slow bending modes behind
# them. With 30 it stops after 1,945 iterations 0.0035 / 0.083 mm from it (60: the same).
RATE_WINDOW = 30
REST_STEP = 1e-12               # mm: a residual below it is rest (rounding of mm coordinates)


@njit(cache=True, fastmath={"reassoc"})
def _inner(a, b):
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i] * b[i]
    return total


def inner(a, b) -> float:
    """The inner product of the (f, 3) arrays ``a`` and ``b``, in one thread: numpy's would call
    the BLAS, whose threads then spin for a while and take the cores from the parallel
    kernels that follow (an iteration 20-40 % slower on two cores)."""
    return float(_inner(np.ascontiguousarray(a).reshape(-1), np.ascontiguousarray(b).reshape(-1)))


@njit(cache=True)
def _largest_square(step):
    largest = 0.0
    for i in range(step.shape[0]):
        square = step[i, 0] * step[i, 0] + step[i, 1] * step[i, 1] + step[i, 2] * step[i, 2]
        if square != square:
            return square               # NaN: a move that is not finite
        largest = max(largest, square)
    return largest


def largest_move(step) -> float:
    """The largest particle move (mm) of ``step`` (f, 3) (NaN if one is not finite)."""
    return float(np.sqrt(_largest_square(np.ascontiguousarray(step))))


def distance_to_go(residual) -> float:
    """The distance (mm) the particles still have to go after the iterations whose residuals
    are ``residual`` (K,), estimated as ``r rho / (1 - rho)``: ``r`` the last residual, ``rho``
    its mean decay per iteration over the last :data:`RATE_WINDOW` iterations (a step
    shrinking by ``rho`` per iteration has that much left in its geometric tail; the last step
    alone understated the distance to the minimum 50 times on the small demo, where a solve
    stopped at 0.01 mm ended 0.55 mm from one started elsewhere). ``inf`` when the residual is
    not shrinking or there is one only; 0 below :data:`REST_STEP` (rest)."""
    last = float(residual[-1])
    if last < REST_STEP:
        return 0.0
    if len(residual) < 2:
        return np.inf
    window = min(RATE_WINDOW, len(residual) - 1)
    rate = (last / residual[-1 - window]) ** (1.0 / window)
    return last * rate / (1.0 - rate) if rate < 1.0 else np.inf


def settled(residual, tolerance) -> bool:
    """Whether :func:`distance_to_go` is below ``tolerance`` (mm)."""
    return distance_to_go(residual) < tolerance


class LBFGSHistory:
    """The last ``size`` L-BFGS pairs ``(s, y, 1 / y.s)`` of (f, 3) arrays, in ring buffers
    (no arrays made per iteration)."""

    def __init__(self, size: int, free: int):
        self.s = np.zeros((max(size, 1), 3 * free))
        self.y = np.zeros_like(self.s)
        self.rho = np.zeros(max(size, 1))
        self.alpha = np.zeros(max(size, 1))
        self.size, self.count, self.next = size, 0, 0

    def __len__(self):
        return self.count

    def clear(self):
        self.count = 0

    def add(self, s, y, rho):
        """Keep the pair ``s``, ``y`` (f, 3) (copied), dropping the oldest when full."""
        if self.size == 0:
            return
        self.s[self.next] = s.ravel()
        self.y[self.next] = y.ravel()
        self.rho[self.next] = rho
        self.next = (self.next + 1) % self.size
        self.count = min(self.count + 1, self.size)

    def order(self) -> np.ndarray:
        """The slots of the pairs kept, oldest first."""
        return (self.next - self.count + np.arange(self.count)) % max(self.size, 1)


@njit(cache=True, fastmath={"reassoc"})
def _lbfgs_back(q, s, y, rho, order, alpha):
    """The first loop of the two-loop recursion on ``q`` (in place), newest pair first."""
    for t in range(order.shape[0] - 1, -1, -1):
        k = order[t]
        a = 0.0
        for i in range(q.shape[0]):
            a += s[k, i] * q[i]
        a *= rho[k]
        alpha[k] = a
        for i in range(q.shape[0]):
            q[i] -= a * y[k, i]


@njit(cache=True, fastmath={"reassoc"})
def _lbfgs_forward(r, s, y, rho, order, alpha):
    """The second loop of the two-loop recursion on ``r`` (in place), oldest pair first."""
    for t in range(order.shape[0]):
        k = order[t]
        b = 0.0
        for i in range(r.shape[0]):
            b += y[k, i] * r[i]
        c = alpha[k] - rho[k] * b
        for i in range(r.shape[0]):
            r[i] += c * s[k, i]


def direction(gradient, history: LBFGSHistory, h0):
    """The L-BFGS step ``-H gradient`` (f, 3) (two-loop recursion, Nocedal and Wright
    algorithm 7.4) for the pairs of ``history`` and the initial inverse Hessian ``h0``."""
    q = gradient.copy()
    order = history.order()
    _lbfgs_back(q.reshape(-1), history.s, history.y, history.rho, order, history.alpha)
    r = np.ascontiguousarray(h0(q))
    _lbfgs_forward(r.reshape(-1), history.s, history.y, history.rho, order, history.alpha)
    return -r
