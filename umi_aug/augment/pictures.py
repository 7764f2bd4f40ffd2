"""Pictures of an augmented export: the contact sheet of original and new episodes (policy images).

PNG files written atomically (temporary file, then rename); matplotlib runs headless (Agg) and is imported only
when a picture is drawn.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from umi_aug.io_utils import atomic_path

__all__ = ["contact_sheet", "pyplot", "save_figure"]


def pyplot():
    """matplotlib.pyplot on the headless Agg backend (imported on first use)."""
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    return plt


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically and close it."""
    plt = pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def contact_sheet(
    episodes: list[np.ndarray],  # E × [T_e, H, W, 3] uint8 (episodes may differ in length)
    path: Path,
    n_cols: int = 7,
    splice_indices: list[int] | None = None,
    row_names: list[str] | None = None,
) -> Path:
    """Grid of frames: one row per episode, ``n_cols − 1`` frames evenly spaced in time up to and including the
    row's splice index (after it the frames are the original ones), then the row's last frame."""
    plt = pyplot()
    n_ep = len(episodes)
    fig, axes = plt.subplots(n_ep, n_cols, figsize=(1.9 * n_cols, 2.0 * n_ep), squeeze=False)
    for e, frames in enumerate(episodes):
        n_t = len(frames)
        last_new = n_t - 1 if splice_indices is None else int(splice_indices[e])
        cols = list(np.linspace(0, last_new, n_cols - 1).round().astype(int)) + [n_t - 1]
        for j, k in enumerate(cols):
            a = axes[e, j]
            a.imshow(frames[k])
            a.set_xticks([])
            a.set_yticks([])
            tag = " splice" if splice_indices is not None and k == last_new else (" end" if k == n_t - 1 else "")
            a.set_title(f"t={k}{tag}", fontsize=7)
        axes[e, 0].set_ylabel(row_names[e] if row_names else f"ep {e}", fontsize=8)
    size = np.asarray(episodes[0][0]).shape[0] if n_ep and len(episodes[0]) else 0
    height = fig.get_figheight()
    # the title sits 0.15 in below the top and the grid 0.55 in (room for the frames' own titles), not at the
    # default fractions of the figure, which leave inches of blank space above a grid of many rows
    fig.subplots_adjust(top=1.0 - 0.55 / height)
    fig.suptitle(f"policy images ({size}², UMI layout): original demo and new episodes (new frames up to the "
                 "splice, original frames after it)", fontsize=9, y=1.0 - 0.15 / height)
    return save_figure(fig, path)
