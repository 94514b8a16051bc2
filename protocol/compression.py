"""Compressed snapshots: int8, delta coding against a named base, top-k and few-level codes with error feedback.

A float32 hash table is incompressible (zstd gains nothing), so a robot sending its whole field
every round at float32 makes the network, not the CPU, set the pace on a slow link. The modes
(``CompressionConfig.compression``):

- ``none``        float32, bit-identical (today's frames);
- ``fp16``        float16 (``wire_dtype="float16"``), lossy, half the bytes;
- ``int8``        every value as int8 with one float32 scale per ``chunk`` values; stateless;
- ``delta+int8``  ``theta - base`` as int8: untouched entries are exact zeros, which zstd squeezes;
- ``delta+topk``  only the ``topk_fraction`` largest entries of ``theta - base`` per tensor, as
                  int8, with their indices as gaps split into byte planes (zstd packs them);
                  tensors up to ``whole_below`` entries (the MLPs) whole;
- ``delta+ternary`` every entry of ``theta - base`` rounded to a step (``level_step`` times its
                  chunk's mean |delta|) and clipped to -1, 0, +1 steps, five codes to a byte;
- ``delta+quinary`` the same with -2..+2 steps, three codes to a byte. Each code decodes to the
                  mean |delta| of its chunk's entries at that level. Every entry moves every
                  round, so no entry lags its neighbours' copy by more than a step; zstd then
                  packs the codes near their entropy (1.2-1.7 bits a value). Tensors up to
                  ``whole_below`` entries go as int8 deltas.
- ``delta+uniform`` one step per tensor (``level_step`` times its mean |delta|), codes not
                  clipped: -2..+2 packed as in quinary, where +-2 stands for "2 or more", whose
                  true codes (int8) follow as escapes in entry order. A step per chunk spends
                  the same bits on a chunk that barely moved as on the hash level that moves
                  most, and clips the latter; one step per tensor spends them where the change
                  is, the least squared error for the bytes (on lego, about half quinary's
                  residual at 1/21 of float32; docs/results.md).

**Error feedback, CHOCO-SGD style.** The sender keeps a public copy ``x_hat``: exactly what its
receivers reconstruct. Each delta is ``theta - x_hat``, and ``x_hat`` advances by what was sent,
so what top-k or rounding leaves out now is in the next delta: the sum of what was sent plus the
residual ``theta - x_hat`` is the sum of the true deltas, and nothing is lost for good.

**Bases.** A delta names its base by round and digest (blake2b-64 over the float32 bytes), and
the frame names the digest of the reconstruction, so a receiver never builds a model from a base
it does not hold: it verifies both, and a receiver missing the base (a lost push, a late joiner,
a restart) asks for the sender's ``latest``, which is always the full float32 ``x_hat``.

Frames stay self-describing: the codec's header meta says the mode, chunk, base and digest; the
array table lists per tensor ``<name>/q`` (int8), ``<name>/scale`` (float32) and, for top-k,
``<name>/gaps`` (uint8 [4, k]); a few-level tensor has ``<name>/codes`` (uint8, codes packed in
base 3 or 5) in place of ``q`` and a scale per chunk and level; a uniform one has ``codes``,
``<name>/escapes`` (int8) and two scales. All are checked against the
model spec before any allocation.
Pure Python + numpy; no torch, no zenoh.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass
from typing import Any, Literal, Mapping

import numpy as np

from protocol.messages import MAX_ROUND, CodedTheta, ModelSpec, Rejected, ThetaSnapshot, is_int

MODES = ("none", "fp16", "int8", "delta+int8", "delta+topk", "delta+ternary", "delta+quinary", "delta+uniform")
CODED_MODES = MODES[2:]  # frames with a coded array table
DELTA_MODES = MODES[3:]  # frames that need a base
LEVEL_MODES = {"delta+ternary": 1, "delta+quinary": 2}  # the largest |code|, in steps
UNIFORM = "delta+uniform"
_ESCAPE = 2  # a uniform code of at least this size is packed as +-2, its value an escape
_MAX_CODE = 127
_PACKING = {1: (3, 5), 2: (5, 3)}  # largest |code| -> (base, codes per byte)
META_FIELDS = {"code", "chunk", "base_round", "base", "digest"}
MAX_CHUNK = 1 << 20
_DIGEST_HEX = 16
_NO_BASE = -1  # base_round of a frame without a base


@dataclass
class CompressionConfig:
    """How this robot's snapshots go on the wire (``[daemon.exchange]``).

    The default is ``delta+uniform`` at a step of 2.25: on lego 1/21.7 of float32 within 0.11 dB,
    and in the room no loss, where ``delta+quinary`` (step 2.0) cost 2 dB (docs/results.md).
    float32 (``none``) is lossless but 16 MB a round on lego: on 20 and 5 Mbit/s links the
    robots of a 5-ring never heard each other (Zenoh closes a link whose put stays blocked), and
    each one trained alone (docs/results.md, "Capped links")."""

    compression: Literal["none", "fp16", "int8", "delta+int8", "delta+topk", "delta+ternary", "delta+quinary",
                         "delta+uniform"] = "delta+uniform"
    # delta+topk: the share of each tensor's entries sent per round (the rest waits, error feedback)
    topk_fraction: float = 0.05
    # delta+topk and the level codes: tensors of at most this many entries go whole, as int8 deltas.
    # These are the decoders' weights: every ray passes through them, they are ~0.3% of lego's
    # snapshot, and sending them whole gained 0.65 dB there with top-k at 5% (docs/results.md). 0 = none.
    whole_below: int = 16384
    # delta+ternary/quinary/uniform: the rounding step, in units of each chunk's (uniform: each
    # tensor's) mean |delta|; what rounds to zero stays in the residual and is sent later.
    # delta+uniform at 2.25 keeps lego's snapshot under 1/20 of float32 (quinary was measured at 2.0).
    level_step: float = 2.25
    chunk: int = 1024  # values per scale: smaller follows the hash levels' ranges closer

    def __post_init__(self) -> None:
        if self.compression not in MODES:
            raise ValueError(f"compression must be one of {MODES}, got {self.compression!r}")
        if not 0.0 < self.topk_fraction <= 0.5:
            raise ValueError(f"topk_fraction must be in (0, 0.5], got {self.topk_fraction!r}")
        if not is_int(self.whole_below) or self.whole_below < 0:
            raise ValueError(f"whole_below must be an integer >= 0, got {self.whole_below!r}")
        if not 0.0 < self.level_step <= 8.0:
            raise ValueError(f"level_step must be in (0, 8], got {self.level_step!r}")
        if not is_int(self.chunk) or not 16 <= self.chunk <= MAX_CHUNK:
            raise ValueError(f"chunk must be an integer in [16, {MAX_CHUNK}], got {self.chunk!r}")


def theta_digest(tensors: Mapping[str, np.ndarray]) -> str:
    """blake2b-64 (hex) of names and float32 bytes, in order: what names a base."""
    h = hashlib.blake2b(digest_size=8)
    for name, a in tensors.items():
        h.update(name.encode())
        h.update(np.ascontiguousarray(a, dtype=np.float32).data)
    return h.hexdigest()


# --------------------------------------------------------------------------- quantisation


def quantise(values: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """float32 [n] -> (int8 [n], float32 scales [ceil(n / chunk)]): symmetric, per chunk."""
    blocks = _blocks(values, chunk)
    scale = (np.abs(blocks).max(axis=1) / np.float32(127)).astype(np.float32)
    with np.errstate(divide="ignore"):
        inverse = np.where(scale > 0, np.float32(1) / np.where(scale > 0, scale, 1), 0).astype(np.float32)
    q = np.clip(np.rint(blocks * inverse[:, None]), -127, 127).astype(np.int8).reshape(-1)[: values.size]
    return q, scale


def level_quantise(values: np.ndarray, chunk: int, levels: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    """float32 [n] -> (codes int8 [n] in [-levels, levels], float32 scales [ceil(n / chunk) * levels]).

    Per chunk, values round to multiples of ``step`` x the chunk's mean |value|, clipped to
    ``levels`` steps; code a decodes to the mean |value| of the chunk's entries with code +-a (the
    least squared error for those entries)."""
    blocks = _blocks(values, chunk)
    size = np.full(blocks.shape[0], chunk, np.float32)
    if size.size:
        size[-1] = values.size - chunk * (size.size - 1)  # the last chunk's padding is no value
    magnitude = np.abs(blocks)
    width = step * magnitude.sum(axis=1) / size  # [m]
    with np.errstate(divide="ignore"):
        inverse = np.where(width > 0, 1 / np.where(width > 0, width, 1), 0).astype(np.float32)
    level = np.minimum(np.floor(magnitude * inverse[:, None] + 0.5), levels)  # [m, chunk]
    scales = np.zeros((blocks.shape[0], levels), np.float32)
    for a in range(1, levels + 1):
        at = level == a
        scales[:, a - 1] = (magnitude * at).sum(axis=1) / np.maximum(at.sum(axis=1), 1)
    codes = (np.sign(blocks) * level).astype(np.int8).reshape(-1)[: values.size]
    return codes, scales.reshape(-1)


def uniform_quantise(values: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """float32 [n] -> (codes int8 [n] in [-127, 127], float32 [width, mean |value| at code +-1]).

    The width is ``step`` x the mean |value|, or the largest |value| / 127 if that is more, so no
    entry is clipped (a residual left in a few entries goes out at once). Code +-1 decodes to the
    mean |value| of its entries, not to the width: entries near the mean would otherwise swap
    sign round after round instead of draining; code a >= 2 decodes to a x width."""
    magnitude = np.abs(values)
    width = np.float32(max(step * magnitude.mean(), magnitude.max() / _MAX_CODE)) if values.size else np.float32(0)
    if not width > 0:
        return np.zeros(values.size, np.int8), np.zeros(2, np.float32)
    codes = np.clip(np.rint(values / width), -_MAX_CODE, _MAX_CODE).astype(np.int8)
    ones = np.abs(codes) == 1
    return codes, np.array([width, magnitude[ones].mean() if ones.any() else 0], np.float32)


def uniform_dequantise(codes: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The float32 values both ends compute from (codes, [width, mean at +-1])."""
    magnitude = np.abs(codes.astype(np.float32)) * scales[0]
    return (np.sign(codes) * np.where(np.abs(codes) == 1, scales[1], magnitude)).astype(np.float32)


def split_escapes(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int8 codes [n] -> (codes clipped to +-2 [n], the codes at +-2 or beyond, in order [e])."""
    return np.clip(codes, -_ESCAPE, _ESCAPE), codes[np.abs(codes) >= _ESCAPE]


def join_escapes(clipped: np.ndarray, escapes: np.ndarray, name: str) -> np.ndarray:
    """The inverse of :func:`split_escapes`; escapes that do not fit the codes are refused."""
    at = np.flatnonzero(np.abs(clipped) == _ESCAPE)
    if at.size != escapes.size:
        raise Rejected("bad_shape", f"{name[:64]!r}: {escapes.size} escapes for {at.size} codes of +-2")
    if escapes.size and not ((np.abs(escapes.astype(np.int16)) >= _ESCAPE).all()
                             and (np.sign(escapes) == np.sign(clipped[at])).all()):
        raise Rejected("bad_field", f"{name[:64]!r}: an escape smaller than 2 steps or of the wrong sign")
    out = clipped.copy()
    out[at] = escapes
    return out


def level_dequantise(codes: np.ndarray, scales: np.ndarray, chunk: int, levels: int) -> np.ndarray:
    """The float32 values both ends compute from (codes, scales): bit-identical on either side."""
    blocks = np.zeros(-(-codes.size // chunk) * chunk, np.int8)
    blocks[: codes.size] = codes
    blocks = blocks.reshape(-1, chunk)  # [m, chunk]
    per_level = scales.reshape(-1, levels)  # [m, levels]
    magnitude = np.zeros(blocks.shape, np.float32)
    for a in range(1, levels + 1):
        magnitude += (np.abs(blocks) == a) * per_level[:, a - 1 : a]
    return (np.sign(blocks) * magnitude).astype(np.float32).reshape(-1)[: codes.size]


def _blocks(values: np.ndarray, chunk: int) -> np.ndarray:
    """float32 [n] -> [ceil(n / chunk), chunk], zero-padded."""
    m = -(-values.size // chunk)
    padded = np.zeros(m * chunk, dtype=np.float32)
    padded[: values.size] = values
    return padded.reshape(m, chunk)


def dequantise(q: np.ndarray, scale: np.ndarray, chunk: int) -> np.ndarray:
    """The float32 values both ends compute from (q, scale): bit-identical on either side."""
    return q.astype(np.float32) * np.repeat(scale, chunk)[: q.size]


def pack_codes(codes: np.ndarray, levels: int) -> np.ndarray:
    """int8 codes [n] in [-levels, levels] -> uint8 [ceil(n / per)]: ``per`` base-(2 levels + 1)
    digits a byte (5 ternary, 3 quinary), so zstd's byte-wise entropy coder sees their joint law."""
    base, per = _PACKING[levels]
    digits = np.zeros(-(-codes.size // per) * per, np.uint8)
    digits[: codes.size] = np.where(codes < 0, codes + base, codes)  # -a -> base - a
    digits = digits.reshape(-1, per)
    packed = np.zeros(digits.shape[0], np.uint8)
    for k in range(per):  # uint8 all along: at most 2 * 81 + ... = 242 (ternary), 124 (quinary)
        packed += digits[:, k] * np.uint8(base**k)
    return packed


def _unpack_table(levels: int) -> np.ndarray:
    """[256, per] int8: the codes each byte packs (bytes that pack none: never looked up)."""
    base, per = _PACKING[levels]
    digits = (np.arange(256)[:, None] // base ** np.arange(per)) % base
    return np.where(digits > levels, digits - base, digits).astype(np.int8)


_UNPACK = {levels: _unpack_table(levels) for levels in _PACKING}


def unpack_codes(packed: np.ndarray, size: int, levels: int, name: str) -> np.ndarray:
    """uint8 [ceil(size / per)] -> int8 codes [size]; a byte that packs no ``per`` digits is refused."""
    base, per = _PACKING[levels]
    if packed.size and int(packed.max()) >= base**per:
        raise Rejected("bad_field", f"{name[:64]!r}: a byte of codes above {base**per - 1}")
    return _UNPACK[levels][packed].reshape(-1)[:size]


def _gap_planes(index: np.ndarray) -> np.ndarray:
    """Sorted indices [k] -> gaps as uint8 byte planes [4, k] (high planes are zeros: zstd packs them)."""
    gaps = np.diff(index, prepend=0).astype("<u4")
    return np.ascontiguousarray(gaps.view(np.uint8).reshape(-1, 4).T)


def _indices(planes: np.ndarray, size: int, name: str) -> np.ndarray:
    """Byte planes [4, k] -> strictly increasing indices below ``size``; hostile ones refused."""
    gaps = np.ascontiguousarray(planes.T).view("<u4").reshape(-1).astype(np.int64)
    if gaps.size and ((gaps[1:] < 1).any() or gaps.sum() >= size):
        raise Rejected("bad_field", f"{name[:64]!r}: top-k indices not increasing or beyond {size} entries")
    return np.cumsum(gaps)


# --------------------------------------------------------------------------- encoding

#: How one tensor is coded: ("q", n) int8 values, ("topk", k) k of them with their gaps, ("codes", n)
#: few-level codes (their number from the mode), ("uniform", e) uniform codes with e escapes.
Form = tuple[str, int]


def _code_tensor(mode: str, name: str, delta: np.ndarray, cfg: CompressionConfig
                 ) -> tuple[list[tuple[str, np.ndarray, str]], np.ndarray]:
    """One tensor's arrays and the float32 delta [n] they decode to."""
    flat = delta.reshape(-1)
    levels = LEVEL_MODES.get(mode)
    if mode == UNIFORM and flat.size > cfg.whole_below:
        codes, scales = uniform_quantise(flat, cfg.level_step)
        clipped, escapes = split_escapes(codes)
        return [(f"{name}/codes", pack_codes(clipped, _ESCAPE), "uint8"), (f"{name}/escapes", escapes, "int8"),
                (f"{name}/scale", scales, "float32")], uniform_dequantise(codes, scales)
    if levels and flat.size > cfg.whole_below:
        codes, scale = level_quantise(flat, cfg.chunk, levels, cfg.level_step)
        return [(f"{name}/codes", pack_codes(codes, levels), "uint8"), (f"{name}/scale", scale, "float32")], \
            level_dequantise(codes, scale, cfg.chunk, levels)
    if mode != "delta+topk":
        q, scale = quantise(flat, cfg.chunk)
        return [(f"{name}/q", q, "int8"), (f"{name}/scale", scale, "float32")], dequantise(q, scale, cfg.chunk)
    share = flat.size if flat.size <= cfg.whole_below else math.ceil(cfg.topk_fraction * flat.size)
    k = min(share, int(np.count_nonzero(flat)))
    index = np.sort(np.argpartition(-np.abs(flat), k - 1)[:k]) if k else np.zeros(0, np.int64)
    q, scale = quantise(flat[index], cfg.chunk)
    decoded = np.zeros_like(flat)
    decoded[index] = dequantise(q, scale, cfg.chunk)
    return [(f"{name}/gaps", _gap_planes(index), "uint8"), (f"{name}/q", q, "int8"),
            (f"{name}/scale", scale, "float32")], decoded


def code_snapshot(msg: ThetaSnapshot, cfg: CompressionConfig, base: tuple[int, str, Mapping[str, np.ndarray]] | None
                  ) -> tuple[ThetaSnapshot, dict[str, np.ndarray]]:
    """(coded snapshot, the float32 tensors a receiver reconstructs from it).

    ``base`` = (round, digest, tensors) for a delta mode; its tensors are what the receivers hold.
    """
    mode = cfg.compression
    if mode not in CODED_MODES:
        raise ValueError(f"{mode!r} is not a coded mode")
    if (base is None) == (mode in DELTA_MODES):
        raise ValueError(f"{mode}: a base is {'needed' if base is None else 'not used'}")
    arrays: dict[str, np.ndarray] = {}
    recon: dict[str, np.ndarray] = {}
    for name, t in msg.tensors.items():
        a = np.asarray(t, dtype=np.float32)
        start = np.asarray(base[2][name], dtype=np.float32) if base is not None else np.zeros_like(a)
        parts, decoded = _code_tensor(mode, name, a - start, cfg)
        arrays.update({n: v for n, v, _ in parts})
        recon[name] = (start.reshape(-1) + decoded).reshape(a.shape) if base is not None else decoded.reshape(a.shape)
    coded = CodedTheta(mode=mode, chunk=cfg.chunk, base_round=base[0] if base else _NO_BASE,
                       base_digest=base[1] if base else "", digest=theta_digest(recon), arrays=arrays)
    return ThetaSnapshot(msg.swarm, msg.sender, msg.round, msg.epoch, msg.signature, {}, coded=coded), recon


def coded_arrays(coded: CodedTheta, spec: ModelSpec) -> list[tuple[str, np.ndarray, str]]:
    """(name, array, wire dtype) in table order, checked against the spec (for our own sends)."""
    out = []
    for name, dtype, shape in coded_layout(coded.mode, coded.chunk, spec, _sent_forms(coded, spec)):
        a = coded.arrays.get(name)
        if a is None or tuple(a.shape) != shape:
            raise ValueError(f"coded array {name!r} missing or not of shape {shape}")
        out.append((name, a, dtype))
    return out


def _sent_forms(coded: CodedTheta, spec: ModelSpec) -> list[Form]:
    if coded.mode == "delta+topk":
        return [("topk", int(np.shape(coded.arrays[f"{p.name}/q"])[0])) for p in spec.params]
    if coded.mode == UNIFORM:
        return [("uniform", int(np.shape(coded.arrays[f"{p.name}/escapes"])[0])) if f"{p.name}/escapes" in coded.arrays
                else ("q", p.size) for p in spec.params]
    return [("codes" if f"{p.name}/codes" in coded.arrays else "q", p.size) for p in spec.params]


def coded_meta(coded: CodedTheta) -> dict[str, Any]:
    return {"code": coded.mode, "chunk": coded.chunk, "base_round": coded.base_round, "base": coded.base_digest,
            "digest": coded.digest}


# --------------------------------------------------------------------------- decoding checks


def coded_layout(mode: str, chunk: int, spec: ModelSpec, forms: list[Form]) -> list[tuple[str, str, tuple[int, ...]]]:
    """The array table a coded frame must have: per tensor (name, wire dtype, shape)."""
    table = []
    for p, (form, k) in zip(spec.params, forms):
        if form == "topk":
            table.append((f"{p.name}/gaps", "uint8", (4, k)))
        if form == "uniform":
            table += [(f"{p.name}/codes", "uint8", (-(-p.size // _PACKING[_ESCAPE][1]),)),
                      (f"{p.name}/escapes", "int8", (k,)), (f"{p.name}/scale", "float32", (2,))]
        elif form == "codes":
            levels = LEVEL_MODES[mode]
            table += [(f"{p.name}/codes", "uint8", (-(-k // _PACKING[levels][1]),)),
                      (f"{p.name}/scale", "float32", (-(-k // chunk) * levels,))]
        else:
            table += [(f"{p.name}/q", "int8", (k,)), (f"{p.name}/scale", "float32", (-(-k // chunk),))]
    return table


def check_meta(meta: Any) -> CodedTheta | None:
    """A theta frame's meta: {} for a plain one, else the coding; the arrays come later."""
    if not isinstance(meta, dict):
        raise Rejected("bad_header", "meta is not a map")
    if not meta:
        return None
    if set(meta) != META_FIELDS:
        raise Rejected("bad_field", f"theta meta must be empty or have exactly {sorted(META_FIELDS)}")
    mode, chunk, base_round, base, digest = (meta[k] for k in ("code", "chunk", "base_round", "base", "digest"))
    if mode not in CODED_MODES:
        raise Rejected("bad_encoding", f"unknown snapshot code, want one of {CODED_MODES}")
    if not is_int(chunk) or not 16 <= chunk <= MAX_CHUNK:
        raise Rejected("bad_field", f"chunk must be an integer in [16, {MAX_CHUNK}]")
    if not (isinstance(digest, str) and len(digest) == _DIGEST_HEX and isinstance(base, str)):
        raise Rejected("bad_field", "digest must be a 16-character string, base a string")
    delta = mode in DELTA_MODES
    if not is_int(base_round) or not (_NO_BASE <= base_round <= MAX_ROUND if delta else base_round == _NO_BASE) \
            or (len(base) == _DIGEST_HEX) != delta or (not delta and base):
        raise Rejected("bad_field", f"{mode}: base_round and base do not fit the code")
    return CodedTheta(mode=mode, chunk=chunk, base_round=base_round, base_digest=base, digest=digest, arrays={})


def check_coded_table(entries: list[tuple[str, str, tuple[int, ...]]], coded: CodedTheta, spec: ModelSpec) -> None:
    """The header's array table against the spec, before any payload byte is read."""
    forms = _received_forms(entries, coded, spec)
    want = coded_layout(coded.mode, coded.chunk, spec, forms)
    if len(entries) != len(want):
        raise Rejected("bad_shape", f"{len(entries)} coded arrays, the spec's {len(spec.params)} tensors need {len(want)}")
    for got, expected in zip(entries, want):
        if got != expected:
            raise Rejected("bad_shape", f"coded array {got[0][:64]!r} {got[1]} {list(got[2])[:4]}, "
                                        f"want {expected[0]!r} {expected[1]} {list(expected[2])}")


def _received_forms(entries: list[tuple[str, str, tuple[int, ...]]], coded: CodedTheta, spec: ModelSpec) -> list[Form]:
    """Each tensor's form as the table states it (top-k counts, few-level codes or int8), within the spec."""
    forms: list[Form] = []
    pos = 0
    for p in spec.params:
        first = entries[pos] if pos < len(entries) else ("", "", ())
        if coded.mode == "delta+topk":
            shape = entries[pos + 1][2] if pos + 1 < len(entries) else ()
            if len(shape) != 1 or shape[0] > p.size:
                raise Rejected("bad_shape", f"tensor {p.name!r}: {list(shape)[:4]} coded values for {p.size} entries")
            forms.append(("topk", shape[0]))
            pos += 3
        elif coded.mode == UNIFORM and first[0] == f"{p.name}/codes":
            shape = entries[pos + 1][2] if pos + 1 < len(entries) else ()
            if len(shape) != 1 or shape[0] > p.size:
                raise Rejected("bad_shape", f"tensor {p.name!r}: {list(shape)[:4]} escapes for {p.size} entries")
            forms.append(("uniform", shape[0]))
            pos += 3
        else:
            few = coded.mode in LEVEL_MODES and first[0] == f"{p.name}/codes"
            forms.append(("codes" if few else "q", p.size))
            pos += 2
    return forms


def check_coded_values(arrays: dict[str, np.ndarray], coded: CodedTheta, spec: ModelSpec) -> CodedTheta:
    """After decompression: scales non-negative, top-k indices in range, code bytes valid
    (indices and codes stored decoded)."""
    out: dict[str, np.ndarray] = {}
    for p in spec.params:
        scale = arrays[f"{p.name}/scale"]
        if scale.size and not (scale >= 0).all():
            raise Rejected("bad_field", f"{p.name[:64]!r}: negative scale")
        out[f"{p.name}/scale"] = scale
        if coded.mode == UNIFORM and f"{p.name}/codes" in arrays:
            out[f"{p.name}/codes"], out[f"{p.name}/escapes"] = arrays[f"{p.name}/codes"], arrays[f"{p.name}/escapes"]
            out[f"{p.name}/levels"] = join_escapes(unpack_codes(arrays[f"{p.name}/codes"], p.size, _ESCAPE, p.name),
                                                   arrays[f"{p.name}/escapes"], p.name)
        elif f"{p.name}/codes" in arrays:
            out[f"{p.name}/codes"] = arrays[f"{p.name}/codes"]
            out[f"{p.name}/levels"] = unpack_codes(arrays[f"{p.name}/codes"], p.size, LEVEL_MODES[coded.mode], p.name)
        else:
            out[f"{p.name}/q"] = arrays[f"{p.name}/q"]
        if coded.mode == "delta+topk":
            out[f"{p.name}/index"] = _indices(arrays[f"{p.name}/gaps"], p.size, p.name)
            out[f"{p.name}/gaps"] = arrays[f"{p.name}/gaps"]
    return CodedTheta(coded.mode, coded.chunk, coded.base_round, coded.base_digest, coded.digest, out)


def reconstruct(coded: CodedTheta, spec: ModelSpec, base: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """The float32 tensors of a checked coded snapshot (its base's for a delta); digest verified."""
    out = {}
    for p in spec.params:
        if coded.mode == UNIFORM and f"{p.name}/levels" in coded.arrays:
            decoded = uniform_dequantise(coded.arrays[f"{p.name}/levels"], coded.arrays[f"{p.name}/scale"])
        elif f"{p.name}/levels" in coded.arrays:
            decoded = level_dequantise(coded.arrays[f"{p.name}/levels"], coded.arrays[f"{p.name}/scale"], coded.chunk,
                                       LEVEL_MODES[coded.mode])
        else:
            decoded = dequantise(coded.arrays[f"{p.name}/q"], coded.arrays[f"{p.name}/scale"], coded.chunk)
        if coded.mode == "delta+topk":
            full = np.zeros(p.size, np.float32)
            full[coded.arrays[f"{p.name}/index"]] = decoded
            decoded = full
        t = decoded if base is None else np.asarray(base[p.name], dtype=np.float32).reshape(-1) + decoded
        out[p.name] = t.reshape(p.shape)
    if any(t.size and not np.isfinite(t).all() for t in out.values()):
        raise Rejected("non_finite", "the reconstructed snapshot overflows")
    if theta_digest(out) != coded.digest:
        raise Rejected("bad_checksum", "the reconstructed snapshot differs from the sender's (digest)")
    return out


# --------------------------------------------------------------------------- both ends


class BaseBook:
    """Receiver side: per sender the newest full model we hold of it, the base its deltas name.

    A plain float32 snapshot (a push in mode ``none``, every ``latest`` reply) or a reconstruction
    becomes the sender's base once it is newer than the one held. Thread-safe (Zenoh callbacks and
    pullers both resolve).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: dict[int, tuple[int, dict[str, np.ndarray], list[str]]] = {}  # sender -> (round, tensors, [digest])

    def seed(self, sender: int, tensors: Mapping[str, np.ndarray]) -> None:
        """A base held before round 0 (theta^0, the same on every robot that shares the init seed)."""
        with self._lock:
            self._held.setdefault(sender, (_NO_BASE, dict(tensors), []))

    def held_round(self, sender: int) -> int | None:
        with self._lock:
            held = self._held.get(sender)
            return None if held is None else held[0]

    def held(self, sender: int) -> tuple[int, str] | None:
        """(round, digest) of the base held for ``sender``: to check it is the sender's public copy."""
        with self._lock:
            held = self._held.get(sender)
            return None if held is None else (held[0], self._digest(held))

    def resolve(self, msg: ThetaSnapshot, spec: ModelSpec) -> ThetaSnapshot | Literal["missing", "old"]:
        """The snapshot with its float32 tensors, or why not: ``missing`` base (ask for a full
        one) or ``old`` (a newer model of that sender is held already: nothing to do)."""
        coded = msg.coded
        with self._lock:
            held = self._held.get(msg.sender)
            if coded is not None and coded.mode in DELTA_MODES:
                if held is not None and msg.round <= held[0]:
                    return "old"
                if held is None or held[0] != coded.base_round or self._digest(held) != coded.base_digest:
                    return "missing"
                tensors = reconstruct(coded, spec, held[1])
            elif coded is not None:
                tensors = reconstruct(coded, spec, None)
            else:
                tensors = msg.tensors
            out = ThetaSnapshot(msg.swarm, msg.sender, msg.round, msg.epoch, msg.signature, tensors, msg.header)
            lossless = coded is not None or msg.header is None or msg.header.wire_dtype == "float32"
            newer = held is None or msg.round > held[0] or (coded is None and msg.round == held[0])
            if lossless and newer:  # a plain frame of the held round is the sender's own word on it
                self._held[msg.sender] = (msg.round, tensors, [coded.digest] if coded is not None else [])
            return out

    @staticmethod
    def _digest(held: tuple[int, dict[str, np.ndarray], list[str]]) -> str:
        if not held[2]:  # computed once, and only when a delta names it
            held[2].append(theta_digest(held[1]))
        return held[2][0]


class SnapshotEncoder:
    """Sender side: the frames of one snapshot, and the public copy ``x_hat`` its deltas start from.

    ``encode`` returns (push, full): the frame for the neighbours, and the lossless float32 frame
    of what they hold after it, served as ``latest`` to whoever lacks the base. The first frame
    of a delta mode, without a base yet, is a full one.
    """

    def __init__(self, cfg: CompressionConfig) -> None:
        self.cfg = cfg
        self._public: tuple[int, str, dict[str, np.ndarray]] | None = None  # (round, digest, x_hat)
        self._lossy: tuple[int, dict[str, np.ndarray]] | None = None  # the last frame as received, if lossy

    def seed(self, tensors: Mapping[str, np.ndarray]) -> None:
        """Start from a base every receiver holds (theta^0, see :meth:`BaseBook.seed`)."""
        copy = {n: np.array(t, dtype=np.float32) for n, t in tensors.items()}
        self._public = (_NO_BASE, theta_digest(copy), copy)

    def public(self) -> tuple[int, str] | None:
        """(round, digest) of ``x_hat``, what every receiver up to date holds of us (delta modes)."""
        if self._public is None:
            return None
        return self._public[0], self._public[1] or theta_digest(self._public[2])

    def held_by_receivers(self) -> tuple[int, dict[str, np.ndarray]] | None:
        """(round, tensors) of our newest snapshot as its receivers rebuild it, when a lossy mode
        makes that differ from theta (C-ADMM runs on it, so both ends of an edge price the same
        disagreement); None for lossless frames or before the first one."""
        return self._lossy

    def encode(self, msg: ThetaSnapshot, spec: ModelSpec, compression: str, wire_dtype: str = "float32"
               ) -> tuple[bytes, bytes]:
        from protocol import codec  # codec imports this module for its checks

        mode = self.cfg.compression
        self._lossy = None
        if mode in ("none", "fp16"):
            dtype = "float16" if mode == "fp16" else wire_dtype
            data = codec.encode(msg, wire_dtype=dtype, compression=compression, spec=spec)
            if dtype == "float16":
                self._lossy = (msg.round, {n: np.asarray(t, np.float32).astype(np.float16).astype(np.float32)
                                           for n, t in msg.tensors.items()})
            return data, data
        if mode == "int8":
            coded, recon = code_snapshot(msg, self.cfg, None)
            self._lossy = (msg.round, recon)
            data = codec.encode(coded, compression=compression, spec=spec)
            return data, data
        if self._public is None:
            full = codec.encode(msg, compression=compression, spec=spec)
            tensors = {n: np.array(t, dtype=np.float32) for n, t in msg.tensors.items()}
            self._public = (msg.round, "", tensors)
            return full, full
        base_round, digest, x_hat = self._public
        coded, recon = code_snapshot(msg, self.cfg, (base_round, digest or theta_digest(x_hat), x_hat))
        push = codec.encode(coded, compression=compression, spec=spec)
        full = codec.encode(ThetaSnapshot(msg.swarm, msg.sender, msg.round, msg.epoch, msg.signature, recon),
                            compression=compression, spec=spec)
        self._public = (msg.round, coded.coded.digest, recon)
        self._lossy = (msg.round, recon)
        return push, full
