"""How well the quasi-static solver's preconditioner matches the energy's curvature (issue 11).

The quasi-static solver (core/quasi_static/) is L-BFGS whose initial inverse Hessian is the
spring Laplacian ``A`` (plus the volume's rank-one term). For every pair ``(s, y)`` the solve
keeps (a step and its change of gradient), the generalised Rayleigh quotient ``q = y.s / s.A s``
says how stiff the energy really is along that step compared with what ``A`` assumes: ``q = 1``
where they agree, ``q = 0.001`` where the energy is a thousand times softer. The smallest
quotients bound the condition number the iterations face (``max q / min q``) and how far the
stopping test's plain step ``(A + K)^-1 grad E`` understates the distance to the minimum (up
to ``1 / min q`` times). This script solves the full demo thigh at one pose with the default
settings and prints the quotients' minimum, median and maximum per window of iterations,
with the residual (largest particle move of the quasi-Newton step) at the window's end.
Writes benchmarks/results/quasi_static_spectrum.md.

    python benchmarks/quasi_static_spectrum.py [--n 20] [--time 0.35] [--cap 1500]
                                               [--window 100]
"""
from __future__ import annotations

import argparse
import os
import platform

import numba
import numpy as np
import scipy.sparse as sparse

from muscle_mss.core import quasi_static as Q
from muscle_mss.core.model import Bones, prepare
from muscle_mss.core.settings import SPRINGS_HOOKE

from bench_quasi_static import quasi_static, thigh_workload

PAPER_MODEL = {"springs": SPRINGS_HOOKE, "connective_tissue": 0.0}
"""The model this study measured (the paper's Hooke springs, no tissue), whatever the
defaults."""
from bench_solver import cpu_model, write_result


def free_laplacian(model, prepared) -> sparse.csr_matrix:
    """The spring Laplacian weighted by stiffness on the free particles (the preconditioner's
    matrix ``A``, per coordinate), in the solver's particle order."""
    ends, _, stiffness, _ = Q.model_springs(model, prepared)
    n = int(prepared.offsets[-1])
    a, b = ends[:, 0], ends[:, 1]
    laplacian = sparse.coo_matrix(
        (np.concatenate([stiffness, stiffness, -stiffness, -stiffness]),
         (np.concatenate([a, b, a, b]), np.concatenate([a, b, b, a]))), shape=(n, n)).tocsr()
    free = Q.preconditioner(model, prepared).free
    return laplacian[free][:, free].tocsr()


def rayleigh_quotients(model, bones, solids, cap):
    """``(quotients (pairs,), result)``: ``y.s / s.A s`` of every pair the default solve kept,
    in order (the solve's :class:`~muscle_mss.core.quasi_static.LBFGSHistory` is watched)."""
    prepared = prepare(model)
    laplacian = free_laplacian(model, prepared)
    quotients = []
    keep = Q.LBFGSHistory.add

    def watched(history, s, y, rho):
        quotients.append((1.0 / rho) / float(np.vdot(s, laplacian @ s)))
        return keep(history, s, y, rho)

    Q.LBFGSHistory.add = watched
    try:
        result = Q.solve(model, Bones(bones, solids), quasi_static(iterations=cap, **PAPER_MODEL),
                         prepared=prepared)
    finally:
        Q.LBFGSHistory.add = keep
    return np.array(quotients), result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="particles per fibre")
    parser.add_argument("--time", type=float, default=0.35, help="pose (s into the motion)")
    parser.add_argument("--cap", type=int, default=1500, help="iteration cap")
    parser.add_argument("--window", type=int, default=100, help="pairs per row")
    args = parser.parse_args(argv)
    model, bones, solids = thigh_workload(args.time, args.n)
    quotients, result = rayleigh_quotients(model, bones, solids, args.cap)
    lines = [
        "# How well the quasi-static preconditioner matches the energy's curvature (issue 11)",
        "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores, numba {numba.__version__}, numpy "
        f"{np.__version__}, Python {platform.python_version()}.", "",
        f"Full demo thigh, N = {args.n}, t = {args.time} s, quasi-static, Hooke springs, no "
        f"tissue, cap {args.cap}: {len(result.residual)} iterations, stopped by "
        f"{result.stopped_by}, "
        f"converged {int(result.converged)}; {len(quotients)} L-BFGS pairs. `python "
        "benchmarks/quasi_static_spectrum.py`. q = y.s / s.A s of each pair, A the spring "
        "Laplacian (the initial inverse Hessian's matrix): the energy is 1/q times softer "
        "along that step than A assumes.", "",
        "| pairs | min q | median q | max q | max / min | residual at the window's end mm |",
        "|---|---|---|---|---|---|"]
    for first in range(0, len(quotients), args.window):
        window = quotients[first:first + args.window]
        last = min(first + len(window), len(result.residual)) - 1
        lines.append(f"| {first}-{first + len(window) - 1} | {window.min():.2g} | "
                     f"{np.median(window):.2g} | {window.max():.2g} | "
                     f"{window.max() / window.min():.3g} | {result.residual[last]:.2g} |")
    if len(quotients):
        lines += ["", f"All pairs: min q {quotients.min():.2g}, median {np.median(quotients):.2g}, "
                  f"max {quotients.max():.2g}."]
    write_result(lines, "quasi_static_spectrum.md")


if __name__ == "__main__":
    main()
