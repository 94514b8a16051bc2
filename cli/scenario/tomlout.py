"""A small TOML writer for the swarm files the runner generates (the stdlib only reads TOML).

Covers what ``cli.config.to_dict`` produces: tables, strings, numbers, booleans and arrays of
them; ``None`` values are left out (TOML has no null, and an absent key means the default).
"""

from __future__ import annotations

import json
import math
from typing import Any


def _key(k: str) -> str:
    k = str(k)
    return k if k and all(c.isalnum() or c in "-_" for c in k) else json.dumps(k)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v if x is not None) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items() if x is not None) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML: {v!r}")


def dumps(data: dict[str, Any], show_unset: bool = False) -> str:
    """Nested dict -> TOML text (sub-dicts become [tables]); ``show_unset``: a None is a comment line."""
    lines: list[str] = []

    def table(d: dict[str, Any], path: list[str]) -> None:
        scalars = [(k, v) for k, v in d.items() if (v is not None or show_unset) and not isinstance(v, dict)]
        subs = [(k, v) for k, v in d.items() if isinstance(v, dict)]
        if path and (scalars or not subs):
            lines.append(f"[{'.'.join(_key(p) for p in path)}]")
        for k, v in scalars:
            lines.append(f"# {_key(k)} unset (decided at run time)" if v is None else f"{_key(k)} = {_value(v)}")
        if scalars or (path and not subs):
            lines.append("")
        for k, v in subs:
            table(v, path + [str(k)])

    table(data, [])
    return "\n".join(lines).rstrip() + "\n"
