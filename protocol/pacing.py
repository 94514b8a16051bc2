"""Recorded messages released at their recorded pace, for replaying a bag.

Pure Python (no zenoh, no torch): a robot replaying its own bag (``agent.data.ros.intake``) and
the publisher that plays a bag as a live camera (``protocol.ros_camera``) both pace with it.
"""

from __future__ import annotations

import threading
import time
from typing import Iterable, Iterator, TypeVar

__all__ = ["paced"]

T = TypeVar("T")


def paced(messages: Iterable[tuple[int, T]], rate: float, stop: threading.Event | None = None) -> Iterator[T]:
    """Each item of ``(recorded time in ns, item)`` once its time has come: ``rate`` x the recorded
    pace from the first item (0: at once). Ends when ``stop`` is set, also while waiting."""
    t_recorded0 = t_wall0 = None
    for t, item in messages:
        if stop is not None and stop.is_set():
            return
        if t_recorded0 is None:
            t_recorded0, t_wall0 = t, time.monotonic()
        if rate > 0:
            delay = t_wall0 + (t - t_recorded0) * 1e-9 / rate - time.monotonic()
            if delay > 0 and (stop.wait(delay) if stop is not None else time.sleep(delay)):
                return
        yield item
