"""Progress of long work: the callback every stage reports to, and the time left of a phase.

A stage calls ``progress(phase, done, total, unit)`` after each unit of its work, e.g.
``("reconstruct", 12, 31, "frame")`` or ``("identify: search", 64, 128, "sample")``. The command
line draws one bar per phase (tqdm, which estimates the time left itself); a node logs the phase
with ``TimeLeft``'s estimate beside its ``/diagnostics``; a benchmark times the phases with
``PhaseSpans``.

What it is not for: logging or drawing (the command line and the nodes do that).
"""

from __future__ import annotations

import time
from collections.abc import Callable

Progress = Callable[[str, int, int, str], None]
"""progress(phase, done, total, unit): ``done`` of ``total`` units of ``phase`` are finished."""


class TimeLeft:
    """Seconds left in each phase, from the rate of its units since its first report."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._first: dict[str, tuple[float, int]] = {}

    def __call__(self, phase: str, done: int, total: int) -> float | None:
        """The estimate after ``done`` of ``total`` units; None until the rate is known."""
        now = self._clock()
        first = self._first.get(phase)
        if first is None or done < first[1]:  # a new phase, or the phase began again
            self._first[phase] = (now, done)
            return None
        began, done0 = first
        if done <= done0 or now <= began:
            return None
        return max(0.0, (total - done) * (now - began) / (done - done0))


class PhaseSpans:
    """A ``Progress`` callback that records when each phase was reported first and last.

    ``spans()``: per phase, the seconds from the callback's creation to its first and last
    report, and the ``done`` and ``total`` of the last. A phase's first report is its start
    where the phase reports 0 done first (the search, the uncertainty), else the end of its
    first unit. Benchmarks time a run's phases with it (``benchmarks/identify_samples.py``).
    """

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self._clock = clock
        self._start = clock()
        self._spans: dict[str, tuple[float, float, int, int]] = {}

    def __call__(self, phase: str, done: int, total: int, unit: str) -> None:
        now = self._clock() - self._start
        first = self._spans.get(phase, (now,))[0]
        self._spans[phase] = (first, now, done, total)

    def spans(self) -> dict[str, dict[str, float]]:
        """{phase: {"first_s", "last_s", "done", "total"}}, in the order the phases began."""
        return {phase: {"first_s": first, "last_s": last, "done": done, "total": total}
                for phase, (first, last, done, total) in self._spans.items()}


def duration(seconds: float | None) -> str:
    """'1 h 02 min', '3 min 20 s', '45 s', or 'unknown' for None."""
    if seconds is None:
        return "unknown"
    seconds = int(round(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"
    if seconds >= 60:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds} s"
