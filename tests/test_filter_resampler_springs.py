"""The Fibre Resampler and Spring Builder filters as plain VTK algorithms (DESIGN §5, issue 3)."""
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibres import resample_fibres
from muscle_mss.core.radii import boundary_from_surface, sphere_radii
from muscle_mss.core.scene import FibreSet, Surface
from muscle_mss.filters import array_names as A
from muscle_mss.filters import vtk_arrays as V
from muscle_mss.filters.fibre_resampler import FibreResampler, muscle_seed
from muscle_mss.filters.scene_io import fibres_to_vtk, surfaces_to_vtk
from muscle_mss.filters.spring_builder import LAYOUTS, SpringBuilder


# ---- synthetic muscles ---------------------------------------------------------------------

def spindle(centre, rows=4, cols=3, half_length=30.0, width=(6.0, 5.0), with_grid=True):
    """A spindle-shaped muscle: rows x cols bent fibres along z and an enclosing ellipsoid."""
    centre = np.asarray(centre, dtype=float)
    z = np.linspace(-half_length, half_length, 7)
    taper = 0.35 + 0.65 * (1.0 - (z / half_length) ** 2)
    polylines, grid = [], []
    for r in range(rows):
        for c in range(cols):
            u = (r / max(rows - 1, 1) - 0.5) * width[0]
            v = (c / max(cols - 1, 1) - 0.5) * width[1]
            bend = 0.02 * (z ** 2) / half_length
            polylines.append(centre + np.column_stack([u * taper + bend, v * taper, z]))
            grid.append((r, c))
    k = np.arange(400) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / 400), np.pi * (1 + 5 ** 0.5) * k
    unit = np.column_stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                            np.cos(polar)])
    points = centre + unit * [0.75 * width[0] + 1.0, 0.75 * width[1] + 1.0, half_length + 1.0]
    surface = Surface(points, ConvexHull(points).simplices.astype(np.int64))
    return FibreSet.from_polylines(polylines, grid if with_grid else None), surface


def scene(with_grid=True, gap=11.0):
    """Three muscles side by side along x whose surfaces touch (gap below their widths)."""
    names = ["vastus_lateralis", "rectus_femoris", "vastus_medialis"]
    built = [spindle([i * gap, 0.3 * i, 0.0], rows=4 + i % 2, cols=3, with_grid=with_grid)
             for i in range(len(names))]
    fibres = fibres_to_vtk({n: b[0] for n, b in zip(names, built)})
    surfaces = surfaces_to_vtk({n: b[1] for n, b in zip(names, built)})
    return names, fibres, surfaces


def resample(fibres, **props):
    f = FibreResampler()
    f.SetInputDataObject(0, fibres)
    for key, value in props.items():
        getattr(f, "Set" + key)(value)
    f.Update()
    return f.GetOutputDataObject(0)


def build(particles, surfaces, bones=None, **props):
    f = SpringBuilder()
    f.SetInputDataObject(0, particles)
    f.SetInputDataObject(1, surfaces)
    if bones is not None:
        f.SetInputDataObject(2, bones)
    for key, value in props.items():
        getattr(f, "Set" + key)(value)
    f.Update()
    return f.GetOutputDataObject(0)


def snapshot(multiblock):
    """Everything of a multiblock, as copies: to compare before and after a filter ran."""
    out = []
    for name, block in V.blocks(multiblock):
        cells = [block.GetCellData().GetAbstractArray(i).GetName()
                 for i in range(block.GetCellData().GetNumberOfArrays())]
        fields = [block.GetFieldData().GetAbstractArray(i).GetName()
                  for i in range(block.GetFieldData().GetNumberOfArrays())]
        out.append((name, V.points_of(block), V.lines_of(block), V.triangles_of(block),
                    V.point_arrays(block), {c: V.cell_array(block, c) for c in cells},
                    {f: V.field(block, f) for f in fields}))
    return out


def assert_same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x[0] == y[0]
        assert np.array_equal(x[1], y[1]) and np.array_equal(x[3], y[3])
        assert all(np.array_equal(p, q) for p, q in zip(x[2], y[2]))
        for d, e in ((x[4], y[4]), (x[5], y[5])):
            assert d.keys() == e.keys() and all(np.array_equal(d[k], e[k]) for k in d)
        assert x[6].keys() == y[6].keys()
        assert all(np.array_equal(x[6][k], y[6][k]) for k in x[6])


def cross_overlaps(model):
    """Pairs of spheres of different muscles that overlap, by brute force over all spheres."""
    centres, radii, owner = [], [], []
    for m, (_, block) in enumerate(V.blocks(model)):
        centres.append(V.point_array(block, A.REST_POSITION))
        radii.append(V.point_array(block, A.RADIUS))
        owner.append(np.full(len(radii[-1]), m))
    centres, radii, owner = map(np.concatenate, (centres, radii, owner))
    spheres = radii > 0
    centres, radii, owner = centres[spheres], radii[spheres], owner[spheres]
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    clash = (owner[:, None] != owner[None]) & (d < radii[:, None] + radii[None])
    return int(clash.sum() // 2)


# ---- Fibre Resampler ---------------------------------------------------------------------------

def test_resampler_output_follows_the_contract():
    names, fibres, _ = scene()
    before = snapshot(fibres)
    out = resample(fibres, ParticlesPerFibre=9)
    assert_same(before, snapshot(fibres))
    blocks = V.blocks(out)
    assert [n for n, _ in blocks] == names
    for (name, block), (_, fib) in zip(blocks, V.blocks(fibres)):
        n_fibres = fib.GetNumberOfLines()
        assert block.GetNumberOfPoints() == 9 * n_fibres
        offsets, connectivity = V.lines_of(block)
        assert np.array_equal(offsets, np.arange(0, 9 * n_fibres + 1, 9))
        assert np.array_equal(connectivity, np.arange(9 * n_fibres))
        rest = V.point_array(block, A.REST_POSITION)
        assert rest.dtype == np.float64 and rest.shape == (9 * n_fibres, 3)
        assert np.array_equal(rest, V.points_of(block))
        fid, fidx = V.point_array(block, A.FIBRE_ID), V.point_array(block, A.FIBRE_INDEX)
        assert fid.dtype == np.int32 and fidx.dtype == np.int32
        assert np.array_equal(fid, np.repeat(np.arange(n_fibres), 9))
        assert np.array_equal(fidx, np.tile(np.arange(9), n_fibres))
        fixed = V.point_array(block, A.FIXED)
        assert fixed.dtype == np.uint8 and np.array_equal(fixed, (fidx == 0) | (fidx == 8))
        grid = V.point_array(block, A.FIBRE_GRID)
        assert grid.dtype == np.int32 and grid.shape == (9 * n_fibres, 2)
        assert np.array_equal(grid, V.cell_array(fib, A.FIBRE_GRID)[fid])
        ends = V.points_of(fib)[V.lines_of(fib)[0][:-1]]
        assert np.array_equal(rest[fidx == 0], ends)
        assert V.field(block, A.MUSCLE_NAME) == name
        assert V.field(block, "ParticlesPerFibre") == 9 and V.field(block, "Randomise") == 1
        assert V.field(block, "Seed") == 0


def test_resampler_without_grid_has_no_fibre_grid():
    _, fibres, _ = scene(with_grid=False)
    for _, block in V.blocks(resample(fibres)):
        assert V.point_array(block, A.FIBRE_GRID, required=False) is None


def test_resampler_is_seeded_per_muscle_and_independent_of_block_order():
    names, fibres, _ = scene()
    a = dict(V.blocks(resample(fibres, Seed=4)))
    b = dict(V.blocks(resample(fibres, Seed=4)))
    c = dict(V.blocks(resample(fibres, Seed=5)))
    reversed_input = V.make_multiblock(V.blocks(fibres)[::-1])
    d = dict(V.blocks(resample(reversed_input, Seed=4)))
    for name in names:
        pa = V.points_of(a[name])
        assert np.array_equal(pa, V.points_of(b[name]))
        assert np.array_equal(pa, V.points_of(d[name]))
        assert not np.allclose(pa, V.points_of(c[name]))
    # the filter places what the core places with the muscle's seed
    fib = dict(V.blocks(fibres))[names[1]]
    offsets, connectivity = V.lines_of(fib)
    expected, *_ = resample_fibres(V.points_of(fib)[connectivity], offsets, 20, True,
                                   muscle_seed(4, names[1]))
    assert np.array_equal(V.points_of(a[names[1]]), expected)


def test_resampler_randomise_off_gives_equal_spacing():
    _, fibres, _ = scene()
    out = resample(fibres, ParticlesPerFibre=7, Randomise=False, Seed=3)
    for _, block in V.blocks(out):
        steps = np.linalg.norm(np.diff(V.points_of(block).reshape(-1, 7, 3), axis=1), axis=2)
        # the fibres are smooth and finely bent: equal arc steps give nearly equal chords
        assert np.allclose(steps, steps.mean(axis=1, keepdims=True), rtol=0.05)


def one_block(name, polydata):
    return V.make_multiblock([(name, polydata)])


@pytest.mark.parametrize("case, message", [
    ("N=1", r"ParticlesPerFibre is 1; it must be at least 2"),
    ("empty", r"fibres.vtm block 'soleus' has no fibres"),
    ("one point", r"fibres.vtm block 'soleus': fibre 1 has 1 point; a fibre needs at least 2"),
    ("zero length", r"fibres.vtm block 'soleus': fibre 0 has zero length"),
    ("no blocks", r"fibres.vtm has no blocks"),
])
def test_resampler_refuses_bad_input_and_leaves_it_unchanged(case, message):
    points = np.array([[0.0, 0, 0], [0, 0, 10], [1, 0, 0], [1, 0, 10], [2, 0, 0]])
    n = 20
    if case == "N=1":
        fibres = one_block("soleus", V.make_polydata(points[:4], line_offsets=[0, 2, 4],
                                                      line_connectivity=np.arange(4)))
        n = 1
    elif case == "empty":
        fibres = one_block("soleus", V.make_polydata(points))
    elif case == "one point":
        fibres = one_block("soleus", V.make_polydata(points, line_offsets=[0, 2, 3, 5],
                                                      line_connectivity=[0, 1, 2, 3, 4]))
    elif case == "zero length":
        fibres = one_block("soleus", V.make_polydata(points, line_offsets=[0, 2],
                                                      line_connectivity=[0, 0]))
    else:
        fibres = V.make_multiblock([])
    before = snapshot(fibres)
    f = FibreResampler()
    f.SetInputDataObject(0, fibres)
    f.SetParticlesPerFibre(n)
    with pytest.raises(MuscleMSSError, match=message):
        f.Update()
    assert f.GetOutputDataObject(0).GetNumberOfBlocks() == 0
    assert_same(before, snapshot(fibres))


# ---- Spring Builder ---------------------------------------------------------------------------

@pytest.mark.parametrize("layout", LAYOUTS)
def test_spring_builder_output_follows_the_contract(layout):
    names, fibres, surfaces = scene()
    particles = resample(fibres, ParticlesPerFibre=8)
    before = snapshot(particles), snapshot(surfaces)
    model = build(particles, surfaces, Layout=layout, NeighbourCount=7, Stiffness=12.5,
                  Damping=0.25, Mass=2.0)
    assert_same(before[0], snapshot(particles))
    assert_same(before[1], snapshot(surfaces))
    blocks = V.blocks(model)
    assert [n for n, _ in blocks] == names
    for (name, block), (_, part) in zip(blocks, V.blocks(particles)):
        count = part.GetNumberOfPoints()
        assert np.array_equal(V.points_of(block), V.points_of(part))
        for array_name, values in V.point_arrays(part).items():
            assert np.array_equal(V.point_array(block, array_name), values)
        offsets, connectivity = V.lines_of(block)
        assert (np.diff(offsets) == 2).all()
        springs = connectivity.reshape(-1, 2)
        assert (springs[:, 0] < springs[:, 1]).all() and springs.max() < count
        assert len(np.unique(springs, axis=0)) == len(springs)
        rest = V.point_array(block, A.REST_POSITION)
        assert np.allclose(V.cell_array(block, A.REST_LENGTH),
                           np.linalg.norm(rest[springs[:, 0]] - rest[springs[:, 1]], axis=1))
        assert (V.cell_array(block, A.STIFFNESS) == 12.5).all()
        assert (V.cell_array(block, A.DAMPING) == 0.25).all()
        mass = V.point_array(block, A.MASS)
        assert mass.dtype == np.float64 and (mass == 2.0).all() and len(mass) == count
        degree = np.bincount(springs.ravel(), minlength=count)
        assert (degree >= (7 if layout == "k-NN" else 3)).all()
        boundary = V.point_array(block, A.BOUNDARY)
        radius = V.point_array(block, A.RADIUS)
        assert boundary.dtype == np.uint8 and radius.dtype == np.float64
        assert (radius[boundary == 0] == 0).all() and (radius >= 0).all()
        assert (radius[boundary == 1] > 0).mean() > 0.9
        # with fibre_grid the boundary is the lattice surface: outer ring + both end faces
        grid = V.point_array(block, A.FIBRE_GRID)
        fidx = V.point_array(block, A.FIBRE_INDEX)
        ring = (grid[:, 0] == 0) | (grid[:, 0] == grid[:, 0].max()) | (grid[:, 1] == 0) | \
            (grid[:, 1] == grid[:, 1].max())
        assert np.array_equal(boundary == 1, ring | (fidx == 0) | (fidx == 7))
        assert V.field(block, A.MUSCLE_NAME) == name and V.field(block, "Layout") == layout
        assert V.field(block, "ParticlesPerFibre") == 8 and V.field(block, "Stiffness") == 12.5
        assert V.field(block, "NeighbourCount") == 7 and V.field(block, "Mass") == 2.0


def test_lattice_spring_counts_through_the_filter():
    fibre_set, surface = spindle([0, 0, 0], rows=8, cols=8)
    fibres = fibres_to_vtk({"m": fibre_set})
    surfaces = surfaces_to_vtk({"m": surface})
    particles = resample(fibres, ParticlesPerFibre=20)
    for layout, springs in (("lattice-6", 3456), ("lattice-26", 13396)):
        block = V.blocks(build(particles, surfaces, Layout=layout))[0][1]
        assert block.GetNumberOfLines() == springs
        assert V.point_array(block, A.BOUNDARY).sum() == 28 * 20 + 2 * 36


@pytest.mark.parametrize("heuristic", [True, False])
@pytest.mark.parametrize("layout", ["lattice-26", "k-NN"])
def test_no_spheres_of_different_muscles_overlap_after_the_shrink(layout, heuristic):
    names, fibres, surfaces = scene(with_grid=layout.startswith("lattice"))
    particles = resample(fibres, ParticlesPerFibre=12)
    model = build(particles, surfaces, Layout=layout, RadiusHeuristic=heuristic)
    assert cross_overlaps(model) == 0
    # the muscles touch: without the shrink their spheres would overlap
    for (name, block), (_, surf) in zip(V.blocks(model), V.blocks(surfaces)):
        rest = V.point_array(block, A.REST_POSITION)
        radius = sphere_radii(rest, V.point_array(block, A.BOUNDARY) == 1, V.points_of(surf),
                              heuristic)
        shrunk = V.point_array(block, A.RADIUS)
        assert (shrunk <= radius).all()
        V.set_point_array(block, A.RADIUS, radius)
    assert cross_overlaps(model) > 0


def test_without_fibre_grid_the_boundary_is_nearest_to_the_surface_vertices():
    names, fibres, surfaces = scene(with_grid=False)
    particles = resample(fibres, ParticlesPerFibre=10)
    model = build(particles, surfaces, Layout="Delaunay")
    for (_, block), (_, surf) in zip(V.blocks(model), V.blocks(surfaces)):
        expected = boundary_from_surface(V.point_array(block, A.REST_POSITION),
                                         V.points_of(surf))
        assert np.array_equal(V.point_array(block, A.BOUNDARY) == 1, expected)
        assert V.point_array(block, A.FIBRE_GRID, required=False) is None


@pytest.mark.parametrize("layout", ["lattice-6", "lattice-26"])
def test_lattice_without_fibre_grid_is_refused_naming_the_muscle(layout):
    _, fibres, surfaces = scene(with_grid=False)
    particles = resample(fibres, ParticlesPerFibre=5)
    before = snapshot(particles)
    with pytest.raises(MuscleMSSError, match=f"block 'vastus_lateralis' has no fibre_grid; "
                                             f"layout {layout} needs"):
        build(particles, surfaces, Layout=layout)
    assert_same(before, snapshot(particles))


def test_ragged_grid_is_refused_naming_the_muscle():
    fibre_set, surface = spindle([0, 0, 0], rows=3, cols=3)
    fibre_set.grid[4] = (5, 5)
    fibres = fibres_to_vtk({"gracilis": fibre_set})
    particles = resample(fibres, ParticlesPerFibre=5)   # k-NN's coarsest
    before = snapshot(particles)
    with pytest.raises(MuscleMSSError, match="block 'gracilis': fibre_grid has no fibre at"):
        build(particles, surfaces_to_vtk({"gracilis": surface}))
    assert_same(before, snapshot(particles))
    # Delaunay and k-NN do not need a full grid
    model = build(particles, surfaces_to_vtk({"gracilis": surface}), Layout="k-NN")
    assert V.blocks(model)[0][1].GetNumberOfLines() > 0


def test_missing_surface_and_bad_properties_are_refused():
    names, fibres, surfaces = scene()
    particles = resample(fibres, ParticlesPerFibre=4)
    partial = V.make_multiblock(V.blocks(surfaces)[:2])
    with pytest.raises(MuscleMSSError, match="muscles.vtm has no block 'vastus_medialis'"):
        build(particles, partial)
    with pytest.raises(MuscleMSSError, match="Stiffness is 0.0; it must be positive"):
        build(particles, surfaces, Stiffness=0.0)
    with pytest.raises(MuscleMSSError, match="Damping is -1.0; it must be at least 0"):
        build(particles, surfaces, Damping=-1.0)
    with pytest.raises(MuscleMSSError, match="'Voronoi' is not one of"):
        SpringBuilder().SetLayout("Voronoi")


def test_error_upstream_is_reported_by_the_spring_builder():
    _, fibres, surfaces = scene()
    resampler = FibreResampler()
    resampler.SetInputDataObject(0, fibres)
    resampler.SetParticlesPerFibre(1)
    builder = SpringBuilder()
    builder.SetInputConnection(0, resampler.GetOutputPort())
    builder.SetInputDataObject(1, surfaces)
    with pytest.raises(MuscleMSSError, match="ParticlesPerFibre"):
        builder.Update()


def test_small_demo_scene_spheres_do_not_overlap_after_the_shrink(small_scene):
    from muscle_mss.filters.scene_io import scene_to_vtk
    muscles, fibres, _, _ = scene_to_vtk(small_scene)
    model = build(resample(fibres, ParticlesPerFibre=10), muscles)
    assert len(V.blocks(model)) == len(small_scene.muscles)
    assert cross_overlaps(model) == 0


def test_with_bones_no_muscle_sphere_overlaps_a_bone_sphere_at_rest(small_scene):
    from muscle_mss.core.bones.spheres import bone_spheres
    from muscle_mss.filters.scene_io import scene_to_vtk
    muscles, fibres, bones, _ = scene_to_vtk(small_scene)
    particles = resample(fibres, ParticlesPerFibre=10)
    alone, cleared = build(particles, muscles), build(particles, muscles, bones)
    assert cross_overlaps(cleared) == 0
    spheres = [bone_spheres(V.points_of(b), V.triangles_of(b)) for _, b in V.blocks(bones)]
    centres = np.concatenate([c for c, _ in spheres])
    bone_radii = np.concatenate([r for _, r in spheres])

    def overlaps(model):
        count = 0
        for _, block in V.blocks(model):
            radius = V.point_array(block, A.RADIUS)
            gap = (np.linalg.norm(V.points_of(block)[:, None] - centres[None], axis=2)
                   - bone_radii).min(axis=1)
            count += int(((radius > 0) & (radius > gap)).sum())
        return count

    assert overlaps(alone) > 50 and overlaps(cleared) == 0
    for (_, a), (_, b) in zip(V.blocks(alone), V.blocks(cleared)):
        ra, rb = V.point_array(a, A.RADIUS), V.point_array(b, A.RADIUS)
        assert (rb <= ra).all() and (rb > 0).sum() > 0.7 * (ra > 0).sum()


def test_without_bones_the_spring_builder_warns_of_the_consequence():
    from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow
    _, fibres, surfaces = scene()
    particles = resample(fibres)
    bone = spindle([0.0, 40.0, 0.0])[1]
    bones = V.make_multiblock([("femur", V.make_polydata(bone.points, triangles=bone.triangles))])
    previous = vtkOutputWindow.GetInstance()
    texts = []
    try:
        for connected in (None, bones):
            window = vtkStringOutputWindow()
            vtkOutputWindow.SetInstance(window)
            build(particles, surfaces, connected)
            texts.append(window.GetOutput())
    finally:
        vtkOutputWindow.SetInstance(previous)
    alone, wired = texts
    assert "Spring Builder: the Bones input is not connected" in alone
    assert "radius array is not cleared of the bones" in alone and "Connect bones.vtm" in alone
    assert "The Rigid Pose Transform clears them" in alone
    assert "Bones input" not in wired
