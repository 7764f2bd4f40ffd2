"""Policy checkpoints: one ``torch.save`` file written atomically (``<path>.tmp-<random>`` + rename).

Payload (loadable with ``torch.load(weights_only=True)``: tensors, numbers, strings, lists and dicts only)::

    {"format": "umi_aug.policy/1", "cfg": <TrainConfig as a plain dict>,
     "state_dicts": {"model", "ema_model" (optional), "optimizer", "lr_scheduler", "ema"},
     "pickles": {"global_step": int, "epoch": int (completed epochs), "epoch_done": bool},
     "rng": {"torch": ByteTensor}}

The layout follows UMI's workspace checkpoints (``cfg`` / ``state_dicts`` / ``pickles``) but without dill, so a
checkpoint never runs code when loaded. The normaliser is inside ``model`` (it is a submodule's buffers).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from umi_aug.errors import PolicyError
from umi_aug.io_utils import atomic_path

__all__ = ["CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint"]

CHECKPOINT_FORMAT = "umi_aug.policy/1"


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (adds ``format``) to ``path`` atomically; returns the path."""
    path = Path(path)
    payload = {"format": CHECKPOINT_FORMAT, **payload}
    with atomic_path(path) as tmp:
        torch.save(payload, str(tmp))
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs).

    Raises:
        PolicyError: missing/unreadable file, or not a umi-aug policy checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise PolicyError(f"checkpoint {path}: no such file")
    try:
        payload = torch.load(str(path), map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - report the file
        raise PolicyError(f"checkpoint {path}: cannot be read ({type(exc).__name__}: {exc})") from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        fmt = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise PolicyError(f"checkpoint {path}: format {fmt!r} is not {CHECKPOINT_FORMAT!r} (a UMI/DP workspace "
                          "checkpoint? only its encoder weights can be used, via policy.encoder.pretrained_path)")
    for key in ("cfg", "state_dicts", "pickles"):
        if key not in payload:
            raise PolicyError(f"checkpoint {path}: key {key!r} missing")
    return payload
