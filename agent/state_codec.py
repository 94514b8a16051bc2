"""A nested state (dicts, lists, tuples, numbers, strings, tensors) <-> JSON text + flat tensors.

Why not pickle: a pickle names the code that rebuilds it, so loading one runs whatever its
author chose. Here the tensors go to a safetensors file under flat names and everything else is
JSON, read back with a fixed vocabulary: decoding a hostile file can fail, but it can only ever
build dicts, lists, tuples, numbers, strings and tensors.

The JSON is the state itself, with a few tagged objects for what JSON lacks::

    {"$tensor": "trainer/field/encoding.table"}   a tensor, by its name in the safetensors file
    {"$tuple": [0.9, 0.99]}                        a tuple (Adam's betas)
    {"$float": "nan"}                              a non-finite float ("nan", "inf", "-inf")
    {"$items": [[0, {...}], [1, {...}]]}           a dict whose keys are not all plain strings
                                                   (the optimiser's state by parameter index)

A tensor's name is its path in the state, joined with ``/``. Floats are written with ``repr``,
which reads back bit for bit, so a resumed run continues exactly.
"""

from __future__ import annotations

import json
import math
from typing import Any

from torch import Tensor

__all__ = ["StateFormatError", "flatten", "unflatten"]

TENSOR, TUPLE, FLOAT, ITEMS = "$tensor", "$tuple", "$float", "$items"
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


class StateFormatError(ValueError):
    """The JSON part of a state file does not describe a state (unknown tag, missing tensor ...)."""


def flatten(state: Any) -> tuple[str, dict[str, Tensor]]:
    """``state`` -> (its JSON text, its tensors by name: detached, on the CPU, contiguous, unshared)."""
    tensors: dict[str, Tensor] = {}
    storages: set[int] = set()

    def enc(obj: Any, path: str) -> Any:
        if isinstance(obj, Tensor):
            path = path or "."
            if path in tensors:
                raise ValueError(f"two tensors would be stored as {path!r}")
            t = obj.detach().cpu().contiguous()
            ptr = t.untyped_storage().data_ptr()
            if ptr in storages and t.numel():  # safetensors refuses tensors that share memory
                t = t.clone()
            storages.add(t.untyped_storage().data_ptr())
            tensors[path] = t
            return {TENSOR: path}
        if obj is None or isinstance(obj, (bool, int, str)):
            return obj
        if isinstance(obj, float):
            return obj if math.isfinite(obj) else {FLOAT: repr(obj)}
        if isinstance(obj, tuple):
            return {TUPLE: [enc(v, _join(path, i)) for i, v in enumerate(obj)]}
        if isinstance(obj, list):
            return [enc(v, _join(path, i)) for i, v in enumerate(obj)]
        if isinstance(obj, dict):
            plain = all(isinstance(k, str) and not k.startswith("$") for k in obj)
            for k in obj:
                if isinstance(k, bool) or not isinstance(k, (int, str)):
                    raise TypeError(f"{path}: a key of type {type(k).__name__} cannot be stored")
            if plain:
                return {k: enc(v, _join(path, k)) for k, v in obj.items()}
            return {ITEMS: [[k, enc(v, _join(path, k))] for k, v in obj.items()]}
        raise TypeError(f"{path or 'state'}: a {type(obj).__name__} cannot be stored")

    skeleton = enc(state, "")
    return json.dumps(skeleton, allow_nan=False, separators=(",", ":")), tensors


def unflatten(text: str, tensors: dict[str, Tensor]) -> Any:
    """The inverse of :func:`flatten`; every tensor must be used exactly once."""
    try:
        skeleton = json.loads(text, parse_constant=_no_constant)
    except (json.JSONDecodeError, RecursionError) as e:
        raise StateFormatError(f"the state is not JSON ({e})") from None
    used: set[str] = set()

    def dec(obj: Any) -> Any:
        if isinstance(obj, list):
            return [dec(v) for v in obj]
        if not isinstance(obj, dict):
            return obj
        tags = [k for k in obj if k.startswith("$")]
        if not tags:
            return {k: dec(v) for k, v in obj.items()}
        if len(obj) != 1:
            raise StateFormatError(f"a tagged object has other keys: {sorted(obj)[:4]}")
        tag, value = tags[0], obj[tags[0]]
        if tag == TENSOR:
            if not isinstance(value, str) or value not in tensors:
                raise StateFormatError(f"names a tensor the file does not hold: {str(value)[:80]!r}")
            if value in used:
                raise StateFormatError(f"tensor {value!r} is used twice")
            used.add(value)
            return tensors[value]
        if tag == TUPLE and isinstance(value, list):
            return tuple(dec(v) for v in value)
        if tag == FLOAT and value in _NON_FINITE:
            return _NON_FINITE[value]
        if tag == ITEMS and isinstance(value, list):
            return dict(_item(pair, dec) for pair in value)
        raise StateFormatError(f"unknown or malformed tag {tag!r}")

    try:
        state = dec(skeleton)
    except RecursionError:
        raise StateFormatError("the state is nested too deeply") from None
    unused = sorted(set(tensors) - used)
    if unused:
        raise StateFormatError(f"{len(unused)} tensor(s) the state does not name, e.g. {unused[0]!r}")
    return state


def _join(path: str, key: int | str) -> str:
    return f"{path}/{key}" if path else str(key)


def _item(pair: Any, dec) -> tuple[int | str, Any]:
    if not (isinstance(pair, list) and len(pair) == 2 and isinstance(pair[0], (int, str))
            and not isinstance(pair[0], bool)):
        raise StateFormatError("an item of a keyed dict is not a [key, value] pair")
    return pair[0], dec(pair[1])


def _no_constant(name: str) -> Any:
    raise StateFormatError(f"bare {name} in the state (non-finite floats are tagged)")
