"""Per-time-point work around the solver (issue 15): bone spheres cached per bone shape and
moved rigidly, penetration statistics over arrays, series writing chosen by the user."""
import numpy as np
import pytest
from test_collisions import icosphere_like

from muscle_mss.core.bones.spheres import bone_spheres
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.contacts.penetration import max_penetration_pairs, max_penetration_per_object
from muscle_mss.core.mesh_checks import surface_problems
from muscle_mss.core.rigid_fit import rigid_fit
from muscle_mss.filters import bone_sets, check_cache
from muscle_mss.app import motion_run, run_output
from muscle_mss.app.cli import main
from muscle_mss.app.run_report import timings_note

SPACING = 3.0


def bone():
    """An egg-shaped closed surface (no rotational symmetry left for the rigid fit to miss)."""
    points, triangles = icosphere_like(radius=20.0, n=24)
    return points * [1.6, 1.0, 0.7] + [5.0, -3.0, 40.0], triangles


def rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.fixture(autouse=True)
def empty_cache():
    bone_sets.clear_bone_cache()
    check_cache.clear_check_cache()
    yield
    bone_sets.clear_bone_cache()
    check_cache.clear_check_cache()


def test_same_bone_is_sampled_once_and_gives_the_same_spheres():
    points, triangles = bone()
    first = bone_sets.cached_bone_spheres(points, triangles, SPACING)
    second = bone_sets.cached_bone_spheres(points.copy(), triangles.copy(), SPACING)
    fresh = bone_spheres(points, triangles, SPACING)
    assert bone_sets.cache_counts == {"sampled": 1, "reused": 1, "moved": 0}
    for a, b, c in zip(first, second, fresh):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, c)
    first[0][:] = 0.0  # a caller's change does not reach the cache
    np.testing.assert_array_equal(
        bone_sets.cached_bone_spheres(points, triangles, SPACING)[0], fresh[0])


def test_moved_bone_gets_the_cached_spheres_moved_with_it():
    points, triangles = bone()
    rest, radii = bone_sets.cached_bone_spheres(points, triangles, SPACING)
    r, t = rotation(3), np.array([12.0, -40.0, 7.5])
    moved, moved_radii = bone_sets.cached_bone_spheres(points @ r.T + t, triangles, SPACING)
    assert bone_sets.cache_counts == {"sampled": 1, "reused": 0, "moved": 1}
    np.testing.assert_allclose(moved, rest @ r.T + t, atol=1e-9)
    np.testing.assert_array_equal(moved_radii, radii)
    # sampling is equivariant: a fresh sampling of the moved bone gives the same spheres
    fresh, _ = bone_spheres(points @ r.T + t, triangles, SPACING)
    assert fresh.shape == moved.shape
    np.testing.assert_allclose(fresh, moved, atol=1e-9)


def test_changed_bone_point_or_spacing_is_sampled_afresh():
    points, triangles = bone()
    bone_sets.cached_bone_spheres(points, triangles, SPACING)
    bent = points @ rotation(5).T
    bent[7] += [0.0, 0.0, 0.05]  # no longer a rigid copy
    got, _ = bone_sets.cached_bone_spheres(bent, triangles, SPACING)
    assert bone_sets.cache_counts == {"sampled": 2, "reused": 0, "moved": 0}
    np.testing.assert_array_equal(got, bone_spheres(bent, triangles, SPACING)[0])
    other, radii = bone_sets.cached_bone_spheres(points, triangles, 2.0 * SPACING)
    assert bone_sets.cache_counts["sampled"] == 3
    np.testing.assert_array_equal(radii, 2.0 * SPACING)
    mirrored = points * [-1.0, 1.0, 1.0]  # a reflection is not a rigid motion
    bone_sets.cached_bone_spheres(mirrored, triangles[:, ::-1], SPACING)
    assert bone_sets.cache_counts["sampled"] == 4


def test_cache_off_samples_every_time_and_bad_bones_still_refused():
    points, triangles = bone()
    for _ in range(2):
        bone_sets.cached_bone_spheres(points, triangles, SPACING, use_cache=False)
    assert bone_sets.cache_counts == {"sampled": 0, "reused": 0, "moved": 0}
    bad = points.copy()
    bad[3] = np.nan
    with pytest.raises(MuscleMSSError, match="femur"):
        bone_sets.cached_bone_spheres(bad, triangles, SPACING, where="femur")


def test_bone_solids_remember_unmodified_blocks_and_refit_a_moved_one():
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from muscle_mss.filters import vtk_arrays as V
    points, triangles = bone()
    bones = V.make_multiblock([("femur", V.make_polydata(points, triangles))])
    fields, transforms = bone_sets.bone_solids(bones)
    again, remembered = bone_sets.bone_solids(bones)
    assert bone_sets.field_counts == {"sampled": 1, "loaded": 0, "reused": 0, "moved": 0,
                                      "remembered": 1}
    assert again is fields
    np.testing.assert_array_equal(remembered, transforms)
    remembered[0, 0, 3] = 99.0  # a caller's change does not reach the memory
    np.testing.assert_array_equal(bone_sets.bone_solids(bones)[1], transforms)
    # the same block moved in place (as a pose filter's output is): fitted again, not remembered
    r, t = rotation(4), np.array([3.0, -8.0, 20.0])
    block = bones.GetBlock(0)
    block.GetPoints().SetData(numpy_to_vtk(points @ r.T + t, deep=True))
    block.Modified()
    _, moved = bone_sets.bone_solids(bones)
    assert bone_sets.field_counts["moved"] == 1 and bone_sets.field_counts["remembered"] == 2
    np.testing.assert_allclose(moved[0], np.hstack([r, t[:, None]]), atol=1e-9)


def test_a_bones_triangle_digest_is_remembered_until_its_cells_change():
    from muscle_mss.filters import vtk_arrays as V
    points, triangles = bone()
    block = V.make_polydata(points, triangles)
    _, _, first = bone_sets._block_shape(block, "femur")
    assert first == bone_sets._triangles_digest(triangles)
    # a new, unmodified posed copy (the pose filter's: the same cell array) is not hashed again
    posed = V.with_points(block, points + 1.0)
    calls = []
    original = bone_sets._triangles_digest
    bone_sets._triangles_digest = lambda t: calls.append(1) or original(t)
    try:
        assert bone_sets._block_shape(posed, "femur")[2] == first and not calls
        # triangles reversed in place, marked modified: a new digest, hashed afresh
        connectivity = V._numpy_view(block.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        connectivity[:] = connectivity[:, ::-1].copy()
        block.GetPolys().Modified()
        _, reversed_triangles, second = bone_sets._block_shape(block, "femur")
    finally:
        bone_sets._triangles_digest = original
    assert calls and second != first
    assert second == bone_sets._triangles_digest(np.asarray(triangles)[:, ::-1])
    np.testing.assert_array_equal(reversed_triangles, np.asarray(triangles)[:, ::-1])


def test_fields_are_stored_on_disk_and_read_back_bitwise_by_a_later_run(tmp_path, monkeypatch):
    from muscle_mss.core.bones import field_store
    monkeypatch.setenv(field_store.ENVIRONMENT, str(tmp_path))
    points, triangles = bone()
    sampled, _ = bone_sets.cached_bone_field(points, triangles)
    assert bone_sets.field_counts["sampled"] == 1
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"]
    bone_sets.clear_bone_cache()                     # a later run: nothing in memory
    loaded, transform = bone_sets.cached_bone_field(points, triangles)
    assert bone_sets.field_counts["sampled"] == 0 and bone_sets.field_counts["loaded"] == 1
    np.testing.assert_array_equal(transform, np.eye(3, 4))
    assert loaded.spacing == sampled.spacing
    for name in ("origin", "dims", "coarse", "brick_index", "bricks"):
        got, want = getattr(loaded, name), getattr(sampled, name)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
    # another bone (one point moved) is another file; a damaged file is sampled again
    bent = points.copy()
    bent[0] += 0.01
    bone_sets.cached_bone_field(bent, triangles)
    assert bone_sets.field_counts["sampled"] == 1 and len(list(tmp_path.iterdir())) == 2
    for stored in tmp_path.iterdir():
        stored.write_bytes(stored.read_bytes()[:100])
    bone_sets.clear_bone_cache()
    bone_sets.cached_bone_field(points, triangles)
    assert bone_sets.field_counts["sampled"] == 1 and bone_sets.field_counts["loaded"] == 0
    # off: neither read nor written
    monkeypatch.setenv(field_store.ENVIRONMENT, "off")
    bone_sets.clear_bone_cache()
    for stored in tmp_path.iterdir():
        stored.unlink()
    bone_sets.cached_bone_field(points, triangles)
    assert bone_sets.field_counts["sampled"] == 1 and not list(tmp_path.iterdir())


def test_placement_verdicts_are_stored_on_disk_and_read_back_by_a_later_run(
        small_scene, tmp_path, monkeypatch):
    """The Spring Builder's placement verdict of a scene is read back from disk when the same
    content was checked before (a later run, a worker process), and checked again when one
    coordinate changes, when its file is damaged, and always with the store off."""
    import dataclasses
    from muscle_mss.core.validation import placement_problems, placement_warnings
    monkeypatch.setenv("MUSCLE_MSS_PLACEMENT_CHECKS", str(tmp_path))
    names = list(small_scene.fibres)
    swapped = dataclasses.replace(small_scene, fibres={
        **small_scene.fibres, names[0]: small_scene.fibres[names[1]],
        names[1]: small_scene.fibres[names[0]]})
    want = {"valid": ([], placement_warnings(small_scene)),
            "swapped": (placement_problems(swapped), [])}
    assert want["swapped"][0]           # fibres outside their muscle: refused
    for scene, name in ((small_scene, "valid"), (swapped, "swapped")):
        before = dict(check_cache.verdict_counts)
        assert check_cache.placement_verdict(scene) == want[name]
        assert check_cache.placement_verdict(scene) == want[name]
        assert check_cache.verdict_counts["checked"] == before["checked"] + 1
        assert check_cache.verdict_counts["loaded"] == before["loaded"] + 1
    assert len(list(tmp_path.iterdir())) == 2
    moved = dataclasses.replace(small_scene, bones={
        name: dataclasses.replace(s, points=s.points + (1e-9 if k == 0 else 0.0))
        for k, (name, s) in enumerate(small_scene.bones.items())})
    before = dict(check_cache.verdict_counts)
    check_cache.placement_verdict(moved)
    assert check_cache.verdict_counts["checked"] == before["checked"] + 1
    for stored in tmp_path.iterdir():
        stored.write_bytes(stored.read_bytes()[:100])
    before = dict(check_cache.verdict_counts)
    assert check_cache.placement_verdict(swapped) == want["swapped"]
    assert check_cache.verdict_counts == {**before, "checked": before["checked"] + 1}
    monkeypatch.setenv("MUSCLE_MSS_PLACEMENT_CHECKS", "off")
    for stored in tmp_path.iterdir():
        stored.unlink()
    assert check_cache.placement_verdict(small_scene) == want["valid"]
    assert not list(tmp_path.iterdir())


def test_rest_surface_checked_once_per_content():
    points, triangles = bone()
    assert check_cache.rest_surface_problems(points, triangles) == []
    assert check_cache.rest_surface_problems(points.copy(), triangles) == []
    assert check_cache.check_counts == {"checked": 1, "reused": 1}
    flipped = triangles[:, ::-1]
    want = surface_problems(points, flipped)
    assert want and check_cache.rest_surface_problems(points, flipped) == want
    moved = points.copy()
    moved[0, 0] += 1e-9
    check_cache.rest_surface_problems(moved, triangles)
    assert check_cache.check_counts == {"checked": 3, "reused": 1}
    assert check_cache.rest_surface_problems(points, flipped) == want
    assert check_cache.check_counts == {"checked": 3, "reused": 2}


def test_rigid_fit_recovers_a_known_motion():
    points, _ = bone()
    r, t = rotation(11), np.array([1.0, 2.0, 3.0])
    got_r, got_t, residual, size = rigid_fit(points, points @ r.T + t)
    np.testing.assert_allclose(got_r, r, atol=1e-12)
    np.testing.assert_allclose(got_t, t, atol=1e-9)
    assert residual < 1e-9
    np.testing.assert_allclose(size, np.ptp(points @ r.T + t, axis=0).max())
    # a reflection is not a rotation: the fit stays a rotation and reports the miss
    mirrored = points * [-1.0, 1.0, 1.0]
    got_r, _, residual, _ = rigid_fit(points, mirrored)
    np.testing.assert_allclose(np.linalg.det(got_r), 1.0)
    assert residual > 1.0
    # the same rotation as NumPy's expression of Kabsch (the one this kernel replaced)
    moved = points @ r.T + t + rng_noise(points.shape)
    a, b = points.mean(axis=0), moved.mean(axis=0)
    u, _, vt = np.linalg.svd((points - a).T @ (moved - b))
    want = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    np.testing.assert_allclose(rigid_fit(points, moved)[0], want, atol=1e-12)


def rng_noise(shape):
    return np.random.default_rng(5).normal(0.0, 0.05, shape)


@pytest.mark.parametrize("seed, cell_radii", [(1, 1.0), (2, 0.3), (3, 2.5)])
def test_penetration_grid_equals_the_reference_bitwise(seed, cell_radii, monkeypatch):
    from muscle_mss.core.contacts import penetration
    monkeypatch.setattr(penetration, "CELL_RADII", cell_radii)   # grids fine and coarse
    rng = np.random.default_rng(seed)
    n, k = 400, 120
    centres = rng.uniform(0, 30, (n, 3))
    radii = rng.uniform(0.2, 2.5, n)
    owner = rng.integers(0, 5, n)
    bone_c, bone_r = rng.uniform(0, 30, (k, 3)), rng.uniform(0.5, 4.0, k)
    fixed = rng.random(n) < 0.3
    for bones in ((bone_c, bone_r), (None, None)):
        want = max_penetration_per_object(centres, radii, owner, 6, *bones, fixed)
        got = max_penetration_pairs(centres, radii, owner, 6, *bones, fixed)
        np.testing.assert_array_equal(got, want)
        assert want[:5].min() > 0 and want[5] == 0  # object 5 has no spheres
    np.testing.assert_array_equal(max_penetration_pairs(np.zeros((0, 3)), [], [], 2), [0, 0])
    # spheres on the grid's cell boundaries (cell = CELL_RADII times the largest radius), a
    # long thin cloud, and radii all 0 (no overlap: a tiny cell)
    lattice = np.stack(np.meshgrid(*[np.arange(4.0)] * 3), axis=-1).reshape(-1, 3)
    lattice = np.vstack([lattice, lattice + rng.normal(0, 0.3, lattice.shape)])
    long_cloud = rng.uniform(0, 1, (300, 3)) * [5.0, 5.0, 600.0]
    for points, size in ((lattice, 0.5), (long_cloud, 2.0), (long_cloud, 0.0)):
        sizes = np.full(len(points), size)
        owners = rng.integers(0, 3, len(points))
        want = max_penetration_per_object(points, sizes, owners, 3)
        np.testing.assert_array_equal(max_penetration_pairs(points, sizes, owners, 3), want)
        assert (want.max() > 0) == (size > 0)


def test_convergence_table_is_written_column_by_column_as_the_csv_module_writes_it(tmp_path):
    rng = np.random.default_rng(3)
    columns = {"iteration": np.arange(40), "seconds": rng.random(40) * np.logspace(-9, 5, 40),
               "collided": np.arange(40, dtype=np.uint8) % 2, "flag": np.arange(40) % 3 == 0,
               "odd": np.array([1e-5, 1e16, -0.0, 1.5e300, np.inf, np.nan, 0.1, 2.0] * 5)}
    for name, extra in (("numbers", {}), ("with text", {"method": ["paper"] * 40})):
        table = {**columns, **extra}
        run_output.write_columns(tmp_path / f"{name}.csv", table)
        run_output.write_csv(tmp_path / f"{name} ref.csv", list(table), zip(*table.values()))
        assert (tmp_path / f"{name}.csv").read_bytes() == \
            (tmp_path / f"{name} ref.csv").read_bytes()


def test_timings_note_lists_the_measured_parts():
    assert timings_note({"solve": 1.234, "surface": 0.1, "statistics": 0.01, "write": 0.05}) \
        == "(solve 1.23 + surface 0.10 + write 0.05 s)"
    assert timings_note({}) == ""


def test_write_option_is_checked_before_solving(small_scene_dir, tmp_path, capsys):
    assert main(["run", str(small_scene_dir), str(tmp_path / "out"), "--write",
                 "surfaces,bones"]) == 2
    assert "--write 'surfaces,bones': bones is not a series" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert run_output.parse_write_option("particles, surfaces") == ("surfaces", "particles")


def test_run_writes_only_the_series_asked_for(small_scene_dir, tmp_path):
    assert main(["run", str(small_scene_dir), str(tmp_path), "--time", "0.5",
                 "--iterations", "5", "--write", "surfaces"]) == 0
    assert (tmp_path / "surfaces.pvd").is_file()
    assert not (tmp_path / "fibres.pvd").exists() and not (tmp_path / "particles.pvd").exists()
    written = sorted(p.name for p in (tmp_path / "series").glob("*.vtm"))
    assert len(written) == 1 and written[0].startswith("surfaces_")


def read_blocks(path):
    from vtkmodules.vtkIOXML import vtkXMLMultiBlockDataReader
    from muscle_mss.filters import vtk_arrays as V
    reader = vtkXMLMultiBlockDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return {name: V.points_of(block) for name, block in V.blocks(reader.GetOutput(), "read")}


def test_every_compressor_reads_back_the_same_series_and_caches_repeat_bitwise(
        small_scene_dir, tmp_path):
    from muscle_mss.filters import vtk_arrays as V
    pipeline = motion_run.build_pipeline(small_scene_dir, {"Iterations": 5})
    result = motion_run.solve_time_point(pipeline, 2)
    assert set(result.timings) == {"solve", "surface", "statistics"}
    for compressor in run_output.COMPRESSORS:
        out = tmp_path / compressor
        run_output.write_time_point(result, str(out), compressor=compressor)
        assert result.timings["write"] > 0
        for name, data in zip(run_output.SERIES,
                              (result.surfaces, result.fibres, result.particles)):
            back = read_blocks(out / run_output.series_file(name, 2))
            want = {n: V.points_of(b) for n, b in V.blocks(data, name)}
            assert back.keys() == want.keys()
            for n in want:
                np.testing.assert_array_equal(back[n], want[n])
    # the second solve of the same time point uses the cached bone fields (the solver's solid
    # bones) and samples no bone afresh: same rows
    before, checks = dict(bone_sets.cache_counts), dict(check_cache.check_counts)
    fields = dict(bone_sets.field_counts)
    pipeline.solver.Modified()
    pipeline.probe.Modified()
    again = motion_run.solve_time_point(pipeline, 2)
    assert bone_sets.cache_counts["sampled"] == before["sampled"]
    assert bone_sets.field_counts["sampled"] == fields["sampled"]
    reuses = ("reused", "moved", "remembered")
    assert sum(bone_sets.field_counts[k] for k in reuses) > sum(fields[k] for k in reuses)
    assert check_cache.check_counts["checked"] == checks["checked"] > 0
    strip = [{k: v for k, v in r.items() if k != "seconds"} for r in result.rows]
    assert strip == [{k: v for k, v in r.items() if k != "seconds"} for r in again.rows]


def test_a_time_points_result_stays_as_it_was_after_later_time_points(small_scene_dir):
    """solve_time_point holds the filters' output blocks without copying them: no later update
    may change a block a filter made before."""
    from muscle_mss.filters import vtk_arrays as V

    def snapshot(result):
        return {(series, name): (V.points_of(block).copy(), {
            k: v.copy() for k, v in V.point_arrays(block).items()})
            for series, data in zip(run_output.SERIES, (result.surfaces, result.fibres,
                                                         result.particles))
            for name, block in V.blocks(data, series)}

    pipeline = motion_run.build_pipeline(small_scene_dir, {"Iterations": 5})
    first = motion_run.solve_time_point(pipeline, 1)
    kept = snapshot(first)
    later = motion_run.solve_time_point(pipeline, 3)
    pipeline.solver.Modified()          # and a re-execution at the same time point
    motion_run.solve_time_point(pipeline, 3)
    now = snapshot(first)
    assert now.keys() == kept.keys() and len(kept) == 3 * len(pipeline_names(first))
    for key, (points, arrays) in kept.items():
        np.testing.assert_array_equal(now[key][0], points)
        assert now[key][1].keys() == arrays.keys()
        for name, values in arrays.items():
            np.testing.assert_array_equal(now[key][1][name], values)
    moved = snapshot(later)
    assert any(not np.array_equal(moved[key][0], kept[key][0]) for key in kept)


def pipeline_names(result):
    return [r["muscle"] for r in result.rows]


def solved_points(pipeline, t):
    from muscle_mss.filters import vtk_arrays as V
    out = motion_run.update_at(pipeline.solver, 0, t)
    return {name: V.points_of(block) for name, block in V.blocks(out)}


def test_solver_checks_its_model_arrays_once_per_change_and_gives_the_same_particles(
        small_scene_dir):
    """The posed model's arrays other than the coordinates are checked, concatenated and
    ordered once while the Rigid Pose Transform hands the same arrays on; a changed property
    upstream or an array modified in place is seen; the particles are bitwise those of a solver
    that never saw the model before."""
    from muscle_mss.filters import MSSCollisionSolver
    from muscle_mss.filters import vtk_arrays as V
    # FibreShortening off: with it the rest lengths, and so the prepared layout, follow the pose
    pipeline = motion_run.build_pipeline(small_scene_dir, {"Iterations": 5,
                                                           "FibreShortening": False})
    solver, times = pipeline.solver, pipeline.times
    blocks = len(V.blocks(motion_run.update_at(pipeline.pose, 0, times[0])))
    solved_points(pipeline, times[0])
    prepared = solver._prepared
    later = solved_points(pipeline, times[2])
    assert solver.setup_counts == {"checked": blocks, "remembered": blocks, "prepared": 1,
                                   "rest state": 0}
    assert solver._prepared is prepared

    def fresh(t):
        other = MSSCollisionSolver()
        other.SetIterations(5)
        other.SetFibreShortening(False)
        for port in range(2):
            other.SetInputConnection(port, pipeline.pose.GetOutputPort(port))
        out = motion_run.update_at(other, 0, t)
        return {name: V.points_of(block) for name, block in V.blocks(out)}

    want = fresh(times[2])
    assert want.keys() == later.keys()
    for name in want:
        np.testing.assert_array_equal(later[name], want[name])

    # a changed spring property upstream: new arrays, checked again, a new ordering
    pipeline.springs.SetStiffness(2.0 * pipeline.springs.GetStiffness())
    stiffer = solved_points(pipeline, times[2])
    assert solver.setup_counts == {"checked": 2 * blocks, "remembered": blocks, "prepared": 2,
                                   "rest state": 0}
    assert solver._prepared is not prepared
    assert any(not np.array_equal(stiffer[n], later[n]) for n in later)
    want = fresh(times[2])
    for name in want:
        np.testing.assert_array_equal(stiffer[name], want[name])

    # an array modified in place (and marked so) is checked again: a bad mass is refused
    model = pipeline.springs.GetOutputDataObject(0)
    name, block = V.blocks(model)[0]
    mass = block.GetPointData().GetArray("mass")
    fixed = V.point_array(block, "fixed")
    mass.SetValue(int(np.flatnonzero(fixed == 0)[0]), -1.0)
    mass.Modified()
    pipeline.pose.Modified()
    with pytest.raises(MuscleMSSError, match=f"block '{name}'.*mass"):
        solver.execute([motion_run.update_at(pipeline.pose, 0, times[1]),
                        motion_run.update_at(pipeline.pose, 1, times[1])],
                       [None, None])


def test_fibre_shortening_keeps_the_factorisation_across_poses_and_the_same_particles(
        small_scene_dir, monkeypatch):
    """With FibreShortening every pose has its own rest lengths, but not its own spring
    matrix: the second time point keeps the first's factorisation (the same object) and
    rebuilds only the spring layout, and its particles are bitwise those of a solver that
    solves that time point alone."""
    from muscle_mss.core import solver as core_solver
    from muscle_mss.filters import MSSCollisionSolver
    from muscle_mss.filters import vtk_arrays as V
    rest_lengths = []       # of the models whose rest state the solve brought up to date
    with_rest_state = core_solver.with_rest_state
    monkeypatch.setattr(core_solver, "with_rest_state", lambda prep, model: (
        rest_lengths.append(model.rest_length), with_rest_state(prep, model))[1])
    pipeline = motion_run.build_pipeline(small_scene_dir, {"Iterations": 40})
    solver, times = pipeline.solver, pipeline.times
    solved_points(pipeline, times[0])
    first = solver._prepared
    factorisations = dict(first.factorisations)
    assert factorisations, "the quasi-static solve factorised nothing"
    later = solved_points(pipeline, times[-3])     # (the last repeats the first pose)
    assert solver.setup_counts["prepared"] == 1 and solver._prepared is first
    assert all(solver._prepared.factorisations[k] is v for k, v in factorisations.items())
    assert len(rest_lengths) == 2
    assert (rest_lengths[1] < rest_lengths[0]).any(), "no fibre shortened: nothing tested"

    other = MSSCollisionSolver()
    other.SetIterations(40)
    for port in range(2):
        other.SetInputConnection(port, pipeline.pose.GetOutputPort(port))
    want = {name: V.points_of(block)
            for name, block in V.blocks(motion_run.update_at(other, 0, times[-3]))}
    assert other.setup_counts["prepared"] == 1 and other.setup_counts["rest state"] == 0
    assert want.keys() == later.keys()
    for name in want:
        np.testing.assert_array_equal(later[name], want[name])


def test_solver_refusing_a_model_refuses_it_again_rather_than_reuse_the_last_one(
        small_scene_dir):
    """A model whose fibres are not numbered 0..k-1 (every fibre_index 0 in one block) is
    refused naming the block, and refused again when asked once more with the same arrays:
    the solver never falls back on the arrays or the ordering of the model before it."""
    from muscle_mss.filters import vtk_arrays as V
    pipeline = motion_run.build_pipeline(small_scene_dir, {"Iterations": 5})
    solver, t = pipeline.solver, pipeline.times[1]
    solved_points(pipeline, t)
    inputs = [motion_run.update_at(pipeline.pose, port, t) for port in range(2)]
    name, block = V.blocks(inputs[0])[0]
    index = block.GetPointData().GetArray("fibre_index")
    for i in range(index.GetNumberOfTuples()):
        index.SetValue(i, 0)
    index.Modified()
    for _ in range(2):
        with pytest.raises(MuscleMSSError, match=f"block '{name}': fibre .* fibre_index"):
            solver.execute(inputs, [None, None])


def test_a_time_point_prepared_while_the_kernels_compile_solves_to_the_same_numbers(
        small_scene_dir):
    """What a run prepares while its kernels compile (``motion_run.prepare_time_point``: the
    stages before the solver, and a spare MVC Surface Deformer and Volume Error Probe fed the
    posed model) changes no number of the time point it then solves."""
    from muscle_mss.filters import vtk_arrays as V

    def numbers(result):
        return {(series, name): V.points_of(block).copy()
                for series, data in zip(run_output.SERIES, (result.surfaces, result.fibres,
                                                             result.particles))
                for name, block in V.blocks(data, series)}, [
            {k: v for k, v in r.items() if k != "seconds"} for r in result.rows]

    settings = {"Iterations": 40}
    prepared = motion_run.build_pipeline(small_scene_dir, settings)
    motion_run.prepare_time_point(prepared, 2)
    posed = motion_run.update_at(prepared.pose, 0, prepared.times[2])
    plain = motion_run.build_pipeline(small_scene_dir, settings)
    points, rows = numbers(motion_run.solve_time_point(prepared, 2))
    assert motion_run.update_at(prepared.pose, 0, prepared.times[2]) is posed  # not re-run
    expected_points, expected_rows = numbers(motion_run.solve_time_point(plain, 2))
    assert rows == expected_rows and points.keys() == expected_points.keys()
    for key, value in expected_points.items():
        np.testing.assert_array_equal(points[key], value)
