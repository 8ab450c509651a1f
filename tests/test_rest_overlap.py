"""Nothing silently wrong at rest: fibres written in pieces are joined into their fibres, a
muscle's belly inside a bone or another muscle is warned about, and the surfaces' overlap with
other muscles is measured after solving (``in_other_muscle_*`` in summary.csv)."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

import bad_input_cases as B
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_pieces import joined_fibres
from muscle_mss.core.contacts.muscle_overlap import vertices_in_other_muscles


def _csr(polylines):
    return (np.concatenate(polylines),
            np.concatenate([[0], np.cumsum([len(p) for p in polylines])]).astype(np.int64))


def _fibres(count=6, points=9):
    rng = np.random.default_rng(3)
    return [np.cumsum(rng.random((points, 3)) + [0.0, 0.0, 5.0], axis=0) + [10.0 * k, 0, 0]
            for k in range(count)]


def _segments(fibres):
    return [f[i:i + 2] for f in fibres for i in range(len(f) - 1)]


def test_segments_in_order_give_back_their_fibres_and_grid_cells():
    fibres = _fibres()
    grid = np.repeat([(k // 3, k % 3) for k in range(6)], 8, axis=0)
    points, offsets, joined_grid, pieces = joined_fibres(*_csr(_segments(fibres)), grid)
    assert pieces == 48
    expect_points, expect_offsets = _csr(fibres)
    assert np.array_equal(points, expect_points) and np.array_equal(offsets, expect_offsets)
    assert joined_grid.tolist() == [[k // 3, k % 3] for k in range(6)]


def test_shuffled_and_reversed_pieces_join_each_fibre_the_way_most_of_it_runs():
    fibres = _fibres()
    segments = _segments(fibres)
    order = np.random.default_rng(5).permutation(len(segments))
    shuffled = [segments[i][::-1] if i % 4 == 1 else segments[i] for i in order]
    points, offsets, _, pieces = joined_fibres(*_csr(shuffled))
    assert pieces == 48 and len(offsets) == 7
    got = sorted(points[a:b].tobytes() for a, b in zip(offsets[:-1], offsets[1:]))
    assert got == sorted(f.tobytes() for f in fibres)
    uneven = [fibres[0][:4], fibres[0][3:7], fibres[0][6:], fibres[1]]   # pieces of any length
    points, offsets, _, pieces = joined_fibres(*_csr(uneven))
    assert pieces == 4 and np.array_equal(points[:offsets[1]], fibres[0])


def test_whole_fibres_and_fibres_sharing_a_tendon_point_are_left_alone():
    fibres = _fibres()
    points, offsets = _csr(fibres)
    assert joined_fibres(points, offsets)[3] == 0
    fan = [np.array([[0.0, 0, 0], [k, 1, 5], [k, 2, 10]]) for k in range(5)]
    assert joined_fibres(*_csr(fan))[3] == 0


def test_branching_and_looping_pieces_are_refused_naming_the_block_and_count():
    segments = _segments(_fibres())
    branch = np.array([segments[3][1], segments[3][1] + [5.0, 0, 0]])
    with pytest.raises(MuscleMSSError, match=r"^fibres.vtm block 'm': its 49 polylines chain end "
                       r"to end, but 3 of them meet at one point \(.*\) mm, so which piece "
                       r"continues which is ambiguous: a fibre cannot branch"):
        joined_fibres(*_csr(segments + [branch]), where="fibres.vtm block 'm'")
    loop = [np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([[1.0, 0, 0], [1, 1, 0]]),
            np.array([[1.0, 1, 0], [0, 0, 0]])]
    with pytest.raises(MuscleMSSError, match=r"its 51 polylines chain end to end, but 3 of them "
                       r"close into a loop"):
        joined_fibres(*_csr(segments + loop), where="fibres.vtm block 'm'")
    grid = np.zeros((48, 2))
    grid[5] = (1, 0)
    with pytest.raises(MuscleMSSError, match=r"the 8 polylines joined into fibre 0 lie in "
                       r"different fibre_grid cells"):
        joined_fibres(*_csr(segments), grid)


def _sphere(centre, radius=10.0, count=400):
    k = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / count), np.pi * (1 + 5 ** 0.5) * k
    points = radius * np.column_stack([np.cos(azimuth) * np.sin(polar),
                                       np.sin(azimuth) * np.sin(polar), np.cos(polar)])
    triangles = ConvexHull(points).simplices.copy()
    for t in triangles:   # outward
        a, b, c = points[t]
        if np.dot(np.cross(b - a, c - a), a) < 0:
            t[[1, 2]] = t[[2, 1]]
    return points + centre, triangles


def test_vertices_inside_another_surface_are_counted_with_their_depth():
    a, b, far = _sphere([0.0, 0, 0]), _sphere([15.0, 0, 0]), _sphere([100.0, 0, 0])
    count, depth = vertices_in_other_muscles([a, b, far])
    inside_b = np.linalg.norm(a[0] - [15.0, 0, 0], axis=1) < 10.0
    assert abs(int(count[0]) - int(inside_b.sum())) <= 3 and count[0] > 20
    assert abs(int(count[1]) - int(count[0])) <= 3 and count[2] == 0   # far apart: none
    assert depth[0] == pytest.approx(5.0, abs=0.2) and depth[2] == 0.0


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    made = {}

    def get(name):
        if name not in made:
            case = next((c for c in B.CASES if c.name == name), B.Case(name, "", ""))
            made[name] = B.make_scene(case, tmp_path_factory.mktemp(name))
        return made[name]
    return get


def _solve(folder, settings=None):
    from muscle_mss.app import motion_run
    from muscle_mss.filters.scene_io import vtk_messages
    with vtk_messages() as window:
        pipeline = motion_run.build_pipeline(str(folder), settings)
        result = motion_run.solve_time_point(pipeline, B.TIME_INDEX)
    return pipeline, result, window.GetOutput()


@pytest.mark.parametrize("layout", ["lattice-26", "k-NN"])
def test_fibres_as_segments_give_the_particles_and_springs_of_the_whole_fibres(layout, folders):
    from muscle_mss.app import motion_run
    from muscle_mss.filters import vtk_arrays as V
    models = []
    for name in ("valid", "fibres-as-segments"):
        pipeline = motion_run.build_pipeline(str(folders(name)), {"Layout": layout})
        pipeline.springs.Update()
        models.append(V.blocks(pipeline.springs.GetOutputDataObject(0), "model"))
    for (name, whole), (_, joined) in zip(*models):
        assert np.array_equal(V.points_of(whole), V.points_of(joined)), name
        assert whole.GetNumberOfCells() == joined.GetNumberOfCells(), name


def test_the_valid_scene_warns_of_nothing_and_reports_its_surfaces_overlap(folders):
    _, result, messages = _solve(folders("valid"))
    assert "Spring Builder" not in messages and "joined" not in messages, messages
    for row in result.rows:   # its touching muscles' coarse surfaces overlap a little at rest
        assert row["in_other_muscle_vertices"] >= 0 and row["in_other_muscle_depth_mm"] >= 0.0
    assert sum(row["in_other_muscle_vertices"] for row in result.rows) > 0


def test_a_folded_surface_confirms_its_inside_vertices_by_winding_numbers():
    from muscle_mss.core.contacts.muscle_overlap import turned_over
    a, b = _sphere([0.0, 0, 0]), _sphere([15.0, 0, 0])
    assert not turned_over(b[0], b[0], b[1])
    folded = b[0].copy()
    top = np.argmax(folded[:, 2])
    folded[top] = [15.0, 0, -5.0]              # the top vertex pushed through the sphere
    assert turned_over(folded, b[0], b[1])
    confirmed = vertices_in_other_muscles([a, (folded, b[1])], [a[0], b[0]])
    assert np.array_equal(confirmed[0], vertices_in_other_muscles([a, (folded, b[1])])[0])


def test_half_in_another_muscle_warns_and_the_summary_shows_the_overlap(folders):
    _, valid, _ = _solve(folders("valid"))
    _, result, messages = _solve(folders("muscle-half-in-muscle"))
    assert "muscles.vtm blocks 'rectus_femoris' and 'vastus_lateralis': 50 % of the fibre " \
           "midpoints of 'rectus_femoris' (8 of 16)" in messages
    rows = {r["muscle"]: r for r in result.rows}
    before = {r["muscle"]: r for r in valid.rows}
    for name in ("rectus_femoris", "vastus_lateralis"):
        assert rows[name]["in_other_muscle_vertices"] > 0.1 * 434       # of 434 vertices
        assert rows[name]["in_other_muscle_depth_mm"] > 3 * before[name][
            "in_other_muscle_depth_mm"]
        assert rows[name]["sphere_overlap_mm"] < 0.1                    # what it showed before
