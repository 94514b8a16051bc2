"""Topology validation and membership: neighbours, reference = lowest live id, epochs."""

import threading

import pytest

from protocol.membership import Membership, Topology, TopologyError


def test_neighbours_of_each_kind():
    ids = [0, 1, 2, 3]
    full = Topology.from_spec("full", ids)
    assert full.neighbours(0) == {1, 2, 3} and len(full.edges) == 6
    ring = Topology.from_spec("ring", ids)
    assert ring.neighbours(0) == {1, 3} and ring.neighbours(2) == {1, 3}
    line = Topology.from_spec("line", ids)
    assert line.neighbours(0) == {1} and line.neighbours(1) == {0, 2} and line.neighbours(3) == {2}
    star = Topology.from_spec("star", ids)
    assert star.neighbours(0) == {1, 2, 3} and star.neighbours(2) == {0}
    star2 = Topology.from_spec("star", ids, hub=2)
    assert star2.neighbours(2) == {0, 1, 3} and star2.neighbours(0) == {2}
    edges = Topology.from_spec("edges", ids, edges=[[3, 0], (1, 2), (0, 3)])
    assert edges.edges == ((0, 3), (1, 2))
    assert edges.neighbours(1) == {2}
    assert not edges.is_connected() and line.is_connected() and not line.is_connected([0, 2])


def test_order_given_defines_line_and_ring():
    line = Topology.from_spec("line", [2, 0, 1])
    assert line.edges == ((0, 1), (0, 2))
    assert line.neighbours(0) == {1, 2}


@pytest.mark.parametrize("kind,ids,kw,match", [
    ("ring", [0, 1], {}, "at least 3"),
    ("full", [0, 0, 1], {}, "duplicate"),
    ("full", [], {}, "at least one"),
    ("full", [0, -1], {}, "non-negative"),
    ("star", [0, 1], {"hub": 5}, "hub"),
    ("edges", [0, 1], {"edges": [[0, 2]]}, "not one of"),
    ("edges", [0, 1], {"edges": [[1, 1]]}, "self loop"),
    ("edges", [0, 1], {"edges": [[0, 1, 2]]}, "pair"),
    ("edges", [0, 1], {}, "needs an edge list"),
    ("mesh", [0, 1], {}, "unknown topology kind"),
    ("line", [0, 1], {"edges": [[0, 1]]}, "only used with kind 'edges'"),
])
def test_invalid_topologies_say_why(kind, ids, kw, match):
    with pytest.raises(TopologyError, match=match):
        Topology.from_spec(kind, ids, **kw)


def test_membership_reference_epoch_and_events():
    m = Membership(Topology.from_spec("line", [0, 1, 2, 3]), self_id=2)
    assert m.alive == {2} and m.reference == 2 and m.epoch == 0 and m.live_neighbours == set()
    assert m.update({0, 1, 2, 3}) is True
    assert m.reference == 0 and m.epoch == 1 and m.live_neighbours == {1, 3}
    assert m.update({3, 0, 1}) is False  # self is always alive: same set, no new epoch
    assert m.epoch == 1
    assert m.update({1, 2, 3}) is True  # the reference died
    assert m.reference == 1 and m.epoch == 2 and not m.is_reference
    assert m.update({2, 3, 99}) is True  # unknown ids are ignored, but remembered
    assert m.alive == {2, 3} and m.reference == 2 and m.is_reference and 99 in m.ignored
    assert m.update(set()) is True
    assert m.live_neighbours == set() and m.neighbours == {1, 3}
    events = m.events
    assert [e.epoch for e in events] == [0, 1, 2, 3, 4]
    assert [e.reference for e in events] == [2, 0, 1, 2, 2]
    assert all(a.time <= b.time for a, b in zip(events, events[1:]))
    t, epoch, alive, reference = events[2]
    assert (epoch, alive, reference) == (2, {1, 2, 3}, 1)


def test_membership_needs_self_in_topology():
    with pytest.raises(TopologyError):
        Membership(Topology.from_spec("full", [0, 1]), self_id=5)


def test_concurrent_updates_count_every_change():
    m = Membership(Topology.from_spec("full", list(range(8))), self_id=0)
    changes = []

    def flap(i):
        for n in range(200):
            changes.append(m.update({0, i} if n % 2 else {0}))

    threads = [threading.Thread(target=flap, args=(i,)) for i in range(1, 4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert m.epoch == sum(changes)
    assert len(m.events) == m.epoch + 1
