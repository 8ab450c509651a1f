"""The ``muscle-mss`` command: validate scenes, write the demo scene, run the demo and motions.

``muscle-mss validate SCENE`` checks every rule of DESIGN §4; ``muscle-mss fibres SCENE``
writes its fibres from its muscle surfaces (:mod:`muscle_mss.app.scene_fibres`);
``muscle-mss demo-scene OUT`` writes the deterministic demo thigh scene (``--region arm``: the
elbow) and its ``preview.png``; ``muscle-mss demo [OUT]`` writes the demo scene and runs its
whole motion; ``muscle-mss run SCENE OUT`` does the same for a user's scene (see
:mod:`muscle_mss.app.run_output` for the files written); ``muscle-mss study SCENE OUT`` writes
the paper's experiments and the fibre-length study as ``OUT/report.html``
(:mod:`muscle_mss.app.study`); ``muscle-mss cache info|clear`` shows or empties the frame cache
(:mod:`muscle_mss.filters.frame_cache`), which ``--cache DIR|off`` points elsewhere or turns
off; ``muscle-mss import-opensim MODEL.osim MOTION.mot OUT --muscles DIR`` writes a scene from
an OpenSim model and muscle surface files (:mod:`muscle_mss.app.opensim_import`).
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import time as wallclock

from muscle_mss.core.errors import MuscleMSSError
from muscle_mss.core.motion import farthest_pose_index
from muscle_mss.core.scene import Scene

from muscle_mss.filters.fibre_generator import DEFAULT_FIBRE_COUNT, DEFAULT_SAMPLES
from muscle_mss.filters.fibre_resampler import DEFAULT_PARTICLES_PER_FIBRE
from .demo_folder import (DEMO_REGIONS, DEMO_SIZES, REGION_THIGH, demo_region_motion,
                          write_demo_scene)
from .run_options import (add_cache_option, add_jobs_option, add_run_options, cache_from,
                          jobs_from, settings_from, writing_from)
from .run_report import ProgressBar, summary_table, timings_note


def scene_counts(scene: Scene) -> str:
    """One line with the numbers of muscles, bones, fibres and time points."""
    fibres = sum(fs.count for fs in scene.fibres.values())
    return (f"{len(scene.muscles)} muscles, {len(scene.bones)} bones, {fibres} fibres, "
            f"{len(scene.motion.times)} time points")


def cmd_validate(args) -> int:
    from muscle_mss.filters.scene_io import check_scene
    scene, problems = check_scene(args.scene)
    if problems:
        for p in problems:
            print(f"error: {p}")
        print(f"{args.scene}: {len(problems)} problem{'s' if len(problems) > 1 else ''}")
        return 1
    print(f"ok: {scene_counts(scene)}")
    from muscle_mss.core.validation import placement_warnings
    for warning in direction_warnings(scene) + placement_warnings(scene):
        print(f"warning: {warning}")
    print(attachment_report(scene))
    return 0


def direction_warnings(scene: Scene) -> list:
    """The sentences of the fibres a run would reverse to run from origin to insertion (the
    Fibre Resampler's rule, :mod:`muscle_mss.core.fibre_direction`), one per muscle."""
    from muscle_mss.core.fibre_direction import direction_warning, oriented_fibre_set
    from muscle_mss.core.scene import FIBRES_FILE
    warnings = []
    for name, fibres in scene.fibres.items():
        directions = oriented_fibre_set(fibres, scene.bones)[1]
        warning = direction_warning(f"{FIBRES_FILE} block '{name}'", directions,
                                    fibres.origin_bone, fibres.insertion_bone)
        if warning:
            warnings.append(warning)
    return warnings


def attachment_report(scene: Scene) -> str:
    """One line per muscle: the origin and insertion bones, each marked as given by the scene
    or inferred from the nearest bone surface (with the mean distance of the fibre ends)."""
    from muscle_mss.core.attachments import INSERTION, ORIGIN, scene_attachments

    def describe(a):
        how = "inferred: nearest bone" if a.inferred else "given"
        return f"{a.bone} ({how}, fibre ends {a.mean_distance:.1f} mm from it on average)"

    lines = ["attachments (origin -> insertion):"]
    for muscle, ends in scene_attachments(scene).items():
        lines.append(f"  {muscle}: {describe(ends[ORIGIN])} -> {describe(ends[INSERTION])}")
    return "\n".join(lines)


def cmd_fibres(args) -> int:
    from .scene_fibres import generate_fibres_file
    print(f"generating fibres for {args.scene}:", flush=True)
    generate_fibres_file(args.scene, args.count, args.points, args.overwrite,
                         lambda line: print(line, flush=True))
    return 0


def cmd_demo_scene(args) -> int:
    scene = write_demo_scene(args.out, args.size, args.region)
    print(f"wrote {args.out} ({args.region}, {args.size}): {scene_counts(scene)}; "
          f"picture {os.path.join(args.out, 'preview.png')}")
    return 0


def run_and_report(scene_folder: str, out: str, settings: dict, scene: Scene,
                   writing=None, pipeline=None, start=None, jobs: int = 1) -> list:
    """Run a whole motion with a progress bar; write summary, series index and pictures; print
    the summary table. ``writing``: a :class:`run_output.Writing` (default: every series, the
    default compressor); ``pipeline``: the scene's, its kernels compiled
    (:func:`prepared_pipeline`), else built here; ``start``: when the command started
    (``time.perf_counter``); ``jobs``: worker processes that solve the time points
    (``motion_run.run_motion``). Returns the summary rows."""
    from . import motion_run, run_output
    from .output_folder import claim
    from .pictures import convergence_picture, poses_picture

    writing = writing or run_output.Writing()
    start = wallclock.perf_counter() if start is None else start
    if pipeline is None:
        compile_kernels(settings)
    bar = {}

    def on_step(result, done, total):
        bar.setdefault("bar", ProgressBar(total, "solving"))
        bar["bar"].update(done, f"t={result.time:.3f} s {timings_note(result.timings)}")

    pipeline, rows = motion_run.run_motion(scene_folder, out, settings, on_step=on_step,
                                           series_names=writing.series,
                                           compressor=writing.compressor, pipeline=pipeline,
                                           jobs=jobs)
    cached = pipeline.frames.summary() if pipeline.frames is not None else None
    run_output.write_summary(out, rows)
    run_output.write_index(out, pipeline.times, series_names=writing.series)
    index = farthest_pose_index(scene.motion)
    claim(out, run_output.CONVERGENCE_PICTURE, run_output.POSES_PICTURE)
    convergence_picture(os.path.join(out, run_output.convergence_file(index)),
                        os.path.join(out, run_output.CONVERGENCE_PICTURE),
                        title=f"convergence at t = {pipeline.times[index]:.3f} s")
    solved_file = (os.path.join(out, run_output.series_file(run_output.SURFACES, index))
                   if run_output.SURFACES in writing.series else None)
    poses_picture(pipeline, index, os.path.join(out, run_output.POSES_PICTURE), solved=solved_file)
    print(summary_table(rows))
    if cached:
        print(cached)
    written = [*map(run_output.index_file, writing.series), run_output.SUMMARY_FILE,
               run_output.CONVERGENCE_PICTURE, run_output.POSES_PICTURE]
    print(f"wrote {out}: {', '.join(written)} in {wallclock.perf_counter() - start:.0f} s")
    return rows


def compiling_meanwhile(settings: dict):
    """A context that leaves the kernels a run with the filter ``settings`` needs compiled,
    saying so on stderr: the default settings' in a second process while the body prepares
    the run (``warm_up.compiling_beside``). It gives True while that process compiles."""
    from .warm_up import compiling_beside, scope_for, stderr_notice
    return compiling_beside(stderr_notice, scope_for(settings))


def prepared_pipeline(scene_folder: str, settings: dict, compiling: bool, time=None,
                      cache=None):
    """``(pipeline, index)``: the pipeline of ``scene_folder`` with ``settings`` (and the
    frame cache in the folder ``cache``, None: none) and the index of its time point nearest
    ``time`` (None: the first), which, while the kernels compile (``compiling``, as
    :func:`compiling_meanwhile` says), is prepared up to its solve
    (``motion_run.prepare_time_point``)."""
    from . import motion_run
    pipeline = motion_run.build_pipeline(scene_folder, settings, cache)
    index = 0 if time is None else time_point_index(pipeline.times, time)
    if compiling:
        motion_run.prepare_time_point(pipeline, index)
    return pipeline, index


def compile_kernels(settings: dict | None = None) -> None:
    """Compile the numeric kernels a run with the filter ``settings`` needs (None: every
    kernel) first when this Python has not yet, saying so on stderr."""
    from muscle_mss.core.kernel_cache import EVERY_KERNEL
    from .warm_up import ensure_compiled, scope_for, stderr_notice
    ensure_compiled(stderr_notice, EVERY_KERNEL if settings is None else scope_for(settings))


@contextlib.contextmanager
def held_output_folder(out: str, overwrite: bool, study: bool = False, places=(), scene=None,
                       check=None, resuming: bool = False):
    """:func:`run_output.output_folder` saying what it did: a lock taken over, an earlier run
    replaced; ``study``: for a study's files (:data:`~.study_report.STUDY_FILES`); ``places``:
    what the run places deeper (:func:`run_output.run_places`); ``scene``: the scene folder it
    reads (its files are never removed); ``check``: called with the folder held, before the
    folder's check; ``resuming``: the run in ``out`` is this one's, interrupted, and is run
    again (its files are replaced without a word)."""
    from .run_output import output_folder
    from muscle_mss.filters.scene_io import scene_files
    from .study_report import STUDY_FILES
    names = {"names": STUDY_FILES, "folders": ()} if study else {}
    inputs = scene_files(scene) if scene is not None else ()
    with output_folder(out, overwrite, places=places, inputs=inputs, check=check,
                       **names) as (removed, note):
        if note:
            print(note, file=sys.stderr)
        if removed and not resuming:
            print(f"replacing the previous run in {out} ({len(removed)} files it wrote removed)")
        yield


def cmd_demo(args) -> int:
    from .demo_folder import check_demo_scene, record_demo_scene
    from .run_output import run_places
    from muscle_mss.filters.scene_io import scene_files
    writing, settings, cache = writing_from(args), settings_from(args), cache_from(args)
    jobs = jobs_from(args)
    start = wallclock.perf_counter()
    scene_folder = os.path.join(args.out, "scene")
    places = run_places(range(len(demo_region_motion(args.region).times)), writing.series)
    # the demo's own folder: an earlier demo's run is replaced, its scene only as it wrote it
    with held_output_folder(args.out, overwrite=True, places=places,
                            check=lambda: check_demo_scene(scene_folder, args.overwrite)):
        with compiling_meanwhile(settings) as compiling:
            scene = write_demo_scene(scene_folder, args.size, args.region)
            record_demo_scene(scene_folder, [*scene_files(scene_folder),
                                             os.path.join(scene_folder, "preview.png")])
            print(f"demo scene ({args.region}, {args.size}): {scene_counts(scene)} -> "
                  f"{scene_folder}", flush=True)
            pipeline, _ = prepared_pipeline(scene_folder, settings, compiling, cache=cache)
        run_and_report(scene_folder, args.out, settings, scene, writing, pipeline, start, jobs)
    return 0


def cmd_run(args) -> int:
    from . import run_record
    from .run_output import convergence_file, run_places
    from muscle_mss.filters.scene_io import load_scene
    writing, settings, cache = writing_from(args), settings_from(args), cache_from(args)
    jobs = jobs_from(args, one_time_point=args.time is not None)
    scene = load_scene(args.scene)
    print(f"{args.scene}: {scene_counts(scene)}")
    times = list(scene.motion.times)
    indices = (range(len(times)) if args.time is None
               else [time_point_index(times, args.time)])
    record = run_record.run_record(args.scene, settings, writing, args.time)
    earlier = None if args.overwrite else run_record.read_record(args.out)
    if earlier is not None:
        differs = run_record.differences(earlier, record)
        if differs:
            raise MuscleMSSError(
                f"output folder {args.out} holds a run with other inputs or options: "
                f"{'; '.join(differs)}; pass --overwrite to replace it, or give the same "
                "options to resume or complete it")
        if run_record.is_complete(args.out, earlier):
            print(f"{args.out}: complete already (the same scene, options and numerics); "
                  "nothing to solve (--overwrite runs it again)")
            return 0
        written = sum(os.path.isfile(os.path.join(args.out, convergence_file(i)))
                      for i in indices)
        print(f"resuming the run in {args.out} (the same scene and options): {written} of "
              f"{len(indices)} time points were written before it stopped; "
              + ("the frame cache gives back those it solved" if cache else
                 "with --cache off they are solved again"))

    def unchanged():
        if earlier is not None and run_record.read_record(args.out) != earlier:
            raise MuscleMSSError(f"output folder {args.out}: another run changed it meanwhile; "
                                 "run again")

    with held_output_folder(args.out, args.overwrite or earlier is not None,
                            places=run_places(indices, writing.series), scene=args.scene,
                            check=unchanged, resuming=earlier is not None):
        run_record.write_record(args.out, record)
        if args.time is None:
            start = wallclock.perf_counter()
            with compiling_meanwhile(settings) as compiling:
                pipeline, _ = prepared_pipeline(args.scene, settings, compiling, cache=cache)
            run_and_report(args.scene, args.out, settings, scene, writing, pipeline, start,
                           jobs)
        else:
            pipeline = run_time_point(args, settings, writing, cache)
        frames = pipeline.frames
        run_record.write_record(args.out, {
            **record, "finished": True,
            "frames": None if frames is None else {"loaded": frames.loaded,
                                                   "solved": frames.solved}})
    return 0


def run_time_point(args, settings, writing, cache=None):
    """``muscle-mss run --time T``: solve and write the time point nearest T; the
    pipeline."""
    from . import motion_run, run_output
    with compiling_meanwhile(settings) as compiling:
        pipeline, index = prepared_pipeline(args.scene, settings, compiling, args.time, cache)
    result = motion_run.solve_time_point(pipeline, index)
    run_output.write_time_point(result, args.out, writing.series, writing.compressor)
    run_output.write_summary(args.out, result.rows)
    run_output.write_index(args.out, [result.time], [result.index], writing.series)
    print(summary_table(result.rows))
    if pipeline.frames is not None:
        print(pipeline.frames.summary())
    return pipeline


def cmd_study(args) -> int:
    """``muscle-mss study``: the paper's experiments and the fibre-length study on a scene."""
    from muscle_mss.filters.scene_io import load_scene
    scene = load_scene(args.scene)
    print(f"{args.scene}: {scene_counts(scene)}")
    compile_kernels()
    with held_output_folder(args.out, args.overwrite, study=True, scene=args.scene):
        path = study_into(args.scene, args.out, args.resolution, args.time, cache_from(args),
                          jobs_from(args))
    print(f"wrote {path} (figures as PNG, their numbers as CSV beside it)")
    return 0


def study_into(scene_folder: str, out: str, resolution=None, time=None, cache=None,
               jobs: int = 1) -> str:
    """Run :func:`~muscle_mss.app.study.run_study` with a progress bar and write its
    report into ``out`` (held by the caller); the report's path. ``cache``: the frame cache's
    folder (None: every frame solved); ``jobs``: worker processes that solve the motion's
    time points."""
    from muscle_mss.filters.scene_io import load_scene
    from .study import run_study
    from .study_report import write_report
    motion = load_scene(scene_folder).motion
    index = (farthest_pose_index(motion) if time is None
             else time_point_index(list(motion.times), time))
    bars = {}

    def progress(label, done, total):
        bars.setdefault(label, ProgressBar(total, label)).update(done)

    study = run_study(scene_folder, resolution or DEFAULT_PARTICLES_PER_FIBRE, index, progress,
                      asked_time=time, cache=cache, jobs=jobs)
    return write_report(study, out)


def cmd_cache(args) -> int:
    """``muscle-mss cache info|clear``: the frame cache's folder, entries, size and bound, or
    remove its entries."""
    from muscle_mss.filters.frame_cache import FrameStore, chosen_folder
    folder = chosen_folder(args.cache)
    if folder is None:
        print("frame cache: off (--cache off or $MUSCLE_MSS_FRAME_CACHE=off)")
        return 0
    cache = FrameStore(folder)
    if args.action == "clear":
        count, size = cache.clear()
        print(f"frame cache {folder}: removed {count} entries ({size / 2 ** 20:.1f} MiB)")
        return 0
    info = cache.info()
    print(f"frame cache {folder}: {info['entries']} entries, {info['bytes'] / 2 ** 20:.1f} MiB "
          f"of at most {info['bound'] / 2 ** 30:g} GiB (least recently used out)")
    return 0


def cmd_import_opensim(args) -> int:
    """``muscle-mss import-opensim``: a scene folder from an OpenSim model, its motion and a
    folder of muscle surface files (:mod:`muscle_mss.app.opensim_import`)."""
    from .opensim_import import import_opensim
    import_opensim(args.model, args.motion, args.out, args.muscles, args.overwrite,
                   args.muscle_units, log_level="error")
    return 0


def time_point_index(times, time: float) -> int:
    """Index of the time point nearest ``time`` (s); a time that is not finite or lies outside
    the motion is refused (ParaView's time slider clamps it with a warning instead)."""
    if not math.isfinite(time):
        raise MuscleMSSError(f"--time {time}: not a finite number; give a time in seconds")
    first, last = times[0], times[-1]
    if not first <= time <= last:
        raise MuscleMSSError(f"--time {time:g} is outside the motion's time range "
                             f"[{first:g}, {last:g}] s; give a time inside it")
    return min(range(len(times)), key=lambda i: abs(times[i] - time))


def _add_region_option(p):
    p.add_argument("--region", choices=DEMO_REGIONS, default=REGION_THIGH,
                   help="thigh: pelvis, femur, tibia, 13 muscles, a walking cycle (default); "
                        "arm: scapula, humerus, ulna, radius, the 7 elbow muscles, elbow flexion "
                        "10 -> 130 -> 10 degrees")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="muscle-mss",
        description="Muscle deformation during motion: mass-spring fibres, sphere collisions "
                    "and mean value coordinates (Janák & Kohout 2014).")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("validate", help="check a scene folder against every rule of the format")
    p.add_argument("scene", help="scene folder (muscles.vtm, fibres.vtm, bones.vtm, motion.csv)")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("fibres", help="write a scene's fibres.vtm from its muscle surfaces and "
                                      "bones (the Fibre Generator)")
    p.add_argument("scene", help="scene folder (muscles.vtm, bones.vtm, optional "
                                 "attachments.csv)")
    p.add_argument("--count", type=int, default=DEFAULT_FIBRE_COUNT,
                   help="fibres per muscle, on the most nearly square grid (default "
                        f"{DEFAULT_FIBRE_COUNT}: 8 x 8)")
    p.add_argument("--points", type=int, default=DEFAULT_SAMPLES,
                   help=f"points per fibre polyline (default {DEFAULT_SAMPLES})")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing fibres.vtm (refused without it)")
    p.set_defaults(func=cmd_fibres)

    p = sub.add_parser("demo-scene", help="write a demo scene (thigh or arm) and preview.png")
    p.add_argument("out", help="folder to write")
    p.add_argument("--size", choices=DEMO_SIZES, default=DEMO_SIZES[0],
                   help="full: 64 fibres per muscle (thigh 13 muscles, arm 7); small: a quick "
                        "variant for tests")
    _add_region_option(p)
    p.set_defaults(func=cmd_demo_scene)

    p = sub.add_parser("demo", help="write the demo scene and run its whole walk")
    p.add_argument("out", nargs="?", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--size", choices=DEMO_SIZES, default=DEMO_SIZES[0])
    _add_region_option(p)
    p.add_argument("--overwrite", action="store_true",
                   help="write the demo scene over an OUT/scene the demo did not write (one you "
                        "edited; refused without it). An earlier demo's run and scene are "
                        "replaced without it")
    add_run_options(p)
    add_jobs_option(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("run", help="run a scene's motion (or one time point) and write results")
    p.add_argument("scene", help="scene folder")
    p.add_argument("out", help="output folder")
    p.add_argument("--time", type=float, help="only the time point nearest this time (s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier run in OUT (refused without it; "
                        "the same run again resumes or completes it)")
    add_run_options(p)
    add_jobs_option(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("study", help="the paper's experiments (spring layouts, volume, time "
                                     "split) and the fibre-length study: OUT/report.html")
    p.add_argument("scene", help="scene folder")
    p.add_argument("out", help="output folder")
    p.add_argument("--time", type=float,
                   help="the layouts' pose: the time point nearest this time (s; default the "
                        "most flexed, where the bones are rotated farthest from rest)")
    p.add_argument("--resolution", type=int, help="particles per fibre N (default "
                                                       f"{DEFAULT_PARTICLES_PER_FIBRE})")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier study in OUT (refused without it)")
    add_cache_option(p)
    add_jobs_option(p)
    p.set_defaults(func=cmd_study)

    p = sub.add_parser("import-opensim", help="a scene from an OpenSim model (bones from its "
                                              "meshes, motion.csv from a .mot) and muscle files")
    p.add_argument("model", help="the OpenSim model (.osim)")
    p.add_argument("motion", help="its motion (.mot or .sto, e.g. inverse kinematics)")
    p.add_argument("out", help="scene folder to write")
    p.add_argument("--muscles", metavar="DIR",
                   help="a folder of one surface file per muscle (STL, OBJ, PLY, VTK, VTP; "
                        "name = file name without suffix) in the model's ground frame at its "
                        "default pose: cleaned and written to muscles.vtm")
    p.add_argument("--muscle-units", choices=("m", "mm", "auto"), default="auto",
                   help="units of the muscle files (default auto: metres when a file's "
                        "bounding box is under 5 units on every side, else mm)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files an earlier import wrote in OUT (refused without it)")
    p.set_defaults(func=cmd_import_opensim)

    p = sub.add_parser("cache", help="the frame cache: where it is, its entries and size "
                                     "(info), or remove its entries (clear)")
    p.add_argument("action", choices=("info", "clear"))
    add_cache_option(p)
    p.set_defaults(func=cmd_cache)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except MuscleMSSError as err:
        label = getattr(err, "filter_label", None)
        print(f"error: {label + ': ' if label else ''}{err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        from muscle_mss.filters.base import interrupted_message
        print(f"\n{interrupted_message(err, f'muscle-mss {args.command}')}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
