"""The contacts between muscles in the quasi-static preconditioner
(core/quasi_static/contact_preconditioner.py): each piece against a dense reference that does not
share its code, and the solve's answer with and without it."""
import numpy as np

from muscle_mss.core import model as S
from muscle_mss.core import quasi_static as Q
from muscle_mss.core.quasi_static.contact_preconditioner import (
    ContactInverseHessian, InverseColumns, inverse_columns_of, muscle_contact_columns,
    particle_columns)
from muscle_mss.core.quasi_static.preconditioner import InitialInverseHessian, preconditioner
from muscle_mss.core.contacts.collision_spheres import Spheres

from test_mss import lattice
from test_quasi_static import quasi_static, two_muscles


def dense_of(operator, size):
    """The (3 size, 3 size) matrix of a linear ``operator`` on (size, 3) arrays, column by
    column."""
    columns = []
    for k in range(3 * size):
        unit = np.zeros(3 * size)
        unit[k] = 1.0
        columns.append(np.asarray(operator(unit.reshape(size, 3))).ravel())
    return np.array(columns).T


def test_inverse_columns_are_the_dense_inverse_whatever_was_asked_before():
    model = two_muscles()
    prep = S.prepare(model)
    pre = preconditioner(model, prep, 0.1)
    f = len(pre.free)
    dense_inverse = dense_of(pre.solve, f)[::3, ::3]      # A^-1, from the banded solve alone
    particles = np.array([f - 1, 0, 5, f // 2, 5])
    first, second = InverseColumns(pre), InverseColumns(pre)
    second.slots(np.arange(f)[::-1])                      # every column, in another order
    for columns in (first, second):
        slot = columns.slots(particles)
        for p, s in zip(particles, slot):
            same = np.flatnonzero(columns.block_of == columns.block_of[p])
            got = columns.columns[s, columns.place_of[same]]
            np.testing.assert_allclose(got, dense_inverse[same, p], rtol=1e-10, atol=1e-14)
    a = first.columns[first.slots(particles)]
    b = second.columns[second.slots(particles)]
    assert np.array_equal(a, b)                           # bitwise: a frame's history is moot


def test_woodbury_update_inverts_the_matrix_with_the_contacts():
    """(A0 + U U^T)^-1 applied by the capacitance per muscle equals a dense solve of that
    matrix: A0 from the initial inverse Hessian (springs, tissue, volume) column by column,
    U from the contacts (two on one particle, several per muscle), each particle's block kept
    whole (share 0)."""
    model = two_muscles()
    prep = S.prepare(model)
    pre = preconditioner(model, prep, 0.1)
    f = len(pre.free)
    rng = np.random.default_rng(7)
    muscle = prep.muscle[pre.free]
    h0 = InitialInverseHessian(pre, muscle, np.array([2.0, 0.5]), rng.normal(size=(f, 3)))
    at = np.array([0, 0, 3, f - 1, f - 4, f // 2, 7])
    column = rng.normal(size=(len(at), 3)) * 3.0
    contact = ContactInverseHessian(h0, at, column, muscle, inverse_columns_of(pre), 0.0)
    matrix = np.linalg.inv(dense_of(lambda r: h0(r.copy()), f))
    for p, u in zip(at, column):
        full = np.zeros((f, 3))
        full[p] = u
        matrix += np.outer(full.ravel(), full.ravel())
    rhs = rng.normal(size=(f, 3))
    expected = np.linalg.solve(matrix, rhs.ravel()).reshape(f, 3)
    np.testing.assert_allclose(contact(rhs), expected, rtol=1e-8, atol=1e-12)
    empty = ContactInverseHessian(h0, at[:0], column[:0], muscle, inverse_columns_of(pre))
    np.testing.assert_allclose(empty(rhs), h0(rhs.copy()), rtol=1e-12)


def test_particle_columns_keep_each_particles_stiffest_directions():
    """Merged columns rebuild each particle's summed stiffness sum u u^T exactly with share
    0, and its largest eigenvalue's part alone with share 1 (numpy's eigh as the reference)."""
    rng = np.random.default_rng(11)
    at = rng.integers(0, 6, size=20)
    column = rng.normal(size=(20, 3))
    column[at == 2] = [1.0, 2.0, 0.5]           # one particle pushed twice along one normal
    for share in (0.0, 1.0):
        merged_at, merged = particle_columns(at, column, share)
        assert np.all(np.diff(merged_at) >= 0)
        for p in np.unique(at):
            block = column[at == p].T @ column[at == p]
            values, vectors = np.linalg.eigh(block)
            if share:
                block = values[-1] * np.outer(vectors[:, -1], vectors[:, -1])
            mine = merged[merged_at == p]
            np.testing.assert_allclose(mine.T @ mine, block, atol=1e-12 * values[-1])
            if share or p == 2:
                assert len(mine) == 1
        none_at, none = particle_columns(at[:0], column[:0], share)      # no contact
        assert none_at.shape == (0,) and none.shape == (0, 3)


def test_muscle_contact_columns_are_the_overlapping_pairs_of_other_muscles():
    rng = np.random.default_rng(2)
    n = 40
    x = rng.uniform(0.0, 6.0, size=(3, n))
    radius = rng.uniform(0.3, 1.2, size=n)
    muscle = rng.integers(0, 3, size=n)
    fixed = rng.random(n) < 0.2
    weight = rng.uniform(1.0, 4.0, size=n)
    spheres = Spheres(np.arange(n), radius, muscle, fixed, np.zeros((3, 0)), np.zeros(0),
                      np.zeros(0, dtype=np.int64))
    lists = [[j for j in range(n) if muscle[j] != muscle[i]] for i in range(n)]
    ends = np.cumsum([0] + [len(item) for item in lists])
    csr = (ends[:-1].copy(), ends[1:].copy(),
           np.concatenate([np.array(item, dtype=np.int32) for item in lists]))
    at, column = muscle_contact_columns(x, weight, spheres, csr)
    expected = []
    for i in range(n):
        for j in lists[i]:
            d = x[:, i] - x[:, j]
            if not fixed[i] and np.linalg.norm(d) < radius[i] + radius[j]:
                expected.append((i, *(np.sqrt(0.5 * (weight[i] + weight[j])) * d
                                       / np.linalg.norm(d))))
    assert len(expected) > 5
    got = sorted(zip(at, *column.T))
    np.testing.assert_allclose(np.array(got), np.array(sorted(expected)), rtol=1e-12)


def pressed_lattices():
    """Two 3 x 2 x 9 lattices side by side, ends fixed, every particle a 0.8 mm sphere, the
    second pushed 0.6 mm into the first: a contact problem with one equilibrium."""
    points, springs, rest = lattice(3, 2, 9, spacing=(2.0, 2.0, 3.0))
    k = len(points)
    index = np.tile(np.arange(9), 6)
    second = points + [5.0, 0.0, 0.0]
    positions = np.concatenate([points, second])
    return S.MSSModel(
        ["a", "b"], np.array([0, k, 2 * k]), positions,
        np.tile((index == 0) | (index == 8), 2), np.ones(2 * k), np.ones(2 * k, bool),
        np.full(2 * k, 0.8), np.repeat(np.arange(12), 9), np.tile(index, 2),
        np.concatenate([springs, springs + k]), np.concatenate([rest, rest]),
        np.full(2 * len(rest), 10.0), np.full(2 * len(rest), 0.5), None, positions.copy())


def test_the_same_equilibrium_with_and_without_contacts_in_the_preconditioner():
    """Both solves meet a tight tolerance at the same particles, with the muscles still
    pressing on each other there (the contact columns in use to the end), and no particle of
    the answer carries a net force above the tolerance's equivalent."""
    model = pressed_lattices()
    answers = []
    for on in (True, False):
        result = Q.solve(model, prepared=S.prepare(model), settings=quasi_static(
            tolerance=1e-9, iterations=5000, projection_passes=0,
            contact_preconditioner=on))
        assert result.converged
        assert result.muscle_pairs[-1] > 0
        answers.append(result.positions)
    moved = np.abs(answers[0] - model.positions).max()
    assert moved > 0.1
    np.testing.assert_allclose(answers[0], answers[1], atol=1e-6)
