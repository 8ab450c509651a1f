"""What a run may do to its output folder (issue 30): it lists every file it writes in the
folder's manifest, ``--overwrite`` removes only the files a previous run's manifest lists (never
a user's file or folder, a link or a path outside the folder), and a run holds a lock on the
folder so that a second run into it is refused."""
import csv
import errno
import fcntl
import os
import shutil

import pytest

import bad_input_cases as B

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.app import output_folder, run_output
from muscle_mss.app.cli import main

MANIFEST = output_folder.MANIFEST_FILE


def _run(scene, out, *options, time="0.5"):
    return main(["run", str(scene), str(out), "--time", time, "--iterations", "3", *options])


def _files(folder):
    return {str(p.relative_to(folder)).replace(os.sep, "/") for p in folder.rglob("*")
            if p.is_file() or p.is_symlink()}


def test_the_manifest_lists_every_file_the_run_wrote_and_nothing_else(small_scene_dir,
                                                                      tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    assert _run(small_scene_dir, tmp_path) == 0
    listed = output_folder.listed_files(str(tmp_path))
    assert (tmp_path / MANIFEST).read_text().startswith("# files written by muscle-mss")
    assert set(listed) == _files(tmp_path) - {MANIFEST, "notes.txt"}
    assert {"summary.csv", "surfaces.pvd", "convergence/convergence_0010.csv",
            "series/surfaces_0010.vtm", "series/surfaces_0010/surfaces_0010_0.vtp"} <= set(listed)
    assert not (tmp_path / output_folder.LOCK_FILE).exists()   # released at the end


def test_overwrite_removes_the_previous_runs_files_and_keeps_the_users(small_scene_dir,
                                                                       tmp_path):
    assert _run(small_scene_dir, tmp_path, time="0.25") == 0
    (tmp_path / "series" / "my_notes.txt").write_text("mine")
    (tmp_path / "my_table.csv").write_text("mine")
    assert _run(small_scene_dir, tmp_path) == 2                  # without --overwrite: refused
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 0
    assert (tmp_path / "series" / "my_notes.txt").read_text() == "mine"
    assert (tmp_path / "my_table.csv").read_text() == "mine"
    assert not list(tmp_path.rglob("*_0005*"))        # the previous run's time point is gone
    assert (tmp_path / "series" / "surfaces_0010.vtm").is_file()
    with open(tmp_path / "summary.csv", newline="") as f:
        assert {float(r["time"]) for r in csv.DictReader(f)} == {0.5}


def test_a_folder_named_like_an_output_is_refused_and_kept(small_scene_dir, tmp_path, capsys):
    """It deleted a user's folder summary.csv/ and the file in it, before."""
    (tmp_path / "summary.csv").mkdir()
    (tmp_path / "summary.csv" / "precious.txt").write_text("mine")
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 2
    err = capsys.readouterr().err
    assert f"output folder {tmp_path} holds summary.csv (a folder), which the run would write " \
           "but muscle-mss did not write" in err and "never removes what it did not write" in err
    assert (tmp_path / "summary.csv" / "precious.txt").read_text() == "mine"
    assert _files(tmp_path) == {"summary.csv/precious.txt"}


def test_results_without_a_manifest_are_refused_even_with_overwrite(small_scene_dir, tmp_path,
                                                                    capsys):
    """A folder written by a version before manifests (or the user's own files by those
    names): nothing tells which files the program wrote, so it removes none."""
    (tmp_path / "series").mkdir()
    (tmp_path / "series" / "surfaces_0003.vtm").write_text("an older run")
    (tmp_path / "surfaces.pvd").write_text("an older run")
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 2
    err = capsys.readouterr().err
    assert "holds surfaces.pvd (a file no manifest lists)" in err
    assert _files(tmp_path) == {"series/surfaces_0003.vtm", "surfaces.pvd"}


def _error_line(err: str) -> str:
    """The first line of the error message in ``err`` (stderr)."""
    return next(line for line in err.splitlines() if line.startswith("error: "))


@pytest.fixture
def unsolved(monkeypatch):
    """Solving fails the test: what is refused must be refused before any solve."""
    from muscle_mss.app import motion_run

    def solve(*args, **kwargs):
        raise AssertionError("solved before the output folder's check")
    monkeypatch.setattr(motion_run, "solve_time_point", solve)


def test_a_file_the_run_would_write_over_deep_in_series_is_kept(small_scene_dir, tmp_path,
                                                               capsys, unsolved):
    (tmp_path / "series").mkdir()
    (tmp_path / "series" / "surfaces_0010.vtm").write_text("mine")
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 2
    assert _error_line(capsys.readouterr().err).startswith(
        f"error: output folder {tmp_path} holds series/surfaces_0010.vtm (a file no manifest "
        "lists), which the run would write but muscle-mss did not write")
    assert (tmp_path / "series" / "surfaces_0010.vtm").read_text() == "mine"


@pytest.mark.parametrize("overwrite", [(), ("--overwrite",)], ids=["plain", "overwrite"])
def test_a_file_where_the_run_writes_a_folder_is_refused_before_solving(
        small_scene_dir, tmp_path, capsys, unsolved, overwrite):
    """A user's file series/surfaces_0010 where time point 10's .vtp folder goes: the run
    solved, then failed "cannot write OUT/series: Not a directory", with or without
    --overwrite (the file is not the run's, so --overwrite leaves it)."""
    scene_digest = B.folder_digest(small_scene_dir)
    (tmp_path / "series").mkdir()
    (tmp_path / "series" / "surfaces_0010").write_text("mine")
    assert _run(small_scene_dir, tmp_path, *overwrite) == 2
    assert _error_line(capsys.readouterr().err).startswith(
        f"error: output folder {tmp_path} holds series/surfaces_0010 (a file where the run "
        "writes a folder), which the run would write but muscle-mss did not write")
    assert _files(tmp_path) == {"series/surfaces_0010"}
    assert (tmp_path / "series" / "surfaces_0010").read_text() == "mine"
    assert B.folder_digest(small_scene_dir) == scene_digest


def test_every_place_is_checked_before_an_earlier_run_is_removed(small_scene_dir, tmp_path,
                                                                capsys):
    """A user's folder where time point 10's .vtm goes, beside an earlier run, with
    --overwrite: refused naming it, and the earlier run is still there."""
    assert _run(small_scene_dir, tmp_path, time="0.25") == 0
    before = B.folder_digest(tmp_path)
    (tmp_path / "series" / "fibres_0010.vtm").mkdir()
    (tmp_path / "series" / "fibres_0010.vtm" / "mine.txt").write_text("mine")
    assert _run(small_scene_dir, tmp_path, "--overwrite", "--write", "fibres") == 2
    assert _error_line(capsys.readouterr().err).startswith(
        f"error: output folder {tmp_path} holds series/fibres_0010.vtm (a folder where the run "
        "writes a file), which the run would write")
    shutil.rmtree(tmp_path / "series" / "fibres_0010.vtm")
    assert B.folder_digest(tmp_path) == before                  # nothing of it was removed


def test_a_folder_the_run_cannot_write_in_is_refused_before_solving(small_scene_dir, tmp_path,
                                                                   capsys, unsolved,
                                                                   monkeypatch):
    (tmp_path / "series").mkdir()
    access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: access(path, mode) and os.path.basename(
        path) != "series")                             # root may write anywhere: say it cannot
    assert _run(small_scene_dir, tmp_path) == 2
    assert _error_line(capsys.readouterr().err) == (
        f"error: output folder {tmp_path}: the run writes into series, which cannot be written "
        "(no write permission); make it writable or choose another folder")
    assert _files(tmp_path) == set()


def _scene_copy(small_scene_dir, folder):
    shutil.copytree(small_scene_dir, folder)
    return folder


@pytest.mark.parametrize("command", ["run", "study"])
def test_overwrite_never_removes_an_input_the_manifest_lists(small_scene_dir, tmp_path, capsys,
                                                             unsolved, command):
    """OUT is the scene folder, its manifest edited by hand to list scene files: --overwrite
    deleted motion.csv and muscles.vtm, then the run failed "muscles.vtm: missing"."""
    scene = _scene_copy(small_scene_dir, tmp_path / "scene")
    (scene / MANIFEST).write_text("# by hand\nsummary.csv\nmotion.csv\nmuscles.vtm\n"
                                  "muscles/muscles_0.vtp\n")
    digest = B.folder_digest(scene)
    options = ("--time", "0.5", "--iterations", "3") if command == "run" else ()
    assert main([command, str(scene), str(scene), "--overwrite", *options]) == 2
    assert _error_line(capsys.readouterr().err) == (
        f"error: output folder {scene}: its manifest {MANIFEST} lists motion.csv, which is "
        f"{scene / 'motion.csv'}, an input of this run (and 2 more inputs); a run never removes "
        "a file it reads, whatever the manifest says: remove those lines from the manifest or "
        "choose another output folder")
    assert B.folder_digest(scene) == digest


def test_an_input_reached_through_a_link_is_never_removed(small_scene_dir, tmp_path, capsys,
                                                          unsolved):
    """OUT a link to the scene folder, or the scene's motion.csv a link to a file the manifest
    lists: the paths are compared resolved."""
    scene = _scene_copy(small_scene_dir, tmp_path / "scene")
    (tmp_path / "out").symlink_to(scene)
    (scene / MANIFEST).write_text("bones.vtm\n")
    digest = B.folder_digest(scene)
    assert _run(scene, tmp_path / "out", "--overwrite") == 2
    assert _error_line(capsys.readouterr().err).startswith(
        f"error: output folder {tmp_path / 'out'}: its manifest {MANIFEST} lists bones.vtm, which "
        f"is {scene / 'bones.vtm'}, an input of this run; a run never removes a file it reads")
    assert B.folder_digest(scene) == digest
    other = tmp_path / "other"
    other.mkdir()
    (other / "table.csv").write_bytes((scene / "motion.csv").read_bytes())
    (scene / "motion.csv").unlink()
    (scene / "motion.csv").symlink_to(other / "table.csv")
    (other / MANIFEST).write_text("table.csv\n")
    assert _run(scene, other, "--overwrite") == 2
    assert "lists table.csv, which is " in _error_line(capsys.readouterr().err)
    assert (other / "table.csv").is_file() and (other / MANIFEST).read_text() == "table.csv\n"


def test_a_run_into_its_scene_folder_keeps_the_scene(small_scene_dir, tmp_path):
    """Writing the results beside the scene's files is allowed, and --overwrite then removes
    the earlier results only."""
    scene = _scene_copy(small_scene_dir, tmp_path / "scene")
    digest = B.folder_digest(scene)
    assert _run(scene, scene) == 0
    assert _run(scene, scene, "--overwrite", time="0.25") == 0
    assert not list(scene.rglob("*_0010*")) and (scene / "series" / "surfaces_0005.vtm").is_file()
    for name in output_folder.listed_files(str(scene)):
        (scene / name).unlink()
    (scene / MANIFEST).unlink()
    for folder in ("series", "convergence"):
        shutil.rmtree(scene / folder, ignore_errors=True)
    assert B.folder_digest(scene) == digest


def test_overwrite_removes_no_link_and_nothing_outside_the_folder(tmp_path):
    out, outside = tmp_path / "out", tmp_path / "outside.txt"
    out.mkdir()
    outside.write_text("not yours")
    (out / "link.csv").symlink_to(outside)
    (out / "series").mkdir()
    (out / "series" / "ours.vtm").write_text("ours")
    (out / MANIFEST).write_text("# manifest\n../outside.txt\n" + str(outside) + "\nlink.csv\n"
                                "series/../../outside.txt\nseries/ours.vtm\n")
    assert output_folder.remove_listed(str(out)) == ["series/ours.vtm"]
    assert outside.read_text() == "not yours" and (out / "link.csv").is_symlink()
    assert not (out / "series").exists() and not (out / MANIFEST).exists()


def test_a_second_run_into_a_held_folder_is_refused_naming_the_other_run(small_scene_dir,
                                                                          tmp_path, capsys):
    with output_folder.output_lock(str(tmp_path)):
        assert _run(small_scene_dir, tmp_path) == 2
    err = capsys.readouterr().err
    assert f"output folder {tmp_path} is in use by another muscle-mss run (pid {os.getpid()}" \
           in err and "wait for it to end or choose another folder" in err
    assert _files(tmp_path) == set()
    assert _run(small_scene_dir, tmp_path) == 0                  # released: the folder is free


def test_a_lock_left_by_a_run_that_died_is_taken_over_with_a_note(small_scene_dir, tmp_path,
                                                                 capsys):
    (tmp_path / output_folder.LOCK_FILE).write_text("4194305\n")    # no process holds it
    assert _run(small_scene_dir, tmp_path) == 0
    err = capsys.readouterr().err
    assert f"note: took over the lock {tmp_path / output_folder.LOCK_FILE} left by pid 4194305, " \
           "which ended without releasing it" in err
    assert not (tmp_path / output_folder.LOCK_FILE).exists()


def test_the_lock_is_released_after_an_error_and_after_ctrl_c(small_scene_dir, tmp_path,
                                                             capsys, monkeypatch):
    from muscle_mss.app import motion_run

    def fails(*args, **kwargs):
        raise MuscleMSSError("a solve that fails")
    monkeypatch.setattr(motion_run, "solve_time_point", fails)
    assert _run(small_scene_dir, tmp_path) == 2                  # refused inside the lock
    assert "error: a solve that fails" in capsys.readouterr().err
    assert not (tmp_path / output_folder.LOCK_FILE).exists()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(motion_run, "solve_time_point", interrupted)
    assert _run(small_scene_dir, tmp_path) == 130
    assert not (tmp_path / output_folder.LOCK_FILE).exists()
    with output_folder.output_lock(str(tmp_path)) as note:     # free, and nothing left over
        assert note is None


def test_the_batch_is_refused_while_another_run_holds_the_folder(small_scene_dir, tmp_path,
                                                                 capsys):
    from muscle_mss.plugin.batch import main as batch
    with output_folder.output_lock(str(tmp_path)):
        assert batch([str(small_scene_dir), str(tmp_path), "--iterations", "3"]) == 1
    assert f"is in use by another muscle-mss run (pid {os.getpid()}" in capsys.readouterr().err
    assert _files(tmp_path) == set()


def test_the_batch_lists_its_files_and_leaves_no_lock(small_scene, small_scene_dir, tmp_path):
    from muscle_mss.plugin.batch import main as batch
    assert batch([str(small_scene_dir), str(tmp_path), "--iterations", "3"]) == 0
    listed = set(output_folder.listed_files(str(tmp_path)))
    assert _files(tmp_path) - {MANIFEST} <= listed
    count = len(small_scene.motion.times)
    assert len([p for p in listed if p.endswith(".vtm")]) == count * len(run_output.SERIES)
    assert not (tmp_path / output_folder.LOCK_FILE).exists()


def test_a_folder_that_cannot_be_locked_is_refused(tmp_path, monkeypatch):
    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))
    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.raises(MuscleMSSError, match=f"output folder {tmp_path} cannot be locked "
                                             r"\(No locks available\); choose a folder on a "
                                             "local file system"):
        with output_folder.output_lock(str(tmp_path)):
            pass


@pytest.fixture
def demo_unsolved(monkeypatch):
    """``muscle-mss demo`` writes its scene and record, and neither prepares nor solves (nor
    renders the preview: a file stands for it, and ParaView's Python has no pyvista)."""
    from muscle_mss.app import cli, pictures
    monkeypatch.setattr(cli, "prepared_pipeline", lambda *args, **kwargs: (None, 0))
    monkeypatch.setattr(pictures, "scene_preview",
                        lambda scene, path: open(path, "w").write("a preview"))
    monkeypatch.setattr(cli, "run_and_report", lambda *args, **kwargs: [])


def _demo(out, *options):
    return main(["demo", str(out), "--size", "small", "--region", "arm", *options])


def test_demo_replaces_its_own_scene_and_refuses_an_edited_one(tmp_path, capsys,
                                                               demo_unsolved):
    from muscle_mss.app.demo_folder import DEMO_SCENE_RECORD
    scene = tmp_path / "scene"
    assert _demo(tmp_path) == 0
    written = B.folder_digest(scene)
    assert (scene / DEMO_SCENE_RECORD).is_file()
    assert _demo(tmp_path) == 0                            # the demo's own: replaced silently
    assert B.folder_digest(scene) == written and "error" not in capsys.readouterr().err
    with open(scene / "motion.csv", "a") as f:             # the user edits the scene
        f.write("# my motion\n")
    (scene / "notes.txt").write_text("mine")
    edited = B.folder_digest(scene)
    assert _demo(tmp_path) == 2
    assert _error_line(capsys.readouterr().err) == (
        f"error: {scene} holds a scene the demo did not write (motion.csv: changed since the "
        "demo wrote it, and 1 more); the demo would write its scene over it: pass --overwrite "
        "to replace it, or choose another output folder")
    assert B.folder_digest(scene) == edited
    assert _demo(tmp_path, "--overwrite") == 0
    assert "note: writing the demo scene over" in capsys.readouterr().err
    assert (scene / "notes.txt").read_text() == "mine"          # not the demo's: kept
    (scene / "notes.txt").unlink()
    assert B.folder_digest(scene) == written


def test_demo_refuses_a_scene_it_did_not_write(small_scene_dir, tmp_path, capsys,
                                               demo_unsolved):
    """A user's own scene in OUT/scene (no record of the demo's files), and a file there."""
    from muscle_mss.app.demo_folder import DEMO_SCENE_RECORD
    shutil.copytree(small_scene_dir, tmp_path / "scene")
    digest = B.folder_digest(tmp_path)
    assert _demo(tmp_path) == 2
    assert _error_line(capsys.readouterr().err) == (
        f"error: {tmp_path / 'scene'} holds a scene the demo did not write (bones.vtm: "
        f"not written by the demo (no record {DEMO_SCENE_RECORD} of the demo's files), and "
        f"{len(_files(tmp_path)) - 1} more); the demo would write its scene over it: pass "
        "--overwrite to replace it, or choose another output folder")
    assert B.folder_digest(tmp_path) == digest
    assert _files(tmp_path) == {f"scene/{name}" for name in _files(small_scene_dir)}
    other = tmp_path / "other"
    other.mkdir()
    (other / "scene").write_text("mine")
    assert _demo(other, "--overwrite") == 2
    assert _error_line(capsys.readouterr().err) == (
        f"error: {other / 'scene'} is a file, where the demo writes its scene folder; move it "
        "away or choose another output folder")
    assert (other / "scene").read_text() == "mine" and _files(other) == {"scene"}
