"""The robot image for container runs, built with podman, also where no registry can be reached.

``dinerf-agent scenario image`` (and ``scenario run --mode compose``, before every run, from the
layer cache) builds the repository's ``Dockerfile``. Only its build arguments change:

- ``BASE_IMAGE``: a registry's ``python:3.11-slim`` (the Dockerfile's default), or, where none
  can be pulled, ``localhost/dinerf-base:bookworm``, made here once and then kept:
  ``debootstrap --variant=minbase bookworm``, python3 and python3-venv installed in the chroot,
  the tree imported with ``podman import``. ``auto`` takes the registry's image when it is
  already here, else the Debian base when debootstrap is installed.
- ``TORCH_INDEX``: the CPU index, or empty (pip's own configuration) when the host's pip finds
  a torch wheel in its find-links (as on this project's VMs).

pip in the build uses the host's pip configuration (``pip config list``: files and ``PIP_*``
merged into one ``/etc/pip.conf``), the local paths it names (certificates, constraints,
find-links, the folder above a ``file://`` index) mounted read-only, and the host's network: the build reaches
the index the host reaches. The image is labelled with its build arguments, so the next build
(the one before a compose run) takes the same ones and comes from the cache.
"""

from __future__ import annotations

import ast
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from cli.scenario.podman import PodmanError, container_flags, podman
from cli.scenario.spec import repo_root

__all__ = ["build_base_image", "build_image", "image_exists", "image_size", "host_pip_config", "BASE_TAG"]

BASE_TAG = "localhost/dinerf-base:bookworm"
REGISTRY_BASE = "python:3.11-slim"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
TORCH_SPEC = "torch==2.13.0"
DEBIAN_MIRROR = "http://deb.debian.org/debian"
LABEL = "io.dinerf.build"  # the build arguments, "base|torch spec|torch index"


def image_exists(tag: str) -> bool:
    return podman("image", "exists", tag, check=False).returncode == 0


def image_size(tag: str) -> int:
    return int(podman("image", "inspect", "--format", "{{.Size}}", tag).stdout.strip() or 0)


def build_base_image(tag: str = BASE_TAG, mirror: str = DEBIAN_MIRROR, echo: Callable[[str], None] = print,
                     force: bool = False) -> str:
    """A Debian bookworm base with python3 and venv, made once (root, debootstrap); returns ``tag``."""
    if image_exists(tag) and not force:
        return tag
    if shutil.which("debootstrap") is None:
        raise PodmanError("no base image can be pulled here and debootstrap is not installed "
                          "(Debian: apt-get install debootstrap), or pass --base IMAGE")
    if os.geteuid() != 0:
        raise PodmanError("debootstrap needs root")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="dinerf-base-", dir="/var/tmp") as tmp:
        root = Path(tmp) / "rootfs"
        echo(f"[image] {tag}: debootstrap --variant=minbase bookworm from {mirror} (once; about a minute)")
        _run(["debootstrap", "--variant=minbase", "bookworm", str(root), mirror], "debootstrap")
        _run(["chroot", str(root), "/bin/sh", "-c",
              "export DEBIAN_FRONTEND=noninteractive; apt-get update -qq && apt-get install -y -qq "
              "--no-install-recommends python3 python3-venv ca-certificates >/dev/null && apt-get clean "
              "&& rm -rf /var/lib/apt/lists/*"], "apt-get in the base's chroot")
        tar = subprocess.Popen(["tar", "-C", str(root), "-c", "."], stdout=subprocess.PIPE)
        try:
            p = subprocess.run(["podman", "import", "--change", 'CMD ["/bin/bash"]', "-", tag], stdin=tar.stdout,
                               capture_output=True, text=True)
        finally:
            tar.stdout.close()
            tar.wait()
        if p.returncode != 0 or tar.returncode != 0:
            raise PodmanError(f"podman import of the base failed: {p.stderr.strip()[-300:]}")
    echo(f"[image] {tag}: {image_size(tag) / 1e6:.0f} MB in {time.monotonic() - t0:.0f} s")
    return tag


def _run(argv: list[str], what: str) -> None:
    p = subprocess.run(argv, capture_output=True, text=True)
    if p.returncode != 0:
        raise PodmanError(f"{what} failed: {(p.stderr or p.stdout).strip()[-300:]}")


def host_pip_config() -> tuple[str, list[Path]]:
    """The host's pip configuration as one pip.conf, and the local paths it names."""
    p = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    sections: dict[str, dict[str, str]] = {}
    env: dict[str, str] = {}
    for line in p.stdout.splitlines():
        key, sep, value = line.partition("=")
        if not sep or "." not in key:
            continue
        section, name = key.rsplit(".", 1)
        try:
            value = str(ast.literal_eval(value))
        except (ValueError, SyntaxError):
            continue
        if name == "config-file":  # PIP_CONFIG_FILE: its settings are listed already
            continue
        if section == ":env:":
            env[name] = value
        else:
            sections.setdefault(section, {})[name] = value
    sections.setdefault("global", {}).update(env)  # the environment wins, as in pip
    paths = []
    for values in sections.values():
        for value in values.values():
            for token in value.split():
                path = Path(token.removeprefix("file://"))
                if token.startswith("file://"):  # a local index: its pages link to files beside it
                    path = path.parent
                if path.is_absolute() and path.exists() and path not in paths:
                    paths.append(path)
    text = "".join(f"[{s}]\n" + "".join(f"{k} = {v}\n" for k, v in kv.items()) for s, kv in sections.items())
    return text, paths


def _torch_index(paths: list[Path]) -> str:
    """Empty (pip's configuration) when the host's pip holds a torch wheel, else the CPU index."""
    return "" if any(p.is_dir() and any(p.glob("torch-*.whl")) for p in paths) else CPU_INDEX


def resolve_base(base: str) -> str:
    """``auto`` -> the registry's python image if it is here, else the Debian base (made if needed)."""
    if base == "auto":
        if image_exists(REGISTRY_BASE) or shutil.which("debootstrap") is None:
            return REGISTRY_BASE
        return "debootstrap"
    return base


def _previous_args(tag: str) -> list[str] | None:
    if not image_exists(tag):
        return None
    text = podman("image", "inspect", "--format", f'{{{{index .Labels "{LABEL}"}}}}', tag, check=False).stdout.strip()
    parts = text.split("|")
    return parts if len(parts) == 3 else None


def build_image(tag: str, base: str = "auto", torch_spec: str | None = None, torch_index: str | None = None,
                log: Path | None = None, echo: Callable[[str], None] = print, mirror: str = DEBIAN_MIRROR) -> float:
    """Build the Dockerfile into ``tag``; returns the seconds it took.

    Arguments left unset (``auto``/None) are those of the image already under ``tag``, so the build
    before each compose run comes from the cache; otherwise see the module docstring.
    """
    previous = _previous_args(tag) if base == "auto" and torch_spec is None and torch_index is None else None
    if previous is not None:
        base, torch_spec, torch_index = previous
        if base == BASE_TAG and not image_exists(BASE_TAG):
            base = "debootstrap"
    base = resolve_base(base)
    if base == "debootstrap":
        base = build_base_image(BASE_TAG, mirror, echo)
    conf, paths = host_pip_config()
    torch_spec = torch_spec or TORCH_SPEC
    if torch_index is None:
        torch_index = _torch_index(paths)
    old = podman("image", "inspect", "--format", "{{.Id}}", tag, check=False).stdout.strip()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="dinerf-pip-") as tmp:
        (Path(tmp) / "pip.conf").write_text(conf)
        mounts = ["-v", f"{tmp}/pip.conf:/etc/pip.conf:ro"]
        for p in paths:
            mounts += ["-v", f"{p}:{p}:ro"]
        argv = ["podman", "build", "--format", "docker", "--network", "host", *container_flags(), *mounts,
                "--build-arg", f"BASE_IMAGE={base}", "--build-arg", f"TORCH_SPEC={torch_spec}",
                "--build-arg", f"TORCH_INDEX={torch_index}", "--label", f"{LABEL}={base}|{torch_spec}|{torch_index}",
                "-t", tag, "-f", str(repo_root() / "Dockerfile"), str(repo_root())]
        source = torch_index or "pip's configuration"
        echo(f"[image] {tag}: building from {base} (torch {torch_spec} from {source})" + (f", log in {log}" if log else ""))
        with (log.open("a") if log else contextlib.nullcontext()) as out:
            p = subprocess.run(argv, stdout=out if log else None, stderr=subprocess.STDOUT if log else None)
    if p.returncode != 0:
        tail = _tail(log) if log else ""
        raise PodmanError(f"podman build of {tag} failed (exit {p.returncode}){': ' + tail if tail else ''}")
    seconds = time.monotonic() - t0
    if old and old != podman("image", "inspect", "--format", "{{.Id}}", tag).stdout.strip():
        podman("rmi", old, check=False)  # the previous build, untagged now (refused while a container uses it)
    echo(f"[image] {tag}: {image_size(tag) / 1e9:.2f} GB, built in {seconds:.0f} s")
    return seconds


def _tail(path: Path) -> str:
    lines = [l for l in path.read_text(errors="replace").splitlines() if l.strip()]
    return " | ".join(lines[-3:])[-400:]
