"""Outcomes of a square study's cells by how far each start configuration is turned away from the demos' start.

The evaluation's start configurations (``umi-aug square-init-configs``) put the wrist camera on a cone of half-angle
θ around each source start's optical axis. The source axes themselves are not stored in the configurations file;
they are the Panda's home pose up to robosuite's small joint noise, so the mean optical axis of all the starts
stands in for them. Each start's angle from that mean axis is its approximate cone angle (a few degrees off for
a given source). Binning outcomes by it says whether a variant's gain comes from the far starts (what cone
augmentation covers) or from every start alike.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["start_angles_deg", "outcomes_by_start_angle", "start_angle_section", "START_ANGLE_EDGES_DEG"]

#: Bin edges (degrees) of the report's table; the last bin is open-ended.
START_ANGLE_EDGES_DEG: tuple[float, ...] = (0.0, 20.0, 30.0, 40.0)


def start_angles_deg(T_world_cam: np.ndarray) -> np.ndarray:
    """Angle (degrees) between each start camera's optical axis (+z of ``T_world_cam``, float [N, 4, 4], world
    frame) and the normalised mean of all those axes. Raises ``ValueError`` on a wrong shape, non-finite poses or
    axes that cancel out (no mean direction)."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise ValueError(f"T_world_cam: expected float [N, 4, 4] with N >= 1, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError("T_world_cam: non-finite values")
    z = T[:, :3, 2] / np.linalg.norm(T[:, :3, 2], axis=1, keepdims=True)
    mean = z.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if norm < 1e-6:
        raise ValueError("T_world_cam: the optical axes cancel out; there is no mean direction")
    return np.degrees(np.arccos(np.clip(z @ (mean / norm), -1.0, 1.0)))


def _bin_label(lo: float, hi: float | None) -> str:
    return f"{lo:g}°–{hi:g}°" if hi is not None else f"≥ {lo:g}°"


def outcomes_by_start_angle(rows: dict[int, dict[str, Any]], angles_deg: np.ndarray,
                            edges_deg: Sequence[float] = START_ANGLE_EDGES_DEG,
                            keys: Sequence[str] = ("success", "pregrasp_reached")) -> list[dict[str, Any]]:
    """Per angle bin ``[edges[i], edges[i+1])`` (the last open-ended): how many of a cell's rollouts (``rows``:
    configuration index → ``eval_sim`` record) started there, and how many of them had each of ``keys`` true.
    Raises ``ValueError`` when a record's configuration has no angle."""
    angles_deg = np.asarray(angles_deg, dtype=np.float64)
    bad = [c for c in rows if not 0 <= int(c) < len(angles_deg)]
    if bad:
        raise ValueError(f"configuration {bad[0]} has no start angle ({len(angles_deg)} configurations)")
    out = []
    for i, lo in enumerate(edges_deg):
        hi = edges_deg[i + 1] if i + 1 < len(edges_deg) else None
        sel = [r for c, r in rows.items() if angles_deg[int(c)] >= lo and (hi is None or angles_deg[int(c)] < hi)]
        out.append({"bin": _bin_label(lo, hi), "n": len(sel), **{k: int(sum(bool(r.get(k)) for r in sel))
                                                                  for k in keys}})
    return out


def start_angle_section(cells: list[dict[str, Any]], rows_of, configs_file: str | Path,
                        edges_deg: Sequence[float] = START_ANGLE_EDGES_DEG) -> list[str]:
    """The report's markdown section: every evaluated cell's successes and pre-grasp poses reached per start-angle
    bin (``rows_of(cell)`` → its records by configuration). Empty when no cell is evaluated or the configurations
    file is not there (then it says so)."""
    evaluated = [(c, rows_of(c)) for c in cells]
    evaluated = [(c, r) for c, r in evaluated if r]
    if not evaluated:
        return []
    path = Path(configs_file)
    if not path.is_file():
        return ["", "## Outcomes by the start's angle", "", f"(`{path}` is not on this machine: no table.)"]
    from umi_aug.eval.runner import load_eval_configs  # lazy, start-up: the evaluation harness

    angles = start_angles_deg(load_eval_configs(path)["T_world_cam"])  # names the file and key it finds wrong
    tables = [(c, outcomes_by_start_angle(r, angles, edges_deg)) for c, r in evaluated]
    bins = [b["bin"] for b in tables[0][1]]
    head = "| cell | " + " | ".join(f"{b}: n / success / pre-grasp" for b in bins) + " |"
    lines = [f"| `{c['name']}` | " + " | ".join(f"{b['n']} / {b['success']} / {b['pregrasp_reached']}" for b in t)
             + " |" for c, t in tables]
    return ["", "## Outcomes by the start's angle", "",
            "Each evaluated start by the angle of its camera's optical axis from the mean axis of all the starts "
            f"in `{path.name}` (≈ its cone angle: the sources' own start axes differ by a few degrees), per cell: "
            "rollouts / successes / pre-grasp poses reached (`umi_aug/square/start_angle.py`). A gain that comes "
            "from covering far starts shows in the far bins only.", "",
            head, "|---|" + "---|" * len(bins), *lines]
