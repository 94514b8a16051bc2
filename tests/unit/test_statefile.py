"""State files (agent.statefile): exact round trips, and every kind of bad file refused in one line and kept."""

from __future__ import annotations

import math
import os
import pickle

import pytest
import torch

from agent import files
from agent.state_codec import StateFormatError, flatten, unflatten
from agent.statefile import CheckpointError, read_state, write_state


def _same(a, b, where="state") -> None:
    """Equal bit for bit, with the same types (a tuple stays a tuple, an int key an int; an
    OrderedDict comes back as a dict, in order)."""
    assert type(a) is type(b) or isinstance(a, dict) and type(b) is dict, (where, type(a), type(b))
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert list(a) == list(b), (where, list(a), list(b))
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}/{i}")
    elif isinstance(a, float) and math.isnan(a):
        assert math.isnan(b), where
    else:
        assert a == b, (where, a, b)


def _state() -> dict:
    shared = torch.arange(6, dtype=torch.float32)
    return {
        "weights": {"layer.0.weight": torch.randn(3, 4), "scalar": torch.tensor(0.1)},
        "optimizer": {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(2)}},
                      "param_groups": [{"lr": 0.1 + 0.2, "betas": (0.9, 0.99), "foreach": None, "params": [0]}]},
        "duals": {7: [shared, shared[:3]]},  # views of one storage: stored apart
        "generator": torch.Generator().manual_seed(5).get_state(),
        "mask": torch.tensor([True, False]),
        "sigma": math.nan, "inf": -math.inf, "flag": False, "name": "x", "nothing": None,
        "$odd": {"$tensor": "not a tag"},  # keys that look like tags are escaped
        "empty": torch.zeros(0, 3),
    }


def test_a_state_comes_back_bit_for_bit_with_its_types(tmp_path):
    state = _state()
    write_state(tmp_path / "s.safetensors", "test", state)
    _same(state, read_state(tmp_path / "s.safetensors", "test"))
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_a_header_length_that_starts_like_a_pickle_still_reads(tmp_path):
    """A safetensors header of 128 + 256k bytes opens with 0x80, a pickle's first byte; found by CI."""
    path = tmp_path / "s.safetensors"
    for pad in range(400):
        write_state(path, "test", {"pad": "x" * pad, "t": torch.ones(2)})
        if path.read_bytes()[0] == 0x80:
            break
    assert path.read_bytes()[0] == 0x80, "no padding gave a header length ending in 0x80"
    assert read_state(path, "test")["pad"] == "x" * pad


def test_the_tensors_are_stored_under_their_paths_and_the_rest_is_json():
    text, tensors = flatten(_state())
    assert "weights/layer.0.weight" in tensors and "optimizer/state/0/exp_avg" in tensors
    assert '"$tuple":[0.9,0.99]' in text and '"$float":"nan"' in text


@pytest.mark.parametrize("text, tensors, why", [
    ('{"$eval": "x"}', {}, "unknown"),
    ('{"$tensor": "missing"}', {}, "does not hold"),
    ('{"a": 1}', {"extra": torch.zeros(1)}, "does not name"),
    ('[{"$tensor": "t"}, {"$tensor": "t"}]', {"t": torch.zeros(1)}, "twice"),
    ('{"a": NaN}', {}, "non-finite"),
    ('{"$items": [[1.5, 2]]}', {}, "pair"),
    ('not json', {}, "not JSON"),
    ("[" * 100000 + "]" * 100000, {}, "deep|JSON"),
])
def test_state_json_outside_the_vocabulary_is_refused(text, tensors, why):
    with pytest.raises(StateFormatError, match=why):
        unflatten(text, tensors)


def _flip_last_byte(path):
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01  # tensor data is at the end of a safetensors file
    path.write_bytes(bytes(data))


def _flip_in_state_text(path):
    data = path.read_bytes()
    assert data.count(b"false") == 1  # "flag": still JSON, and a state that means something else
    path.write_bytes(data.replace(b"false", b"true "))


class _Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))  # loading this pickle creates the marker file


@pytest.mark.parametrize("spoil, why", [
    (lambda p: p.write_bytes(pickle.dumps(_Payload(p.parent / "pwned"))), "pickle"),
    (lambda p: torch.save(_Payload(p.parent / "pwned"), p), "pickle"),
    (_flip_last_byte, "checksum mismatch"),
    (_flip_in_state_text, "checksum mismatch"),
    (lambda p: p.write_bytes(p.read_bytes()[:-7]), "truncated: its tensors need"),
    (lambda p: p.write_bytes(p.read_bytes() + b"\0" * 8), "damaged safetensors data"),
    (lambda p: p.write_bytes(p.read_bytes()[:40]), "truncated"),
    (lambda p: p.write_bytes(p.read_bytes()[:5]), "too short"),
    (lambda p: p.write_bytes(b""), "empty"),
    (lambda p: p.write_bytes(b"\xff\xfe not a state file at all " * 8), "not a safetensors file"),
    (lambda p: (p.unlink(), p.mkdir()), "directory"),
])
def test_a_bad_file_is_refused_in_one_line_and_kept(tmp_path, spoil, why):
    path = tmp_path / "s.safetensors"
    write_state(path, "test", _state())
    spoil(path)
    before = path.read_bytes() if path.is_file() else None
    with pytest.raises(CheckpointError, match=why) as e:
        read_state(path, "test")
    assert "\n" not in str(e.value) and str(e.value).startswith(str(path))
    assert path.exists() and (before is None or path.read_bytes() == before)
    assert not (tmp_path / "pwned").exists(), "the file's code ran"


def test_the_pickle_payload_of_these_tests_is_live(tmp_path):
    """The payload above does run when unpickled: its not running in read_state means something."""
    pickle.loads(pickle.dumps(_Payload(tmp_path / "ran")))
    assert (tmp_path / "ran").exists()


def test_a_safetensors_file_of_someone_else_or_of_another_kind_is_refused(tmp_path):
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, tmp_path / "model.safetensors")
    with pytest.raises(CheckpointError, match="not one dinerf wrote"):
        read_state(tmp_path / "model.safetensors", "test")
    write_state(tmp_path / "s.safetensors", "round-snapshot", {"a": torch.zeros(1)})
    with pytest.raises(CheckpointError, match="'round-snapshot' file, not a 'robot-checkpoint'"):
        read_state(tmp_path / "s.safetensors", "robot-checkpoint")


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "s.safetensors"
    write_state(path, "test", {"a": torch.ones(1)})
    old = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        write_state(path, "test", {"a": torch.zeros(1)})
    assert path.read_bytes() == old and sorted(os.listdir(tmp_path)) == ["s.safetensors"]


def test_writing_over_a_directory_fails_and_keeps_it(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(OSError):
        files.atomic_write_text(tmp_path / "d", "x")
    assert (tmp_path / "d").is_dir() and sorted(os.listdir(tmp_path)) == ["d"]


def test_a_fifo_a_device_and_a_symlink_out_of_the_folder_are_refused_without_reading(tmp_path):
    """A FIFO would block the reader for ever and /dev/zero fill its memory: neither is opened as
    a state file. A symlink is followed only within the folder given."""
    import threading

    fifo = tmp_path / "fifo.safetensors"
    os.mkfifo(fifo)
    done: list = []
    reader = threading.Thread(target=lambda: done.append(pytest.raises(CheckpointError, read_state, fifo, "test")))
    reader.start()
    reader.join(timeout=10)
    assert done and "is a FIFO" in str(done[0].value), "read_state hung on a FIFO"
    (tmp_path / "zero.safetensors").symlink_to("/dev/zero")
    with pytest.raises(CheckpointError, match="is a character device"):
        read_state(tmp_path / "zero.safetensors", "test")
    with pytest.raises(CheckpointError, match="outside"):
        read_state(tmp_path / "zero.safetensors", "test", within=tmp_path)
    write_state(tmp_path / "real.safetensors", "test", {"a": torch.ones(1)})
    (tmp_path / "inside.safetensors").symlink_to("real.safetensors")
    assert torch.equal(read_state(tmp_path / "inside.safetensors", "test", within=tmp_path)["a"], torch.ones(1))


def test_a_file_larger_than_the_machine_can_hold_is_refused_before_reading(tmp_path):
    from agent.statefile import memory_limit

    path = tmp_path / "huge.safetensors"
    with open(path, "wb") as f:
        f.truncate(memory_limit() + 1)  # sparse: no disk used
    with pytest.raises(CheckpointError, match="more than the"):
        read_state(path, "test")
