"""Files written so that a crash at any moment leaves either the old file or the new one, and
JSON files read so that a bad one is one clear error.

A daemon may be SIGKILLed or lose power mid-write; its checkpoint must still be the last complete
one. So the bytes go to a temporary file beside the target, are fsynced, renamed over the target
(atomic on POSIX), and the directory is fsynced too: without that last step the rename itself
may not survive a power cut, and the old file (or none) comes back.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path
from typing import Any, Callable

__all__ = ["atomic_write_bytes", "atomic_write_text", "read_json"]


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` atomically and durably (see the module docstring).

    The temporary file has a unique name (two writers never share one) and ends in ``.tmp``;
    it is removed if anything fails, and the target is then untouched. It is created with the
    process's umask, as ``open`` would (``mkstemp`` would make it private to its owner)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_json(path: str | Path, error: Callable[[str], Exception]) -> Any:
    """The JSON document in ``path``. A file that cannot be read, is not UTF-8 or is not JSON
    raises ``error("<path>: ...")``: one line for the user, whichever of the three it is."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise error(f"{path}: not valid JSON: {e}") from None
    except OSError as e:
        raise error(f"{path}: cannot be read ({e.strerror or e})") from None
