"""Turn expected failures (bad config, bad data, unreachable peers) into one clear line, not a traceback."""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import typer

F = TypeVar("F", bound=Callable)


class UserError(Exception):
    """A problem the user can fix; printed without a traceback."""


def friendly_errors(fn: F) -> F:
    """Decorator for typer commands: known error types become ``error: ...`` and exit code 2."""
    from agent.data.views import DataError
    from agent.statefile import CheckpointError
    from cli.config import ConfigError

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (UserError, DataError, ConfigError, CheckpointError, FileNotFoundError) as e:
            _fail(str(e))
        except OSError as e:  # the file system said no (a file where a folder must be, no permission ...)
            _fail(f"{e.filename}: {e.strerror}" if e.filename and e.strerror else str(e))

    return wrapper  # type: ignore[return-value]


def _fail(message: str) -> None:
    typer.secho(f"error: {' '.join(message.split())}", err=True, fg=typer.colors.RED)
    raise typer.Exit(2) from None
