"""Liveness beyond direct neighbours (gossip of ages), pure logic with explicit clocks."""

from protocol.membership import AliveView, Membership, Topology


def test_direct_tokens_and_self_are_alive():
    v = AliveView(2, expiry_s=2.0)
    v.set_direct({1, 3}, now=0.0)
    assert v.alive(now=100.0) == {1, 2, 3}  # direct tokens never expire while present


def test_relayed_evidence_expires_after_the_last_witness_loses_the_token():
    # line 1 - 2 - 3: robot 3 hears of robot 1 only through robot 2's reports
    r2, r3 = AliveView(2), AliveView(3, expiry_s=2.0)
    r2.set_direct({1, 3}, now=0.0)
    r3.set_direct({2}, now=0.0)
    r3.merge(r2.report(now=0.0), now=0.05)
    assert 1 in r3.alive(now=0.1)
    r2.set_direct({3}, now=1.0)  # robot 1 killed: robot 2 sees the token go at t=1
    for t in (1.5, 2.0, 2.5):  # robot 2 keeps reporting, but no longer vouches for 1
        r3.merge(r2.report(now=t), now=t)
    assert 1 not in r2.alive(now=1.0)  # the witness stops vouching at once
    assert 1 in r3.alive(now=2.0)  # r3's last evidence is from t=0.05: still within 2 s
    assert 1 not in r3.alive(now=2.1)  # ... and gone once it is older than the expiry


def test_ages_grow_as_they_travel_so_gossip_cannot_keep_a_dead_robot_alive():
    a, b = AliveView(2, expiry_s=2.0), AliveView(3, expiry_s=2.0)
    a.merge({1: 0.0}, now=0.0)  # one last report of robot 1
    for t in [0.5 * k for k in range(1, 10)]:  # a and b gossip back and forth
        b.merge(a.report(now=t), now=t)
        a.merge(b.report(now=t), now=t)
    assert 1 not in a.alive(now=4.5) and 1 not in b.alive(now=4.5)


def test_a_token_seen_leaving_overrides_older_relayed_evidence():
    v = AliveView(2, expiry_s=2.0)
    v.set_direct({1}, now=0.0)
    v.set_direct(set(), now=1.0)  # robot 1 left at t=1
    v.merge({1: 0.2}, now=1.1)  # a neighbour's report from before the departure (t=0.9)
    v.merge({1: 0.0}, now=1.3)  # sent just before the departure, arrived after it: within the grace
    assert 1 not in v.alive(now=1.4)
    assert v.direct == frozenset()
    v.merge({1: 0.0}, now=5.0)  # robot 1 came back and someone sees it
    assert 1 in v.alive(now=5.1)


def test_membership_reference_follows_the_alive_view():
    topo = Topology.from_spec("line", [1, 2, 3])
    m = Membership(topo, 3)
    v = AliveView(3, expiry_s=2.0)
    v.set_direct({2}, now=0.0)
    v.merge({1: 0.1, 2: 0.0, 3: 0.0}, now=0.0)
    m.update(v.alive(now=0.0))
    assert m.reference == 1 and m.live_neighbours == {2}
    m.update(v.alive(now=3.0))  # no more news of robot 1
    assert m.reference == 2


def test_last_heard_counts_silence_from_the_last_message_or_from_the_start():
    from protocol.membership import LastHeard

    clock = LastHeard(since=100.0)
    assert clock.silence_s(3, now=101.5) == 1.5  # never heard: counted from the start
    clock.heard(3, now=102.0)
    clock.heard(3, now=101.0)  # a late callback never moves the clock back
    assert clock.silence_s(3, now=104.0) == 2.0
    assert clock.silent([3, 4], after_s=3.0, now=104.0) == {4}  # 4: never heard, 4 s
    assert clock.silent([3, 4], after_s=3.0, now=105.0) == {3, 4}
    assert clock.silent([3], after_s=3.0, now=104.9) == frozenset()
