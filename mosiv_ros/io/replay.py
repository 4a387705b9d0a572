"""Pacing of a bag replay: when each recorded message is due on the wall clock.

Used by ``bag_replay_node``; kept here, free of ROS, so that the timing rule is tested on its own.
It does not publish anything.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

M = TypeVar("M")


def paced(
    messages: Iterable[M],
    log_time_ns: Callable[[M], int],
    rate: float,
    *,
    stop: threading.Event | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], bool] | None = None,
) -> Iterator[M]:
    """Yield messages when they are due: recorded time gaps divided by ``rate``.

    ``rate`` 1.0 replays in real time, 2.0 twice as fast, 0 as fast as possible. The schedule is
    anchored on the first message, so a slow consumer does not accumulate drift. Setting ``stop``
    ends the iteration, also during a wait. ``clock`` and ``sleep`` (which returns True when it
    was interrupted by ``stop``) default to the monotonic clock and ``stop.wait``.
    """
    if rate < 0:
        raise ValueError(f"replay rate must be >= 0 (0 = as fast as possible), got {rate}")
    stop = stop or threading.Event()
    sleep = sleep or stop.wait
    start_wall = None
    start_log = 0
    for message in messages:
        if stop.is_set():
            return
        if rate > 0:
            if start_wall is None:
                start_wall, start_log = clock(), log_time_ns(message)
            due = start_wall + (log_time_ns(message) - start_log) * 1e-9 / rate
            wait = due - clock()
            if wait > 0 and sleep(wait):
                return
        yield message
