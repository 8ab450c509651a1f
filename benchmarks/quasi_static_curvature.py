"""Why the quasi-static solve takes hundreds of iterations with the connective tissue (issue 26).

Table 1 solves the full demo thigh at one pose (N = 20, ConnectiveTissue ``--tissue``, bones as
solids) with one thing changed at a time: muscle-muscle contacts off, every contact off, the
volume term off as well, a start 1,000 paper-relaxation iterations along (with the same tissue),
a stronger tissue, FibreShortening with TissueAlongFibres 0.1, a looser Tolerance. It prints
iterations, seconds and the distance to the first row's answer (mean / max mm).

Table 2 takes the first row's answer and compares, muscle by muscle, the curvature of the
springs' and the tissue's energy there (its Hessian ``H``, the springs' geometric stiffness
``k (1 - r / l)`` across each spring included: negative for a compressed spring) with the
matrix ``A`` the solver's initial inverse Hessian assumes (the spring Laplacian plus the tissue,
each spring ``k`` in every direction): the share of compressed springs, the smallest
eigenvalues of ``A^-1 H`` (1: ``A`` is right; 0.001: the energy is a thousand times softer
along that mode than ``A`` says) and how many lie below 0.05, and the smallest eigenvalue of
``H`` over the smallest tissue stiffness (below 1: compressed springs take stiffness away from
the tissue; negative: without the volume term and the contacts the muscle would buckle).
L-BFGS on a spectrum from ``lambda_min`` to 1 needs of the order of ``1 / sqrt(lambda_min)``
iterations per factor e of the residual, whatever its line search does.
Writes benchmarks/results/quasi_static_curvature.md.

    python benchmarks/quasi_static_curvature.py [--time 0.75] [--tissue 0.1]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np
import scipy.linalg as linalg
import scipy.sparse as sparse

from muscle_mss.core import solver as S
from muscle_mss.core.fibre_shortening import shortened_rest_lengths
from muscle_mss.core.model import Bones, prepare
from muscle_mss.core.quasi_static.preconditioner import model_springs, preconditioner
from muscle_mss.core.settings import METHOD_RELAXATION, SPRINGS_HOOKE, SolverSettings

from bench_quasi_static import distance, quasi_static, thigh_workload
from bench_solver import machine, write_result


HOOKE_MODEL = {"springs": SPRINGS_HOOKE, "tissue_along": 1.0}
"""The model this study measured (Hooke springs, an isotropic tissue), whatever the defaults."""


def variants(tissue):
    """Table 1's rows: ``(label, settings keywords, start from the paper relaxation,
    FibreShortening)``."""
    return (("as the defaults set it (Hooke springs, isotropic tissue)", {}, False, False),
            ("no muscle-muscle contacts", {"muscle_muscle": False}, False, False),
            ("no contacts", {"muscle_muscle": False, "muscle_bone": False}, False, False),
            ("no contacts, no volume term", {"muscle_muscle": False, "muscle_bone": False,
                                             "bulk_modulus": 0.0}, False, False),
            ("started after 1,000 paper iterations", {}, True, False),
            (f"ConnectiveTissue {3 * tissue:g}", {"connective_tissue": round(3 * tissue, 9)},
             False, False),
            (f"ConnectiveTissue {10 * tissue:g}", {"connective_tissue": round(10 * tissue, 9)},
             False, False),
            ("FibreShortening, TissueAlongFibres 0.1", {"tissue_along": 0.1}, False, True),
            ("Tolerance 0.01 mm", {"tolerance": 0.01}, False, False),
            ("Tolerance 0.1 mm", {"tolerance": 0.1}, False, False))


def ablation_rows(model, bones, solids, tissue, cap):
    """Table 1, and the first row's result (the reference answer)."""
    prepared = prepare(model)
    shortened = dataclasses.replace(model, rest_length=shortened_rest_lengths(model))
    shortened_prepared = prepare(shortened)
    rows, reference = [], None
    for label, values, from_paper, shorten in variants(tissue):
        m, p = (shortened, shortened_prepared) if shorten else (model, prepared)
        settings = quasi_static(**{"iterations": cap, "connective_tissue": tissue,
                                   **HOOKE_MODEL, **values})
        tick = time.perf_counter()
        start = None
        if from_paper:
            start = S.solve(m, Bones(bones, solids), prepared=p, settings=
                            SolverSettings.build(method=METHOD_RELAXATION, iterations=1000,
                                                 connective_tissue=tissue, tissue_along=1.0,
                                                 fibre_shortening=False)).positions
        paper_seconds = time.perf_counter() - tick
        result = S.solve(m, Bones(bones, solids), settings, prepared=p, start=start)
        seconds = time.perf_counter() - tick
        reference = result if reference is None else reference
        rows.append((label, result.iterations, seconds, paper_seconds, result.converged,
                     *distance(result.positions, reference.positions), os.getloadavg()[0]))
        print(rows[-1], flush=True)
    return rows, reference, prepared


def muscle_hessians(model, prepared, positions, tissue_ratio, m):
    """``(H, A)`` dense on muscle ``m``'s free coordinates (3 per particle, solver order) at
    ``positions`` (n, 3) input order: the springs' Hessian with their geometric stiffness plus
    the tissue, and the solver's Laplacian plus the tissue (Table 2's matrices)."""
    ends, rest, stiffness, ptr = model_springs(model, prepared)
    tissue = preconditioner(model, prepared, tissue_ratio).tissue
    lo, hi = prepared.offsets[m], prepared.offsets[m + 1]
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)[prepared.order][lo:hi]
    pair = ends[ptr[m]:ptr[m + 1]] - lo
    k, r = stiffness[ptr[m]:ptr[m + 1]], rest[ptr[m]:ptr[m + 1]]
    d = x[pair[:, 1]] - x[pair[:, 0]]
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    free = np.flatnonzero(~prepared.fixed[lo:hi])
    coordinates = (3 * free[:, None] + np.arange(3)).ravel()
    size = 3 * (hi - lo)

    def assembled(across):
        block = k[:, None, None] * (across[:, None, None] * np.eye(3) + (1.0 - across)[
            :, None, None] * u[:, :, None] * u[:, None, :])
        rows, cols, values = [np.arange(size)], [np.arange(size)], [np.repeat(tissue[lo:hi], 3)]
        for p, q, sign in ((0, 0, 1.0), (1, 1, 1.0), (0, 1, -1.0), (1, 0, -1.0)):
            rows.append(np.repeat(3 * pair[:, p, None] + np.arange(3), 3, axis=1).ravel())
            cols.append(np.tile(3 * pair[:, q, None] + np.arange(3), 3).ravel())
            values.append((sign * block).ravel())
        matrix = sparse.coo_matrix((np.concatenate(values), (np.concatenate(rows),
                                                            np.concatenate(cols))),
                                   shape=(size, size)).tocsr()
        return matrix[coordinates][:, coordinates].toarray()

    return (assembled(1.0 - r / length), assembled(np.ones_like(length)),
            float((length < r).mean()), float(tissue[lo:hi][free].min()))


def curvature_rows(model, prepared, positions, tissue_ratio):
    """Table 2: per muscle, compressed springs, the spectrum of ``A^-1 H`` and ``H``'s
    smallest eigenvalue over the smallest tissue stiffness."""
    rows = []
    for m, name in enumerate(model.names):
        hessian, assumed, compressed, least_tissue = muscle_hessians(
            model, prepared, positions, tissue_ratio, m)
        relative = linalg.eigh(hessian, assumed, eigvals_only=True)
        own = linalg.eigvalsh(hessian, subset_by_index=[0, 0])[0]
        rows.append((name, 100.0 * compressed, relative[0], relative[-1],
                     int((relative < 0.05).sum()), len(relative), own / least_tissue))
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time", type=float, default=0.75, help="pose (s into the motion)")
    parser.add_argument("--tissue", type=float, default=0.1, help="ConnectiveTissue")
    parser.add_argument("--cap", type=int, default=1500, help="iteration cap")
    args = parser.parse_args(argv)
    model, bones, solids = thigh_workload(args.time, 20)
    S.solve(model, Bones(bones, solids), quasi_static(iterations=2))
    ablation, reference, prepared = ablation_rows(model, bones, solids, args.tissue, args.cap)
    curvature = curvature_rows(model, prepared, reference.positions, args.tissue)
    lines = [
        "# Why the quasi-static solve takes hundreds of iterations (issue 26)", "",
        f"Machine: {machine()}. `python benchmarks/quasi_static_curvature.py --time "
        f"{args.time} --tissue {args.tissue:g}`: the full demo thigh at t = {args.time} s, "
        f"N = 20, quasi-static, ConnectiveTissue {args.tissue:g} (isotropic), Tolerance "
        f"0.001 mm, cap {args.cap}, bones as solids.", "",
        "Table 1: one thing changed at a time. Seconds include the paper relaxation's where a "
        "row starts from it (its share beside). Distance to the first row's answer, mean / "
        "max mm.", "",
        "| variant | iterations | seconds | of which paper s | converged | to the first row | "
        "load |", "|---|---|---|---|---|---|---|"]
    for label, its, seconds, paper, converged, mean, largest, load in ablation:
        lines.append(f"| {label} | {its} | {seconds:.2f} | {paper:.2f} | "
                     f"{'yes' if converged else 'no'} | {mean:.3f} / {largest:.2f} | "
                     f"{load:.2f} |")
    lines += [
        "", "Table 2: at the first row's answer, per muscle, the springs' and tissue's Hessian "
        "H (geometric stiffness included) against the matrix A the preconditioner assumes "
        "(Laplacian plus tissue). Eigenvalues of A^-1 H: 1 where A is right, small where the "
        "energy is softer than A says. Last column: H's smallest eigenvalue over the "
        "smallest tissue stiffness (negative: the springs alone would buckle there; the "
        "volume term and the contacts, left out of H, hold it).", "",
        "| muscle | compressed springs % | smallest of A^-1 H | largest | below 0.05 (of) | "
        "H smallest / tissue |", "|---|---|---|---|---|---|"]
    for name, compressed, least, most, soft, size, own in curvature:
        lines.append(f"| {name} | {compressed:.0f} | {least:.2g} | {most:.2f} | {soft} "
                     f"({size}) | {own:.2g} |")
    write_result(lines, "quasi_static_curvature.md")


if __name__ == "__main__":
    main()
