"""RRT* in 3-D position space (numpy), shortcut smoothing and arc-length resampling.

Used for the obstacle-mode initial guess (paper §3.2): the camera position is planned around the inflated obstacle
hull (the edge test moves the whole gripper, see :mod:`.init_guess`); the optimiser then refines the full SE(3)
trajectory. Deterministic for a given ``rng``.
Edges are checked by a caller-supplied vectorised ``segments_free(a [N, 3], b [N, 3]) -> bool [N]``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from umi_aug.traj.config import RRTConfig
from umi_aug.traj.constants import RRT_MAX_NEIGHBOURS, SHORTCUT_ALL_PAIRS_MAX

__all__ = ["rrt_star", "shortcut_path", "resample_polyline"]

SegmentsFree = Callable[[np.ndarray, np.ndarray], np.ndarray]


def rrt_star(start: np.ndarray, goal: np.ndarray, segments_free: SegmentsFree, lo: np.ndarray, hi: np.ndarray,
             cfg: RRTConfig, rng: np.random.Generator) -> np.ndarray | None:
    """RRT* from ``start`` to ``goal`` inside the box ``[lo, hi]``.

    Steering step ``cfg.step``, goal bias ``cfg.goal_bias``, choose-parent and rewire within
    ``cfg.rewire_radius``; stops ``cfg.extra_iterations`` after the first solution or after ``cfg.max_iterations``.

    Returns:
        path: np.ndarray | None,  # [M, 3] from start to goal (None when no path was found)
    """
    start = np.asarray(start, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)
    if segments_free(start[None], goal[None])[0]:
        return np.stack([start, goal])
    cap = cfg.max_iterations + 2
    nodes = np.empty((cap, 3))
    parent = np.full(cap, -1, dtype=np.int64)
    cost = np.zeros(cap)
    nodes[0] = start
    n = 1
    best_goal_parent, best_goal_cost = -1, np.inf
    first_found_at = None
    r2 = cfg.rewire_radius ** 2
    for it in range(cfg.max_iterations):
        if first_found_at is not None and it - first_found_at >= cfg.extra_iterations:
            break
        to_goal = rng.random() < cfg.goal_bias
        sample = goal if to_goal else lo + rng.random(3) * (hi - lo)
        d2 = np.sum((nodes[:n] - sample) ** 2, axis=1)
        near = int(np.argmin(d2))
        dist = float(np.sqrt(d2[near]))
        if dist < 1e-9:
            continue
        if to_goal and first_found_at is None:
            # greedy CONNECT (RRT-Connect style): the longest free prefix of the straight line to the goal,
            # in whole steps, checked with one vectorised call
            k_steps = int(np.ceil(dist / cfg.step))
            pts = nodes[near] + (goal - nodes[near]) * (np.arange(1, k_steps + 1) / k_steps)[:, None]
            prev = np.vstack([nodes[near][None], pts[:-1]])
            free = segments_free(prev, pts)
            m = k_steps if free.all() else int(np.argmin(free))
            if m == 0:
                continue
            new = pts[m - 1]
        else:
            new = nodes[near] + (sample - nodes[near]) * min(1.0, cfg.step / dist)
            if not segments_free(nodes[near][None], new[None])[0]:
                continue
        # choose parent (lazy): cheaper neighbours than `near`, checked in cost order until one is free
        dn = np.sum((nodes[:n] - new) ** 2, axis=1)
        nb = np.flatnonzero(dn <= r2)
        if nb.size > RRT_MAX_NEIGHBOURS:
            nb = nb[np.argsort(dn[nb])[:RRT_MAX_NEIGHBOURS]]
        c_near = cost[near] + float(np.sqrt(dn[near]))
        c_via = cost[nb] + np.sqrt(dn[nb])
        best, best_c = near, c_near
        for j in np.argsort(c_via):
            if c_via[j] >= best_c - 1e-12:
                break
            if nb[j] != near and segments_free(nodes[nb[j]][None], new[None])[0]:
                best, best_c = int(nb[j]), float(c_via[j])
                break
        nodes[n], parent[n], cost[n] = new, best, best_c
        # rewire: neighbours reachable more cheaply through the new node (one vectorised check)
        cand = nb[cost[nb] > best_c + np.sqrt(dn[nb]) + 1e-12]
        if cand.size:
            free = segments_free(np.broadcast_to(new, (cand.size, 3)), nodes[cand])
            for k in cand[free]:
                parent[k] = n
                cost[k] = best_c + float(np.sqrt(dn[k]))
        n += 1
        dg = float(np.linalg.norm(goal - new))
        if dg <= cfg.step and cost[n - 1] + dg < best_goal_cost and segments_free(new[None], goal[None])[0]:
            best_goal_parent, best_goal_cost = n - 1, cost[n - 1] + dg
            if first_found_at is None:
                first_found_at = it
    if best_goal_parent < 0:
        return None
    path = [goal]
    k = best_goal_parent
    guard = 0
    while k >= 0 and guard <= cap:
        path.append(nodes[k])
        k = parent[k]
        guard += 1
    return np.array(path[::-1])


def shortcut_path(path: np.ndarray, segments_free: SegmentsFree, passes: int, rng: np.random.Generator) -> np.ndarray:
    """Shortcut smoothing. Short paths (≤ ``SHORTCUT_ALL_PAIRS_MAX`` nodes): every node pair is checked in one
    vectorised call and the path greedily jumps to the farthest node with a free straight segment (deterministic,
    optimal in node count for this visibility graph from the start). Longer paths: ``passes`` random pairs (i, j),
    the nodes between them replaced by a straight segment when it is free. Start and goal are always kept."""
    path = np.asarray(path, dtype=np.float64)
    m = path.shape[0]
    if m <= 2:
        return path
    if m <= SHORTCUT_ALL_PAIRS_MAX:
        i, j = np.triu_indices(m, k=2)
        free = np.zeros((m, m), dtype=bool)
        free[i, j] = segments_free(path[i], path[j])
        free[np.arange(m - 1), np.arange(1, m)] = True
        keep = [0]
        while keep[-1] != m - 1:
            a = keep[-1]
            keep.append(int(np.flatnonzero(free[a])[-1]))
        return path[keep]
    for _ in range(passes):
        m = path.shape[0]
        if m <= 2:
            break
        i, j = sorted(rng.choice(m, size=2, replace=False))
        if j - i < 2:
            continue
        if segments_free(path[i][None], path[j][None])[0]:
            path = np.concatenate([path[: i + 1], path[j:]])
    return path


def resample_polyline(path: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly spaced in arc length along a polyline (ends exact).

    Returns:
        points: np.ndarray,  # [n, 3]
        s: np.ndarray,  # [n] arc-length fraction in [0, 1]
    """
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    lam = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(0.0, 1.0, n)
    if lam[-1] <= 0:
        return np.repeat(path[:1], n, axis=0), s
    u = s * lam[-1]
    pts = np.stack([np.interp(u, lam, path[:, i]) for i in range(3)], axis=-1)
    pts[0], pts[-1] = path[0], path[-1]
    return pts, s
