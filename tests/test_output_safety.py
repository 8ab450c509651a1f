"""What a run may do to its output folder (issue 30): it lists every file it writes in the
folder's manifest, ``--overwrite`` removes only the files a previous run's manifest lists (never
a user's file or folder, a link or a path outside the folder), and a run holds a lock on the
folder so that a second run into it is refused."""
import csv
import errno
import fcntl
import os

import pytest

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.filters import output_folder, run_output
from muscle_mss.filters.cli import main

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


def test_a_file_the_run_would_write_over_deep_in_series_is_kept(small_scene_dir, tmp_path,
                                                               capsys):
    (tmp_path / "series").mkdir()
    (tmp_path / "series" / "surfaces_0010.vtm").write_text("mine")
    assert _run(small_scene_dir, tmp_path, "--overwrite") == 2
    assert f"cannot write {tmp_path / 'series' / 'surfaces_0010.vtm'}: something muscle-mss " \
           "did not write is there" in capsys.readouterr().err
    assert (tmp_path / "series" / "surfaces_0010.vtm").read_text() == "mine"


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
    from muscle_mss.filters import motion_run
    assert _run(small_scene_dir, tmp_path, time="7") == 2        # refused inside the lock
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
