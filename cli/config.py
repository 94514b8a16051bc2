"""Typed configuration: TOML tables -> dataclasses, with errors that name the offending key.

Each concern owns its dataclass next to its code (``FieldConfig`` in ``agent.nerf.field``,
``TransportConfig`` in ``protocol.transport`` ...). This module reads TOML files and applies
``section.key=value`` overrides from the command line; filling a dataclass from a dict
(:func:`agent.config_io.from_dict`, re-exported here) rejects unknown keys, so that a typo in a
TOML file is an error instead of a silently ignored setting.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, TypeVar

from agent.config_io import ConfigError, from_dict, merge_tables, to_dict

__all__ = ["ConfigError", "from_dict", "to_dict", "load_toml", "apply_overrides", "overrides_table", "merge_tables"]

T = TypeVar("T")


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    except UnicodeDecodeError as e:  # TOML is UTF-8: a binary file, or another encoding
        raise ConfigError(f"{path}: not valid TOML: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot be read ({e.strerror or e})") from None


def _parse_scalar(text: str) -> Any:
    """Parse a command-line value the way TOML would (``3``, ``1e-2``, ``true``, ``"x"``, ``[1, 2]``)."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # a bare word is a string


def overrides_table(overrides: list[str]) -> dict[str, Any]:
    """``a.b.c=value`` overrides as the nested table they set (what was given, as a file would give it)."""
    table: dict[str, Any] = {}
    for item in overrides:
        key, _, text = item.partition("=")
        *parents, last = key.strip().split(".")
        node = table
        for p in parents:
            node = node.setdefault(p, {}) if isinstance(node.get(p, {}), dict) else {}
        node[last] = _parse_scalar(text.strip())
    return table


def apply_overrides(cfg: T, overrides: list[str]) -> T:
    """Apply ``a.b.c=value`` overrides to a (nested) dataclass, re-validating the result."""
    data = to_dict(cfg)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        node = data
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise ConfigError(f"override {key!r}: no section {p!r}")
            node = node[p]
        if parts[-1] not in node:
            raise ConfigError(f"override {key!r}: unknown key {parts[-1]!r}; known: {sorted(node)}")
        node[parts[-1]] = _parse_scalar(text.strip())
    return from_dict(type(cfg), data)
