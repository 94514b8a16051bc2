"""Chaining pairwise estimates from the reference robot to robots that do not neighbour it."""

from __future__ import annotations

import heapq
from collections.abc import Hashable, Mapping

import numpy as np
import torch

from agent.align.payload import AlignmentResult
from agent.geometry import sim3_inverse

__all__ = ["compose_along_graph"]


def compose_along_graph(reference: Hashable, estimates: Mapping[tuple[Hashable, Hashable], np.ndarray | AlignmentResult | None]
                        ) -> dict[Hashable, np.ndarray]:
    """``T_ref_from_robot`` for every robot reachable from ``reference`` through the estimates.

    ``estimates[(a, b)]`` is ``T_a_from_b`` (a 4x4 array, or an :class:`AlignmentResult`, of which
    only the successful ones count). Edges are used in both directions. The chain follows a
    maximum spanning tree grown from the reference (Prim), weighted by inliers (plain arrays
    weigh 1), with ties broken by fewer hops: the most trusted path wins. Unreachable robots are
    absent from the result; the reference maps to the identity.
    """
    adj: dict[Hashable, list[tuple[float, Hashable, np.ndarray]]] = {}
    for (a, b), est in estimates.items():
        if est is None:
            continue
        if isinstance(est, AlignmentResult):
            if not est.success or est.T_a_from_b is None:
                continue
            t, w = np.asarray(est.T_a_from_b, dtype=np.float64), float(est.inliers)
        else:
            t, w = np.asarray(est, dtype=np.float64), 1.0
        if t.shape != (4, 4) or not np.isfinite(t).all():
            raise ValueError(f"estimate for {(a, b)} is not a finite 4x4 matrix")
        adj.setdefault(a, []).append((w, b, t))  # from a we can reach b: T_a_from_b
        adj.setdefault(b, []).append((w, a, _sim3_inv(t)))
    out = {reference: np.eye(4)}
    heap: list = []
    counter = 0

    def push(node: Hashable, hops: int) -> None:
        nonlocal counter
        for w, nxt, t in adj.get(node, []):
            if nxt not in out:
                heapq.heappush(heap, (-w, hops + 1, counter, node, nxt, t))
                counter += 1

    push(reference, 0)
    hops_of = {reference: 0}
    while heap:
        _, hops, _, src, dst, t = heapq.heappop(heap)
        if dst in out:
            continue
        out[dst] = out[src] @ t  # T_ref_from_dst = T_ref_from_src @ T_src_from_dst
        hops_of[dst] = hops
        push(dst, hops)
    return out


def _sim3_inv(t: np.ndarray) -> np.ndarray:
    return sim3_inverse(torch.from_numpy(t)).numpy()
