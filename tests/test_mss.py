"""Mass-spring kernel (core/mss.py): forces against a NumPy reference, rest, relaxation."""
import numpy as np
import pytest

from muscle_mss.core import mss


def reference_forces(x, v, springs, rest, k, c):
    """Hooke + damping along the spring, one spring at a time (the obviously correct way)."""
    force = np.zeros_like(x)
    for (a, b), length0, ks, cs in zip(springs, rest, k, c):
        d = x[b] - x[a]
        length = np.linalg.norm(d)
        if length == 0:
            continue
        f = (ks * (length - length0) + cs * np.dot(v[b] - v[a], d) / length) * d / length
        force[a] += f
        force[b] -= f
    return force


def lattice(rows, cols, n, spacing=(3.0, 4.0, 2.5)):
    """Particles of a rows x cols x n lattice (row, col, index order) and its 26-springs."""
    r, c, i = np.meshgrid(np.arange(rows), np.arange(cols), np.arange(n), indexing="ij")
    points = np.stack([r * spacing[0], c * spacing[1], i * spacing[2]], -1).reshape(-1, 3)
    ident = ((r * cols + c) * n + i)
    springs = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            for di in (-1, 0, 1):
                if (dr, dc, di) <= (0, 0, 0):
                    continue
                r2, c2, i2 = r + dr, c + dc, i + di
                ok = (r2 >= 0) & (r2 < rows) & (c2 >= 0) & (c2 < cols) & (i2 >= 0) & (i2 < n)
                springs.append(np.stack([ident[ok], ((r2 * cols + c2) * n + i2)[ok]], -1))
    springs = np.concatenate(springs)
    rest = np.linalg.norm(points[springs[:, 1]] - points[springs[:, 0]], axis=1)
    return points.astype(float), springs, rest


def test_forces_match_reference_on_lattice_and_irregular_springs():
    rng = np.random.default_rng(0)
    pts, springs, rest = lattice(3, 3, 12)
    n1 = len(pts)
    extra = rng.integers(n1, n1 + 60, size=(300, 2))          # a second, irregular muscle
    extra = extra[extra[:, 0] != extra[:, 1]]
    extra = np.concatenate([extra, extra[:5]])                  # repeated springs too
    springs = np.concatenate([springs, extra])
    rest = np.concatenate([rest, rng.random(len(extra)) * 3])
    k = np.where(rng.random(len(springs)) < 0.8, 10.0, 4.0)
    c = np.where(rng.random(len(springs)) < 0.5, 0.5, 0.0)
    offsets = np.array([0, n1, n1 + 60])
    x = np.concatenate([pts, rng.random((60, 3)) * 5]) + rng.normal(scale=0.3, size=(n1 + 60, 3))
    v = rng.normal(size=x.shape)
    layout = mss.spring_layout(springs, rest, k, c, offsets)
    assert len(layout.runs_int) > 0 and len(layout.scattered_int) > 0
    got = mss.spring_forces(x, v, layout, offsets)
    want = reference_forces(x, v, springs, rest, k, c)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-9 * np.abs(want).max())


def test_lattice_26_in_grid_order_is_13_dense_runs():
    pts, springs, rest = lattice(4, 4, 10)
    layout = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                               np.full(len(rest), 0.5), [0, len(pts)])
    assert len(layout.runs_int) == 13
    assert len(layout.scattered_int) == 0
    assert (layout.lane_rest >= 0).sum() == len(springs)


def test_lattice_order_sorts_by_grid_then_index():
    fibre_id = np.repeat([2, 0, 1, 3], 3)
    fibre_index = np.tile([2, 0, 1], 4)
    grid = np.repeat([[1, 1], [0, 0], [0, 1], [1, 0]], 3, axis=0)
    order = mss.lattice_order(fibre_id, fibre_index, grid)
    assert [tuple(grid[o]) + (fibre_index[o],) for o in order] == sorted(
        tuple(g) + (i,) for g, i in zip(grid, fibre_index))


def test_zero_length_spring_gives_no_force():
    x = np.zeros((2, 3))
    layout = mss.spring_layout([[0, 1]], [1.0], [10.0], [0.5], [0, 2])
    assert np.array_equal(mss.spring_forces(x, np.ones((2, 3)), layout, [0, 2]), np.zeros((2, 3)))


def test_lattice_at_rest_stays_at_rest():
    pts, springs, rest = lattice(3, 4, 9)
    layout = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                               np.full(len(rest), 0.5), [0, len(pts)])
    x, v = mss.mss_steps(pts, np.zeros_like(pts), np.ones(len(pts)), np.zeros(len(pts), bool),
                         layout, [0, len(pts)], 0.05, 200)
    assert np.abs(x - pts).max() < 1e-9
    assert np.abs(v).max() < 1e-8


def test_stretched_lattice_relaxes_to_rest_lengths_and_fixed_stay():
    pts, springs, rest = lattice(3, 3, 6)
    centre = pts.mean(axis=0)
    stretched = centre + 1.2 * (pts - centre)
    fixed = np.zeros(len(pts), bool)
    layout = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                               np.full(len(rest), 0.5), [0, len(pts)])
    before = np.linalg.norm(stretched[springs[:, 1]] - stretched[springs[:, 0]], axis=1)
    assert np.abs(before / rest - 1).max() > 0.19
    x, _ = mss.mss_steps(stretched, np.zeros_like(pts), np.ones(len(pts)), fixed, layout,
                         [0, len(pts)], 0.05, 3000)
    after = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    assert np.abs(after / rest - 1).max() < 1e-3
    fixed[[0, 5, 20]] = True
    x, v = mss.mss_steps(stretched, np.zeros_like(pts), np.ones(len(pts)), fixed, layout,
                         [0, len(pts)], 0.05, 50)
    assert np.array_equal(x[fixed], stretched[fixed])
    assert np.array_equal(v[fixed], np.zeros((3, 3)))
    assert np.abs(x[~fixed] - stretched[~fixed]).max() > 0.1


def test_steps_are_bitwise_reproducible():
    pts, springs, rest = lattice(3, 3, 7)
    rng = np.random.default_rng(1)
    start = pts + rng.normal(scale=0.4, size=pts.shape)
    layout = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                               np.full(len(rest), 0.5), [0, len(pts)])
    runs = [mss.mss_steps(start, np.zeros_like(pts), np.ones(len(pts)),
                          np.zeros(len(pts), bool), layout, [0, len(pts)], 0.05, 30)[0]
            for _ in range(2)]
    assert np.array_equal(runs[0], runs[1])


def test_wrong_row_count_is_refused():
    layout = mss.spring_layout([[0, 1]], [1.0], [10.0], [0.5], [0, 2])
    with pytest.raises(mss.MuscleMSSError, match="rows"):
        mss.spring_forces(np.zeros((3, 3)), np.zeros((2, 3)), layout, [0, 2])


def cube_cage(size=2.0):
    """A cube's 8 corners and its 12 outward triangles."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float) * size
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return corners, triangles


def cage_volume(x, triangles):
    return np.einsum("ij,ij", x[triangles[:, 0]],
                     np.cross(x[triangles[:, 1]], x[triangles[:, 2]])) / 6.0


def test_drag_slows_every_velocity_by_the_implicit_factor_and_is_stable_at_any_strength():
    pts = np.array([[0.0, 0, 0], [5.0, 0, 0]])
    layout = mss.spring_layout(np.zeros((0, 2)), [], [], [], [0, 2])
    v0 = np.array([[1.0, -2.0, 0.5], [0.0, 3.0, 0.0]])
    for drag in (0.0, 2.0, 1e9):
        x, v = mss.mss_steps(pts, v0, np.ones(2), np.zeros(2, bool), layout, [0, 2], 0.05, 3,
                             drag=drag)
        keep = 1.0 / (1.0 + 0.05 * drag)
        np.testing.assert_allclose(v, v0 * keep ** 3, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(x, pts + 0.05 * v0 * (keep + keep ** 2 + keep ** 3),
                                   rtol=1e-12)


def test_drag_beyond_the_explicit_damping_limit_still_relaxes_a_stretched_lattice():
    pts, springs, rest = lattice(3, 3, 6)
    stretched = pts.mean(axis=0) + 1.2 * (pts - pts.mean(axis=0))
    layout = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                               np.full(len(rest), 0.5), [0, len(pts)])
    # the same strength as damping along the springs breaks c dt n / m < 2 (n = 26): it diverges
    explicit = mss.spring_layout(springs, rest, np.full(len(rest), 10.0),
                                 np.full(len(rest), 50.0), [0, len(pts)])
    with np.errstate(all="ignore"):
        x, _ = mss.mss_steps(stretched, np.zeros_like(pts), np.ones(len(pts)),
                             np.zeros(len(pts), bool), explicit, [0, len(pts)], 0.05, 100)
    assert not (np.abs(x - pts) < 1e3).all()
    x, v = mss.mss_steps(stretched, np.zeros_like(pts), np.ones(len(pts)),
                         np.zeros(len(pts), bool), layout, [0, len(pts)], 0.05, 2000, drag=50.0)
    after = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1)
    assert np.abs(after / rest - 1).max() < 1e-3
    assert np.abs(v).max() < 1e-3


def test_volume_step_is_backward_euler_on_the_gradient_of_the_volume_energy():
    corners, triangles = cube_cage()
    rng = np.random.default_rng(3)
    x = corners * 0.9 + rng.normal(scale=0.05, size=corners.shape)
    rest_volume = cage_volume(corners, triangles)
    bulk = 7.0
    cages = mss.VolumeCages(np.array([0, 12]), triangles, np.array([rest_volume]))
    layout = mss.spring_layout(np.zeros((0, 2)), [], [], [], [0, 8])

    def energy(y):
        return 0.5 * bulk * rest_volume * (cage_volume(y, triangles) / rest_volume - 1.0) ** 2

    def numeric_gradient(function):
        gradient = np.zeros_like(x)
        for i in range(8):
            for axis in range(3):
                step = np.zeros_like(x)
                step[i, axis] = 1e-6
                gradient[i, axis] = (function(x + step) - function(x - step)) / 2e-6
        return gradient.ravel()

    force = -numeric_gradient(energy)
    g = numeric_gradient(lambda y: cage_volume(y, triangles))
    for dt in (1e-3, 0.05, 1.0):   # mass 1 g: explicit Euler blows up above 0.41 s here
        _, v = mss.mss_steps(x, np.zeros_like(x), np.ones(8), np.zeros(8, bool), layout, [0, 8],
                             dt, 1, bulk_modulus=bulk, cages=cages)
        # (M + dt^2 K) dv = dt f with the volume's stiffness K = bulk / V_rest g g^T
        expected = np.linalg.solve(np.eye(24) + dt * dt * bulk / rest_volume * np.outer(g, g),
                                   dt * force)
        np.testing.assert_allclose(v.ravel(), expected, rtol=1e-6, atol=1e-9 * dt)
        assert (np.einsum("ij,ij->i", v, x - x.mean(axis=0)) > 0).all()   # a shrunk cage swells


def test_a_stiff_volume_term_is_stable_at_a_step_far_beyond_its_explicit_limit():
    corners, triangles = cube_cage()
    rest_volume = cage_volume(corners, triangles)
    cages = mss.VolumeCages(np.array([0, 12]), triangles, np.array([rest_volume]))
    springs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    layout = mss.spring_layout(springs, np.full(4, 2.0), np.full(4, 10.0), np.full(4, 0.5),
                               [0, 8])
    squeezed = corners * [0.8, 0.8, 1.0]
    # bulk 1e4 on a 1 g cube: the explicit volume step is stable below 0.011 s
    x, v = mss.mss_steps(squeezed, np.zeros_like(corners), np.ones(8), np.zeros(8, bool),
                         layout, [0, 8], 0.05, 400, drag=5.0, bulk_modulus=1e4, cages=cages)
    assert np.isfinite(x).all() and np.abs(x).max() < 10.0
    assert abs(cage_volume(x, triangles) / rest_volume - 1.0) < 1e-4


def test_volume_force_is_zero_at_rest_and_restores_a_squeezed_lattice_volume():
    corners, triangles = cube_cage()
    cages = mss.VolumeCages(np.array([0, 12]), triangles,
                            np.array([cage_volume(corners, triangles)]))
    no_springs = mss.spring_layout(np.zeros((0, 2)), [], [], [], [0, 8])
    x, v = mss.mss_steps(corners, np.zeros_like(corners), np.ones(8), np.zeros(8, bool),
                         no_springs, [0, 8], 0.05, 100, bulk_modulus=5.0, cages=cages)
    assert np.array_equal(x, corners) and not v.any()
    # springs only on the cube's edges along z: a squeeze in x and y meets no spring
    springs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    layout = mss.spring_layout(springs, np.full(4, 2.0), np.full(4, 10.0), np.full(4, 0.5),
                               [0, 8])
    squeezed = corners * [0.8, 0.8, 1.0]
    for bulk, kept in ((0.0, False), (5.0, True)):
        x, _ = mss.mss_steps(squeezed, np.zeros_like(corners), np.ones(8), np.zeros(8, bool),
                             layout, [0, 8], 0.05, 400, drag=5.0, bulk_modulus=bulk, cages=cages)
        ratio = cage_volume(x, triangles) / cages.rest_volume[0]
        assert (abs(ratio - 1.0) < 1e-3) == kept, ratio
