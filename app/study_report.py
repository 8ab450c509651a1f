"""Write a :class:`~muscle_mss.app.study.Study` as ``OUT/report.html`` with its figures as
PNG and every figure's numbers as CSV beside it (:data:`STUDY_FILES`), plus the motion's
``summary.csv``. The report embeds its figures, so that it opens from disk on its own (no
network, no other file needed)."""
from __future__ import annotations

import base64
import html
import os

import numpy as np

from muscle_mss.filters import array_names as A
from . import output_folder as folder
from .pictures import MUSCLE_COLOURS
from .reference_lengths import length_change_pct
from .run_output import SUMMARY_COLUMNS, SUMMARY_FILE, write_csv
from .study import (ACCEPTED_VOLUME_ERROR_PCT, BEND_LIMIT, LAYOUT_QUASI_STATIC_CAP,
                    PAPER_VOLUME_ERROR_PCT, PHASES, SLOPE_WINDOW, Study,
                    follow_slope)

REPORT_FILE = "report.html"
DISPLACEMENT = "layouts_displacement"
SLOPES = "layouts_slope"
LAYOUT_TABLE = "layouts.csv"
DISTANCES = "layout_distances.csv"
FIBRE_LENGTH = "fibre_length"
TORTUOSITY = "tortuosity"
VOLUME = "volume"
TIME_SPLIT = "time_split.csv"
FIGURES = (DISPLACEMENT, SLOPES, FIBRE_LENGTH, TORTUOSITY, VOLUME)
STUDY_FILES = (REPORT_FILE, *(f"{name}.png" for name in FIGURES),
               *(f"{name}.csv" for name in (DISPLACEMENT, SLOPES, FIBRE_LENGTH, VOLUME)),
               LAYOUT_TABLE, DISTANCES, TIME_SPLIT, SUMMARY_FILE)
"""Everything a study writes in its output folder."""
REFERENCE_LABEL = "OpenSim muscle-tendon length (from the first time)"
"""The legend entry of a muscle's length in the scene's OpenSim model, as its change from the
first time point (``reference_lengths.csv``)."""
PHASE_LABELS = {"mss": "MSS", "muscle_cd": "muscle CD", "bone_cd": "bone CD",
                "projection": "final collision passes"}


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot
    return pyplot


def _colour(m: int) -> str:
    return MUSCLE_COLOURS[m % len(MUSCLE_COLOURS)]


def _label(name: str) -> str:
    return name.replace("_", " ")


def _save(figure, out, name, legend_axes=None) -> str:
    """Save ``figure`` as ``out/name.png``; ``legend_axes``: whose lines a legend right of
    the whole figure names (small multiples)."""
    if legend_axes is None:
        figure.tight_layout()
    else:
        handles, labels = legend_axes.get_legend_handles_labels()
        figure.legend(handles, labels, fontsize=8, loc="upper right")
        figure.tight_layout(rect=(0.0, 0.0, 0.84, 1.0))
    path = os.path.join(out, f"{name}.png")
    figure.savefig(path)
    _pyplot().close(figure)
    return path


def _grid(count: int):
    columns = int(np.ceil(np.sqrt(count)))
    return int(np.ceil(count / columns)), columns


def displacement_figure(study: Study, out: str) -> str:
    """Fig. 5 per layout: mean displacement per iteration per muscle, log scale."""
    pyplot = _pyplot()
    rows, columns = _grid(len(study.layouts))
    figure, axes = pyplot.subplots(rows, columns, figsize=(6 * columns + 2.4, 4.2 * rows),
                                   dpi=110, sharey=True, squeeze=False)
    for ax, layout in zip(axes.ravel(), study.layouts):
        k = len(layout.displacement)
        for m, name in enumerate(study.motion.muscles):
            ax.plot(np.arange(1, k + 1), np.maximum(layout.displacement[:, m], 1e-12),
                    color=_colour(m), lw=1.0, label=_label(name))
        ax.axvspan(SLOPE_WINDOW[0] * k, SLOPE_WINDOW[1] * k, color="0.9", zorder=0)
        ax.set_yscale("log")
        ax.set_title(f"{layout.layout}: paper relaxation at t = {study.time:.3f} s")
        ax.set_xlabel("iteration")
        ax.set_ylabel("mean displacement per iteration (mm)")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.ravel()[len(study.layouts):]:
        ax.axis("off")
    return _save(figure, out, DISPLACEMENT, axes.ravel()[0])


def slope_figure(study: Study, out: str) -> str:
    """Fig. 6: the later phase's slope per layout, one bar per muscle."""
    pyplot = _pyplot()
    names = study.motion.muscles
    figure, ax = pyplot.subplots(figsize=(11.5, 4.8), dpi=110)
    width = 0.8 / max(len(names), 1)
    for m, name in enumerate(names):
        ax.bar(np.arange(len(study.layouts)) + (m - (len(names) - 1) / 2) * width,
               [layout.slopes[m] for layout in study.layouts], width, color=_colour(m),
               label=_label(name))
    ax.set_xticks(np.arange(len(study.layouts)), [x.layout for x in study.layouts])
    ax.set_ylabel("slope of log10(mean displacement, mm) per iteration")
    ax.set_title(f"later phase (iterations {_window_text(study)}): steeper is faster")
    ax.axhline(0.0, color="black", lw=0.8)
    ax.grid(True, axis="y", alpha=0.3)
    _legend_beside(ax)
    return _save(figure, out, SLOPES)


def _legend_beside(ax) -> None:
    """The legend right of the axes, where it hides no line or bar."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


def _window_text(study: Study) -> str:
    k = len(study.layouts[0].displacement) if study.layouts else 0
    return f"{int(SLOPE_WINDOW[0] * k) + 1}-{int(SLOPE_WINDOW[1] * k)}"


def fibre_length_figure(study: Study, out: str) -> str:
    """Per muscle: fibre strain (mean, band least..largest) and the path's strain over time;
    where the scene has an OpenSim model's length of the muscle (``reference_lengths.csv``),
    its change from the first time point too."""
    pyplot = _pyplot()
    series = study.motion
    reference = study.reference_lengths or {}
    # the figure's legend names the lines of the first panel that has them all
    legend_from = next((m for m, name in enumerate(series.muscles) if name in reference), 0)
    rows, columns = _grid(len(series.muscles))
    figure, axes = pyplot.subplots(rows, columns, figsize=(3.6 * columns + 2.0, 2.8 * rows),
                                   dpi=110, squeeze=False)
    for m, (ax, name) in enumerate(zip(axes.ravel(), series.muscles)):
        strain = 100.0 * series.fibre_strain[:, m]
        ax.fill_between(series.times, strain[:, 1], strain[:, 2], color=_colour(m), alpha=0.25,
                        label="fibres, least-largest")
        ax.plot(series.times, strain[:, 0], color=_colour(m), lw=1.6, label="fibres, mean")
        ax.plot(series.times, 100.0 * series.path_strain[:, m], color="black", lw=1.0, ls="--",
                label="origin-insertion path")
        if name in reference:
            times, lengths = reference[name]
            ax.plot(times, length_change_pct(lengths), color="0.45", lw=1.2, ls=":",
                    label=REFERENCE_LABEL)
        ax.set_title(_label(name), fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("length change from rest (%)")
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[len(series.muscles):]:
        ax.axis("off")
    return _save(figure, out, FIBRE_LENGTH, axes.ravel()[legend_from])


def _lines_over_time(study: Study, out: str, name: str, values, ylabel: str, title: str,
                     limits) -> str:
    pyplot = _pyplot()
    series = study.motion
    figure, ax = pyplot.subplots(figsize=(11.5, 5), dpi=110)
    for m, muscle in enumerate(series.muscles):
        ax.plot(series.times, values[:, m], color=_colour(m), lw=1.3, label=_label(muscle))
    for value, text, style in limits:
        ax.axhline(value, color="black", lw=1.0, ls=style, label=text)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    _legend_beside(ax)
    return _save(figure, out, name)


def tortuosity_figure(study: Study, out: str) -> str:
    return _lines_over_time(
        study, out, TORTUOSITY, study.motion.bend,
        "largest fibre bend (arc / chord over that at rest)",
        "buckling: the fibre of each muscle most bent beyond its rest shape",
        [(BEND_LIMIT, f"buckled above {BEND_LIMIT:g}", "--")])


def volume_figure(study: Study, out: str) -> str:
    return _lines_over_time(
        study, out, VOLUME, study.motion.volume_error, "volume error (%)",
        "volume change of each muscle's surface from rest",
        [(PAPER_VOLUME_ERROR_PCT, f"paper's mean {PAPER_VOLUME_ERROR_PCT:g} %", ":"),
         (ACCEPTED_VOLUME_ERROR_PCT, f"paper's accepted {ACCEPTED_VOLUME_ERROR_PCT:g} %", "--")])


def layout_rows(study: Study) -> list:
    """layouts.csv's rows (header first)."""
    rows = [("layout", "springs_per_particle", "memory_mb", "time_step_s", "paper_seconds",
             "paper_iterations_to_threshold", "median_slope", "quasi_static_iterations",
             "quasi_static_seconds", "quasi_static_converged", "mean_volume_error_pct",
             "max_volume_error_pct")]
    for x in study.layouts:
        iterations, seconds, converged = x.quasi_static
        rows.append((x.layout, x.springs_per_particle, x.memory_mb, x.time_step,
                     x.paper_seconds,
                     x.to_threshold, float(np.nanmedian(x.slopes)), iterations, seconds,
                     int(converged), float(x.volume_error.mean()), float(x.volume_error.max())))
    return rows


def distance_rows(study: Study) -> list:
    """layout_distances.csv's rows (header first): every pair's particle distances, mm."""
    rows = [("layout_a", "layout_b", "mean_mm", "max_mm")]
    for i, a in enumerate(study.layouts):
        for b in study.layouts[i + 1:]:
            d = np.linalg.norm(a.positions - b.positions, axis=1)
            rows.append((a.layout, b.layout, float(d.mean()), float(d.max())))
    return rows


def time_split_rows(study: Study) -> list:
    """time_split.csv's rows (header first): seconds per part over the motion and per time
    point, and its share."""
    totals = study.motion.phases.sum(axis=0)
    whole = max(float(totals.sum()), 1e-300)
    rows = [("part", "seconds", "seconds_per_time_point", "share_pct")]
    for p, total in zip(PHASES, totals):
        rows.append((PHASE_LABELS[p], float(total), float(total) / len(study.motion.times),
                     100.0 * float(total) / whole))
    return rows


def write_tables(study: Study, out: str) -> None:
    """Every CSV of the study (:data:`STUDY_FILES`)."""
    series = study.motion
    muscles = series.muscles
    header = ["layout", A.ITERATION, *muscles]
    write_csv(os.path.join(out, f"{DISPLACEMENT}.csv"), header, (
        (x.layout, k + 1, *x.displacement[k]) for x in study.layouts
        for k in range(len(x.displacement))))
    write_csv(os.path.join(out, f"{SLOPES}.csv"), ("layout", A.MUSCLE, "slope"), (
        (x.layout, m, float(s)) for x in study.layouts for m, s in zip(muscles, x.slopes)))
    for name, rows in ((LAYOUT_TABLE, layout_rows(study)), (DISTANCES, distance_rows(study)),
                       (TIME_SPLIT, time_split_rows(study))):
        write_csv(os.path.join(out, name), rows[0], rows[1:])
    cells = [(t, k, m) for t in range(len(series.times)) for k, m in enumerate(muscles)]
    write_csv(os.path.join(out, f"{FIBRE_LENGTH}.csv"), (
        A.TIME, A.MUSCLE, A.MEAN_FIBRE_STRAIN, "min_fibre_strain", A.MAX_FIBRE_STRAIN,
        "path_length_mm", "path_strain", A.MAX_ARC_CHORD, "rest_max_arc_chord",
        A.MAX_FIBRE_BEND, "buckled_fibres"), (
        (series.times[t], m, *series.fibre_strain[t, k], series.path_length[t, k],
         series.path_strain[t, k], series.arc_chord[t, k], series.rest_arc_chord[k],
         series.bend[t, k], int(series.buckled[t, k]))
        for t, k, m in cells))
    write_csv(os.path.join(out, f"{VOLUME}.csv"), (A.TIME, A.MUSCLE, A.VOLUME_ERROR_PCT), (
        (series.times[t], m, series.volume_error[t, k]) for t, k, m in cells))
    write_csv(os.path.join(out, SUMMARY_FILE), SUMMARY_COLUMNS,
              ([r[c] for c in SUMMARY_COLUMNS] for r in series.rows))


def _image(out: str, name: str, alt: str, numbers: str | None = None) -> str:
    """The figure ``name``.png embedded, captioned ``alt`` and the CSV with its numbers
    (``numbers``, default ``name``)."""
    with open(os.path.join(out, f"{name}.png"), "rb") as f:
        data = base64.b64encode(f.read()).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f'<figcaption>{html.escape(alt)} ({name}.png; numbers in {numbers or name}.csv)'
            "</figcaption></figure>")


def _cell(value) -> str:
    if isinstance(value, (float, np.floating)):
        return "–" if not np.isfinite(value) else f"{value:.4g}"
    return html.escape(str(value))


def _slope(value: float) -> str:
    return "–" if not np.isfinite(value) else f"{value:.2f}"


def _table(rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>"
                   for row in rows[1:])
    return f"<table><tr>{head}</tr>{body}</table>"


def muscle_rows(study: Study) -> list:
    """The report's per-muscle table over the motion (header first)."""
    series = study.motion
    rows = [("muscle", "fibre strain % (mean: least / largest over time)",
             "path change % (least / largest)",
             "fibres follow the path (slope; the rest shape stretched, volume kept)",
             "largest arc/chord (at rest), largest bend (arc/chord over its rest value)",
             f"time points with a fibre bent above {BEND_LIMIT:g}",
             "volume error % (mean / max)")]
    for k, name in enumerate(series.muscles):
        mean = 100.0 * series.fibre_strain[:, k, 0]
        path = 100.0 * series.path_strain[:, k]
        own = [r for r in series.rows if r[A.MUSCLE] == name]
        rows.append((name, f"{mean.min():.1f} / {mean.max():.1f}",
                     f"{path.min():.1f} / {path.max():.1f}",
                     f"{_slope(follow_slope(own))} "
                     f"({_slope(follow_slope(own, A.MEAN_KEPT_SHAPE_STRAIN))})",
                     f"{series.arc_chord[:, k].max():.2f} ({series.rest_arc_chord[k]:.2f}), "
                     f"{series.bend[:, k].max():.2f}",
                     int(np.count_nonzero(series.buckled[:, k])),
                     f"{series.volume_error[:, k].mean():.2f} / "
                     f"{series.volume_error[:, k].max():.2f}"))
    return rows


def buckling_text(study: Study) -> str:
    """Which muscles buckle where: a sentence per muscle with fibres above the limit."""
    series = study.motion
    lines = []
    for k, name in enumerate(series.muscles):
        at = np.flatnonzero(series.buckled[:, k])
        if len(at):
            worst = int(np.argmax(series.bend[:, k]))
            lines.append(f"<li><b>{html.escape(_label(name))}</b>: {len(at)} of "
                         f"{len(series.times)} time points (t = "
                         f"{', '.join(f'{series.times[t]:g}' for t in at[:8])}"
                         f"{' …' if len(at) > 8 else ''} s), at most "
                         f"{int(series.buckled[:, k].max())} fibres; bend up to "
                         f"{series.bend[worst, k]:.2f} at t = {series.times[worst]:g} s "
                         f"(arc/chord {series.arc_chord[worst, k]:.2f}, "
                         f"{series.rest_arc_chord[k]:.2f} at rest)</li>")
    if not lines:
        return (f"<p>No fibre of any muscle bends beyond {BEND_LIMIT:g} times its arc/chord "
                "at rest at any time point: no buckling.</p>")
    return ("<p>Buckled (a fibre whose arc/chord is more than "
            f"{BEND_LIMIT:g} times its own at rest):</p><ul>") + \
        "".join(lines) + "</ul>"


STYLE = ("body{font-family:sans-serif;max-width:1250px;margin:2em auto;color:#222}"
         "table{border-collapse:collapse;margin:1em 0;font-size:90%}"
         "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
         "th{background:#eee}td:first-child{text-align:left}img{max-width:100%}"
         "figcaption{font-size:85%;color:#555}")


def pose_text(study: Study) -> str:
    """Which pose the layouts solve, as the report says it: the most flexed (the bones rotated
    farthest from rest), or the time point nearest the ``--time`` asked, beside the most
    flexed when that is another."""
    at = f"time point {study.index} (t = {study.time:g} s)"
    flexed = ", where the bones are rotated farthest from rest"
    if study.asked_time is None:
        return at + flexed
    asked = f"{at}, the nearest to the t = {study.asked_time:g} s asked with --time"
    if study.flexed_index is None or study.flexed_index == study.index:
        return asked + flexed
    return (f"{asked} (the most flexed pose, where the bones are rotated farthest from rest, is "
            f"t = {study.motion.times[study.flexed_index]:g} s)")


def report_html(study: Study, out: str) -> str:
    """The report's text: every section with its embedded figures and tables."""
    series = study.motion
    volume = series.volume_error
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>muscle-mss study</title>"
        f"<style>{STYLE}</style></head><body>",
        f"<h1>muscle-mss study of {html.escape(study.scene)}</h1>",
        f"<p>{len(series.muscles)} muscles, {len(series.times)} time points, "
        f"{study.resolution} particles per fibre. Machine: {html.escape(study.machine)}. "
        f"The study took {study.seconds:.0f} s.</p>",
        "<h2>1. Spring layouts (the paper's Fig. 5 and 6)</h2>",
        f"<p>Each layout solves {pose_text(study)}, "
        "by the paper relaxation (its default iterations, the paper's model: no connective "
        "tissue, no fibre shortening) and by the quasi-static method (the solver's defaults, "
        f"at most {LAYOUT_QUASI_STATIC_CAP} iterations). "
        "Fig. 5: each muscle's mean particle displacement per iteration. Fig. 6: the slope of "
        f"its later phase, a least-squares line through log10(displacement) over iterations "
        f"{_window_text(study)} (shaded in Fig. 5): the more negative, the faster the layout "
        "settles. <i>to threshold</i>: the first iteration at which every muscle moved less "
        "than the DisplacementThreshold (0: not within the iterations). A layout whose "
        "relaxation diverges at the solver's time step runs at half of it (<i>time_step_s</i>; "
        "Delaunay's stiffer springs need 0.025 s).</p>",
        _image(out, DISPLACEMENT, "mean displacement per iteration per muscle and layout"),
        _image(out, SLOPES, "slope of the later phase per layout and muscle"),
        _table(layout_rows(study)),
        "<p>How far the layouts' solved particles (paper relaxation) lie apart, mm:</p>",
        _table(distance_rows(study)),
        "<h2>2. Fibre length over the motion</h2>",
        "<p>Per muscle, its fibres' length change from rest (mean line, band from the least to "
        "the largest fibre) beside the change of its origin-insertion path (the distance "
        "between the centroids of the fibres' end particles on the bones, dashed). Fibres "
        "that follow the joint motion track the dashed line; <i>slope</i> is the fibres' mean "
        "strain regressed on their ends' (1: they follow; near 0: they keep their length, and "
        "a shortening muscle folds); in brackets the slope its rest shape would give, stretched "
        "with its volume kept (curved fibres of a muscle that thickens as it shortens change "
        "less than its ends).</p>",
        _image(out, FIBRE_LENGTH, "fibre length change and path length change per muscle"),
        _table(muscle_rows(study)),
        _image(out, TORTUOSITY, "largest fibre bend (arc/chord over that at rest) per muscle "
               "over time", numbers=FIBRE_LENGTH),
        buckling_text(study),
        "<h2>3. Volume</h2>",
        f"<p>Mean volume error over all muscles and time points {volume.mean():.2f} % "
        f"(the paper's {PAPER_VOLUME_ERROR_PCT:g} %), largest {volume.max():.2f} % "
        f"({'within' if volume.max() <= ACCEPTED_VOLUME_ERROR_PCT else 'above'} the "
        f"{ACCEPTED_VOLUME_ERROR_PCT:g} % the paper accepts).</p>",
        _image(out, VOLUME, "volume error per muscle over time"),
        "<h2>4. Time split (the paper's Table 1)</h2>",
        "<p>The solver's seconds over the motion at the default layout, per part.</p>",
        _table(time_split_rows(study)),
        "<p>Per time point and muscle, every number of the run is in summary.csv.</p>",
        "</body></html>"]
    return "\n".join(parts)


def write_report(study: Study, out: str) -> str:
    """Write the figures, tables and ``report.html`` into ``out`` (held by the caller,
    :func:`~muscle_mss.app.run_output.output_folder`); return the report's path."""
    folder.claim(out, *STUDY_FILES)
    displacement_figure(study, out)
    slope_figure(study, out)
    fibre_length_figure(study, out)
    tortuosity_figure(study, out)
    volume_figure(study, out)
    write_tables(study, out)
    path = os.path.join(out, REPORT_FILE)
    with open(path, "w", encoding="utf-8") as f:
        f.write(report_html(study, out))
    return path
