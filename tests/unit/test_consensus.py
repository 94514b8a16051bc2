"""C-ADMM on problems with a known answer, independent of NeRF and of the network. The tests of
the arithmetic take every neighbour's value as it comes (robust consensus off: its clipping is
tested in tests/unit/test_robust.py, on these problems too)."""

import pytest
import torch

from agent.consensus import Consensus, ConsensusConfig, disagreement
from agent.robust import RobustConfig
from protocol.membership import Topology


def _plain(**kw) -> ConsensusConfig:
    return ConsensusConfig(**kw, robust=RobustConfig(enabled=False))


def test_penalty_gradient_matches_autograd():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(7, 3, generator=g, requires_grad=True)
    own = [torch.randn(7, 3, generator=g)]
    nbrs = {2: [torch.randn(7, 3, generator=g)], 5: [torch.randn(7, 3, generator=g)]}
    c = Consensus([p], _plain(rho0=0.7))
    c.begin_round(0, own, nbrs)
    c.duals[0] = torch.randn(7, 3, generator=g)  # as if the edges' duals summed to this
    c.add_penalty_grad([p])
    explicit = p.grad.clone()
    p.grad = None
    anchors = [(own[0] + t[0]) / 2 for t in nbrs.values()]
    value = (p * c.duals[0]).sum() + 0.7 * sum(((p - a) ** 2).sum() for a in anchors)
    value.backward()
    assert torch.allclose(explicit, p.grad, atol=1e-5)


def test_a_parameter_with_a_rho_scale_is_penalised_and_priced_that_much_more():
    table, mlp = torch.zeros(4), torch.zeros(4)
    c = Consensus([table, mlp], _plain(rho0=0.1, mlp_rho_scale=30.0), rho_scales=[1.0, 30.0])
    nbrs = {2: [torch.ones(4), torch.ones(4)]}
    c.begin_round(0, [table, mlp], nbrs)
    c.add_penalty_grad([table, mlp])
    assert torch.allclose(mlp.grad, 30 * table.grad) and bool((table.grad != 0).all())
    c.dual_update([table, mlp], nbrs)
    assert torch.allclose(c.edge_duals[2][1], 30 * c.edge_duals[2][0])
    with pytest.raises(ValueError):
        Consensus([table], _plain(), rho_scales=[1.0, 2.0])
    with pytest.raises(ValueError):
        ConsensusConfig(mlp_rho_scale=0.0)


def test_the_trainer_gives_the_hash_table_rho_and_the_mlps_the_scaled_rho():
    from agent.data.loaders import load_views
    from agent.trainer import RobotTrainer, TrainConfig

    views = load_views("procedural:views=4,width=8")
    trainer = RobotTrainer(views, TrainConfig(), torch.eye(4), consensus=ConsensusConfig(mlp_rho_scale=100.0))
    names = [n for n, _ in trainer.field.named_parameters()]
    scales = dict(zip(names, trainer.consensus.rho_scales))
    assert scales["encoding.table"] == 1.0 and all(v == 100.0 for n, v in scales.items() if n != "encoding.table")


def test_rho_schedule_and_validation():
    cfg = ConsensusConfig(rho0=0.5, rho_growth=1.1, rho_max=0.6)
    assert cfg.rho(0) == 0.5 and cfg.rho(1) == pytest.approx(0.55) and cfg.rho(5) == 0.6
    with pytest.raises(ValueError):
        ConsensusConfig(rho0=0.0)


def _least_squares_problem(n_robots, dim, rows, seed):
    g = torch.Generator().manual_seed(seed)
    a = [torch.randn(rows, dim, generator=g, dtype=torch.float64) for _ in range(n_robots)]
    b = [torch.randn(rows, generator=g, dtype=torch.float64) for _ in range(n_robots)]
    x_star = torch.linalg.lstsq(torch.cat(a), torch.cat(b)).solution
    return a, b, x_star


def newton_step(cons: Consensus, x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> None:
    """The exact primal step of ``||a x - b||^2`` + the consensus terms (quadratic: one Newton
    step with the gradient from ``add_penalty_grad`` and the Hessian ``2 a^T a + 2 rho n I``)."""
    x.grad = None
    ((a @ x - b) ** 2).sum().backward()
    cons.add_penalty_grad([x])
    hessian = 2 * a.T @ a + 2 * cons.rho * cons.num_neighbours * torch.eye(len(x), dtype=x.dtype)
    with torch.no_grad():
        x -= torch.linalg.solve(hessian, x.grad)


def test_distributed_least_squares_on_a_ring_of_5_reaches_the_centralised_optimum():
    """Each robot sees only its rows, too few to determine x alone (rows < dim).

    The primal step is exact (:func:`newton_step`).
    """
    n, dim = 5, 8
    a, b, x_star = _least_squares_problem(n, dim, rows=4, seed=1)
    topo = Topology.from_spec("ring", list(range(n)))
    xs = [torch.zeros(dim, dtype=torch.float64, requires_grad=True) for _ in range(n)]
    cons = [Consensus([x], _plain(rho0=1.0)) for x in xs]
    for k in range(300):
        snapshot = [x.detach().clone() for x in xs]
        for i in range(n):
            cons[i].begin_round(k, [snapshot[i]], {j: [snapshot[j]] for j in topo.neighbours(i)})
            newton_step(cons[i], xs[i], a[i], b[i])
        new = [x.detach().clone() for x in xs]
        for i in range(n):
            cons[i].dual_update([new[i]], {j: [new[j]] for j in topo.neighbours(i)})
    for x in xs:
        rel = float((x.detach() - x_star).norm() / x_star.norm())
        assert rel < 1e-4, rel
    assert max(disagreement([[x.detach()] for x in xs])) < 1e-4


def test_without_consensus_robots_do_not_agree():
    """The same problem with no neighbours: a check that the test above can fail."""
    n, dim = 5, 8
    a, b, x_star = _least_squares_problem(n, dim, rows=4, seed=1)
    xs = [torch.linalg.lstsq(a[i], b[i]).solution for i in range(n)]
    assert max(float((x - x_star).norm() / x_star.norm()) for x in xs) > 0.1


def test_state_roundtrip_and_shape_mismatch():
    p = torch.zeros(3)
    c = Consensus([p], _plain(rho0=1.0))
    c.dual_update([torch.ones(3)], {2: [torch.zeros(3)], 5: [2 * torch.ones(3)]})
    state = c.state_dict()
    c2 = Consensus([torch.zeros(3)], _plain())
    c2.load_state_dict(state)
    assert set(c2.edge_duals) == {2, 5}
    assert all(torch.equal(c2.edge_duals[j][0], c.edge_duals[j][0]) for j in (2, 5))
    with pytest.raises(ValueError, match="shapes"):
        Consensus([torch.zeros(4)], _plain()).load_state_dict(state)
    with pytest.raises(ValueError, match="older"):
        c2.load_state_dict({"duals": [torch.zeros(3)], "rho": 1.0, "round": 0})


def test_a_neighbour_not_heard_exerts_no_dual():
    """Its edge's dual waits for it: a dead neighbour must not keep pushing theta_i (Adam turns a
    constant push on entries without data into full-size steps)."""
    p = torch.zeros(2, requires_grad=True)
    c = Consensus([p], _plain(rho0=1.0))
    c.dual_update([torch.zeros(2)], {2: [torch.ones(2)], 3: [-3 * torch.ones(2)]})  # y_12 = -1, y_13 = 3
    assert torch.equal(c.edge_duals[2][0], -torch.ones(2)) and torch.equal(c.edge_duals[3][0], 3 * torch.ones(2))
    c.begin_round(1, [p.detach()], {2: [torch.ones(2)], 3: [torch.ones(2)]})
    assert torch.equal(c.duals[0], 2 * torch.ones(2))  # both edges: the summed dual of before
    c.begin_round(2, [p.detach()], {2: [p.detach()]})  # robot 3 gone: only y_12 acts
    c.add_penalty_grad([p])
    assert torch.equal(p.grad, -torch.ones(2))
    c.begin_round(3, [p.detach()], {})  # alone: no dual at all
    assert torch.equal(c.duals[0], torch.zeros(2))


def test_reset_duals_forgets_the_disagreement_only():
    p = torch.zeros(4)
    c = Consensus([p], _plain(rho0=0.5))
    c.dual_update([torch.ones(4)], {2: [torch.zeros(4)]})
    c.begin_round(1, [p], {2: [p]})
    assert torch.equal(c.duals[0], torch.full((4,), 0.5))
    c.reset_duals()
    assert torch.equal(c.duals[0], torch.zeros(4)) and not c.edge_duals and c.rho == 0.5
    c.begin_round(2, [p], {2: [p]})
    assert torch.equal(c.duals[0], torch.zeros(4))


def test_an_edge_silent_for_forget_edge_after_rounds_restarts_its_dual():
    """A cut link heals: the dual it had priced a disagreement of rounds ago and must not push now;
    a single missed round (a late snapshot) keeps it."""
    p = torch.zeros(2)
    for limit, kept in ((2, False), (3, True), (0, True)):
        c = Consensus([p], _plain(rho0=1.0, forget_edge_after=limit))
        c.begin_round(0, [p], {2: [p], 3: [p]})
        c.dual_update([torch.zeros(2)], {2: [torch.ones(2)], 3: [torch.ones(2)]})  # y_12 = y_13 = -1
        for k in (1, 2):  # robot 2 silent for rounds 1 and 2; robot 3 heard throughout
            c.begin_round(k, [p], {3: [p]})
            c.dual_update([torch.zeros(2)], {3: [torch.zeros(2)]})
        c.begin_round(3, [p], {2: [p], 3: [p]})
        assert torch.equal(c.duals[0], -2 * torch.ones(2) if kept else -torch.ones(2)), (limit, c.duals[0])
        assert (2 in c.edge_duals) == kept
    # The daemon's order: the returning neighbour is heard at the end of a round (dual update)
    # before any begin_round sees it; the stale dual must not be accumulated onto.
    for limit, expect in ((2, -1.0), (0, -2.0)):
        c = Consensus([p], _plain(rho0=1.0, forget_edge_after=limit))
        c.begin_round(0, [p], {2: [p]})
        c.dual_update([torch.zeros(2)], {2: [torch.ones(2)]})  # y_12 = -1
        for k in (1, 2, 3):
            c.begin_round(k, [p], {})
            if k == 3:  # robot 2 heard again at the end of round 3
                c.dual_update([torch.zeros(2)], {2: [torch.ones(2)]})
        c.begin_round(4, [p], {2: [p]})
        assert torch.equal(c.duals[0], torch.full((2,), expect)), (limit, c.duals[0])
    c = Consensus([p], _plain(rho0=1.0))
    c.begin_round(0, [p], {2: [p]})
    c.dual_update([torch.zeros(2)], {2: [torch.ones(2)]})
    c.begin_round(2, [p], {2: [p]})  # one round missed: kept
    assert torch.equal(c.duals[0], -torch.ones(2))
    c2 = Consensus([p], _plain())
    c2.load_state_dict(c.state_dict())
    assert c2.edge_round == {2: 0}
    with pytest.raises(ValueError, match="forget_edge_after"):
        ConsensusConfig(forget_edge_after=-1)
