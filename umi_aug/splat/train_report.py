"""Outputs of a finished training run: ``metrics.json``, ``contact_sheet.png`` (one row per held-out view:
ground truth | render | |error| x ``ERROR_GAIN``, masked-out pixels dimmed) and ``curve.png`` (held-out and training
PSNR / SSIM against iteration and against training seconds; only for a run evaluated at two iterations or more: a
dataset scene's run, evaluated once after its last step, has no curve to draw). All writes are atomic."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from umi_aug.io_utils import atomic_path

__all__ = ["write_outputs", "config_dict", "contact_sheet", "plot_curve", "ERROR_GAIN"]

#: The error column shows ``min(1, ERROR_GAIN * |render - gt|)``.
ERROR_GAIN: float = 4.0
#: Brightness of masked-out pixels in the sheet.
MASK_DIM: float = 0.35
#: ``curve.png`` is drawn for a history of at least this many evaluations.
MIN_CURVE_POINTS: int = 2


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def contact_sheet(rows: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], path: Path) -> Path:
    """Write rows of ``(gt [H, W, 3], render [H, W, 3], mask [H, W])`` (float in [0, 1], bool) as a PNG."""
    tiles = []
    for gt, rgb, mask in rows:
        dim = np.where(mask[..., None], 1.0, MASK_DIM)
        err = np.clip(ERROR_GAIN * np.abs(rgb - gt), 0.0, 1.0) * mask[..., None]
        tiles.append(np.concatenate([gt * dim, rgb * dim, err], axis=1))
    sheet = (np.concatenate(tiles, axis=0) * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(sheet[..., ::-1]))
    if not ok:
        raise OSError(f"PNG encoding failed for {path}")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buf.tobytes())
    return path


def plot_curve(history: Sequence[dict], path: Path) -> Path:
    """PSNR and SSIM (held-out, train) against iteration and training seconds."""
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    it = [h["iteration"] for h in history]
    sec = [h["seconds"] for h in history]
    for row, metric, unit in ((0, "psnr", "PSNR (dB)"), (1, "ssim", "SSIM")):
        for col, (x, xl) in enumerate(((it, "iteration"), (sec, "training seconds"))):
            ax = axes[row, col]
            for split, style in (("heldout", "o-"), ("train", "s--")):
                ax.plot(x, [h[f"{split}_{metric}"] for h in history], style, label=split, ms=3)
            ax.set_xlabel(xl)
            ax.set_ylabel(unit)
            ax.grid(alpha=0.3)
            ax.legend()
    fig.suptitle("fisheye 3DGS training (masked pixels)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(str(tmp), format="png", dpi=90)
    plt.close(fig)
    return path


def config_dict(cfg: Any) -> dict:
    """The trainer config (:class:`umi_aug.splat.train.SplatTrainConfig`) as a JSON-ready dict (tuples as lists):
    stored in checkpoints and ``metrics.json``. (This module takes the trainer's objects duck-typed, so that it
    does not import the trainer that calls it.)"""
    d = asdict(cfg)
    d["background"] = list(cfg.background)
    return d


@torch.no_grad()
def write_outputs(out: Path, result: Any, cfg: Any, intr, data: Any,
                  sheet_idx: Sequence[int], deg: int, scale: float, n_train: int, n_held: int) -> None:
    """Write ``metrics.json``, ``contact_sheet.png`` and ``curve.png`` into ``out`` (``curve.png`` only for a
    history of two evaluations or more; a stale one from an earlier run in ``out`` is removed otherwise).

    ``result``: :class:`umi_aug.splat.train.SplatTrainResult`; ``cfg``: its ``SplatTrainConfig``; ``data``: the
    trainer's views (``poses``, ``images``, ``masks``, ``names``)."""
    from umi_aug.splat.renderer import render  # lazy, start-up: numba, scipy

    idx = list(sheet_idx)[: max(cfg.sheet_views, 1)]
    rows = []
    bg = torch.tensor(cfg.background, dtype=torch.float32)
    for i in idx:
        rgb = render(result.gaussians, data.poses[i], intr, bg, deg, filter=cfg.filter).rgb.clamp(0, 1).numpy()
        rows.append((data.images[i].numpy(), rgb, data.masks[i].numpy()))
    if rows:
        contact_sheet(rows, out / "contact_sheet.png")
    if len(result.history) >= MIN_CURVE_POINTS:
        plot_curve(result.history, out / "curve.png")
    else:  # one point is no curve (matplotlib's 2 x 2 figure cost ~0.5-1 s of a dataset scene's stage)
        (out / "curve.png").unlink(missing_ok=True)
    metrics = {
        "heldout_psnr": result.heldout_psnr, "heldout_ssim": result.heldout_ssim,
        "n_gaussians": result.gaussians.n, "n_train_views": n_train, "n_heldout_views": n_held,
        "heldout_views": [data.names[i] for i in idx], "scene_scale_m": scale,
        "image_size": [intr.width, intr.height], "config": config_dict(cfg), "history": result.history,
        "timings": result.timings,
        "note": "seconds = training time (evaluation and checkpoints excluded); PSNR/SSIM over masked-in pixels",
    }
    with atomic_path(out / "metrics.json") as tmp:
        Path(tmp).write_text(json.dumps(_json_safe(metrics), indent=2) + "\n")
