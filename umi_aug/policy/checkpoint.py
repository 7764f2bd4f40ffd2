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
import zipfile
from pathlib import Path
from typing import Any

import torch

from umi_aug.errors import PolicyError
from umi_aug.io_utils import atomic_path

__all__ = ["CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint", "slim_checkpoint", "checkpoint_file_problem"]

CHECKPOINT_FORMAT = "umi_aug.policy/1"


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (adds ``format``) to ``path`` atomically; returns the path."""
    path = Path(path)
    payload = {"format": CHECKPOINT_FORMAT, **payload}
    with atomic_path(path) as tmp:
        torch.save(payload, str(tmp))
    return path


def slim_checkpoint(src: str | os.PathLike, dest: str | os.PathLike, half: bool = False) -> Path:
    """Write the part of checkpoint ``src`` that inference reads to ``dest``: ``cfg``, ``pickles`` and the weights
    (the EMA model's when it has one, else the model's), without the optimiser, scheduler, EMA counters and RNG
    (a quarter of the file with Adam's two moments). ``half``: floating weights as float16, except the normaliser's
    buffers (ranges float16 cannot hold); :meth:`Policy.from_checkpoint` loads them into the float32 model.
    Training cannot resume from the result. An existing ``dest`` and non-finite weights are refused."""
    if Path(dest).exists():
        raise PolicyError(f"slim checkpoint {dest} exists; it is never replaced (it could be the training "
                          "checkpoint itself): pick another path")
    payload = load_checkpoint(src)
    sd = payload["state_dicts"]
    key = "ema_model" if "ema_model" in sd else "model"
    weights = {}
    for name, t in sd[key].items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise PolicyError(f"checkpoint {src}: {key}.{name} holds NaN or Inf; not slimmed")
        if half and t.is_floating_point() and "normalizer" not in name and t.numel():
            if t.abs().max().item() > torch.finfo(torch.float16).max:
                raise PolicyError(f"checkpoint {src}: {key}.{name} exceeds float16's range; slim it with half=False")
            t = t.to(torch.float16)
        weights[name] = t
    out = {k: v for k, v in payload.items() if k not in ("format", "state_dicts", "rng")}
    out["state_dicts"] = {key: weights}
    out["slim"] = {"from": Path(src).name, "weights": key, "half": bool(half)}
    return save_checkpoint(dest, out)


def checkpoint_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be a checkpoint file — ``"no such file"``, or ``"is a directory, not a checkpoint
    file; did you mean …/checkpoints/latest.ckpt?"`` (a training run folder) — or None when it is a file."""
    path = Path(path)
    if path.is_file():
        return None
    if not path.is_dir():
        return "no such file"
    found = [p for p in (path / "checkpoints" / "latest.ckpt", path / "latest.ckpt") if p.is_file()]
    hint = (f"did you mean {found[0]}?" if found else
            "pass the .ckpt file itself (train/train.py writes <run folder>/checkpoints/latest.ckpt)")
    return f"is a directory, not a checkpoint file; {hint}"


def _unreadable_why(path: Path, exc: Exception) -> str:
    """A short reason ``torch.load`` failed on ``path``, without torch's advice about ``weights_only``."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head:
        return "the file is empty"
    if not zipfile.is_zipfile(path) and not head.startswith(b"\x80"):  # torch.save: a zip (or a legacy pickle)
        try:
            head.decode("utf-8")
            return "a text file, not a PyTorch checkpoint"
        except UnicodeDecodeError:
            return "not a PyTorch checkpoint (neither a torch zip archive nor a pickle)"
    if "weights only" in str(exc).lower() or "weights_only" in str(exc):
        return ("a PyTorch file holding Python objects that a safe load refuses: a checkpoint of another program, "
                "e.g. a UMI/DP workspace checkpoint, whose encoder weights policy.encoder.pretrained_path can use")
    return f"a damaged or truncated PyTorch file: {type(exc).__name__}"


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs).

    Raises:
        PolicyError: missing/unreadable file, or not a umi-aug policy checkpoint.
    """
    path = Path(path)
    problem = checkpoint_file_problem(path)
    if problem:
        raise PolicyError(f"checkpoint {path}: {problem}")
    try:
        payload = torch.load(str(path), map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - report the file
        raise PolicyError(f"checkpoint {path}: cannot be read ({_unreadable_why(path, exc)}); expected the "
                          "latest.ckpt a training run writes (train/train.py → <run folder>/checkpoints/latest.ckpt)"
                          ) from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        fmt = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise PolicyError(f"checkpoint {path}: format {fmt!r} is not {CHECKPOINT_FORMAT!r} (a UMI/DP workspace "
                          "checkpoint? only its encoder weights can be used, via policy.encoder.pretrained_path)")
    for key in ("cfg", "state_dicts", "pickles"):
        if key not in payload:
            raise PolicyError(f"checkpoint {path}: key {key!r} missing")
    return payload
