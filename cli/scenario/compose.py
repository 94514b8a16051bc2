"""A scenario as a ``docker-compose.yml``: one service per robot, one network per topology link.

Each link a-b is its own internal bridge network with a /29 of ``198.18.0.0/15`` (Docker takes
the first address for its gateway; ``a`` gets ``.2``, ``b`` gets ``.3``), and a robot's service
is attached only to the networks of its links, so, as with the namespaces of ``--mode netns``,
only neighbours can reach each other. A robot listens on its address on each of its links and
connects to its neighbours' addresses there (``--listen``/``--connect``), so the endpoints in
the command lines match the static addresses.

Links are mutual TLS (``tls/``) with the certificates ``--data`` writes into each robot folder
(``tls/``; the CA stays in ``./data/ca``, which no service mounts), unless the scenario says
``[security] insecure = true``.
Mounts per service: its own robot folder read-only at ``/data/robot``, the swarm TOML and
``scene.json`` read-only in ``/swarm``, and its run dir ``./runs/robot<id>`` at ``/run/robot``.
The image is built from the repository's ``Dockerfile`` (CPU torch).

The YAML is written here (no YAML library needed): block style, every string double-quoted
(a JSON string is a valid YAML double-quoted scalar).
"""

from __future__ import annotations

import ipaddress
import json
import os
from pathlib import Path
from typing import Any

from cli.scenario.runner import link_scheme, prepare_split, swarm_document
from cli.scenario.spec import ScenarioSpec, repo_root
from cli.scenario.tomlout import dumps as toml_dumps

__all__ = ["compose_document", "write_compose", "dump_yaml", "link_addresses"]

BASE = "198.18.0.0/15"
PORT = 7447
IMAGE = "dinerf-agent:latest"


def link_addresses(links: list[tuple[int, int]], base: str = BASE) -> dict[tuple[int, int], dict[str, Any]]:
    """{(a, b): {"subnet": ..., a: addr, b: addr}} for the sorted links."""
    subnets = ipaddress.ip_network(base).subnets(new_prefix=29)
    out = {}
    for (a, b), net in zip(sorted((min(x, y), max(x, y)) for x, y in links), subnets):
        out[(a, b)] = {"subnet": str(net), a: str(net.network_address + 2), b: str(net.network_address + 3)}
    return out


def network_name(a: int, b: int) -> str:
    return f"link-{a}-{b}"


def compose_document(spec: ScenarioSpec, compose_dir: Path) -> dict[str, Any]:
    """The compose file as a dict (paths relative to ``compose_dir``, where it will be written)."""
    addrs = link_addresses(spec.links)
    context = os.path.relpath(repo_root(), compose_dir.resolve())
    services: dict[str, Any] = {}
    for i in spec.ids:
        mine = [(key, info) for key, info in addrs.items() if i in key]
        cmd = ["up", "--id", str(i), "--data", "/data/robot", "--swarm", "/swarm/swarm.toml", "--run-dir", "/run/robot"]
        for _, info in mine:
            cmd += ["--listen", *link_scheme(spec, [f"tcp/{info[i]}:{PORT}"])]
        for (a, b), info in mine:
            other = b if i == a else a
            cmd += ["--connect", *link_scheme(spec, [f"tcp/{info[other]}:{PORT}"])]
        services[f"robot{i}"] = {
            "build": {"context": context, "dockerfile": "Dockerfile"},
            "image": IMAGE,
            "user": "${DINERF_UID:-1000}:${DINERF_GID:-1000}",  # the run dirs' owner on the host
            "command": cmd,
            "environment": {"PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": str(spec.daemon.threads)},
            "volumes": [
                f"./data/robot{i}:/data/robot:ro",
                "./swarm.toml:/swarm/swarm.toml:ro",
                "./data/scene.json:/swarm/scene.json:ro",
                f"./runs/robot{i}:/run/robot",
            ],
            "networks": {network_name(*key): {"ipv4_address": info[i]} for key, info in mine},
            "stop_grace_period": "20s",
        }
    networks = {
        network_name(*key): {"driver": "bridge", "internal": True, "ipam": {"config": [{"subnet": info["subnet"]}]}}
        for key, info in addrs.items()
    }
    return {"services": services, "networks": networks}  # no top-level name: docker-compose 1.x rejects it


def write_compose(spec: ScenarioSpec, path: Path, with_data: bool = False) -> Path:
    """Write ``path`` (docker-compose.yml) and ``swarm.toml`` beside it; with ``with_data`` the split too."""
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    doc = compose_document(spec, folder)
    header = (f"# written by `dinerf-agent scenario compose {spec.name}`: one service per robot, one network per link.\n"
              f"# Robot folders: `dinerf-agent scenario compose {spec.name} --data` writes them into ./data;\n"
              f"# then `DINERF_UID=$(id -u) DINERF_GID=$(id -g) docker compose up --build` (run dirs appear in ./runs).\n")
    path.write_text(header + dump_yaml(doc))
    swarm = swarm_document(spec, "scene.json", None, spec.name)
    (folder / "swarm.toml").write_text(f"# swarm file of scenario {spec.name!r} for docker compose\n" + toml_dumps(swarm))
    if with_data:
        prepare_split(spec, folder / "data")
        for i in spec.ids:  # created here, not by Docker (which would make them root's: the robot is not root)
            (folder / "runs" / f"robot{i}").mkdir(parents=True, exist_ok=True)
    return path


def _scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return json.dumps(v)
    return json.dumps(str(v))


def dump_yaml(data: Any, indent: int = 0) -> str:
    """dict/list/scalars -> block-style YAML."""
    pad = "  " * indent
    lines: list[str] = []
    if isinstance(data, dict):
        for k, v in data.items():
            key = k if isinstance(k, str) and k.replace("-", "").replace("_", "").isalnum() else json.dumps(str(k))
            if isinstance(v, (dict, list)) and v:
                lines.append(f"{pad}{key}:")
                lines.append(dump_yaml(v, indent + 1).rstrip("\n"))
            elif isinstance(v, dict):
                lines.append(f"{pad}{key}: {{}}")
            elif isinstance(v, list):
                lines.append(f"{pad}{key}: []")
            else:
                lines.append(f"{pad}{key}: {_scalar(v)}")
    elif isinstance(data, list):
        for v in data:
            if isinstance(v, (dict, list)) and v:
                inner = dump_yaml(v, indent + 1).rstrip("\n").splitlines()
                first = inner[0].lstrip()
                lines.append(f"{pad}- {first}")
                lines.extend(inner[1:])
            else:
                lines.append(f"{pad}- {_scalar(v) if not isinstance(v, (dict, list)) else ('{}' if isinstance(v, dict) else '[]')}")
    else:
        lines.append(f"{pad}{_scalar(data)}")
    return "\n".join(lines) + "\n"
