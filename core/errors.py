"""The project's one error type (DESIGN §8).

Every check of user input raises :class:`MuscleMSSError` with a sentence that names what is
wrong and where (file, block, row, fibre) and the rule it breaks, so that a user can act on it.
"""
from __future__ import annotations

import os

import numpy as np


class MuscleMSSError(ValueError):
    """Bad input or an impossible request, described for the user.

    The message names the file / block / row and the broken rule, e.g.
    ``"fibres.vtm block 'gracilis': fibre 12 has 1 point; a fibre needs at least 2"``.
    """


def memory_limit() -> int:
    """Bytes one array of muscle-mss may ask for: a quarter of the machine's physical memory
    (8 GiB when the system does not say). Larger requests are refused before they are made:
    an allocation that succeeds by swapping stalls the machine for minutes before failing."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 4
    except (ValueError, OSError, AttributeError):
        return 8 * 1024 ** 3


def check_memory(what: str, nbytes: float, advice: str) -> None:
    """Raise :class:`MuscleMSSError` naming ``what``, its size and ``advice`` when ``nbytes``
    exceeds :func:`memory_limit`."""
    limit = memory_limit()
    if nbytes > limit:
        raise MuscleMSSError(f"{what} would need {nbytes / 1024 ** 3:.3g} GiB, more than the "
                             f"{limit / 1024 ** 3:.3g} GiB (a quarter of this machine's memory) "
                             f"one array may take; {advice}")


def checked_points(points, what="points") -> np.ndarray:
    """``points`` as a contiguous (n, 3) float64 array; raise :class:`MuscleMSSError` naming
    ``what`` when they are not (n, 3) or a coordinate is NaN or infinite."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MuscleMSSError(f"{what} must be an (n, 3) array; got shape {points.shape}")
    if not np.isfinite(points).all():
        bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise MuscleMSSError(f"{what}: point {bad} has a NaN or infinite coordinate")
    return points


class PoseError(MuscleMSSError):
    """A muscle that cannot be solved in the pose asked: its ends too close for fibre shortening,
    or a solve that diverged. The core does not know the pose's time; the MSS Collision Solver
    filter adds it with :meth:`at`. The message is ``muscle 'NAME'[ at time T s]`` followed by
    ``text`` (which starts with ``:`` or a space)."""

    def __init__(self, muscle: str, text: str, time: float | None = None):
        self.muscle, self.text, self.time = muscle, text, time
        when = "" if time is None else f" at time {time:g} s"
        super().__init__(f"muscle '{muscle}'{when}{text}")

    def at(self, time) -> "PoseError":
        """The same error naming the time point ``time`` (s); itself when ``time`` is None."""
        return self if time is None else PoseError(self.muscle, self.text, float(time))


class Interrupted(KeyboardInterrupt):
    """The user stopped a run (Ctrl-C): not bad input. A filter interrupted inside VTK records
    it and ``Update()`` raises it, so the run stops as the Ctrl-C asked (the CLI exits with 130)
    instead of going on with empty outputs."""


def first_problem(problems) -> MuscleMSSError:
    """The error to raise for a non-empty list of problem sentences: the first one, saying how
    many more there are (``muscle-mss validate`` lists them all)."""
    more = f" (and {len(problems) - 1} more problems)" if len(problems) > 1 else ""
    return MuscleMSSError(problems[0] + more)
