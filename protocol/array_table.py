"""The array table: how a theta or keyframes payload is laid out, written and checked.

The decompressed payload of a ``theta`` or ``keyframes`` message is the concatenation, in header
order, of the raw little-endian C-order buffers listed in ``header["arrays"]`` as
``[name, dtype, shape]``. This module owns the wire dtypes, packs arrays into one buffer on
encode, checks a received table against the model spec (theta) or the keyframe layout before
any payload byte is read, and cuts the payload back into arrays. Pure Python + numpy.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from protocol.compression import check_coded_table
from protocol.expectation import Expectation
from protocol.messages import (KEYFRAME_ARRAYS, KEYFRAME_CAMERA_DIM, KIND_STATUS, KIND_THETA, MAX_ROUND, CodedTheta,
                               Rejected, is_int)
from protocol.untrusted import describe

#: Array dtypes that may appear on the wire, as little-endian numpy dtypes.
ARRAY_DTYPES = {
    "float32": np.dtype("<f4"),
    "float16": np.dtype("<f2"),
    "uint8": np.dtype("u1"),
    "int8": np.dtype("i1"),
    "int32": np.dtype("<i4"),
}

#: A checked table: (name, numpy dtype, shape) per array, in payload order.
ArrayTable = list[tuple[str, np.dtype, tuple[int, ...]]]


def pack_arrays(arrays: list[tuple[str, np.ndarray, np.dtype]]) -> tuple[bytearray, list]:
    """Concatenate arrays (converted to the given wire dtype) into one buffer with one copy."""
    total = sum(a.size * dt.itemsize for _, a, dt in arrays)
    raw = bytearray(total)
    table = []
    offset = 0
    for name, a, dt in arrays:
        n = a.size * dt.itemsize
        if n:
            dest = np.frombuffer(raw, dtype=dt, count=a.size, offset=offset).reshape(a.shape)
            with np.errstate(over="ignore"):  # float16 overflow becomes inf, refused just below
                np.copyto(dest, a, casting="unsafe")
        wire_name = next(k for k, v in ARRAY_DTYPES.items() if v == dt)
        table.append([name, wire_name, [int(d) for d in a.shape]])
        offset += n
    return raw, table


def table_bytes(table: ArrayTable) -> int:
    """Payload bytes the arrays of a checked table need."""
    return sum(dt.itemsize * math.prod(shape) for _, dt, shape in table)


def check_array_table(table: Any, msg_kind: str, wire_dtype: str, expect: Expectation,
                      coded: CodedTheta | None = None) -> ArrayTable:
    """Validate the header's array table for this kind; raise Rejected('bad_shape'|'too_large'|...).

    ``coded``: a compressed snapshot's coding (from its meta), whose arrays the spec also fixes."""
    entries = _table_entries(table, expect)
    if msg_kind == KIND_STATUS:
        if entries:
            raise Rejected("bad_shape", "status messages carry no arrays")
        return []
    if msg_kind == KIND_THETA and coded is not None:
        assert expect.spec is not None  # checked with the signature
        if wire_dtype != "float32":
            raise Rejected("bad_encoding", "a compressed snapshot decodes to float32")
        check_coded_table(entries, coded, expect.spec)
    elif msg_kind == KIND_THETA:
        _check_theta_table(entries, wire_dtype, expect)
    else:
        _check_keyframe_table(entries, expect)
    return [(name, ARRAY_DTYPES[dtype], shape) for name, dtype, shape in entries]


def _table_entries(table: Any, expect: Expectation) -> list[tuple[str, str, tuple[int, ...]]]:
    """Each entry as (name, wire dtype name, shape), refusing any malformed entry."""
    if not isinstance(table, list):
        raise Rejected("bad_header", "arrays is not a list")
    if len(table) > expect.max_tensors:
        raise Rejected("too_large", f"{len(table)} arrays > cap {expect.max_tensors}")
    entries = []
    for entry in table:
        if (not isinstance(entry, list) or len(entry) != 3 or not isinstance(entry[0], str)
                or not isinstance(entry[1], str) or entry[1] not in ARRAY_DTYPES  # a list would not hash
                or not isinstance(entry[2], list) or len(entry[2]) > 8
                or not all(is_int(d) and 0 <= d <= MAX_ROUND for d in entry[2])):
            raise Rejected("bad_shape", f"malformed array entry {describe(entry)}")
        entries.append((entry[0], entry[1], tuple(entry[2])))
    return entries


def _check_theta_table(entries: list[tuple[str, str, tuple[int, ...]]], wire_dtype: str,
                       expect: Expectation) -> None:
    """A snapshot carries exactly the spec's tensors, in order, in the frame's wire dtype."""
    spec = expect.spec
    assert spec is not None  # checked with the signature
    if len(entries) != len(spec.params):
        raise Rejected("bad_shape", f"{len(entries)} tensors, the spec has {len(spec.params)}")
    for (name, dtype, shape), p in zip(entries, spec.params):
        if name != p.name or dtype != wire_dtype or shape != p.shape:
            raise Rejected("bad_shape", f"tensor {name[:64]!r} {dtype} {list(shape)[:8]}, "
                                        f"spec wants {p.name!r} {wire_dtype} {list(p.shape)}")


def _check_keyframe_table(entries: list[tuple[str, str, tuple[int, ...]]], expect: Expectation) -> None:
    """Descriptors, points and keyframe index of one count P, optionally keypoints and cameras."""
    names = [e[0] for e in entries]
    if names not in (list(KEYFRAME_ARRAYS[:3]), list(KEYFRAME_ARRAYS)):
        raise Rejected("bad_shape", f"keyframe arrays {describe(names)}, want {', '.join(KEYFRAME_ARRAYS[:3])}"
                                    f" [, {', '.join(KEYFRAME_ARRAYS[3:])}]")
    (_, d_dtype, d_shape), (_, p_dtype, p_shape), (_, k_dtype, k_shape) = entries[:3]
    if d_dtype not in ("uint8", "float32") or p_dtype != "float32" or k_dtype != "int32":
        raise Rejected("bad_shape", "keyframe dtypes must be uint8|float32, float32, int32")
    if len(d_shape) != 2 or not 1 <= d_shape[1] <= expect.max_descriptor_dim:
        raise Rejected("bad_shape", f"descriptors shape {list(d_shape)}")
    count = d_shape[0]
    if p_shape != (count, 3) or k_shape != (count,):
        raise Rejected("bad_shape", f"points {list(p_shape)} / keyframe_index {list(k_shape)} vs P={count}")
    if count > expect.max_keyframe_points:
        raise Rejected("too_large", f"{count} keyframe points > cap {expect.max_keyframe_points}")
    if len(entries) == 5:
        (_, uv_dtype, uv_shape), (_, c_dtype, c_shape) = entries[3:]
        if uv_dtype != "float32" or c_dtype != "float32":
            raise Rejected("bad_shape", "keypoints and keyframe_cameras must be float32")
        if uv_shape != (count, 2) or len(c_shape) != 2 or c_shape[1] != KEYFRAME_CAMERA_DIM:
            raise Rejected("bad_shape", f"keypoints {list(uv_shape)} / keyframe_cameras {list(c_shape)[:4]} vs P={count}")
        if c_shape[0] > expect.max_keyframes:
            raise Rejected("too_large", f"{c_shape[0]} keyframes > cap {expect.max_keyframes}")


def unpack_arrays(raw: bytes | memoryview, table: ArrayTable) -> dict[str, np.ndarray]:
    """Cut a decompressed payload into own, writable, native-endian arrays; refuse NaN/inf."""
    arrays: dict[str, np.ndarray] = {}
    offset = 0
    for name, dt, shape in table:
        count = math.prod(shape)
        a = np.frombuffer(raw, dtype=dt, count=count, offset=offset).reshape(shape)
        offset += count * dt.itemsize
        if dt.kind == "f" and a.size and not np.isfinite(a).all():
            raise Rejected("non_finite", f"NaN or inf in {name[:64]!r}")
        # own, writable, native-endian copies; float32 bits are preserved exactly
        arrays[name] = a.astype(dt.newbyteorder("=") if dt.kind != "f" else np.float32)
    return arrays
