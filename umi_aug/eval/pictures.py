"""``init_success.png``: start camera positions and viewing directions coloured by outcome (paper Fig. 3a style)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from umi_aug.io_utils import atomic_path

__all__ = ["plot_init_success"]

_COLOURS = {"success": "#1a9850", "failure": "#d73027", "pending": "#bdbdbd"}


def plot_init_success(path: str | Path, T_world_cam: np.ndarray, records: dict[int, dict[str, Any]],
                      selected: Sequence[int], title: str = "", arrow_m: float = 0.03) -> Path:
    """Two views (3-D and top-down) of the start cameras: a dot at each position, a short line along the optical
    axis (``arrow_m`` metres), green = success, red = failure, grey = selected but not evaluated yet.

    Args:
        T_world_cam: np.ndarray,  # [N, 4, 4] start wrist-camera poses (OpenCV axes), metres
        records: finished rollouts by configuration index.
        selected: configuration indices of this run.
    """
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    sel = np.asarray(list(selected), dtype=int)
    pos = T_world_cam[sel, :3, 3]
    fwd = T_world_cam[sel, :3, 2]
    outcome = np.array(["pending" if i not in records else ("success" if records[i]["success"] else "failure")
                        for i in sel])
    fig = plt.figure(figsize=(12, 5.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    for name in ("pending", "success", "failure"):  # failures drawn last (on top)
        m = outcome == name
        if not m.any():
            continue
        c = _COLOURS[name]
        p, f = pos[m], fwd[m]
        ax3.scatter(p[:, 0], p[:, 1], p[:, 2], s=6, c=c, label=f"{name} ({m.sum()})", depthshade=False)
        seg = np.stack([p, p + arrow_m * f], axis=1)
        for s in seg:
            ax3.plot(s[:, 0], s[:, 1], s[:, 2], c=c, lw=0.5, alpha=0.7)
        ax2.scatter(p[:, 0], p[:, 1], s=6, c=c, label=f"{name} ({m.sum()})", zorder=3 if name == "failure" else 2)
        ax2.quiver(p[:, 0], p[:, 1], f[:, 0], f[:, 1], color=c, angles="xy", scale_units="xy",
                   scale=1.0 / arrow_m, width=0.002, alpha=0.7, zorder=3 if name == "failure" else 2)
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.set_title("start wrist cameras (lines: viewing direction)")
    ax3.legend(loc="upper left", fontsize=8)
    ax2.set_aspect("equal")
    ax2.set_xlabel("x [m]")
    ax2.set_ylabel("y [m]")
    ax2.set_title("top view")
    ax2.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
