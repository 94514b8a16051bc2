"""Progress of long local work (loading images, SfM, evaluation), told to whoever listens.

The library never draws: a command installs a listener (``cli.options.progress_listener``) for
the block that may take a while, and ``track``/``stage`` here report to it; with none installed
they cost nothing.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Iterable, Iterator, Protocol, TypeVar

__all__ = ["Listener", "listening", "track", "stage"]

T = TypeVar("T")


class Listener(Protocol):
    def begin(self, description: str, total: int | None) -> object: ...
    def advance(self, task: object) -> None: ...
    def end(self, task: object) -> None: ...


_listener: ContextVar[Listener | None] = ContextVar("dinerf_progress", default=None)


@contextmanager
def listening(listener: Listener) -> Iterator[None]:
    token = _listener.set(listener)
    try:
        yield
    finally:
        _listener.reset(token)


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """``items``, one step of a bar per item."""
    listener = _listener.get()
    if listener is None:
        yield from items
        return
    task = listener.begin(description, total if total is not None else _length(items))
    try:
        for item in items:
            yield item
            listener.advance(task)
    finally:
        listener.end(task)


@contextmanager
def stage(description: str) -> Iterator[None]:
    """A step of unknown length (a spinner): e.g. COLMAP's matching."""
    listener = _listener.get()
    task = listener.begin(description, None) if listener else None
    try:
        yield
    finally:
        if listener:
            listener.end(task)


def _length(items: Iterable) -> int | None:
    try:
        return len(items)  # type: ignore[arg-type]
    except TypeError:
        return None
