"""Where a muscle's fibres start and end (muscle_mss.core.attachment_areas): the areas of its
surface on its origin and insertion bones, the bones inferred when the scene names none, and
the attachments table's rules; checked on a cylinder of a muscle between two disc-shaped bones,
with a third bone along its belly."""
import numpy as np
import pytest

from muscle_mss.core.attachment_areas import (FALLBACK_SHARE, TOUCH_DISTANCE, attachment_rows,
                                              inferred_bones, scene_areas)
from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.fibre_generation import fibre_grid_shape, generate_scene_fibres
from muscle_mss.core.scene import Surface
from muscle_mss.core.volume import winding_numbers

from test_fibre_generation import straight, tube

LENGTH = 80.0


def cylinder_along_z(z0, z1, radius, x=0.0, around=24, along=12):
    """A closed surface: the cylinder of ``radius`` mm around the line x, y = ``x``, 0 from z0
    to z1 mm."""
    centre, tangent = straight(z1 - z0)
    points, triangles = tube(centre, tangent, lambda s: radius, z1 - z0, around, along, 3)[:2]
    return Surface(points + np.array([x, 0.0, z0]), triangles)


@pytest.fixture(scope="module")
def muscle():
    return Surface(*tube(*straight(LENGTH), lambda s: 10.0, LENGTH, 32, 30, 4)[:2])


def bones_at(insertion_gap=1.0):
    """Pelvis-like disc under the muscle (1 mm gap), tibia-like disc ``insertion_gap`` mm above
    it, and a thin rod lying 1.5 mm beside its belly."""
    return {"upper": cylinder_along_z(-6.0, -1.0, 16.0),
            "lower": cylinder_along_z(LENGTH + insertion_gap, LENGTH + insertion_gap + 5.0, 16.0),
            "rod": cylinder_along_z(20.0, 60.0, 3.0, x=14.5)}


def test_the_areas_are_where_the_muscle_ends_touch_their_bones_not_its_belly(muscle):
    areas = scene_areas({"m": muscle}, bones_at(), {"m": ("upper", "lower")})["m"]
    z, x = muscle.points[:, 2], muscle.points[:, 0]
    assert areas.touching == (True, True)
    assert areas.origin[z == 0.0].all() and areas.insertion[z == LENGTH].all()   # the caps
    assert z[areas.origin].max() <= TOUCH_DISTANCE - 1.0 + 1e-9
    assert z[areas.insertion].min() >= LENGTH - (TOUCH_DISTANCE - 1.0) - 1e-9
    belly = (x > 9.0) & (z > 20.0) & (z < 60.0)         # 1.5 mm from the rod, no attachment
    assert not (areas.origin | areas.insertion)[belly].any()


def test_an_end_that_does_not_touch_its_bone_is_attached_by_its_last_part(muscle):
    areas = scene_areas({"m": muscle}, bones_at(insertion_gap=8.0), {"m": ("upper", "lower")})
    areas = areas["m"]
    z = muscle.points[:, 2]
    assert areas.touching == (True, False)
    np.testing.assert_array_equal(areas.insertion, z >= LENGTH * (1.0 - FALLBACK_SHARE) - 1e-9)


def test_a_muscle_far_from_its_bone_is_refused_naming_it(muscle):
    with pytest.raises(MuscleMSSError) as err:
        scene_areas({"m": muscle}, bones_at(insertion_gap=30.0), {"m": ("upper", "lower")})
    text = str(err.value)
    assert "muscles.vtm block 'm'" in text and "insertion bone 'lower'" in text
    assert "30.0 mm" in text and "attachments.csv" in text


def test_bones_are_inferred_from_the_ends_the_first_listed_is_the_origin(muscle):
    bones = bones_at()
    assert scene_areas({"m": muscle}, bones, {})["m"].origin_bone == "upper"
    backwards = {name: bones[name] for name in ("lower", "rod", "upper")}
    areas = scene_areas({"m": muscle}, backwards, {})["m"]
    assert (areas.origin_bone, areas.insertion_bone) == ("lower", "upper")
    assert muscle.points[areas.origin, 2].min() > LENGTH - 3.0      # the end at that bone


def test_an_end_between_two_bones_asks_for_the_attachments_file(muscle):
    bones = dict(bones_at(), twin=cylinder_along_z(-6.5, -1.5, 16.0))
    with pytest.raises(MuscleMSSError) as err:
        scene_areas({"m": muscle}, bones, {})
    assert "'upper'" in str(err.value) and "'twin'" in str(err.value)
    assert "attachments.csv" in str(err.value) and "muscle,origin_bone,insertion_bone" in \
        str(err.value)
    same = {"upper": bones["upper"], "rod": bones["rod"]}
    with pytest.raises(MuscleMSSError, match="both ends are nearest 'upper'"):
        inferred_bones(muscle.points, np.c_[np.zeros(len(muscle.points)),
                                            np.full(len(muscle.points), 9.0)],
                       list(same), "m")


def test_the_scenes_fibres_run_from_bone_to_bone_inside_the_muscle(muscle):
    fibres = generate_scene_fibres({"m": muscle}, bones_at(), {}, count=12, samples=20)["m"]
    assert (fibres.origin_bone, fibres.insertion_bone) == ("upper", "lower")
    assert fibres.count == 12 and sorted(map(tuple, fibres.grid)) == \
        [(r, c) for r in range(3) for c in range(4)]
    ends = fibres.points.reshape(12, 20, 3)[:, [0, -1], 2]
    assert np.all(ends[:, 0] < 1.5) and np.all(ends[:, 1] > LENGTH - 1.5)
    assert np.all(winding_numbers(fibres.points, muscle.points, muscle.triangles) > 0.5)


def test_grid_shapes_are_the_most_nearly_square():
    assert [fibre_grid_shape(n) for n in (64, 60, 7, 1)] == [(8, 8), (6, 10), (1, 7), (1, 1)]
    with pytest.raises(MuscleMSSError, match="at least one fibre"):
        fibre_grid_shape(0)


@pytest.mark.parametrize("rows,message", [
    ([{"muscle": "m", "origin_bone": "upper"}], "column(s) insertion_bone missing"),
    ([{"muscle": "x", "origin_bone": "upper", "insertion_bone": "lower"}],
     "row 2: 'x' is not a muscle of muscles.vtm"),
    ([{"muscle": "m", "origin_bone": "upper", "insertion_bone": "lower"},
      {"muscle": "m", "origin_bone": "upper", "insertion_bone": "lower"}],
     "row 3: 'm' is listed twice"),
    ([{"muscle": "m", "origin_bone": "upper", "insertion_bone": "femur"}],
     "row 2, column insertion_bone: 'femur' is not a bone of bones.vtm"),
])
def test_attachments_table_rows_are_checked_naming_row_and_rule(rows, message):
    with pytest.raises(MuscleMSSError) as err:
        attachment_rows(rows, ["m"], ["upper", "lower"])
    assert str(err.value).startswith("attachments.csv") and message in str(err.value)
    good = [{"muscle": " m ", "origin_bone": "upper", "insertion_bone": "lower"}]
    assert attachment_rows(good, ["m"], ["upper", "lower"]) == {"m": ("upper", "lower")}
