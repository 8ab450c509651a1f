"""What a run prints: its progress bar, the table of each muscle over the whole motion and the
note of one time point's seconds by part."""
from __future__ import annotations

import math
import sys
import time as wallclock

from muscle_mss.core.cage_drift import CAGE_DRIFT_LIMIT
from muscle_mss.filters import array_names as A


class ProgressBar:
    """A one-line text progress bar on stderr: done/total, time point, seconds per step."""

    def __init__(self, total: int, label: str, stream=sys.stderr, width: int = 30):
        self.total, self.label, self.stream, self.width = total, label, stream, width
        self.start = wallclock.perf_counter()

    def update(self, done: int, note: str = "") -> None:
        filled = int(self.width * done / max(self.total, 1))
        rate = (wallclock.perf_counter() - self.start) / max(done, 1)
        self.stream.write(f"\r{self.label} [{'#' * filled}{'.' * (self.width - filled)}] "
                          f"{done}/{self.total} {note} {rate:.2f} s/step")
        if done >= self.total:
            self.stream.write("\n")
        self.stream.flush()


def summary_table(rows) -> str:
    """Per muscle over the whole motion: mean and max volume error, max fibre strain, how its fibres
    follow its end-to-end length (:func:`~.study.follow_slope`) and how its rest shape stretched
    with its volume kept would (``kept``), their largest arc / chord (above 1 a fibre bends or
    folds) and bend (that over its rest value: above 1 a fibre bends more than at rest), max
    sphere overlap, the deepest surface vertex newly in a bone (outside it at rest) as written
    (after the MVC Surface Deformer's push out), the deepest inside another muscle, and the
    deepest newly in a bone before the push, the largest drift of a surface vertex off its cage
    (mm), the largest share of the connective tissue in the muscle's load (%), mean iterations
    and seconds per time point; then the mean over muscles, and a line for each muscle with
    vertices that left their cage (:mod:`muscle_mss.core.cage_drift`)."""
    from .study import follow_slope
    by_muscle = {}
    for r in rows:
        by_muscle.setdefault(r[A.MUSCLE], []).append(r)
    header = (f"{'muscle':28s} {'vol err % mean':>14s} {'max':>7s} {'max strain':>10s} "
              f"{'follows':>7s} {'kept':>5s} {'arc/chord':>9s} {'bend':>5s} {'overlap mm':>10s} "
              f"{'new in bone mm':>14s} {'in muscle mm':>12s} "
              f"{'pushed mm':>10s} {'drift mm':>8s} "
              f"{'tissue %':>8s} {'iters':>6s} {'s/time':>7s}")
    lines = [header, "-" * len(header)]
    means = []
    for name, rs in by_muscle.items():
        err = [float(r[A.VOLUME_ERROR_PCT]) for r in rs]
        means.append(sum(err) / len(err))
        lines.append(f"{name:28s} {means[-1]:14.2f} {max(err):7.2f} "
                     f"{max(float(r[A.MAX_FIBRE_STRAIN]) for r in rs):10.3f} "
                     f"{_or_dash(follow_slope(rs), 7, 2)} "
                     f"{_or_dash(follow_slope(rs, A.MEAN_KEPT_SHAPE_STRAIN), 5, 2)} "
                     f"{_deepest(rs, A.MAX_ARC_CHORD, 9, 2)} "
                     f"{_deepest(rs, A.MAX_FIBRE_BEND, 5, 2)} "
                     f"{max(float(r[A.SPHERE_OVERLAP_MM]) for r in rs):10.3f} "
                     f"{_deepest(rs, A.NEW_IN_BONE_DEPTH_AFTER_MM, 14)} "
                     f"{_deepest(rs, A.IN_OTHER_MUSCLE_DEPTH_MM, 12)} "
                     f"{_deepest(rs, A.NEW_IN_BONE_DEPTH_MM)} "
                     f"{_deepest(rs, A.CAGE_DRIFT_MM, 8, 2)} "
                     f"{max(float(r[A.TISSUE_SHARE_PCT]) for r in rs):8.1f} "
                     f"{sum(int(r[A.ITERATIONS]) for r in rs) / len(rs):6.0f} "
                     f"{sum(float(r[A.SECONDS]) for r in rs) / len(rs):7.2f}")
    lines.append("-" * len(header))
    lines.append(f"{'mean over muscles':28s} {sum(means) / max(len(means), 1):14.2f}")
    for name, rs in by_muscle.items():
        left = [r for r in rs if float(r[A.CAGE_DRIFT_VERTICES] or 0) > 0]
        if left:
            worst = max(left, key=lambda r: float(r[A.CAGE_DRIFT_MM]))
            lines.append(
                f"warning: {name}: surface vertices left their cage by more than "
                f"{CAGE_DRIFT_LIMIT:g} mm at {len(left)} of {len(rs)} time points (at worst "
                f"{int(worst[A.CAGE_DRIFT_VERTICES])} vertices, up to "
                f"{float(worst[A.CAGE_DRIFT_MM]):.1f} mm, at t = {float(worst[A.TIME]):g} s; "
                "point data cage_drift): the surface there does not follow the particles (a "
                "surface much finer than its cage: raise ParticlesPerFibre)")
    return "\n".join(lines)


def _or_dash(value: float, width: int, digits: int) -> str:
    return f"{value:{width}.{digits}f}" if math.isfinite(value) else f"{'-':>{width}s}"


def _deepest(rows, column, width=10, digits=3) -> str:
    """The largest value of a column as text ``width`` wide, "-" when no row has one (no bones
    connected)."""
    values = [float(r[column]) for r in rows if r.get(column, "") != ""]
    return _or_dash(max(values) if values else math.nan, width, digits)


def timings_note(timings: dict) -> str:
    """``solve 1.20 + surface 0.10 + write 0.05 s``: one time point's seconds by part (those of
    :attr:`motion_run.TimePointResult.timings` that were measured)."""
    parts = [f"{name} {timings[name]:.2f}" for name in ("solve", "surface", "write")
             if name in timings]
    return f"({' + '.join(parts)} s)" if parts else ""
