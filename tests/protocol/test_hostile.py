"""Frames an attacker would write, one per finding of the review: each ends as Rejected with its reason.

Both entry points are tried: ``read_header`` (called in a Zenoh callback, so an escaping exception
would kill the callback) and ``decode``, which must give the real reason, not the catch-all.
"""

from __future__ import annotations

import pytest

from protocol import codec
from protocol.messages import Rejected
from tests.protocol.helpers import expectation, split_frame, valid_frame


def _reason(data: bytes, entry=codec.decode, **kw) -> Rejected:
    with pytest.raises(Rejected) as exc:
        entry(data, expectation(**kw))
    return exc.value


def _with_header(**changes) -> bytes:
    header, payload = split_frame(valid_frame())
    return codec.pack_frame(dict(header, **changes), payload)


@pytest.mark.parametrize("entry", [codec.read_header, codec.decode])
@pytest.mark.parametrize("dtype", [["float32"], {"float32": 1}, [], None, 3])
def test_array_entry_with_an_unhashable_or_odd_dtype_is_bad_shape(entry, dtype):
    header, _ = split_frame(valid_frame())
    table = [list(row) for row in header["arrays"]]
    table[0][1] = dtype
    exc = _reason(_with_header(arrays=table), entry)
    assert exc.reason == "bad_shape" and "malformed array entry" in exc.detail, exc
