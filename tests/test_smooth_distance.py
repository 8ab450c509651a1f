"""The continuously differentiable lookup of the bone distance fields (core/bones/smooth_distance.py)
that the quasi-static contact energy uses."""
import numpy as np
from numba import njit

from muscle_mss.core.bones.distance import sample
from muscle_mss.core.bones.field_sampling import bone_field_set
from muscle_mss.core.bones.smooth_distance import smooth_sample
from test_bone_distance import box_mesh, sphere_mesh

RADIUS = 20.0
SPACING = 1.0


@njit(cache=True)
def _lookups(points, grid, smooth):
    out = np.zeros((points.shape[0], 4))
    for p in range(points.shape[0]):
        if smooth:
            v = smooth_sample(0, points[p, 0], points[p, 1], points[p, 2], grid)
        else:
            v = sample(0, points[p, 0], points[p, 1], points[p, 2], grid)
        out[p, 0], out[p, 1], out[p, 2], out[p, 3] = v
    return out


def field(mesh):
    return bone_field_set([mesh], spacing=SPACING)


def test_a_flat_face_s_distance_is_reproduced_exactly_with_its_gradient():
    # near the middle of a box's face the signed distance is linear: the B-spline of linear
    # node values is that linear function
    fields = field(box_mesh([-30.0, -30.0, -30.0], [30.0, 30.0, 30.0]))
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-5, 5, 200), rng.uniform(-5, 5, 200),
                              rng.uniform(27.0, 33.0, 200)])
    got = _lookups(points, fields.grid(), True)
    np.testing.assert_allclose(got[:, 0], points[:, 2] - 30.0, atol=1e-5)
    np.testing.assert_allclose(got[:, 1:], np.tile([0.0, 0.0, 1.0], (200, 1)), atol=1e-5)


def test_the_gradient_is_continuous_across_cell_faces_where_the_trilinear_one_jumps():
    fields = field(sphere_mesh(RADIUS))
    grid = fields.grid()
    origin = fields.origin[0]
    # points on fine cell faces (x on a node plane) near the sphere's surface, approached
    # from both sides
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(300, 3))
    points = RADIUS * directions / np.linalg.norm(directions, axis=1)[:, None]
    points[:, 0] = origin[0] + np.round((points[:, 0] - origin[0]) / SPACING) * SPACING
    step = np.array([1e-6, 0.0, 0.0])
    jump = {}
    for smooth in (True, False):
        below = _lookups(points - step, grid, smooth)
        above = _lookups(points + step, grid, smooth)
        jump[smooth] = np.abs(above[:, 1:] - below[:, 1:]).max()
    assert jump[True] < 1e-4
    assert jump[False] > 100 * jump[True]      # the kink the smooth lookup removes


def test_the_gradient_is_the_derivative_of_the_value_and_the_value_the_distance():
    fields = field(sphere_mesh(RADIUS, levels=5))
    grid = fields.grid()
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    points = directions * rng.uniform(RADIUS - 3.0, RADIUS + 3.0, 200)[:, None]
    got = _lookups(points, grid, True)
    exact = np.linalg.norm(points, axis=1) - RADIUS
    # the icosphere's facets lie inside the sphere by up to ~0.03 mm; the smoothing adds
    # about spacing^2 / (8 R)
    assert np.abs(got[:, 0] - exact).max() < 0.05
    h = 1e-4
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        difference = (_lookups(points + e, grid, True)[:, 0]
                      - _lookups(points - e, grid, True)[:, 0]) / (2 * h)
        np.testing.assert_allclose(got[:, 1 + axis], difference, atol=1e-4)
    assert np.abs(np.linalg.norm(got[:, 1:], axis=1) - 1.0).max() < 0.02
