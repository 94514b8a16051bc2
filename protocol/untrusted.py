"""Looking at values decoded from a peer's msgpack without trusting their size or shape.

``str()`` of a hostile value is not safe in a refusal message: msgpack nests up to 1024 levels,
deeper than Python's recursion limit for ``repr``, and a 1 MiB header can hold thousands of long
strings, all formatted before any ``[:80]`` cuts them. :func:`describe` looks one level deep and
bounds what it prints; :func:`nesting_depth` measures depth with an explicit stack. Pure Python.
"""

from __future__ import annotations

from typing import Any

_TEXT = 32  # characters of a string shown in a description
_ITEMS = 3  # items of a list shown in a description
_ITEM_TEXT = 12  # characters of a string shown for each of those items


def describe(value: Any, limit: int = _TEXT) -> str:
    """A short description of ``value`` for a refusal: its type, size and a bounded preview."""
    if isinstance(value, list):
        shown = ", ".join(_describe_flat(v, min(limit, _ITEM_TEXT)) for v in value[:_ITEMS])
        more = ", ..." if len(value) > _ITEMS else ""
        return f"list of {len(value)} [{shown}{more}]"
    return _describe_flat(value, limit)


def _describe_flat(value: Any, limit: int) -> str:
    """Scalars by bounded repr, containers by type and length only (never recursing)."""
    if value is None or isinstance(value, (bool, int, float)):
        text = repr(value)
        return text if len(text) <= limit else f"{text[:limit]}..."
    if isinstance(value, str):
        return repr(value) if len(value) <= limit else f"{value[:limit]!r}... ({len(value)} characters)"
    if isinstance(value, (bytes, bytearray)):
        return f"{len(value)} bytes"
    if isinstance(value, (list, tuple)):
        return f"list of {len(value)}"
    if isinstance(value, dict):
        return f"map of {len(value)}"
    return type(value).__name__


def nesting_depth(value: Any, limit: int) -> int:
    """Container nesting of ``value`` (a scalar is 0, ``[1]`` is 1), counted up to ``limit + 1``.

    Iterative, so any depth msgpack accepts is measured without recursion; stops early once the
    limit is passed.
    """
    deepest = 0
    stack = [(value, 0)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, dict):
            children = v.values()
        elif isinstance(v, list):
            children = v
        else:
            continue
        depth += 1
        deepest = max(deepest, depth)
        if deepest > limit:
            return deepest
        stack.extend((child, depth) for child in children)
    return deepest
