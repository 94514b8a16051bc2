"""Looking at values decoded from a peer's msgpack without trusting their size or shape.

``str()`` of a hostile value is not safe in a refusal message: msgpack nests up to 1024 levels,
deeper than Python's recursion limit for ``repr``, and a 1 MiB header can hold thousands of long
strings, all formatted before any ``[:80]`` cuts them. :func:`describe` looks one level deep and
bounds what it prints.

Nesting itself needs no check of its own: every field check tests a value's type before looking
inside it, so a container where a scalar belongs is refused for that field's reason without
being walked (a walk of every header would cost up to 4x msgpack's own unpacking). Pure Python.
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
