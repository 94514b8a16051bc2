"""Fuzzing the receiver: 60,000 hostile inputs over every kind, each refused for a reason or a valid message.

Inputs are mutations of valid theta, status and keyframe frames (bit flips, truncations, splices,
header and body fields replaced by values of every msgpack type, nested and huge, lies about
lengths and sizes, zstd bombs and corrupt zstd frames, hostile array contents) plus random
bytes. Most mutations re-seal the frame (lengths and checksum fixed), so they get past the cheap
checks to the ones behind them. Fixed seed: a failure reproduces. ``pytest -s`` prints the
refusals counted by reason.

The properties: ``decode`` raises nothing but :class:`Rejected`, and never through its safety
net (that would be a check's own bug); ``read_header`` refuses with the same reason whenever it
refuses; every accepted frame is a valid message, which encodes and decodes back to itself.
"""

from __future__ import annotations

import random
import struct
import time
from collections import Counter
from typing import Any, Callable

import msgpack
import numpy as np
import pytest
import zstandard

from protocol import codec
from protocol.compression import LEVEL_MODES, CompressionConfig, code_snapshot
from protocol.messages import KIND_KEYFRAMES, KIND_STATUS, KIND_THETA, Rejected, Status
from tests.protocol.helpers import (Packed, deep_list, expectation, frame_of, keyframe_summary,
                                    keyframe_summary_with_cameras, pack_map, rle_zstd_frame, small_spec,
                                    snapshot, split_frame, status_message)

SEED = 20240611
INPUTS = 60_000


def _seal(header: dict, payload: bytes, rng: random.Random, lengths: bool = True) -> bytes:
    """A frame of this header and payload; usually with true lengths and checksum, so it gets far."""
    header = dict(header)
    if lengths and rng.random() < 0.9:
        header["payload_length"] = len(payload)
    if rng.random() < 0.9:  # (over a Packed value it is the checksum of another header: refused)
        header["checksum"] = codec.frame_checksum(header, payload)
    return frame_of(pack_map(header), payload)


# --------------------------------------------------------------------------- hostile values


_SCALARS: list[Any] = [
    None, True, False, 0, 1, -1, 2, 3, 5, 7, 255, 2**31 - 1, 2**31, -(2**31), 2**63 - 1, -(2**63), 2**64 - 1,
    0.0, -0.0, 1.5, float("nan"), float("inf"), float("-inf"), 1e308, "", "x", "theta", "status", "keyframes",
    "float32", "float16", "uint8", "int32", "zstd", "none", "testswarm", "0" * 16, "\u00e9\u6f22", "k" * 4096,
    b"", msgpack.ExtType(5, b""), Packed(b"\xc7\x00\xff"),  # empty ext: msgpack lets it through, -1 is a timestamp
]
_TOO_LONG = [Packed(msgpack.packb("s" * 4097)), Packed(msgpack.packb(b"b")), Packed(msgpack.packb([0] * 5000)),
             Packed(b"\xc1"), Packed(b"\xd9"), Packed(b"")]  # beyond msgpack's limits, reserved or cut short
_DEEP = [deep_list(d) for d in (4, 5, 100, 1023, 1024, 5000)]


def hostile_value(rng: random.Random) -> Any:
    """A value of any msgpack type: scalars at the edges, containers nested and huge, malformed bytes."""
    roll = rng.random()
    if roll < 0.45:
        return rng.choice(_SCALARS)
    if roll < 0.55:
        return rng.choice(_TOO_LONG)
    if roll < 0.65:
        return rng.choice(_DEEP)
    if roll < 0.8:
        return [hostile_value(rng) if rng.random() < 0.3 else rng.choice(_SCALARS) for _ in range(rng.randrange(5))]
    if roll < 0.9:
        return {rng.choice(["a", "image_bytes", "box_from_shared", ""]): rng.choice(_SCALARS)
                for _ in range(rng.randrange(4))}
    return [rng.choice(_SCALARS)] * rng.choice([16, 100, 4096])


_NUMBERS = [0, 1, -1, 0.5, 1.0, 1e6, 1e-6, 1e200, 1e308, -1e308, 1e-300, float("nan"), float("inf"), 2**64 - 1,
            -(2**63), True]


def _hostile_meta(rng: random.Random) -> Any:
    """Keyframe meta: image_bytes at the edges, field boxes of extreme numbers or nearly a similarity."""
    roll = rng.random()
    if roll < 0.2:
        return {"image_bytes": rng.choice(_SCALARS)}
    if roll < 0.5:
        return {"image_bytes": 1, "box_from_shared": [rng.choice(_NUMBERS) for _ in range(16)]}
    if roll < 0.9:
        box = np.diag([rng.choice([0.5, 1.0, 2.0])] * 3 + [1.0]).flatten().tolist()
        box[rng.randrange(16)] = rng.choice(_NUMBERS)
        return {"image_bytes": 1, "box_from_shared": box}
    return hostile_value(rng)


def _hostile_entry(entry: list, rng: random.Random) -> Any:
    """An array-table entry with one part (name, dtype, shape or a dimension) replaced."""
    entry = [entry[0], entry[1], list(entry[2])]
    part = rng.randrange(5)
    if part < 3:
        entry[part] = hostile_value(rng)
    elif part == 3 and entry[2]:
        entry[2][rng.randrange(len(entry[2]))] = rng.choice([0, 1, -1, 2**31, 2**40, 1.0, None, "3", 200_001])
    else:
        entry = rng.choice([entry[:2], entry + [0], {"name": entry[0]}, entry[0]])
    return entry


# --------------------------------------------------------------------------- the valid frames


class Base:
    """One valid frame, taken apart: header map, wire payload, raw body."""

    def __init__(self, data: bytes):
        self.data = data
        self.header, self.payload = split_frame(data)
        self.kind = self.header["kind"]
        compressed = self.header["compression"] == "zstd"
        self.raw = zstandard.ZstdDecompressor().decompress(self.payload) if compressed else self.payload


def _coded(mode: str, **kw: Any) -> bytes:
    """A compressed snapshot (a delta against another snapshot for the delta modes)."""
    base = snapshot(seed=7).tensors
    cfg = CompressionConfig(compression=mode, topk_fraction=0.25, chunk=16,
                            whole_below=0 if mode in LEVEL_MODES or mode == "delta+uniform" else 16384)  # on every tensor
    coded, _ = code_snapshot(snapshot(), cfg, None if mode == "int8" else (4, "0123456789abcdef", base))
    return codec.encode(coded, spec=small_spec(), **kw)


def _bases() -> list[Base]:
    with_box = keyframe_summary_with_cameras()
    box = np.diag([0.5, 0.5, 0.5, 1.0])
    box[:3, 3] = [0.1, -0.2, 0.3]
    with_box.box_from_shared = box
    return [
        Base(codec.encode(snapshot())),
        Base(codec.encode(snapshot(sender=2, seed=1), compression="none")),
        Base(codec.encode(snapshot(sender=0, seed=2), wire_dtype="float16")),
        Base(codec.encode(status_message())),
        Base(codec.encode(status_message(alive_ages={0: 1.5, 1: 0.0}, psnr=31.0), compression="none")),
        Base(codec.encode(keyframe_summary())),
        Base(codec.encode(keyframe_summary(np.float32, points=20), compression="none")),
        Base(codec.encode(with_box)),
        Base(_coded("delta+topk")),
        Base(_coded("delta+int8", compression="none")),
        Base(_coded("int8")),
        Base(_coded("delta+ternary")),
        Base(_coded("delta+quinary", compression="none")),
        Base(_coded("delta+uniform")),
    ]


# --------------------------------------------------------------------------- mutations


def random_bytes(base: Base, rng: random.Random) -> bytes:
    data = rng.randbytes(rng.choice([0, 1, 3, 7, 8, 12, 64, 300]))
    return codec.MAGIC + data if rng.random() < 0.5 else data


def bit_flips(base: Base, rng: random.Random) -> bytes:
    data = bytearray(base.data)
    for _ in range(rng.randint(1, 8)):
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    if data == base.data:  # the same bit flipped twice: not a mutation at all
        data[0] ^= 1
    return bytes(data)


def truncate_or_extend(base: Base, rng: random.Random) -> bytes:
    if rng.random() < 0.7:
        return base.data[: rng.randrange(len(base.data))]
    return base.data + rng.randbytes(rng.randint(1, 64))


def splice(base: Base, rng: random.Random, bases: list[Base] | None = None) -> bytes:
    """Another frame's tail after this one's head, or a chunk of this frame cut, repeated or moved."""
    data = base.data
    i, j = sorted(rng.randrange(len(data) + 1) for _ in range(2))
    choice = rng.randrange(3)
    if choice == 0 and bases:
        other = rng.choice(bases).data
        return data[:i] + other[rng.randrange(len(other)) :]
    if choice == 1:
        return data[:i] + data[j:]
    return data[:j] + data[i:j] + data[j:]


def replace_header_field(base: Base, rng: random.Random) -> bytes:
    """One header field replaced, deleted or added, resealed."""
    header = dict(base.header)
    roll = rng.random()
    if roll < 0.6:
        header[rng.choice(codec.HEADER_FIELDS)] = hostile_value(rng)
    elif roll < 0.7:
        del header[rng.choice(codec.HEADER_FIELDS)]
    elif roll < 0.8:
        header[rng.choice(["extra", "", b"", "Kind"])] = hostile_value(rng)
    elif roll < 0.9 and header["arrays"]:
        table = list(header["arrays"])
        k = rng.randrange(len(table))
        table[k] = _hostile_entry(table[k], rng)
        header["arrays"] = rng.choice([table, table[:k], table + table[:1], table[::-1]])
    else:
        header["meta"] = _hostile_meta(rng)
    return _seal(header, base.payload, rng)


def lie_about_lengths(base: Base, rng: random.Random) -> bytes:
    """raw_length, payload_length or the prefix's header length off by a little or a lot."""
    header = dict(base.header)
    delta = rng.choice([-1, 1, -8, 8, 4096, 2**20, 2**31, 2**33])
    which = rng.randrange(3)
    if which < 2:
        name = ("raw_length", "payload_length")[which]
        header[name] = max(0, header[name] + delta)
        return _seal(header, base.payload, rng, lengths=False)
    data = bytearray(base.data)
    (length,) = struct.unpack_from("<I", data, 4)
    struct.pack_into("<I", data, 4, max(0, min(2**32 - 1, length + delta)))
    return bytes(data)


_ZSTD_EVILS: list[bytes] = []


def _zstd_evils() -> list[bytes]:
    """Bombs (declared and undeclared size), a huge window, a skippable frame, an empty frame."""
    if not _ZSTD_EVILS:
        window = bytearray(rle_zstd_frame(2**17, False))
        window[5] = 0xF8  # window descriptor: exponent 31, far beyond the receiver's window cap
        _ZSTD_EVILS.extend([
            rle_zstd_frame(2**30, True), rle_zstd_frame(2**30, False), rle_zstd_frame(2**17, True),
            rle_zstd_frame(2**17, False), bytes(window), b"\x50\x2a\x4d\x18\x04\x00\x00\x00abcd",
            zstandard.ZstdCompressor().compress(b""),
        ])
    return _ZSTD_EVILS


def evil_payload(base: Base, rng: random.Random) -> bytes:
    """A zstd payload that lies: bombs, wrong or missing content size, trailing data, flipped bits."""
    header = dict(base.header, compression="zstd")
    raw = base.raw
    choice = rng.randrange(6)
    if choice == 0:
        payload = rng.choice(_zstd_evils())
    elif choice == 1:
        payload = zstandard.ZstdCompressor(write_content_size=False).compress(raw + b"\x00" * rng.choice([0, 1, 4096]))
    elif choice == 2:
        payload = zstandard.ZstdCompressor().compress(raw[: len(raw) - rng.randint(0, 8)])
    elif choice == 3:
        frame = zstandard.ZstdCompressor().compress(raw)
        payload = frame + rng.choice([frame, b"\x00", rng.randbytes(9)])
    else:
        payload = bytearray(zstandard.ZstdCompressor(write_checksum=rng.random() < 0.5).compress(raw))
        for _ in range(rng.randint(1, 3)):
            payload[rng.randrange(len(payload))] ^= 1 << rng.randrange(8)
        payload = bytes(payload)
    return _seal(header, payload, rng)


def hostile_body(base: Base, rng: random.Random) -> bytes:
    """A correctly framed payload whose content is hostile: status fields, NaN, bad indices and cameras."""
    if base.kind == KIND_STATUS:
        body = msgpack.unpackb(base.raw)
        body[rng.choice(list(Status.BODY_FIELDS) + ["extra"])] = hostile_value(rng)
        if rng.random() < 0.1:
            del body[rng.choice(list(Status.BODY_FIELDS))]
        raw = pack_map(body)
    else:
        raw = bytearray(base.raw)
        for _ in range(rng.randint(1, 4)):
            at = rng.randrange(0, len(raw) - 3, 4) if len(raw) > 4 else 0
            raw[at : at + 4] = rng.choice([np.float32(np.nan).tobytes(), np.float32(-np.inf).tobytes(),
                                          np.int32(-1).tobytes(), np.int32(2**31 - 1).tobytes(),
                                          np.float32(0.0).tobytes(), np.float16(np.inf).tobytes() * 2])
        raw = bytes(raw)
    header = dict(base.header, raw_length=len(raw))
    if rng.random() < 0.5:
        return _seal(dict(header, compression="none"), raw, rng)
    return _seal(dict(header, compression="zstd"), zstandard.ZstdCompressor().compress(raw), rng)


def untouched(base: Base, rng: random.Random) -> bytes:
    return base.data


#: Mutations that always change a frame and never fix its checksum: nothing they make may be accepted.
UNSEALED = ("random_bytes", "bit_flips", "truncate_or_extend")

MUTATIONS: list[tuple[Callable[[Base, random.Random], bytes], int]] = [
    (random_bytes, 5), (bit_flips, 12), (truncate_or_extend, 6), (splice, 6), (replace_header_field, 30),
    (lie_about_lengths, 8), (evil_payload, 12), (hostile_body, 20), (untouched, 1),
]


# --------------------------------------------------------------------------- properties


def _same_message(a: Any, b: Any) -> bool:
    """Same kind, identity and content (header bytes may differ: a forger packs bodies its own way)."""
    if type(a) is not type(b) or (a.swarm, a.sender, a.round, a.epoch) != (b.swarm, b.sender, b.round, b.epoch):
        return False
    if a.kind == KIND_THETA and (a.coded is not None or b.coded is not None):
        x, y = a.coded, b.coded
        return (a.signature == b.signature and x is not None and y is not None and list(x.arrays) == list(y.arrays)
                and (x.mode, x.chunk, x.base_round, x.base_digest, x.digest)
                == (y.mode, y.chunk, y.base_round, y.base_digest, y.digest)
                and all(np.array_equal(x.arrays[n], y.arrays[n]) for n in x.arrays))
    if a.kind == KIND_THETA:
        return (a.signature == b.signature and list(a.tensors) == list(b.tensors)
                and all(a.tensors[n].tobytes() == b.tensors[n].tobytes() for n in a.tensors))
    if a.kind == KIND_STATUS:
        return all(getattr(a, f) == getattr(b, f) for f in Status.BODY_FIELDS)
    arrays = ("descriptors", "points", "keyframe_index", "keypoints", "keyframe_cameras", "box_from_shared")
    same = [(x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
            for x, y in ((getattr(a, n), getattr(b, n)) for n in arrays)]
    return all(same) and a.image_bytes == b.image_bytes


def _assert_round_trips(msg: Any, expect: codec.Expectation) -> None:
    """An accepted frame is a message we could have sent ourselves: it encodes, and decodes to itself."""
    h = msg.header
    options = {"wire_dtype": h.wire_dtype, "spec": expect.spec} if h.kind == KIND_THETA else {}
    again = codec.decode(codec.encode(msg, compression=h.compression, **options), expect)
    assert _same_message(msg, again), h


def _outcome(data: bytes, expect: codec.Expectation) -> str:
    """The reason it is refused for (the same from read_header, never via the safety net), or "accepted"."""
    try:
        codec.read_header(data, expect)
        header_reason = None
    except Rejected as exc:
        header_reason = exc.reason
    try:
        msg = codec.decode(data, expect)
    except Rejected as exc:
        assert not exc.detail.startswith(codec.UNEXPECTED), f"a check raised: {exc}"
        assert header_reason in (None, exc.reason), (header_reason, exc.reason)
        return exc.reason
    assert header_reason is None, f"read_header refused ({header_reason}) what decode accepted"
    _assert_round_trips(msg, expect)
    return "accepted"


def _run(inputs: int, seed: int) -> tuple[Counter, Counter, list[str]]:
    """(outcomes by (outcome, kind), inputs by mutation, failures) of ``inputs`` generated inputs."""
    rng = random.Random(seed)
    bases = _bases()
    expect = expectation()
    mutations = [(lambda b, r: splice(b, r, bases)) if m is splice else m for m, _ in MUTATIONS]
    names = [m.__name__ for m, _ in MUTATIONS]
    weights = [w for _, w in MUTATIONS]
    outcomes: Counter = Counter()
    per_mutation: Counter = Counter()
    failures: list[str] = []
    for i in range(inputs):
        base = bases[i % len(bases)]
        k = rng.choices(range(len(mutations)), weights)[0]
        data = mutations[k](base, rng)
        per_mutation[names[k]] += 1
        try:
            outcome = _outcome(data, expect)
            outcomes[outcome, base.kind] += 1
            if outcome == "accepted" and names[k] in UNSEALED:
                failures.append(f"#{i} {names[k]} of {base.kind} was accepted: the checksum missed it")
        except Exception as exc:  # collected, all reported together
            failures.append(f"#{i} {names[k]} of {base.kind}: {type(exc).__name__}: {str(exc)[:200]} "
                            f"input {data[:48]!r}... ({len(data)} bytes)")
    return outcomes, per_mutation, failures


def _print_table(outcomes: Counter) -> None:
    kinds = (KIND_THETA, KIND_STATUS, KIND_KEYFRAMES)
    totals = Counter()
    for (outcome, _), count in outcomes.items():
        totals[outcome] += count
    print(f"  {'outcome':20s} {'total':>6s} " + " ".join(f"{k:>9s}" for k in kinds))
    for outcome, total in totals.most_common():
        print(f"  {outcome:20s} {total:6d} " + " ".join(f"{outcomes[outcome, k]:9d}" for k in kinds))


@pytest.mark.filterwarnings("error")  # a warning per hostile frame would flood the log: it fails the check
def test_fuzz_decode_only_ever_rejects_or_returns_a_valid_message():
    t0 = time.perf_counter()
    outcomes, per_mutation, failures = _run(INPUTS, SEED)
    elapsed = time.perf_counter() - t0
    print(f"\nfuzz: {INPUTS} inputs in {elapsed:.1f} s ({INPUTS / elapsed:.0f}/s), seed {SEED}")
    print("  by mutation: " + ", ".join(f"{n} {c}" for n, c in per_mutation.most_common()))
    _print_table(outcomes)
    assert not failures, f"{len(failures)} inputs failed a property:\n" + "\n".join(failures[:10])
    assert sum(outcomes.values()) == INPUTS >= 50_000
    # the mutations reach every layer: framing, header, array table, payload, body, for every kind
    seen = {outcome for outcome, _ in outcomes}
    assert {"bad_magic", "bad_length", "garbage", "bad_header", "bad_kind", "bad_checksum", "bad_shape",
            "bad_encoding", "decompression_bomb", "too_large", "bad_field", "non_finite", "accepted"} <= seen
    for kind in (KIND_THETA, KIND_STATUS, KIND_KEYFRAMES):
        assert outcomes["accepted", kind] and outcomes["bad_checksum", kind] and outcomes["decompression_bomb", kind]
