"""UMI's ``LinearNormalizer`` as ``UmiDataset.get_normalizer`` builds it (umi_stack.md §8), from low-dim samples.

UMI's policy loads the normaliser with ``load_state_dict``, so the object handed to UMI's workspace must have UMI's
layout: a module whose ``params_dict`` (``nn.ParameterDict``) maps each key to ``{scale [D], offset [D],
input_stats: {min, max, mean, std} [D]}`` (state-dict keys ``params_dict.<key>.scale``, ...), all float32.
:func:`umi_normalizer` returns UMI's own ``diffusion_policy.model.common.normalizer.LinearNormalizer`` when UMI's
code is importable, and otherwise :class:`UmiLayoutNormalizer`, umi-aug's implementation of the same layout (its
state dict loads into UMI's class and back).

The rules (UMI's ``UmiDataset.get_normalizer``; statistics pooled over batch and time, ``B·T`` rows):

* ``action``: per robot a range normaliser (to [-1, 1], ``RANGE_EPS``) on the 3 position dims, identity on the 6
  rotation dims, range on the gripper dim, concatenated;
* obs low-dim: range for ``*pos`` / ``*pos_wrt*`` / ``*pos_abs`` / ``*gripper_width``, identity for
  ``*rot_axis_angle`` / ``*rot_axis_angle_wrt*``; any other key is refused;
* every rgb key: the image identity normaliser (scale 1, offset 0, stats min 0, max 1, mean 0.5, std sqrt(1/12)).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

from umi_aug.errors import PolicyError

__all__ = ["RANGE_EPS", "NormalizerField", "array_stats", "range_field", "identity_field", "image_identity_field",
           "umi_normalizer_fields", "UmiLayoutNormalizer", "umi_importable", "umi_normalizer", "normalizer_fields"]

#: UMI's ``range_eps``: a dimension whose range is below this is constant (shifted to 0, unit scale).
RANGE_EPS = 1e-7
#: The four input statistics UMI stores per key, in its order.
STAT_NAMES: tuple[str, ...] = ("min", "max", "mean", "std")

#: One key of the normaliser: ``{"scale", "offset", "min", "max", "mean", "std"}`` → float32 [D].
NormalizerField = dict


def array_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per-dimension min/max/mean/std of ``x`` [N, D] (float32 in, as UMI's samples; computed in float64 and
    returned as float32 [D])."""
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[0] == 0:
        raise PolicyError(f"normaliser statistics need a non-empty [N, D] array, got shape {x.shape}")
    x64 = x.astype(np.float64)
    return {"min": x64.min(0).astype(np.float32), "max": x64.max(0).astype(np.float32),
            "mean": x64.mean(0).astype(np.float32), "std": x64.std(0).astype(np.float32)}


def range_field(stats: Mapping[str, np.ndarray], out_min: float = -1.0, out_max: float = 1.0) -> NormalizerField:
    """UMI's range normaliser (``get_range_normalizer_from_stat``): [min, max] → [out_min, out_max]; dimensions
    whose range is below :data:`RANGE_EPS` are shifted to the middle of the output range with scale 1."""
    lo = np.asarray(stats["min"], np.float32)
    hi = np.asarray(stats["max"], np.float32)
    rng = hi - lo
    const = rng < RANGE_EPS
    rng = np.where(const, np.float32(out_max - out_min), rng)
    scale = np.float32(out_max - out_min) / rng
    offset = np.float32(out_min) - scale * lo
    offset = np.where(const, np.float32((out_max + out_min) / 2) - lo, offset)
    return {"scale": scale.astype(np.float32), "offset": offset.astype(np.float32),
            **{k: np.asarray(stats[k], np.float32) for k in STAT_NAMES}}


def identity_field(stats: Mapping[str, np.ndarray]) -> NormalizerField:
    """UMI's identity normaliser (``get_identity_normalizer_from_stat``): scale 1, offset 0, the data's stats."""
    d = np.asarray(stats["min"]).shape
    return {"scale": np.ones(d, np.float32), "offset": np.zeros(d, np.float32),
            **{k: np.asarray(stats[k], np.float32) for k in STAT_NAMES}}


def image_identity_field() -> NormalizerField:
    """UMI's ``get_image_identity_normalizer``: one dimension, scale 1, offset 0, stats of U(0, 1)."""
    return {"scale": np.ones(1, np.float32), "offset": np.zeros(1, np.float32), "min": np.zeros(1, np.float32),
            "max": np.ones(1, np.float32), "mean": np.full(1, 0.5, np.float32),
            "std": np.full(1, np.sqrt(1.0 / 12.0), np.float32)}


def _concat(fields: list[NormalizerField]) -> NormalizerField:
    return {k: np.concatenate([f[k] for f in fields]).astype(np.float32) for k in fields[0]}


def umi_normalizer_fields(data: Mapping[str, np.ndarray], lowdim_keys: list[str], rgb_keys: list[str],
                          n_robots: int) -> dict[str, NormalizerField]:
    """The normaliser of UMI's rules (module docstring) from pooled samples.

    Args:
        data: ``{"action": [N, 10·R], <low-dim key>: [N, D]}`` float32, ``N = B·T`` rows (time steps pooled).
        lowdim_keys: obs low-dim keys, in ``shape_meta`` order; rgb_keys: image keys, in ``shape_meta`` order.
        n_robots: R (the action holds 10 dims per robot: pos 3, rot6d 6, gripper 1).
    Returns:
        ``{key: field}`` with ``action`` first, then the low-dim keys, then the rgb keys (UMI's order).
    """
    act = np.asarray(data["action"])
    if act.shape[-1] != 10 * n_robots:
        raise PolicyError(f"normaliser: key 'action' has {act.shape[-1]} dims; expected 10 per robot × {n_robots}")
    parts = []
    for i in range(n_robots):
        a = act[:, 10 * i: 10 * (i + 1)]
        parts += [range_field(array_stats(a[:, :3])), identity_field(array_stats(a[:, 3:9])),
                  range_field(array_stats(a[:, 9:]))]
    out = {"action": _concat(parts)}
    for key in lowdim_keys:
        st = array_stats(np.asarray(data[key]))
        if key.endswith("pos") or "pos_wrt" in key or key.endswith("pos_abs") or key.endswith("gripper_width"):
            out[key] = range_field(st)
        elif key.endswith("rot_axis_angle") or "rot_axis_angle_wrt" in key:
            out[key] = identity_field(st)
        else:
            raise PolicyError(f"normaliser: observation key {key!r} has no UMI normaliser rule (UMI's "
                              "UmiDataset.get_normalizer raises 'unsupported' for it)")
    for key in rgb_keys:
        out[key] = image_identity_field()
    return out


class UmiLayoutNormalizer(nn.Module):
    """umi-aug's normaliser with the layout of UMI's ``LinearNormalizer`` (used when UMI's code is not importable).

    ``params_dict[key]`` is an ``nn.ParameterDict`` ``{scale, offset, input_stats: {min, max, mean, std}}`` of
    float32 [D] parameters without gradients; ``normalize`` / ``unnormalize`` map ``x`` [..., D] (a tensor for one
    key, or a dict of keys) as ``x · scale + offset`` / ``(x - offset) / scale``. Its state dict (``params_dict.
    <key>.scale``, ``params_dict.<key>.input_stats.min``, ...) loads into UMI's class and back.
    """

    def __init__(self) -> None:
        super().__init__()
        self.params_dict = nn.ParameterDict()

    def set_field(self, key: str, field: Mapping[str, np.ndarray]) -> None:
        """Store ``field`` (:data:`NormalizerField`) under ``key``."""
        t = {k: torch.as_tensor(np.asarray(field[k], np.float32)).flatten() for k in ("scale", "offset", *STAT_NAMES)}
        d = t["scale"].shape
        if any(v.shape != d for v in t.values()) or (t["scale"] == 0).any() or not torch.isfinite(t["scale"]).all():
            raise PolicyError(f"normaliser key {key!r}: scale/offset/stats must share one shape with finite, non-zero "
                              f"scale; got { {k: tuple(v.shape) for k, v in t.items()} }")
        par = lambda v: nn.Parameter(v, requires_grad=False)  # noqa: E731
        self.params_dict[key] = nn.ParameterDict({
            "scale": par(t["scale"]), "offset": par(t["offset"]),
            "input_stats": nn.ParameterDict({k: par(t[k]) for k in STAT_NAMES})})

    def keys(self) -> list[str]:
        return list(self.params_dict.keys())

    def _apply_field(self, x: Any, key: str, forward: bool) -> torch.Tensor:
        if key not in self.params_dict:
            raise PolicyError(f"normaliser: no key {key!r}; have {self.keys()}")
        p = self.params_dict[key]
        x = torch.as_tensor(x)
        scale, offset = p["scale"].to(x.device), p["offset"].to(x.device)
        shape = x.shape
        x = x.to(scale.dtype).reshape(-1, scale.shape[0])
        y = x * scale + offset if forward else (x - offset) / scale
        return y.reshape(shape)

    def normalize(self, x: Any, key: str | None = None) -> Any:
        """``x`` [..., D] of ``key``, or ``{key: x}`` (every key must be known, as in UMI)."""
        if isinstance(x, Mapping):
            return {k: self._apply_field(v, k, True) for k, v in x.items()}
        return self._apply_field(x, key if key is not None else "_default", True)

    def unnormalize(self, x: Any, key: str | None = None) -> Any:
        if isinstance(x, Mapping):
            return {k: self._apply_field(v, k, False) for k, v in x.items()}
        return self._apply_field(x, key if key is not None else "_default", False)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):  # noqa: D401 - torch hook
        """Rebuild ``params_dict`` from ``<prefix>params_dict.<key>.<name>`` entries (keys are created on load,
        as UMI's ``DictOfTensorMixin`` does)."""
        root = prefix + "params_dict."
        fields: dict[str, dict[str, torch.Tensor]] = {}
        for name, value in state_dict.items():
            if not name.startswith(root):
                continue
            parts = name[len(root):].split(".")
            if len(parts) == 2 and parts[1] in ("scale", "offset"):
                fields.setdefault(parts[0], {})[parts[1]] = value
            elif len(parts) == 3 and parts[1] == "input_stats" and parts[2] in STAT_NAMES:
                fields.setdefault(parts[0], {})[parts[2]] = value
            else:
                unexpected_keys.append(name)
        self.params_dict = nn.ParameterDict()
        for key, f in fields.items():
            missing = [k for k in ("scale", "offset", *STAT_NAMES) if k not in f]
            if missing:
                error_msgs.append(f"normaliser key {key!r}: state dict lacks {missing}")
                continue
            self.set_field(key, {k: v.detach().cpu().numpy() for k, v in f.items()})


def umi_importable() -> bool:
    """True when UMI's ``diffusion_policy`` package (its normaliser and dataset base classes) imports here."""
    try:
        import diffusion_policy.dataset.base_dataset  # noqa: F401
        import diffusion_policy.model.common.normalizer  # noqa: F401
    except ImportError:
        return False
    return True


def umi_normalizer(fields: Mapping[str, Mapping[str, np.ndarray]]) -> nn.Module:
    """The normaliser holding ``fields``: UMI's ``LinearNormalizer`` when importable, else
    :class:`UmiLayoutNormalizer` (the same state-dict layout and values)."""
    if umi_importable():
        # lazy, optional dependency: diffusion_policy
        from diffusion_policy.model.common.normalizer import LinearNormalizer, SingleFieldLinearNormalizer

        norm = LinearNormalizer()
        for key, f in fields.items():
            norm[key] = SingleFieldLinearNormalizer.create_manual(
                scale=np.asarray(f["scale"], np.float32), offset=np.asarray(f["offset"], np.float32),
                input_stats_dict={k: np.asarray(f[k], np.float32) for k in STAT_NAMES})
        return norm
    norm = UmiLayoutNormalizer()
    for key, f in fields.items():
        norm.set_field(key, f)
    return norm


def normalizer_fields(norm: nn.Module) -> dict[str, dict[str, np.ndarray]]:
    """``{key: {scale, offset, min, max, mean, std}}`` float32 arrays of a UMI-layout normaliser (UMI's or ours),
    read from its state dict."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, value in norm.state_dict().items():
        parts = name.split(".")
        if parts[0] != "params_dict":
            continue
        out.setdefault(parts[1], {})[parts[-1]] = value.detach().cpu().numpy()
    return out
