"""PullPacing: pull late from a neighbour whose pushes are slow, early again once they are fast."""

from protocol.exchange import PullPacing


def test_a_wasted_pull_doubles_the_delay_up_to_the_cap_either_order():
    p = PullPacing(base_s=2.0, max_s=5.0)
    assert p.delay(3) == 2.0
    p.pulled(3, 4)
    p.pushed(3, 4, waited_s=3.0)  # the push was only slow: the pull duplicated it
    assert p.delay(3) == 4.0
    p.pushed(3, 5, waited_s=4.5)  # push first, then the pull also brings round 5
    p.pulled(3, 5)
    assert p.delay(3) == 5.0  # capped
    p.pulled(3, 5)  # the same round again counts once
    assert p.delay(3) == 5.0 and p.delay(2) == 2.0  # per neighbour


def test_a_needed_pull_or_a_fast_push_brings_the_delay_back_down():
    p = PullPacing(base_s=2.0, max_s=16.0)
    for r in range(3):
        p.pulled(1, r)
        p.pushed(1, r, waited_s=3.0)
    assert p.delay(1) == 16.0
    p.pulled(1, 3)  # its push never comes (a one-sided link) ...
    assert p.delay(1) == 16.0
    p.pulled(1, 4)  # ... so that pull was needed: ask earlier
    assert p.delay(1) == 8.0
    p.pushed(1, 5, waited_s=5.0)  # not fast enough to trust
    assert p.delay(1) == 8.0
    p.pushed(1, 6, waited_s=1.0)
    p.pushed(1, 7, waited_s=0.0)  # arrived before our barrier began
    assert p.delay(1) == 2.0
    for r in range(8, 12):
        p.pushed(1, r, waited_s=0.5)
    assert p.delay(1) == 2.0  # never below the base
