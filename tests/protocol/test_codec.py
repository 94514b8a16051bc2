"""Codec: round trips, and every malformed input refused with its own reason."""

from __future__ import annotations

import time
import tracemalloc

import msgpack
import numpy as np
import pytest
import zstandard

from protocol import codec
from protocol.codec import Expectation, decode, encode, read_header
from protocol.messages import (REJECT_REASONS, KeyframeSummary, ModelSpec, Rejected, Status,
                               ThetaSnapshot)
from tests.protocol.helpers import (ROUND, SENDER, SWARM, expectation, keyframe_summary,
                                    keyframe_summary_with_cameras, keys, malformed_cases, reframe,
                                    rle_zstd_frame, small_spec, snapshot, split_frame, status_message,
                                    valid_frame)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_float32_round_trip_is_bit_identical(compression):
    msg = snapshot()
    # include values whose bits must survive exactly: subnormals, -0.0, extremes
    msg.tensors["mlp.0.bias"][:4] = [np.float32(1e-45), -0.0, np.finfo(np.float32).max, np.finfo(np.float32).tiny]
    got = decode(encode(msg, compression=compression), expectation())
    assert isinstance(got, ThetaSnapshot)
    assert list(got.tensors) == list(msg.tensors)
    for name, t in msg.tensors.items():
        assert got.tensors[name].dtype == np.float32
        assert got.tensors[name].tobytes() == t.tobytes(), name
        assert got.tensors[name].flags.writeable
    h = got.header
    assert (h.sender, h.round, h.epoch, h.swarm, h.compression, h.wire_dtype) == (SENDER, ROUND, 0, SWARM, compression,
                                                                                   "float32")
    assert h.signature == small_spec().signature()


def test_float16_is_smaller_and_close():
    msg = snapshot()
    f32 = encode(msg, compression="none")
    f16 = encode(msg, wire_dtype="float16", compression="none")
    assert len(split_frame(f16)[1]) * 2 == len(split_frame(f32)[1])  # half the payload
    got = decode(f16, expectation())
    for name, t in msg.tensors.items():
        assert got.tensors[name].dtype == np.float32
        np.testing.assert_allclose(got.tensors[name], t, rtol=1e-3, atol=1e-4)
    assert any(not np.array_equal(got.tensors[n], t) for n, t in msg.tensors.items())  # it is lossy


def test_encode_refuses_what_peers_would_reject():
    msg = snapshot()
    msg.tensors["grid.table"][0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        encode(msg)
    big = snapshot()
    big.tensors["grid.table"][0, 0] = 1e6  # fine in float32, overflows float16
    encode(big)
    with pytest.raises(ValueError, match="float16 overflow"):
        encode(big, wire_dtype="float16")
    with pytest.raises(ValueError, match="wire_dtype"):
        encode(snapshot(), wire_dtype="int8")
    with pytest.raises(ValueError, match="round"):
        encode(snapshot(round=-1))
    with pytest.raises(ValueError, match="swarm"):
        encode(snapshot(swarm="a/b"))
    other = ModelSpec(small_spec().params[:2], {})
    with pytest.raises(ValueError):
        encode(snapshot(), spec=other)


VIEWS = {"keyframes": 42, "held_out": 5, "dropped": 1, "newest_age_s": 0.4, "coverage": [2.0, 1.0, 0.25]}


def test_status_round_trip_and_type_checks():
    msg = status_message(suspects={3: "quarantined", 5: "ahead_of_pace"}, views=VIEWS)
    got = decode(encode(msg), expectation(), kind="status")
    assert isinstance(got, Status)
    for name in Status.BODY_FIELDS + ("swarm", "sender", "round", "epoch"):
        assert getattr(got, name) == getattr(msg, name), name
    # a type error in a body field is refused on decode
    header, payload = split_frame(encode(msg, compression="none"))
    body = msgpack.unpackb(payload)
    for field, value, reason in [("pose", [0.0] * 6, "bad_field"), ("loss", "low", "bad_field"),
                                 ("bytes_in", -1, "bad_field"), ("neighbours_heard", [True], "bad_field"),
                                 ("psnr", float("nan"), "non_finite"), ("phase", 3, "bad_field"),
                                 ("suspects", [[3, "evil"]], "bad_field"), ("suspects", [[-1, "refused"]], "bad_field"),
                                 ("suspects", {"3": "refused"}, "bad_field"),
                                 ("views", dict(VIEWS, keyframes=-1), "bad_field"),
                                 ("views", dict(VIEWS, coverage=[1.0, float("nan"), 0.0]), "bad_field"),
                                 ("views", {"keyframes": 3}, "bad_field"), ("views", [1, 2], "bad_field")]:
        bad = dict(body, **{field: value})
        raw = msgpack.packb(bad)
        frame = codec.pack_frame(dict(header, raw_length=len(raw), payload_length=len(raw)), raw)
        with pytest.raises(Rejected) as exc:
            decode(frame, expectation())
        assert exc.value.reason == reason, field
    with pytest.raises(ValueError):
        encode(status_message(pose=[0.0] * 3))


@pytest.mark.parametrize("descriptor_dtype", [np.uint8, np.float32])
def test_keyframe_summary_round_trip(descriptor_dtype):
    msg = keyframe_summary(descriptor_dtype)
    got = decode(encode(msg), expectation(), kind="keyframes")
    assert isinstance(got, KeyframeSummary)
    assert got.descriptors.dtype == descriptor_dtype
    np.testing.assert_array_equal(got.descriptors, msg.descriptors)
    np.testing.assert_array_equal(got.points, msg.points)
    np.testing.assert_array_equal(got.keyframe_index, msg.keyframe_index)
    assert got.image_bytes == 123456


def test_keyframe_summary_point_cap():
    data = encode(keyframe_summary(points=50))
    with pytest.raises(Rejected) as exc:
        decode(data, expectation(max_keyframe_points=10))
    assert exc.value.reason == "too_large"


@pytest.mark.parametrize("name,reason,data,key_id", malformed_cases(), ids=[c[0] for c in malformed_cases()])
def test_each_malformed_kind_is_rejected_with_its_reason(name, reason, data, key_id):
    key = keys().parse(keys().theta(key_id, ROUND, to=0))
    with pytest.raises(Rejected) as exc:
        decode(data, expectation(), kind="theta", key=key)
    assert exc.value.reason == reason, (name, str(exc.value))
    assert exc.value.reason in REJECT_REASONS


def test_the_valid_frame_used_by_the_malformed_cases_is_accepted():
    key = keys().parse(keys().theta(SENDER, ROUND, to=0))
    assert decode(valid_frame(), expectation(), kind="theta", key=key).round == ROUND


def test_kind_filter_and_missing_spec():
    with pytest.raises(Rejected) as exc:
        decode(encode(status_message()), expectation(), kind="theta")
    assert exc.value.reason == "bad_kind"
    with pytest.raises(Rejected) as exc:
        decode(valid_frame(), Expectation(SWARM))  # no model spec: cannot accept snapshots
    assert exc.value.reason == "bad_signature"
    # but status messages need no spec
    assert decode(encode(status_message()), Expectation(SWARM)).sender == 2


def test_caps_refuse_before_work():
    data = valid_frame()
    for cap, reason in [(dict(max_wire_bytes=100), "too_large"), (dict(max_decompressed_bytes=100), "too_large"),
                        (dict(max_header_bytes=50), "too_large")]:
        with pytest.raises(Rejected) as exc:
            decode(data, expectation(**cap))
        assert exc.value.reason == reason, cap


def test_header_is_covered_by_the_checksum():
    data = reframe(valid_frame(), round=ROUND + 1, fix_checksum=False)
    with pytest.raises(Rejected) as exc:
        decode(data, expectation())
    assert exc.value.reason == "bad_checksum"


@pytest.mark.parametrize("declare_size", [True, False])
def test_real_decompression_bomb_is_refused_quickly_without_allocating(declare_size):
    bomb = rle_zstd_frame(2**30 + 2**17, declare_size)  # > 1 GiB of zeros
    assert len(bomb) < 64 * 1024
    # it is a genuine zstd frame: a small one built the same way really decompresses
    small = rle_zstd_frame(4 * 2**17, declare_size)
    assert zstandard.ZstdDecompressor().decompressobj().decompress(small) == bytes(4 * 2**17)
    # the header declares exactly what the spec needs, the frame would give 1 GiB
    data = reframe(valid_frame(), payload=bomb)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(Rejected) as exc:
            decode(data, expectation())
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert exc.value.reason == "decompression_bomb", str(exc.value)
    assert elapsed < 0.5
    assert peak < 8 * 1024 * 1024, f"peak traced allocation {peak} bytes"


def test_bomb_declaring_its_full_size_is_too_large():
    bomb = rle_zstd_frame(2**30 + 2**17, True)
    data = reframe(valid_frame(), payload=bomb, raw_length=2**30 + 2**17)
    with pytest.raises(Rejected) as exc:
        decode(data, expectation())
    assert exc.value.reason == "too_large"


def test_read_header_is_cheap_and_matches_decode():
    data = valid_frame()
    h = read_header(data, expectation(), kind="theta")
    assert (h.sender, h.round) == (SENDER, ROUND)
    corrupted = bytearray(data)
    corrupted[-1] ^= 0xFF
    read_header(bytes(corrupted), expectation())  # payload is not looked at
    with pytest.raises(Rejected):
        decode(bytes(corrupted), expectation())


def test_non_bytes_input_is_rejected():
    for bad in (None, "DNRF", 42, [1, 2]):
        with pytest.raises(Rejected) as exc:
            decode(bad, expectation())
        assert exc.value.reason == "garbage"


def test_model_spec_signature_is_stable_and_sensitive():
    a = small_spec()
    assert a.signature() == small_spec().signature()
    assert len(a.signature()) == 16
    assert ModelSpec(a.params, {"levels": 4, "width": 9}).signature() != a.signature()
    reordered = ModelSpec(tuple(reversed(a.params)), a.arch)
    assert reordered.signature() != a.signature()
    with pytest.raises(ValueError, match="duplicate"):
        ModelSpec(a.params + a.params[:1], {})
    with pytest.raises(ValueError, match="JSON"):
        ModelSpec(a.params, {"f": object()})


def test_expectation_validates_swarm():
    with pytest.raises(ValueError, match="swarm"):
        Expectation("bad swarm")


def test_keyframe_summary_with_cameras_round_trip_and_refusals():
    msg = keyframe_summary_with_cameras()
    got = decode(encode(msg), expectation(), kind="keyframes")
    np.testing.assert_array_equal(got.keypoints, msg.keypoints)
    np.testing.assert_array_equal(got.keyframe_cameras, msg.keyframe_cameras)
    assert decode(encode(keyframe_summary()), expectation(), kind="keyframes").keyframe_cameras is None  # optional
    with pytest.raises(ValueError, match="together"):
        encode(KeyframeSummary(**{**msg.__dict__, "keyframe_cameras": None}))
    with pytest.raises(ValueError, match="beyond"):
        encode(KeyframeSummary(**{**msg.__dict__, "keyframe_cameras": msg.keyframe_cameras[:2]}))

    # Hostile frames that encode() would never write: a sender that lies in its array table.
    def forged(cams, table_rows):
        header, _ = split_frame(encode(msg))
        arrays = [msg.descriptors, msg.points, msg.keyframe_index, msg.keypoints, cams]
        raw = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)
        table = [list(row) for row in header["arrays"]]
        table[4][2] = list(cams.shape)
        table.extend(table_rows)
        return reframe(encode(msg), raw=raw, arrays=table)

    cases = [
        (forged(msg.keyframe_cameras[:2], []), "bad_field", "beyond"),  # index 4 with 2 cameras
        (forged(np.where(np.arange(16) == 12, -1.0, msg.keyframe_cameras).astype(np.float32), []), "bad_field", "focal"),
        (forged(msg.keyframe_cameras[:, :8].copy(), []), "bad_shape", "keyframe_cameras"),
    ]
    for data, reason, text in cases:
        with pytest.raises(Rejected) as exc:
            decode(data, expectation(), kind="keyframes")
        assert exc.value.reason == reason and text in str(exc.value), (reason, exc.value)
    with pytest.raises(Rejected) as exc:
        decode(encode(msg), expectation(max_keyframes=4), kind="keyframes")
    assert exc.value.reason == "too_large"


def test_keyframe_summary_carries_a_field_box_and_refuses_a_bad_one():
    box = np.diag([0.5, 0.5, 0.5, 1.0])
    box[:3, 3] = [0.1, -0.2, 0.3]
    msg = keyframe_summary_with_cameras()
    msg.box_from_shared = box
    got = decode(encode(msg), expectation(), kind="keyframes")
    np.testing.assert_array_equal(got.box_from_shared, box)  # float64 on the wire: bit for bit
    assert decode(encode(keyframe_summary()), expectation(), kind="keyframes").box_from_shared is None  # optional

    sheared = box.copy()
    sheared[0, 1] = 0.2
    mirrored = box @ np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="box_from_shared"):
        encode(KeyframeSummary(**{**msg.__dict__, "box_from_shared": sheared}))

    # A hostile sender writes the meta itself: shear, reflection, NaN, wrong length, strings.
    cases = [sheared.flatten().tolist(), mirrored.flatten().tolist(),
             [float("nan")] + box.flatten().tolist()[1:], box.flatten().tolist()[:12], ["1"] * 16,
             (box * 0).flatten().tolist()]
    for bad in cases:
        frame = reframe(encode(msg), meta={"image_bytes": msg.image_bytes, "box_from_shared": bad})
        with pytest.raises(Rejected) as exc:
            decode(frame, expectation(), kind="keyframes")
        assert exc.value.reason == "bad_field" and "box_from_shared" in str(exc.value), bad
