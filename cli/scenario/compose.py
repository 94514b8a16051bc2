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
``scene.json`` read-only in ``/swarm``, and its run dir ``./robots/<id>`` at ``/run/robot`` (the
layout of a ``scenario run`` folder). Zenoh's shared memory is off, as between machines. The
image is built from the repository's ``Dockerfile`` (CPU torch).

Faults: a link impaired for the whole run (``[[faults.netem]]`` from round 0 without an end,
e.g. a rate cap) is part of the network, so the file says it: a ``robot<i>-links`` service
per robot on such a link runs ``tc`` in that robot's namespace once it has started. The faults
with a time (kill, restart, freeze, cut, netem for some rounds) are not compose's to say:
``scenario run --mode compose`` applies them from outside (:mod:`cli.scenario.podman`).

The YAML is written here (no YAML library needed): block style, every string double-quoted
(a JSON string is a valid YAML double-quoted scalar).
"""

from __future__ import annotations

import ipaddress
import json
import os
from pathlib import Path
from typing import Any

from cli.scenario.netns import netem_args
from cli.scenario.runner import link_scheme, prepare_split, swarm_document
from cli.scenario.spec import NetemFault, ScenarioSpec, repo_root
from cli.scenario.tomlout import dumps as toml_dumps

__all__ = ["compose_document", "write_compose", "dump_yaml", "link_addresses", "robot_command", "static_impairments",
           "qdisc_variants"]

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


def robot_command(spec: ScenarioSpec, i: int, addrs: dict[tuple[int, int], dict[str, Any]]) -> list[str]:
    """Robot i's ``up`` in its container: it listens on its address on each of its links and
    connects to its neighbours' addresses there."""
    mine = [(key, info) for key, info in addrs.items() if i in key]
    cmd = ["up", "--id", str(i), "--data", "/data/robot", "--swarm", "/swarm/swarm.toml", "--run-dir", "/run/robot"]
    for _, info in mine:
        cmd += ["--listen", *link_scheme(spec, [f"tcp/{info[i]}:{PORT}"])]
    for (a, b), info in mine:
        other = b if i == a else a
        cmd += ["--connect", *link_scheme(spec, [f"tcp/{info[other]}:{PORT}"])]
    return cmd


def static_impairments(spec: ScenarioSpec) -> list[NetemFault]:
    """The ``[[faults.netem]]`` that last the whole run (rate caps, a slow link): the links
    themselves, which the compose file sets up; the others have a time and need the runner."""
    return [f for f in spec.faults.netem if f.from_round == 0 and (f.to_round is None or f.to_round >= spec.rounds)]


def qdisc_variants(delay_ms: float, jitter_ms: float, loss: float, rate_mbit: float) -> list[list[str]]:
    """``tc qdisc replace ... root`` arguments to try in turn: netem, then for a rate cap alone
    ``tbf`` (kernels without ``sch_netem``; a queue of ~1000 full frames, as netem's limit)."""
    out = [["netem", *netem_args(delay_ms, jitter_ms, loss, rate_mbit)]]
    if rate_mbit and not delay_ms and not loss:
        out.append(["tbf", "rate", f"{rate_mbit:g}mbit", "burst", "32kb", "limit", "1514000"])
    return out


# The link service's shell: the interface that holds a link's address gets the qdisc. Compose
# substitutes $VARS in every string, so the dollars are doubled when it goes into the file.
_QDISC_SH = """set -e
qdisc() {
  dev=$(ip -o -4 addr show to "$1/32" | { read -r _ d _; echo "$d"; })
  [ -n "$dev" ] || { echo "no interface with address $1" >&2; return 1; }
  shift; tc qdisc replace dev "$dev" root "$@" && echo "$dev: $*"
}
"""


def link_service(spec: ScenarioSpec, i: int, addrs: dict[tuple[int, int], dict[str, Any]], image: str) -> dict | None:
    """``robot<i>-links``: ``tc`` on robot i's ends of its links impaired for the whole run, as root
    with NET_ADMIN in robot i's network namespace (the robot itself stays unprivileged); it exits
    once done. None when robot i has no such link."""
    lines = []
    for f in static_impairments(spec):
        key = (min(f.link), max(f.link))
        if i in key:
            variants = qdisc_variants(f.delay_ms, f.jitter_ms, f.loss, f.rate_mbit)
            lines.append(" || ".join(f"qdisc {addrs[key][i]} {' '.join(v)}" for v in variants))
    if not lines:
        return None
    return {"image": image, "user": "0:0", "network_mode": f"service:robot{i}", "cap_add": ["NET_ADMIN"],
            "depends_on": [f"robot{i}"], "entrypoint": ["sh", "-c", (_QDISC_SH + "\n".join(lines)).replace("$", "$$")],
            "healthcheck": {"disable": True}, "restart": "no"}


def compose_document(spec: ScenarioSpec, compose_dir: Path, image: str = IMAGE) -> dict[str, Any]:
    """The compose file as a dict (paths relative to ``compose_dir``, where it will be written)."""
    addrs = link_addresses(spec.links)
    context = os.path.relpath(repo_root(), compose_dir.resolve())
    services: dict[str, Any] = {}
    for i in spec.ids:
        mine = [(key, info) for key, info in addrs.items() if i in key]
        services[f"robot{i}"] = {
            "build": {"context": context, "dockerfile": "Dockerfile"},
            "image": image,
            "user": "${DINERF_UID:-1000}:${DINERF_GID:-1000}",  # the run dirs' owner on the host
            "command": robot_command(spec, i, addrs),
            "environment": {"PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": str(spec.daemon.threads)},
            "volumes": [
                f"./data/robot{i}:/data/robot:ro",
                "./swarm.toml:/swarm/swarm.toml:ro",
                "./data/scene.json:/swarm/scene.json:ro",
                f"./robots/{i}:/run/robot",  # as `scenario run` lays out its run dirs
            ],
            "networks": {network_name(*key): {"ipv4_address": info[i]} for key, info in mine},
            "stop_grace_period": "20s",
        }
        if (links := link_service(spec, i, addrs, image)) is not None:
            services[f"robot{i}-links"] = links
    networks = {
        network_name(*key): {"driver": "bridge", "internal": True, "ipam": {"config": [{"subnet": info["subnet"]}]}}
        for key, info in addrs.items()
    }
    return {"services": services, "networks": networks}  # no top-level name: docker-compose 1.x rejects it


def _header(spec: ScenarioSpec) -> str:
    lines = [f"# written by `dinerf-agent scenario compose {spec.name}`: one service per robot, one network per link.",
             f"# Robot folders: `dinerf-agent scenario compose {spec.name} --data` writes them into ./data;",
             "# then `DINERF_UID=$(id -u) DINERF_GID=$(id -g) docker compose up --build` (run dirs appear in ./robots).",
             f"# With podman, faults included: `dinerf-agent scenario run {spec.name} --mode compose` (as root)."]
    static = static_impairments(spec)
    if static:
        lines.append("# Links impaired for the whole run: the robot<i>-links services (tc, once the robot has started).")
    timed = {**spec.faults.counts(), **({"netem": len(spec.faults.netem) - len(static)} if static else {})}
    timed = {k: n for k, n in timed.items() if n}
    if timed:
        lines.append("# Not in this file, applied from outside by `scenario run --mode compose` at their rounds: "
                     + ", ".join(f"{n} {k}" for k, n in timed.items()) + " (scenario.toml [faults]).")
    return "\n".join(lines) + "\n"


def write_compose(spec: ScenarioSpec, path: Path, with_data: bool = False, image: str = IMAGE) -> Path:
    """Write ``path`` (docker-compose.yml) and ``swarm.toml`` beside it; with ``with_data`` the split too."""
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    doc = compose_document(spec, folder, image)
    path.write_text(_header(spec) + dump_yaml(doc))
    swarm = swarm_document(spec, "scene.json", None, spec.name, separate_hosts=True)
    (folder / "swarm.toml").write_text(f"# swarm file of scenario {spec.name!r} for docker compose\n" + toml_dumps(swarm))
    if with_data:
        prepare_split(spec, folder / "data")
        for i in spec.ids:  # made here, not by the container engine (which would make them root's)
            (folder / "robots" / str(i)).mkdir(parents=True, exist_ok=True)
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
