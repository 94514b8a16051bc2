"""A robot's field as ``field.safetensors`` + ``field.json``: what another program needs to evaluate it.

The tensors are the field's own (``NGPField.state_dict()``: the hash table and the two MLPs) and
the occupancy grid as bytes; the JSON says how they compute density and colour, with no
reference to this package: the hash grid's levels, resolutions, which levels are indexed densely
and which hashed, the primes, each MLP layer's tensors and activation, the coordinate chain from
the shared frame to the grid, and the renderer's settings. docs/export.md is the specification;
tests/outputs/ re-implements the density in numpy from these two files alone.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from agent.nerf.encoding import HASH_PRIMES
from agent.nerf.field import NGPField
from agent.trainer import RobotTrainer

__all__ = ["FORMAT", "VERSION", "export_weights", "field_config"]

FORMAT = "dinerf-field"
VERSION = 1


def _layers(prefix: str, seq: nn.Sequential) -> list[dict]:
    """``y = act(x @ weight.T + bias)`` per Linear of ``seq``, with the activation that follows it."""
    mods = list(seq)
    out = []
    for k, m in enumerate(mods):
        if isinstance(m, nn.Linear):
            act = "relu" if k + 1 < len(mods) and isinstance(mods[k + 1], nn.ReLU) else "none"
            out.append({"weight": f"{prefix}.{k}.weight", "bias": f"{prefix}.{k}.bias",
                        "in": m.in_features, "out": m.out_features, "activation": act})
    return out


def field_config(trainer: RobotTrainer) -> dict:
    """The JSON document describing the field of ``trainer`` (see docs/export.md)."""
    field: NGPField = trainer.field
    g, enc = field.cfg.grid, field.encoding
    lw = trainer.level_weights()
    m = trainer.cfg.march
    return {
        "format": FORMAT, "version": VERSION, "tensors": "field.safetensors",
        "frame": {
            "box_from_shared": trainer.box_from_shared.double().cpu().tolist(),
            "unbounded": field.unbounded,
        },
        "hash_grid": {
            "table": "encoding.table", "num_levels": g.num_levels, "features_per_level": g.features_per_level,
            "table_size": enc.table_size, "resolutions": g.resolutions(),
            "dense": [level in enc.dense_levels for level in range(g.num_levels)],
            "primes": list(HASH_PRIMES),
            "level_weights": None if lw is None else lw.cpu().tolist(),
        },
        "density_mlp": {"input": "hash_grid features", "layers": _layers("density_mlp", field.density_mlp),
                        "density": "exp(out[0] + density_bias), 0 outside [0, 1]^3",
                        "density_bias": field.cfg.density_bias, "geo": "out[1:]", "geo_features": field.cfg.geo_features},
        "color_mlp": {"input": "concat(geo, SH(unit direction))", "layers": _layers("color_mlp", field.color_mlp),
                      "sh_degree": field.cfg.sh_degree, "output": "sigmoid"},
        "occupancy": {"tensor": "occupancy", "resolution": trainer.grid.cfg.resolution,
                      "index": "(i * R + j) * R + k of the cell (i, j, k) = floor((grid + 1) * R / 2)"},
        "render": {"step_size": m.step_size, "near": m.near, "far": m.far, "cone_angle": m.cone_angle,
                   "early_stop_eps": m.early_stop_eps, "background": [1.0, 1.0, 1.0]},
    }


def export_weights(trainer: RobotTrainer, out: Path, about: dict | None = None) -> tuple[Path, Path]:
    """Write ``out/field.safetensors`` and ``out/field.json``; ``about``: provenance merged into the JSON."""
    from safetensors.torch import save_file

    out.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().float().contiguous() for k, v in trainer.field.state_dict().items()}
    tensors["occupancy"] = trainer.grid.occupied.cpu().to(torch.uint8).contiguous()
    st, js = out / "field.safetensors", out / "field.json"
    save_file(tensors, str(st), metadata={"format": FORMAT, "version": str(VERSION), "config": js.name})
    js.write_text(json.dumps({**field_config(trainer), **(about or {})}, indent=2) + "\n")
    return st, js
