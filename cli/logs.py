"""Operator logs: one timestamped, levelled line per event on stderr (``-v``/``-q``, ``DINERF_LOG``);
stdout keeps a command's data (``status --json``, ``config show``) clean for scripts."""

from __future__ import annotations

import logging
import os
import sys

__all__ = ["LOGGER", "configure", "level_from"]

LOGGER = logging.getLogger("dinerf")
_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}


def level_from(verbose: int, quiet: int, env: str | None) -> int:
    """``DINERF_LOG`` (debug|info|warning|error) sets the base level; each -v lowers it, each -q raises it."""
    base = logging.INFO
    if env:
        if env.strip().lower() not in _LEVELS:
            raise ValueError(f"DINERF_LOG={env!r}: expected one of {', '.join(_LEVELS)}")
        base = _LEVELS[env.strip().lower()]
    return min(max(base - 10 * verbose + 10 * quiet, logging.DEBUG), logging.ERROR)


def configure(verbose: int = 0, quiet: int = 0) -> None:
    """Install the one handler: ``2026-12-01 23:59:01.123 INFO    [robot 1] round 3 ...``."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s.%(msecs)03d %(levelname)-7s %(message)s",
                                           datefmt="%Y-%m-%d %H:%M:%S"))
    LOGGER.handlers[:] = [handler]
    LOGGER.propagate = False
    LOGGER.setLevel(level_from(verbose, quiet, os.environ.get("DINERF_LOG")))
