"""Network namespaces for real: they are made, they isolate, links cut/heal/delay, and they go away.

Needs root and iproute2 (skipped otherwise, with the reason). Every test uses its own prefix,
so it never touches another run's namespaces, and checks that nothing is left behind.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from cli.scenario.netns import NetnsLab, cleanup_stale, list_namespaces, netem_available, run_ip
from tests.scenarios.netns_helpers import needs_netns, probe, start_echo, wait_gone

pytestmark = [needs_netns, pytest.mark.netns]
ROOT = Path(__file__).resolve().parents[2]


def prefix() -> str:
    return f"dnt{os.getpid() % 10000}x{int(time.monotonic() * 1000) % 100000}"


def ours(pfx: str) -> list[str]:
    return [n for n in list_namespaces() if n.startswith(pfx + "-")]


def test_create_isolate_and_remove():
    pfx = prefix()
    lab = NetnsLab([1, 2, 3], [(1, 2), (2, 3)], prefix=pfx)
    with lab:
        names = ours(pfx)
        assert sorted(names) == sorted(lab.ns(r) for r in (1, 2, 3))
        # veths really exist, one per link end, with the link's /30 address
        links2 = run_ip("-o", "addr", "show", ns=lab.ns(2)).stdout
        assert "v1" in links2 and "v3" in links2 and "198.18.0.2/30" in links2 and "198.18.0.5/30" in links2
        # none of our interfaces is in the root namespace
        assert "v1@" not in run_ip("-o", "link", "show").stdout
        servers = [start_echo(lab, r) for r in (1, 3)]
        try:
            assert probe(lab, 2, lab.link(1, 2).addr(1))["ok"]
            assert probe(lab, 2, lab.link(2, 3).addr(3))["ok"]
            far = probe(lab, 1, lab.link(2, 3).addr(3))  # 1 and 3 are not neighbours
            assert not far["ok"] and "unreachable" in far["error"]
        finally:
            for s in servers:
                s.kill()
                s.wait()
    assert wait_gone(names) == []
    assert ours(pfx) == []


def test_cut_blocks_tcp_and_heal_restores_it():
    pfx = prefix()
    with NetnsLab([1, 2], [(1, 2)], prefix=pfx) as lab:
        server = start_echo(lab, 1)
        addr = lab.link(1, 2).addr(1)
        try:
            assert probe(lab, 2, addr)["ok"]
            lab.set_link(1, 2, up=False)
            cut = probe(lab, 2, addr, timeout=1.0)
            assert not cut["ok"], cut
            lab.set_link(1, 2, up=True)
            deadline = time.monotonic() + 5
            while not (healed := probe(lab, 2, addr))["ok"] and time.monotonic() < deadline:
                time.sleep(0.2)
            assert healed["ok"], healed
        finally:
            server.kill()
            server.wait()
    assert ours(pfx) == []


@pytest.mark.parametrize("impair", ["relay"] + (["netem"] if netem_available() else []))
def test_delay_is_measurable_and_removable(impair):
    """100 ms one way: a round trip takes >= 200 ms; removed, it is back to about nothing."""
    pfx = prefix()
    with NetnsLab([1, 2], [(1, 2)], prefix=pfx, impairable=[(1, 2)], impair=impair) as lab:
        assert lab.impair_backend(1, 2) == impair
        server = start_echo(lab, 1)
        addr = lab.link(1, 2).addr(1)
        try:
            clean = statistics.median(probe(lab, 2, addr, n=5)["rtts"])
            lab.impair(1, 2, delay_ms=100)
            slow = probe(lab, 2, addr, n=5)
            assert slow["connect"] >= 0.19, slow  # SYN out, SYN-ACK back
            assert min(slow["rtts"]) >= 0.195 and statistics.median(slow["rtts"]) < 0.35, slow
            lab.impair(1, 2)
            again = statistics.median(probe(lab, 2, addr, n=5)["rtts"])
            assert clean < 0.05 and again < 0.05, (clean, again)
        finally:
            server.kill()
            server.wait()
    assert ours(pfx) == []


def test_loss_drops_its_share_and_tcp_still_delivers(tmp_path):
    """10% loss per packet each way, 2 MB: the emulator drops ~10% of the frames, TCP delivers all."""
    pfx = prefix()
    lab = NetnsLab([1, 2], [(1, 2)], prefix=pfx, impairable=[(1, 2)], impair="relay", log_dir=tmp_path)
    with lab:
        server = start_echo(lab, 1)
        addr = lab.link(1, 2).addr(1)
        try:
            lab.impair(1, 2, delay_ms=20)
            clean = probe(lab, 2, addr, n=1, size=2_000_000, timeout=60)
            lab.impair(1, 2, delay_ms=20, loss=0.1)
            lossy = probe(lab, 2, addr, n=1, size=2_000_000, timeout=120)
            assert clean["ok"] and lossy["ok"], (clean, lossy)
        finally:
            server.kill()
            server.wait()
    assert ours(pfx) == []
    events = [json.loads(x) for x in (tmp_path / "relay-1-2.log").read_text().splitlines() if x.startswith("{")]
    sets = [e for e in events if e["event"] == "set"]
    final = [e for e in events if e["event"] == "exit"][-1]
    before = sets[-1]  # counters when the loss was switched on
    frames = sum(final[d]["frames"] - before[d]["frames"] for d in ("to1->to2", "to2->to1"))
    dropped = sum(final[d]["dropped"] - before[d]["dropped"] for d in ("to1->to2", "to2->to1"))
    assert frames > 1000, final
    assert 0.07 < dropped / frames < 0.13, (dropped, frames)


@pytest.mark.parametrize("impair", ["relay"] + (["netem"] if netem_available() else []))
def test_a_rate_cap_makes_a_transfer_take_size_over_rate(impair):
    """20 Mbit/s: 2.5 MB take at least 1 s (2.5e6 * 8 / 20e6), and not much more; clean, far less."""
    pfx = prefix()
    with NetnsLab([1, 2], [(1, 2)], prefix=pfx, impairable=[(1, 2)], impair=impair) as lab:
        server = start_echo(lab, 1)
        addr = lab.link(1, 2).addr(1)
        try:
            clean = probe(lab, 2, addr, n=1, size=2_500_000, timeout=60)
            lab.impair(1, 2, rate_mbit=20)
            capped = probe(lab, 2, addr, n=1, size=2_500_000, timeout=60)
            lab.impair(1, 2)
            again = probe(lab, 2, addr, n=1, size=2_500_000, timeout=60)
        finally:
            server.kill()
            server.wait()
        assert clean["ok"] and capped["ok"] and again["ok"], (clean, capped, again)
        print(f"2.5 MB: clean {clean['rtts'][0]:.2f} s, at 20 Mbit/s {capped['rtts'][0]:.2f} s, "
              f"clean again {again['rtts'][0]:.2f} s")
        assert 1.0 <= capped["rtts"][0] < 1.6, capped  # headers and acks cost a few percent
        assert clean["rtts"][0] < 0.5 and again["rtts"][0] < 0.5, (clean, again)
    assert ours(pfx) == []


CHILD = textwrap.dedent("""
    import sys, time
    from cli.scenario.netns import NetnsLab, signals_raise
    lab = NetnsLab([1, 2, 3], [(1, 2), (2, 3)], prefix=sys.argv[1], impairable=[(2, 3)])
    with signals_raise():
        try:
            lab.create()
            print(' '.join(lab.namespaces), flush=True)
            time.sleep(60)
        finally:
            lab.cleanup()
""")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cleanup_after_signal(sig):
    pfx = prefix()
    child = subprocess.Popen([sys.executable, "-c", CHILD, pfx], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    names = child.stdout.readline().split()
    assert len(names) == 4 and all(n in list_namespaces() for n in names)  # 3 robots + 1 relay
    child.send_signal(sig)
    child.wait(timeout=20)
    assert wait_gone(names) == []
    assert ours(pfx) == []


def test_cleanup_stale_removes_a_killed_runs_leftovers_only():
    pfx = prefix()
    child = subprocess.Popen([sys.executable, "-c", CHILD, pfx], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    names = child.stdout.readline().split()
    live = NetnsLab([1, 2], [(1, 2)], prefix=pfx).create()  # this process is alive: not stale
    try:
        child.kill()  # SIGKILL: no cleanup ran
        child.wait(timeout=10)
        assert all(n in list_namespaces() for n in names)
        removed = cleanup_stale(pfx)
        assert sorted(removed) == sorted(names)
        assert sorted(ours(pfx)) == sorted(live.namespaces)
    finally:
        live.cleanup()
    assert ours(pfx) == []
