"""Compressed snapshots: round trips of every mode, error feedback, bases, fallback, hostile frames."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from protocol import codec
from protocol.compression import (LEVEL_MODES, MODES, BaseBook, CompressionConfig, SnapshotEncoder, code_snapshot,
                                  pack_codes, theta_digest, unpack_codes)
from protocol.exchange import ExchangeTiming, SnapshotExchange
from protocol.keys import Keys
from protocol.loopback import LoopbackHub, LoopbackNetwork
from protocol.membership import LastHeard
from protocol.messages import Rejected, ThetaSnapshot
from protocol.rounds import Mailbox
from tests.protocol.helpers import SWARM, expectation, reframe, small_spec, small_tensors, snapshot, split_frame

SPEC = small_spec()
CHUNK = 16


def _cfg(mode: str, fraction: float = 0.25) -> CompressionConfig:
    """Top-k on every tensor, however small (the small spec's tensors are all below the default)."""
    return CompressionConfig(compression=mode, topk_fraction=fraction, chunk=CHUNK, whole_below=0)


def _step(theta: dict[str, np.ndarray], rng: np.random.Generator, scale: float = 0.05) -> dict[str, np.ndarray]:
    """theta after a round of training: every entry moves a little, a few a lot."""
    out = {}
    for n, a in theta.items():
        d = rng.standard_normal(a.shape).astype(np.float32) * scale
        d[rng.random(a.shape) < 0.1] *= 20
        out[n] = (a + d).astype(np.float32)
    return out


def _send(enc: SnapshotEncoder, book: BaseBook, tensors: dict[str, np.ndarray], r: int) -> tuple[ThetaSnapshot, int]:
    """Encode round r's snapshot, decode it as a receiver would, resolve it against the receiver's bases."""
    msg = ThetaSnapshot(SWARM, 1, r, 0, SPEC.signature(), tensors)
    push, _ = enc.encode(msg, SPEC, "zstd")
    got = book.resolve(codec.decode(push, expectation(), kind="theta"), SPEC)
    assert isinstance(got, ThetaSnapshot), got
    return got, len(push)


def _chunk_bound(values: np.ndarray) -> np.ndarray:
    """Per entry, half an int8 step of its chunk (the largest rounding error), plus float slack."""
    flat = values.reshape(-1)
    pad = np.zeros(-(-flat.size // CHUNK) * CHUNK, np.float32)
    pad[: flat.size] = np.abs(flat)
    step = pad.reshape(-1, CHUNK).max(axis=1) / 127
    return (np.repeat(step / 2, CHUNK)[: flat.size] * 1.0001 + 1e-6).reshape(values.shape)


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_round_trips_within_its_quantisation_error(mode):
    rng = np.random.default_rng(1)
    base = small_tensors(0)
    x = _step(base, rng)
    enc, book = SnapshotEncoder(_cfg(mode)), BaseBook()
    enc.seed(base)
    book.seed(1, base)
    got, _ = _send(enc, book, x, 3)
    for n, want in x.items():
        err = np.abs(got.tensors[n] - want)
        if mode == "none":
            assert got.tensors[n].tobytes() == want.tobytes()
        elif mode == "fp16":
            assert (err <= np.abs(want) * 2**-11 + 1e-7).all()
        elif mode == "int8":
            assert (err <= _chunk_bound(want)).all()
        elif mode == "delta+int8":
            assert (err <= _chunk_bound(want - base[n])).all() and err.max() > 0
        elif mode == "delta+uniform":  # every entry within the tensor's one step (half of it past +-1)
            delta = want - base[n]
            step = _cfg(mode).level_step * np.abs(delta).mean()
            assert err.max() > 0 and (err <= step * 1.0001 + 1e-6).all()
            assert (err[np.abs(delta) >= 1.5 * step] <= step / 2 * 1.0001 + 1e-6).all()
        elif mode in LEVEL_MODES:  # every entry moved by one of a chunk's few steps, towards theta
            delta = (want - base[n]).reshape(-1)
            moved = (got.tensors[n] - base[n]).reshape(-1)
            chunks = -(-delta.size // CHUNK)
            assert len(np.unique(np.abs(moved[moved != 0]).round(5))) <= chunks * LEVEL_MODES[mode]  # up to float error
            assert (np.sign(moved[moved != 0]) == np.sign(delta[moved != 0])).all()
            assert np.square(err).sum() < np.square(delta).sum() / 2
        else:  # top-k: the largest quarter of |delta| sent, within int8 error; the rest still the base
            delta = (want - base[n]).reshape(-1)
            sent = np.flatnonzero(got.tensors[n].reshape(-1) != base[n].reshape(-1))
            k = int(np.ceil(0.25 * delta.size))
            assert len(sent) <= k and np.abs(delta[sent]).min() >= np.sort(np.abs(delta))[-k] - 1e-6
            assert (err.reshape(-1)[sent] <= np.abs(delta).max() / 254 * 1.0001 + 1e-6).all()


def test_a_delta_costs_a_fraction_of_float32_and_untouched_entries_nothing():
    rng = np.random.default_rng(2)
    big = {"grid.table": rng.standard_normal((4096, 2)).astype(np.float32)}
    spec = type(SPEC).from_tensors(big)
    touched = {"grid.table": big["grid.table"].copy()}
    touched["grid.table"][:100] += 0.5  # 100 of 4096 hash entries saw data this round
    sizes = {}
    for mode in ("none", "delta+int8", "delta+topk"):
        enc = SnapshotEncoder(CompressionConfig(compression=mode, topk_fraction=0.05))
        enc.seed(big)
        sizes[mode] = len(enc.encode(ThetaSnapshot(SWARM, 1, 1, 0, spec.signature(), touched), spec, "zstd")[0])
    assert sizes["delta+int8"] < sizes["none"] / 20 and sizes["delta+topk"] < sizes["none"] / 20, sizes


def test_topk_sends_small_tensors_whole_and_the_table_by_its_share():
    """The decoders' weights go whole every round (every ray depends on them); a large table sends
    only its share, and the receiver rebuilds both from the same frame."""
    rng = np.random.default_rng(5)
    theta0 = {"grid.table": rng.standard_normal((20000, 2)).astype(np.float32),
              "mlp.0.weight": rng.standard_normal((64, 32)).astype(np.float32)}
    spec = type(SPEC).from_tensors(theta0)
    theta1 = _step(theta0, rng)
    cfg = CompressionConfig(compression="delta+topk", topk_fraction=0.05, chunk=CHUNK)
    coded, recon = code_snapshot(ThetaSnapshot(SWARM, 1, 3, 0, spec.signature(), theta1), cfg,
                                 (2, theta_digest(theta0), theta0))
    assert coded.coded.arrays["mlp.0.weight/q"].size == 64 * 32
    assert coded.coded.arrays["grid.table/q"].size == 2000
    assert np.abs(recon["mlp.0.weight"] - theta1["mlp.0.weight"]).max() < 0.02  # int8 rounding only
    assert (recon["grid.table"] != theta0["grid.table"]).sum() == 2000


@pytest.mark.parametrize("mode", ["delta+int8", "delta+topk", "delta+ternary", "delta+quinary", "delta+uniform"])
def test_error_feedback_what_is_not_sent_now_is_sent_later(mode):
    """sum of the deltas received + the residual kept == sum of the true deltas; and once theta stops
    moving, the residual drains to the rounding error of the last steps."""
    rng = np.random.default_rng(3)
    theta0 = small_tensors(0)
    enc, book = SnapshotEncoder(_cfg(mode, fraction=0.1)), BaseBook()
    enc.seed(theta0)
    book.seed(1, theta0)
    theta, held = theta0, theta0
    received = {n: np.zeros(a.shape, np.float64) for n, a in theta0.items()}
    for r in range(8):
        theta = _step(theta, rng)
        got, _ = _send(enc, book, theta, r)
        for n in theta:
            received[n] += got.tensors[n].astype(np.float64) - held[n]
        held = got.tensors
    for n in theta:
        residual = theta[n].astype(np.float64) - held[n]
        truth = theta[n].astype(np.float64) - theta0[n]
        assert np.allclose(received[n] + residual, truth, atol=1e-5), n
    before = max(float(np.abs(theta[n] - held[n]).max()) for n in theta)
    for r in range(8, 40):  # theta stands still: the residual goes out, round by round
        held = _send(enc, book, theta, r)[0].tensors
    after = max(float(np.abs(theta[n] - held[n]).max()) for n in theta)
    assert before > (0.0 if mode == "delta+int8" else 0.05) and after <= before / 100, (before, after)


@pytest.mark.parametrize("levels, per, top", [(1, 5, 242), (2, 3, 124)])
def test_codes_pack_several_to_a_byte_and_bytes_that_pack_none_are_refused(levels, per, top):
    rng = np.random.default_rng(7)
    codes = rng.integers(-levels, levels + 1, size=1003).astype(np.int8)
    packed = pack_codes(codes, levels)
    assert packed.dtype == np.uint8 and packed.size == -(-1003 // per) and packed.max() <= top
    assert (unpack_codes(packed, codes.size, levels, "t") == codes).all()
    with pytest.raises(Rejected) as exc:
        unpack_codes(np.array([top + 1], np.uint8), per, levels, "t")
    assert exc.value.reason == "bad_field"


def test_ternary_costs_under_a_twentieth_and_keeps_every_entry_within_a_round_of_theta():
    """On a table moving everywhere a little each round (Laplace steps), the ternary deltas stay
    under 1/20 of float32 with zstd, and the receivers' copy lags theta by less than one round's
    move, where top-k at fewer bytes lets the lag grow round after round."""
    rng = np.random.default_rng(11)
    theta0 = {"grid.table": (rng.standard_normal((1 << 18, 2)) * 1e-2).astype(np.float32)}
    spec = type(SPEC).from_tensors(theta0)
    lag = {}
    for mode in ("delta+ternary", "delta+topk"):
        enc = SnapshotEncoder(CompressionConfig(compression=mode, topk_fraction=0.05))
        enc.seed(theta0)
        theta, sizes = theta0, []
        for r in range(1, 6):
            theta = {"grid.table": theta["grid.table"] + rng.laplace(size=(1 << 18, 2)).astype(np.float32) * 1e-3}
            sizes.append(len(enc.encode(ThetaSnapshot(SWARM, 1, r, 0, spec.signature(), theta), spec, "zstd")[0]))
            held = enc.held_by_receivers()
            assert held is not None and held[0] == r
        lag[mode] = float(np.sqrt(np.mean(np.square(theta["grid.table"] - held[1]["grid.table"]))))
        if mode == "delta+ternary":
            assert max(sizes) < 4 * spec.num_values / 20, sizes
    one_round = np.sqrt(2) * 1e-3  # the rms of one round's Laplace move
    assert lag["delta+ternary"] < one_round < lag["delta+topk"], lag


def test_uniform_spends_the_bytes_where_the_table_moves():
    """A table whose first level moves 100x more than the rest: one step per tensor leaves a
    fraction of the quinary code's residual (which clips that level) in fewer bytes."""
    rng = np.random.default_rng(12)
    theta0 = {"grid.table": np.zeros((1 << 17, 2), np.float32)}
    spec = type(SPEC).from_tensors(theta0)
    scale = np.full((1 << 17, 1), 1e-5, np.float32)
    scale[: 1 << 14] = 1e-3  # the coarse level: every ray passes through it
    lag, sizes = {}, {}
    for mode in ("delta+quinary", "delta+uniform"):
        enc = SnapshotEncoder(CompressionConfig(compression=mode))
        enc.seed(theta0)
        theta, sizes[mode] = theta0, 0
        for r in range(1, 6):
            theta = {"grid.table": theta["grid.table"] + rng.laplace(size=(1 << 17, 2)).astype(np.float32) * scale}
            sizes[mode] += len(enc.encode(ThetaSnapshot(SWARM, 1, r, 0, spec.signature(), theta), spec, "zstd")[0])
        lag[mode] = float(np.sqrt(np.mean(np.square(theta["grid.table"] - enc.held_by_receivers()[1]["grid.table"]))))
    assert sizes["delta+uniform"] < sizes["delta+quinary"] and lag["delta+uniform"] < lag["delta+quinary"] / 2, (sizes, lag)


def test_lossless_frames_leave_nothing_held_apart_from_theta():
    enc = SnapshotEncoder(CompressionConfig(compression="none"))
    enc.encode(snapshot(), SPEC, "zstd")
    assert enc.held_by_receivers() is None
    enc16 = SnapshotEncoder(CompressionConfig(compression="fp16"))
    enc16.encode(snapshot(), SPEC, "zstd")
    r, held = enc16.held_by_receivers()
    assert r == snapshot().round and all(held[n].tobytes() == snapshot().tensors[n].astype(np.float16)
                                         .astype(np.float32).tobytes() for n in held)


def test_a_receiver_without_the_base_is_told_so_and_never_builds_a_model():
    theta0, theta1 = small_tensors(0), small_tensors(1)
    enc = SnapshotEncoder(_cfg("delta+int8"))
    enc.seed(theta0)
    push, full = enc.encode(ThetaSnapshot(SWARM, 1, 4, 0, SPEC.signature(), theta1), SPEC, "zstd")
    msg = codec.decode(push, expectation(), kind="theta")
    assert BaseBook().resolve(msg, SPEC) == "missing"  # a late joiner, a restart
    other = BaseBook()
    other.seed(1, small_tensors(2))  # another theta^0: the digest tells
    assert other.resolve(msg, SPEC) == "missing"
    late = BaseBook()
    got = late.resolve(codec.decode(full, expectation(), kind="theta"), SPEC)  # the latest: lossless x_hat
    assert isinstance(got, ThetaSnapshot) and late.held_round(1) == 4
    assert late.resolve(msg, SPEC) == "old"  # the push of that round, after the full one: nothing to do
    enc_next = enc.encode(ThetaSnapshot(SWARM, 1, 5, 0, SPEC.signature(), small_tensors(3)), SPEC, "zstd")[0]
    nxt = late.resolve(codec.decode(enc_next, expectation(), kind="theta"), SPEC)
    assert isinstance(nxt, ThetaSnapshot) and theta_digest(nxt.tensors) == nxt_digest(enc_next)


def nxt_digest(frame: bytes) -> str:
    return split_frame(frame)[0]["meta"]["digest"]


def test_a_reconstruction_that_differs_from_the_senders_is_refused():
    theta0 = small_tensors(0)
    coded, _ = code_snapshot(snapshot(), _cfg("delta+int8"), (2, theta_digest(theta0), theta0))
    coded.coded.digest = "f" * 16  # the sender claims another model than the delta builds
    book = BaseBook()
    book.seed(1, theta0)
    coded.coded.base_round = -1
    coded.coded.base_digest = theta_digest(theta0)
    msg = codec.decode(codec.encode(coded, spec=SPEC), expectation(), kind="theta")
    with pytest.raises(Rejected) as exc:
        book.resolve(msg, SPEC)
    assert exc.value.reason == "bad_checksum"


def _topk_frame(**changes) -> tuple[ThetaSnapshot, bytes]:
    theta0 = small_tensors(1)
    coded, _ = code_snapshot(snapshot(), _cfg("delta+topk"), (2, theta_digest(theta0), theta0))
    for name, value in changes.items():
        coded.coded.arrays[name] = value
    return coded, codec.encode(coded, spec=SPEC, compression="none")


def _ternary_frame(short: bool = False, **changes) -> tuple[ThetaSnapshot, bytes]:
    """A delta+ternary frame (the table ternary, the 8 biases int8); ``None`` values become bytes of 255."""
    theta0 = small_tensors(1)
    cfg = CompressionConfig(compression="delta+ternary", chunk=CHUNK, whole_below=8)
    coded, _ = code_snapshot(snapshot(), cfg, (2, theta_digest(theta0), theta0))
    assert "grid.table/codes" in coded.coded.arrays and "mlp.0.bias/q" in coded.coded.arrays
    for name, value in changes.items():
        coded.coded.arrays[name] = np.full_like(coded.coded.arrays[name], 255) if value is None else value
    data = codec.encode(coded, spec=SPEC, compression="none")
    if short:  # the table's codes one byte short, the header saying so
        header, payload = split_frame(data)
        arrays = [list(e) for e in header["arrays"]]
        arrays[0][2] = [arrays[0][2][0] - 1]
        data = reframe(data, arrays=arrays, raw=payload[1:], compression="zstd")
    return coded, data


def _uniform_frame(**changes) -> bytes:
    """A delta+uniform frame (the table coded, the 8 biases int8) with arrays replaced."""
    theta0 = small_tensors(1)
    cfg = CompressionConfig(compression="delta+uniform", chunk=CHUNK, whole_below=8)
    coded, _ = code_snapshot(snapshot(), cfg, (2, theta_digest(theta0), theta0))
    assert coded.coded.arrays["grid.table/escapes"].size >= 2
    for name, change in changes.items():
        coded.coded.arrays[name] = change(coded.coded.arrays[name])
    return codec.encode(coded, spec=SPEC, compression="none")


def _planes(gaps: list[int]) -> np.ndarray:
    """Top-k gaps as the byte planes [4, k] of the wire."""
    return np.ascontiguousarray(np.array(gaps, dtype="<u4").view(np.uint8).reshape(-1, 4).T)


def _hostile() -> list[tuple[str, str, bytes]]:
    coded, good = _topk_frame()
    assert coded.coded.arrays["mlp.0.bias/q"].size == 2  # 8 entries, a quarter sent
    header, payload = split_frame(good)
    meta = header["meta"]
    arrays = header["arrays"]
    too_many = [list(e) for e in arrays]
    for e in too_many:
        if e[0] == "mlp.0.bias/q":
            e[2] = [9]  # more values than the 8 entries of the tensor
    return [
        ("index beyond the tensor", "bad_field", _topk_frame(**{"mlp.0.bias/gaps": _planes([0, 8])})[1]),
        ("indices not increasing", "bad_field", _topk_frame(**{"mlp.0.bias/gaps": _planes([3, 0])})[1]),
        ("a gap past 2**31", "bad_field", _topk_frame(**{"mlp.0.bias/gaps": _planes([2**32 - 1, 1])})[1]),
        ("negative scale", "bad_field", _topk_frame(**{"mlp.0.bias/scale": -np.ones(1, np.float32)})[1]),
        ("NaN scale", "non_finite", reframe(good, raw=payload.replace(
            np.float32(coded.coded.arrays["mlp.0.bias/scale"][0]).tobytes(), np.float32("nan").tobytes()),
            compression="zstd")),
        ("more values than entries", "bad_shape", reframe(good, arrays=too_many)),
        ("unknown code", "bad_encoding", reframe(good, meta={**meta, "code": "delta+lz4"})),
        ("meta field missing", "bad_field", reframe(good, meta={k: v for k, v in meta.items() if k != "digest"})),
        ("a delta without a base", "bad_field", reframe(good, meta={**meta, "base": ""})),
        ("int8 layout with top-k arrays", "bad_shape", reframe(good, meta={**meta, "code": "delta+int8"})),
        ("coded on a float16 wire", "bad_encoding", reframe(good, wire_dtype="float16")),
        ("chunk of zero", "bad_field", reframe(good, meta={**meta, "chunk": 0})),
        ("a map as the digest", "bad_field", reframe(good, meta={**meta, "digest": {"a": 1}})),
        ("a ternary byte above 242", "bad_field", _ternary_frame(**{"grid.table/codes": None})[1]),
        ("ternary layout with top-k arrays", "bad_shape", reframe(good, meta={**meta, "code": "delta+ternary"})),
        ("ternary codes one byte short", "bad_shape", _ternary_frame(short=True)[1]),
        ("an escape too few", "bad_shape", _uniform_frame(**{"grid.table/escapes": lambda e: e[:-1]})),
        ("an escape of the wrong sign", "bad_field", _uniform_frame(**{"grid.table/escapes": lambda e: -e})),
        ("an escape under 2 steps", "bad_field", _uniform_frame(**{"grid.table/escapes": np.sign})),
    ]


@pytest.mark.parametrize("case", _hostile(), ids=lambda c: c[0])
def test_hostile_compressed_frames_are_refused_in_one_line(case):
    _, reason, data = case
    with pytest.raises(Rejected) as exc:
        codec.decode(data, expectation(), kind="theta")
    assert exc.value.reason == reason, str(exc.value)
    assert "\n" not in str(exc.value) and len(str(exc.value)) < 300


def test_a_lost_push_is_made_good_by_a_pull_of_the_full_snapshot_over_the_network():
    """Two exchanges on the in-memory network: robot 1's push of round 1 never leaves; its
    round-2 delta names a base robot 2 lacks, so robot 2 pulls the full snapshot, and from then on
    takes deltas again, each bit-identical to robot 1's public copy."""
    hub = LoopbackHub(links=[(1, 2)])
    keys = Keys(SWARM)
    nets = {i: LoopbackNetwork(hub, keys, i).open() for i in (1, 2)}
    stop, events = threading.Event(), []
    timing = ExchangeTiming(round_timeout_s=5.0, pull_after_s=0.2, silent_after_s=3.0, join_timeout_s=2.0,
                            resend_delay_s=0.1)
    ex = {i: SnapshotExchange(nets[i], keys, i, frozenset({3 - i}), Mailbox(max_ahead=4), LastHeard(), timing, stop,
                              lambda s: None, lambda kind, **f: events.append((kind, f)), lambda r, d: None,
                              compression=_cfg("delta+int8")) for i in (1, 2)}
    for e in ex.values():
        e.expect = expectation()
        e.seed(small_tensors(0))
        e.start()
    try:
        rng = np.random.default_rng(5)
        theta = small_tensors(0)
        sent: dict[int, bytes] = {}
        for r in (1, 2, 3):
            theta = _step(theta, rng)
            msg = ThetaSnapshot(SWARM, 1, r, 0, SPEC.signature(), theta)
            if r == 1:  # encoded and served as latest, but the push is lost
                push, full = ex[1].encoder.encode(msg, SPEC, "zstd")
                nets[1].set_latest(full, round=r)
            else:
                ex[1].publish(msg, SPEC, "float32", "zstd")
            sent[r] = ex[1].latest[1] if r > 1 else full
            got = ex[2].mailbox.wait(r, lambda: {1}, 5.0) if r > 1 else None
            if got is not None:
                assert got.complete, f"round {r} never arrived"
                want = codec.decode(sent[r], expectation(), kind="theta").tensors
                assert all(got.items[1].tensors[n].tobytes() == want[n].tobytes() for n in want)
            ex[2].mailbox.advance(r)
        kinds = [k for k, _ in events]
        assert kinds.count("base_missing") == 1 and kinds.count("pulled") == 1, events
        assert ex[1].bytes_sent()[2] > 0
    finally:
        stop.set()
        for e in ex.values():
            e.close()
        for n in nets.values():
            n.close()


def test_a_latest_reply_past_the_claimed_round_never_becomes_the_base():
    """A reply of a round past what the sender claims (a forgery: nobody vouches for it) is
    dropped before it is resolved; taken as the base, it made every real delta after it "old"."""
    hub = LoopbackHub(links=[(1, 2)])
    keys = Keys(SWARM)
    nets = {i: LoopbackNetwork(hub, keys, i).open() for i in (1, 2)}
    timing = ExchangeTiming(round_timeout_s=2.0, pull_after_s=0.2, silent_after_s=3.0, join_timeout_s=1.0,
                            resend_delay_s=0.1)
    ex = SnapshotExchange(nets[2], keys, 2, frozenset({1}), Mailbox(max_ahead=4), LastHeard(), timing,
                          threading.Event(), lambda s: None, lambda kind, **f: None, lambda r, d: None,
                          compression=_cfg("delta+quinary"))
    ex.expect = expectation()
    ex.seed(small_tensors(0))
    try:
        forged = ThetaSnapshot(SWARM, 1, 3, 0, SPEC.signature(), small_tensors(1))
        nets[1].set_latest(codec.encode(forged, spec=SPEC), round=3)
        assert ex.fetch_latest(1, at_most=1) is None
        assert ex.bases.held_round(1) == -1  # still theta^0: robot 1's real round-1 delta resolves
        enc = SnapshotEncoder(_cfg("delta+quinary"))
        enc.seed(small_tensors(0))
        push, _ = enc.encode(ThetaSnapshot(SWARM, 1, 1, 0, SPEC.signature(), small_tensors(2)), SPEC, "zstd")
        got = ex.bases.resolve(codec.decode(push, expectation(), kind="theta"), SPEC)
        assert not isinstance(got, str), got
    finally:
        for n in nets.values():
            n.close()


def test_config_refuses_what_cannot_work():
    for bad in ({"compression": "lz4"}, {"topk_fraction": 0.0}, {"topk_fraction": 0.9}, {"chunk": 3}):
        with pytest.raises(ValueError):
            CompressionConfig(**bad)


class _Recorder:
    """A Network stand-in that records puts (a unit test of one sender's queue)."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, int]] = []
        self.gate = threading.Event()

    def publish(self, key: str, data: bytes) -> None:
        self.gate.wait(10)
        self.puts.append((key, len(data)))


def test_a_slow_link_queues_deltas_until_they_would_outweigh_the_full_snapshot():
    """While one put is stuck, deltas queue behind it (each is the next one's base); the full
    snapshot replaces them only once the queue would carry more bytes than it. A resend of a round
    that is already queued adds nothing."""
    from protocol.exchange import NeighbourSender

    net = _Recorder()
    sender = NeighbourSender(net, lambda k: f"theta/{k}", lambda text: None)
    try:
        full, delta = b"F" * 1000, b"d" * 300
        sender.offer_frames(1, delta, full)  # taken at once, stuck in publish
        time.sleep(0.2)
        for k in (2, 3, 4):  # 3 x 300 < 1000: queued
            sender.offer_frames(k, delta, full)
        sender.resend(4, delta, full, delay_s=0.0)  # round 4 waits already
        sender.offer_frames(5, delta, full)  # 4 x 300 > 1000: the full snapshot instead
        net.gate.set()
        sender.idle(10)
        assert net.puts == [("theta/1", 300), ("theta/5", 1000)], net.puts
        net.puts.clear()
        net.gate.clear()
        sender.offer_frames(6, delta, full)
        time.sleep(0.2)
        for k in (7, 8):
            sender.offer_frames(k, delta, full)
        net.gate.set()
        sender.idle(10)
        assert net.puts == [("theta/6", 300), ("theta/7", 300), ("theta/8", 300)], net.puts
    finally:
        sender.close()
