"""State files (checkpoints, round snapshots, the baseline's model): safetensors + JSON, checksummed.

Format: one ``.safetensors`` file. Every tensor of the state is stored under its flat name
(``agent.state_codec``); the header's ``__metadata__`` (string to string, part of the
safetensors format) holds

    format   "dinerf-state"        anything else is not ours and is refused
    version  "1"
    kind     "robot-checkpoint", "round-snapshot", "baseline" ...: a file of another kind is refused
    state    the JSON rest of the state, with each tensor as {"$tensor": name}
    sha256   over kind, state and, name by name in sorted order, each tensor's name, dtype,
             shape and bytes

Loading never runs code from the file (no pickle; the JSON decodes to plain data only), and it
refuses, with one line naming the file, anything that is not exactly what was written: not a
regular file (a FIFO would hang the reader, /dev/zero would fill the memory), a symlink out of
the folder it must stay in, larger than the machine can hold, empty, truncated, not
safetensors, a pickle, another kind, a checksum that does not match. Its size is known before a
byte is read. A refused file is left where it is, for the user to look at.

One file rather than a sidecar JSON: a single ``os.replace`` publishes state and tensors
together, so they can never be from two different saves.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import struct
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agent.files import atomic_write_bytes
from agent.state_codec import StateFormatError, flatten, unflatten

__all__ = ["CheckpointError", "write_state", "read_state"]

FORMAT = "dinerf-state"
VERSION = "1"
_MAX_HEADER = 100 << 20  # safetensors' own limit
_PICKLE_MAGIC = (b"\x80", b"PK\x03\x04")  # a pickle (protocol 2+), a torch.save zip
# A safetensors file opens with its header length (u64 LE) and then '{': a length whose low byte is
# 0x80 starts like a pickle, so the JSON brace decides first.
_SAFETENSORS_BRACE = 8


class CheckpointError(RuntimeError):
    """A state file that cannot be used. ``str()`` is one line: ``<path>: <reason>``."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = " ".join(str(reason).split())  # one line, whatever the cause printed
        super().__init__(f"{self.path}: {self.reason}")


def _digest(kind: str, state: str, tensors: dict[str, Tensor]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([FORMAT, VERSION, kind, state]).encode())
    for name in sorted(tensors):
        t = tensors[name]
        h.update(json.dumps([name, str(t.dtype), list(t.shape)]).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().data)
    return h.hexdigest()


def write_state(path: str | Path, kind: str, state: Any) -> None:
    """Write ``state`` as a state file of ``kind``, atomically (``agent.files``)."""
    from safetensors.torch import save

    text, tensors = flatten(state)
    meta = {"format": FORMAT, "version": VERSION, "kind": kind, "state": text,
            "sha256": _digest(kind, text, tensors)}
    atomic_write_bytes(path, save(tensors, metadata=meta))


def read_state(path: str | Path, kind: str, within: str | Path | None = None) -> Any:
    """The state in ``path`` (tensors on the CPU), or :class:`CheckpointError` saying why not.
    ``within``: a folder that ``path`` must not leave, symlinks followed (a run folder)."""
    path = Path(path)
    data = _read_bytes(path, within)
    meta = _metadata(path, data)
    if meta.get("kind") != kind:
        raise CheckpointError(path, f"a {meta.get('kind')!r} file, not a {kind!r}")
    from safetensors import SafetensorError
    from safetensors.torch import load

    try:
        tensors = load(data)
    except SafetensorError as e:
        raise CheckpointError(path, f"damaged safetensors data ({e})") from None
    text = meta.get("state", "")
    if _digest(kind, text, tensors) != meta.get("sha256"):
        raise CheckpointError(path, "checksum mismatch: the file is damaged")
    try:
        return unflatten(text, tensors)
    except StateFormatError as e:
        raise CheckpointError(path, f"malformed state: {e}") from None


def memory_limit() -> int:
    """The largest state file read into memory: half the machine's RAM (a bigger one is refused
    in one line rather than ending in a MemoryError)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def _kind_of(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _open_regular(path: Path, within: str | Path | None) -> tuple[int, int]:
    """(file descriptor, size) of ``path``, which must be a regular file (inside ``within``).
    O_NONBLOCK: opening a FIFO for reading would otherwise wait for a writer, for ever."""
    if within is not None:
        real, folder = os.path.realpath(path), os.path.realpath(within)
        if os.path.commonpath([real, folder]) != folder:
            raise CheckpointError(path, f"is a symlink to {real}, outside {folder}: not followed")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except IsADirectoryError:
        raise CheckpointError(path, "is a directory, not a state file") from None
    except OSError as e:
        raise CheckpointError(path, f"cannot be read ({e.strerror or e})") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        what = _kind_of(info.st_mode)
        raise CheckpointError(path, f"is {what}, not a state file" if what != "not a regular file" else what)
    if info.st_size > (limit := memory_limit()):
        os.close(fd)
        raise CheckpointError(path, f"is {info.st_size / 1e9:.1f} GB, more than the {limit / 1e9:.1f} GB a state "
                                    "file may take here (half the memory)")
    return fd, info.st_size


def _read_bytes(path: Path, within: str | Path | None = None) -> bytes:
    fd, size = _open_regular(path, within)
    try:
        with os.fdopen(fd, "rb") as f:
            data = f.read(size + 1)  # one more: a file that grew since fstat is read as it was sized
    except OSError as e:
        raise CheckpointError(path, f"cannot be read ({e.strerror or e})") from None
    if len(data) != size:
        raise CheckpointError(path, "changed while it was read (another writer?)")
    if not data:
        raise CheckpointError(path, "is empty (a save that never completed?)")
    looks_safetensors = data[_SAFETENSORS_BRACE:_SAFETENSORS_BRACE + 1] == b"{"
    if data.startswith(_PICKLE_MAGIC) and not looks_safetensors:
        raise CheckpointError(path, "is a pickle (torch.save), which dinerf never loads: it could run code")
    return data


def _metadata(path: Path, data: bytes) -> dict[str, str]:
    """The safetensors header's ``__metadata__``, checked to be a dinerf state file's."""
    if len(data) < 8:
        raise CheckpointError(path, "too short to be a safetensors file (truncated?)")
    (size,) = struct.unpack("<Q", data[:8])
    if size > min(len(data) - 8, _MAX_HEADER):
        raise CheckpointError(path, "truncated, or not a safetensors file (its header runs past the end)")
    try:
        header = json.loads(data[8:8 + size].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        raise CheckpointError(path, "not a safetensors file (its header is not JSON)") from None
    _check_length(path, header, len(data) - 8 - size)
    meta = header.get("__metadata__") if isinstance(header, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(path, "a safetensors file, but not one dinerf wrote (no dinerf-state metadata)")
    if meta.get("version") != VERSION:
        raise CheckpointError(path, f"format version {meta.get('version')!r}; this dinerf reads {VERSION!r}")
    return meta


def _check_length(path: Path, header: Any, data_bytes: int) -> None:
    """A file cut short says so (safetensors itself would only say "not fully covered")."""
    entries = header.values() if isinstance(header, dict) else ()
    ends = [e["data_offsets"][1] for e in entries if isinstance(e, dict) and isinstance(e.get("data_offsets"), list)
            and len(e["data_offsets"]) == 2 and isinstance(e["data_offsets"][1], int)]
    if ends and max(ends) > data_bytes:
        raise CheckpointError(path, f"truncated: its tensors need {max(ends)} bytes of data, it has {data_bytes}")
