"""Robust consensus costs an honest swarm nothing: no honest neighbour's model is clipped, found
erratic or unrelated, so every robot ends bit for bit as it would without it; and a poisoner caught
in its first forged round costs it nothing either (the in-process simulation of a real swarm's
files, the daemons' wire included)."""

from __future__ import annotations

import torch

from tests.system.harness import make_swarm, simulate


def test_an_honest_swarm_ends_bit_for_bit_as_without_robust_consensus(tmp_path):
    swarm = make_swarm(tmp_path, robots=3, topology="full")
    robust = simulate(swarm)
    plain = simulate(swarm, overrides=["training.consensus.robust.enabled=false"])
    for i, robot in robust.robots.items():
        clipper = robot.trainer.consensus.clipper
        assert (clipper.clipped_count, clipper.erratic_count, clipper.uncorrelated_count) == (0, 0, 0), i
        assert clipper.cfg.enabled and not plain.robots[i].trainer.consensus.clipper.cfg.enabled
        theirs = plain.robots[i].trainer.theta()
        for name, t in robot.trainer.theta().items():
            assert torch.equal(t, theirs[name]), (i, name)


def _noise(sender: int, round_index: int, theta):
    if sender != 3 or round_index < 1:
        return None
    g = torch.Generator().manual_seed(round_index)
    return {n: torch.randn(t.shape, generator=g) * t.pow(2).mean().sqrt() for n, t in theta.items()}


def test_a_poisoner_named_in_its_first_round_leaves_the_honest_robots_as_if_it_had_fallen_silent(tmp_path):
    swarm = make_swarm(tmp_path, robots=3, topology="full")
    attacked = simulate(swarm, forge=_noise)
    silent = simulate(swarm, silent_from={3: 1})
    for i in (1, 2):
        assert attacked.robots[i].trainer.consensus.clipper.quarantined == {3}, i
        theirs = silent.robots[i].trainer.theta()
        for name, t in attacked.robots[i].trainer.theta().items():
            assert torch.equal(t, theirs[name]), (i, name)
