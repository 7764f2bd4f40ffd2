"""Observation encoder: one image backbone per camera + flattened low-dim observations (UMI's ``TimmObsEncoder``
layout: features of the sorted rgb keys, each (T·D), then the sorted low-dim keys flattened).

Backbones:

* :class:`ClipVitBackbone` — the CLIP ViT vision tower (transformers ``CLIPVisionModel``; OpenAI ViT-B/16 by
  default: 768 wide, 12 layers, 12 heads, patch 16, quick-GELU). Feature = the CLS token after the final
  LayerNorm (``pooler_output``), the same tensor as timm's ``forward(...)[:, 0]`` for ``vit_base_patch16_clip_224``.
  Weights from a local HF folder, or a file holding HF, timm or UMI-checkpoint keys; random init otherwise.
* :class:`ResNetBackbone` — a pure-torch ResNet-18-style network with GroupNorm (UMI replaces BatchNorm by
  GroupNorm when not pretrained), global average pooling; ``resnet_width`` scales it down for CPU.

Fixed against UMI (umi_stack.md §4): images are normalised with the backbone's mean/std (CLIP for the ViT) and
random crop + colour jitter run only in training mode, and evaluation takes the centred crop of the same side
resized back (UMI's ``eval_transform``), so apparent sizes match training (UMI: no normalisation; jitter also at
inference).
"""

from __future__ import annotations

import copy
import logging
import re
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from umi_aug.errors import PolicyError
from umi_aug.policy.config import EncoderConfig
from umi_aug.policy.image_aug import (
    CLIP_MEAN, CLIP_STD, IMAGENET_MEAN, IMAGENET_STD, center_crop_resize, color_jitter, normalize_image,
    random_crop_resize, random_gaussian_blur,
)

__all__ = ["ObsEncoder", "ClipVitBackbone", "ResNetBackbone", "load_weights_file", "timm_clip_to_hf",
           "build_backbone", "SpatialSoftmax"]

log = logging.getLogger(__name__)

_NORM = {"clip": (CLIP_MEAN, CLIP_STD), "imagenet": (IMAGENET_MEAN, IMAGENET_STD)}


# ---------------------------------------------------------------------------------------------- weights files
def load_weights_file(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a weights file: ``.safetensors``, or a torch pickle (``.bin/.pt/.pth/.ckpt``) holding a state
    dict, ``{'state_dict': …}``, ``{'model': …}`` or a UMI/DP checkpoint ``{'state_dicts': {'ema_model'|'model'}}``.

    Torch pickles load with ``weights_only=True`` first; a UMI checkpoint (dill-pickled, with an OmegaConf config)
    needs a full unpickle, which runs only on this explicitly configured local file (and needs ``dill``).
    """
    path = Path(path)
    if not path.is_file():
        raise PolicyError(f"policy.encoder.pretrained_path: {path} is not a file or folder")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file  # lazy, optional dependency: safetensors

        return load_file(str(path))
    try:
        obj: Any = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as first:  # noqa: BLE001 - fall back to a full unpickle of a configured local file
        try:
            try:
                import dill as pickle_module
            except ImportError:
                import pickle as pickle_module
            log.warning("%s is not a plain weights file (%s); unpickling it fully (UMI checkpoint?)", path,
                        type(first).__name__)
            obj = torch.load(str(path), map_location="cpu", weights_only=False, pickle_module=pickle_module)
        except Exception as exc:
            raise PolicyError(f"policy.encoder.pretrained_path: cannot read {path}: {exc}. A UMI checkpoint needs "
                              "`pip install dill omegaconf`; or save its state dict with torch.save.") from exc
    for key in ("state_dicts", "state_dict", "model", "module"):
        if isinstance(obj, Mapping) and key in obj and isinstance(obj[key], Mapping):
            inner = obj[key]
            if key == "state_dicts":
                inner = inner.get("ema_model") or inner.get("model") or inner
            obj = inner
    if not isinstance(obj, Mapping) or not any(torch.is_tensor(v) for v in obj.values()):
        raise PolicyError(f"policy.encoder.pretrained_path: {path} holds no state dict of tensors")
    return {k: v for k, v in obj.items() if torch.is_tensor(v)}


def timm_clip_to_hf(sd: Mapping[str, torch.Tensor], prefix: str = "") -> dict[str, torch.Tensor]:
    """timm ``vit_*_clip_*`` keys (under ``prefix``) → transformers ``CLIPVisionModel`` keys (``vision_model.*``).

    cls_token → class_embedding, pos_embed → position_embedding, patch_embed.proj → patch_embedding, norm_pre →
    pre_layrnorm, blocks.i.{norm1, attn.qkv (split q/k/v), attn.proj, norm2, mlp.fc1, mlp.fc2} →
    encoder.layers.i.{layer_norm1, self_attn.{q,k,v}_proj, self_attn.out_proj, layer_norm2, mlp.fc1, mlp.fc2},
    norm → post_layernorm. Other keys (heads) are dropped.
    """
    out: dict[str, torch.Tensor] = {}
    vm = "vision_model."  # stripped again by ClipVitBackbone when the model's own keys have no such prefix
    n = len(prefix)
    for key, v in sd.items():
        if not key.startswith(prefix):
            continue
        k = key[n:]
        if k == "cls_token":
            out[vm + "embeddings.class_embedding"] = v.reshape(-1)
        elif k == "pos_embed":
            out[vm + "embeddings.position_embedding.weight"] = v.reshape(-1, v.shape[-1])
        elif k == "patch_embed.proj.weight":
            out[vm + "embeddings.patch_embedding.weight"] = v
        elif k.startswith("norm_pre."):
            out[vm + "pre_layrnorm." + k[len("norm_pre."):]] = v
        elif k.startswith("norm."):
            out[vm + "post_layernorm." + k[len("norm."):]] = v
        else:
            m = re.match(r"blocks\.(\d+)\.(.+)$", k)
            if not m:
                continue
            i, rest = m.group(1), m.group(2)
            base = f"{vm}encoder.layers.{i}."
            if rest.startswith("attn.qkv."):
                q, kk, vv = v.chunk(3, dim=0)
                kind = rest.split(".")[-1]
                out[base + f"self_attn.q_proj.{kind}"] = q
                out[base + f"self_attn.k_proj.{kind}"] = kk
                out[base + f"self_attn.v_proj.{kind}"] = vv
            else:
                for a, b in (("attn.proj.", "self_attn.out_proj."), ("norm1.", "layer_norm1."),
                             ("norm2.", "layer_norm2."), ("mlp.fc1.", "mlp.fc1."), ("mlp.fc2.", "mlp.fc2.")):
                    if rest.startswith(a):
                        out[base + b + rest[len(a):]] = v
    return out


def _hf_vision_keys(sd: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Keys ``…vision_model.X`` → ``vision_model.X`` (CLIPModel, CLIPVisionModel, or a wrapped copy of either)."""
    out = {}
    for k, v in sd.items():
        i = k.find("vision_model.")
        if i >= 0:
            out[k[i:]] = v
    return out


def _timm_prefixes(sd: Mapping[str, torch.Tensor]) -> list[str]:
    return sorted(k[: -len("cls_token")] for k in sd if k.endswith("cls_token") and not k.endswith("class_token"))


# ---------------------------------------------------------------------------------------------- backbones
class ClipVitBackbone(nn.Module):
    """CLIP ViT vision tower → CLS feature [N, hidden] (post-LayerNorm). Input: normalised [N, 3, S, S]."""

    def __init__(self, cfg: EncoderConfig, image_size: int, rgb_key: str = "") -> None:
        super().__init__()
        # lazy, optional dependency: transformers
        import transformers
        from transformers import CLIPVisionConfig, CLIPVisionModel

        transformers.logging.set_verbosity_error()
        self.pretrained = False
        path = Path(cfg.pretrained_path) if cfg.pretrained_path else None
        if path is not None and path.is_dir():
            try:
                self.model = CLIPVisionModel.from_pretrained(str(path), local_files_only=True)
            except Exception as exc:  # noqa: BLE001 - report the folder
                raise PolicyError(f"policy.encoder.pretrained_path: cannot load a CLIP vision model from folder "
                                  f"{path}: {exc}") from exc
            if self.model.config.image_size != image_size:
                raise PolicyError(f"policy.encoder.pretrained_path: {path} is a {self.model.config.image_size}² "
                                  f"model but task.image_size={image_size}")
            self.pretrained = True
        else:
            conf = CLIPVisionConfig(
                hidden_size=cfg.vit_hidden_size, intermediate_size=cfg.vit_mlp_size,
                num_hidden_layers=cfg.vit_layers, num_attention_heads=cfg.vit_heads, image_size=image_size,
                patch_size=cfg.vit_patch_size, hidden_act="quick_gelu", projection_dim=512)
            self.model = CLIPVisionModel(conf)
            if path is not None:
                self._load_file(path, rgb_key)
                self.pretrained = True
        self.feature_dim = int(self.model.config.hidden_size)

    def _load_file(self, path: Path, rgb_key: str) -> None:
        sd = load_weights_file(path)
        hf = _hf_vision_keys(sd)
        if not hf:
            prefixes = _timm_prefixes(sd)
            if not prefixes:
                raise PolicyError(f"policy.encoder.pretrained_path: {path} has neither CLIP (vision_model.*) nor timm "
                                  "ViT (cls_token, blocks.*) keys")
            pick = [p for p in prefixes if rgb_key and rgb_key in p] or prefixes
            if len(prefixes) > 1:
                log.info("%s: %d ViTs found (%s); using %r", path, len(prefixes), prefixes, pick[0])
            hf = timm_clip_to_hf(sd, pick[0])
        own = self.model.state_dict()
        if not any(k.startswith("vision_model.") for k in own):  # transformers 5 names keys without the prefix
            hf = {k[len("vision_model."):]: v for k, v in hf.items()}
        wrong = {k: (tuple(v.shape), tuple(own[k].shape)) for k, v in hf.items() if k in own and v.shape != own[k].shape}
        if wrong:
            raise PolicyError(f"policy.encoder.pretrained_path: {path} does not fit the configured ViT "
                              f"(file shape, model shape): {dict(list(wrong.items())[:4])}")
        missing = [k for k in own if k not in hf and not k.endswith("position_ids")]
        if missing:
            raise PolicyError(f"policy.encoder.pretrained_path: {path} lacks {len(missing)} vision weights, e.g. "
                              f"{missing[:4]}")
        self.model.load_state_dict({k: v for k, v in hf.items() if k in own}, strict=False)
        log.info("loaded CLIP vision weights from %s", path)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [N, 3, S, S] → [N, hidden]
        return self.model(pixel_values=x).pooler_output


def _gn(c: int) -> nn.GroupNorm:
    """UMI's BatchNorm → GroupNorm replacement: c/16 groups when divisible, else c/8 (at least 1)."""
    return nn.GroupNorm(max(1, c // 16 if c % 16 == 0 else c // 8), c)


class _StridedPointwiseConv(nn.Conv2d):
    """A 1×1 convolution with stride ``s`` and no padding, computed as a stride-1 1×1 convolution of every ``s``-th
    pixel (``x[..., ::s, ::s]``): the same output, the same weight, the same checkpoint keys as
    ``nn.Conv2d(c_in, c_out, 1, s, bias=False)``, which is its reference. oneDNN's own strided 1×1 backward-weights
    kernel on channels-last input with fewer input channels than its block (16 on AVX-512) writes past its
    workspace: wrong weight gradients, a hang or a crash ("double free or corruption"; oneDNN issue #6035, seen
    with torch 2.13.0 at resnet_width=8). The stride-1 kernel does not take that path."""

    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__(c_in, c_out, 1, 1, bias=False)
        self.subsample = int(stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.subsample > 1:
            fmt = torch.channels_last if x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous() \
                else torch.contiguous_format
            x = x[..., ::self.subsample, ::self.subsample].contiguous(memory_format=fmt)
        return super().forward(x)


class _BasicBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.norm1 = _gn(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.norm2 = _gn(c_out)
        self.down = None if stride == 1 and c_in == c_out else nn.Sequential(
            _StridedPointwiseConv(c_in, c_out, stride), _gn(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return torch.relu(y + (x if self.down is None else self.down(x)))


class SpatialSoftmax(nn.Module):
    """Keypoints of a feature map (Levine et al. 2016; robomimic's and Diffusion Policy's ResNet pooling): a 1×1
    convolution to ``K`` maps, a softmax over each map's H·W cells, and each map's expected cell centre
    ``(x, y)`` in [−1, 1] (x along the width, left → right; y along the height, top → bottom) → ``[N, 2K]`` as
    ``[x_0, y_0, x_1, y_1, …]``. Unlike global average pooling it keeps WHERE a feature is in the image."""

    def __init__(self, in_channels: int, n_keypoints: int) -> None:
        super().__init__()
        self.n_keypoints = int(n_keypoints)
        self.keypoint_maps = nn.Conv2d(in_channels, self.n_keypoints, 1)

    @staticmethod
    def cell_centres(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
        """``[H·W, 2]`` (x, y) of the cell centres in [−1, 1] (row-major), dtype/device of ``like``."""
        ys = torch.linspace(-1.0, 1.0, h, dtype=like.dtype, device=like.device)
        xs = torch.linspace(-1.0, 1.0, w, dtype=like.dtype, device=like.device)
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        maps = self.keypoint_maps(feat)  # [N, K, H, W]
        n, k, h, w = maps.shape
        attn = torch.softmax(maps.reshape(n, k, h * w).float(), dim=-1)
        return (attn @ self.cell_centres(h, w, attn)).reshape(n, 2 * k)


class ResNetBackbone(nn.Module):
    """ResNet-18 layout (stem 7×7/2 + max-pool, 4 stages of basic blocks, widths w·[1, 2, 4, 8]) with GroupNorm,
    then global average pooling → [N, 8w] (``resnet_pool: avg``) or a spatial softmax → [N, 2K] keypoint
    coordinates (``resnet_pool: spatial_softmax``, K = ``spatial_softmax_keypoints``; robomimic's ResNet18Conv +
    SpatialSoftmax). ``resnet_width=64, resnet_blocks=[2,2,2,2]`` is ResNet-18."""

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        w = int(cfg.resnet_width)
        self.stem = nn.Sequential(nn.Conv2d(3, w, 7, 2, 3, bias=False), _gn(w), nn.ReLU(), nn.MaxPool2d(3, 2, 1))
        stages, c = [], w
        for s, n in enumerate(cfg.resnet_blocks):
            c_out = w * 2 ** s
            blocks = [_BasicBlock(c, c_out, 1 if s == 0 else 2)] + [_BasicBlock(c_out, c_out, 1) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            c = c_out
        self.stages = nn.Sequential(*stages)
        self.pool = SpatialSoftmax(c, cfg.spatial_softmax_keypoints) if cfg.resnet_pool == "spatial_softmax" else None
        self.feature_dim = 2 * cfg.spatial_softmax_keypoints if self.pool is not None else c
        self.pretrained = False
        if cfg.pretrained_path:
            sd = load_weights_file(cfg.pretrained_path)
            try:
                self.load_state_dict(sd)
            except RuntimeError as exc:
                raise PolicyError(f"policy.encoder.pretrained_path: {cfg.pretrained_path} does not fit the "
                                  f"ResNet backbone: {exc}") from exc
            self.pretrained = True
        # channels-last (NHWC) activations and weights: oneDNN's CPU convolutions, their backward above all, run
        # 1.2-1.3x faster on it than on NCHW (issue #29; NCHW, cfg.channels_last=False, is the reference)
        self.memory_format = torch.channels_last if cfg.channels_last else torch.contiguous_format
        self.to(memory_format=self.memory_format)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feat = self.stages(self.stem(x.contiguous(memory_format=self.memory_format)))
        return feat.mean(dim=(-2, -1)) if self.pool is None else self.pool(feat)


def build_backbone(cfg: EncoderConfig, image_size: int, rgb_key: str = "") -> nn.Module:
    if cfg.name == "clip_vit":
        return ClipVitBackbone(cfg, image_size, rgb_key)
    if cfg.name == "resnet":
        return ResNetBackbone(cfg)
    raise PolicyError(f"policy.encoder.name={cfg.name!r}: expected 'clip_vit' or 'resnet'")


# ---------------------------------------------------------------------------------------------- encoder
class ObsEncoder(nn.Module):
    """``{key: [B, T, ...]}`` → ``[B, Σ_rgb T·D + Σ_lowdim T·d]`` (sorted rgb keys, then sorted low-dim keys).

    Args:
        shape_meta: UMI-style ``{'obs': {key: {shape, horizon, type, ignore_by_policy}}}``.
        cfg: :class:`EncoderConfig`.
        warn_random_init: log a warning when the backbone starts from random weights (off when the weights are
            about to be loaded from a policy checkpoint).
    """

    def __init__(self, shape_meta: Mapping[str, Any], cfg: EncoderConfig, warn_random_init: bool = True) -> None:
        super().__init__()
        obs = shape_meta["obs"]
        self.cfg = cfg
        self.rgb_keys = sorted(k for k, v in obs.items() if v["type"] == "rgb")
        self.lowdim_keys = sorted(k for k, v in obs.items() if v["type"] == "low_dim"
                                  and not v.get("ignore_by_policy", False))
        self.key_shape = {k: tuple(v["shape"]) for k, v in obs.items()}
        self.key_horizon = {k: int(v["horizon"]) for k, v in obs.items()}
        sizes = {self.key_shape[k][1:] for k in self.rgb_keys}
        if len(sizes) > 1 or any(s[0] != s[1] for s in sizes):
            raise PolicyError(f"ObsEncoder: all cameras need one square image size, got {sizes}")
        self.image_size = next(iter(sizes))[0] if sizes else 0
        self.backbones = nn.ModuleDict()
        if self.rgb_keys:
            first = build_backbone(cfg, self.image_size, self.rgb_keys[0])
            for k in self.rgb_keys:
                if k == self.rgb_keys[0] or cfg.share_rgb_model:
                    self.backbones[k] = first
                elif cfg.pretrained_path:
                    self.backbones[k] = build_backbone(cfg, self.image_size, k)
                else:
                    self.backbones[k] = copy.deepcopy(first)
            if cfg.frozen:
                for p in self.backbones.parameters():
                    p.requires_grad_(False)
        self.pretrained = bool(self.rgb_keys) and all(getattr(b, "pretrained", False) for b in self.backbones.values())
        if self.rgb_keys and not self.pretrained and warn_random_init:
            msg = ("observation encoder %r starts from RANDOM weights (policy.encoder.pretrained_path is not set); "
                   "the paper fine-tunes a CLIP-pretrained ViT-B/16: point pretrained_path at a local HF CLIP folder")
            (log.warning if cfg.name == "clip_vit" else log.info)(msg, cfg.name)
        self.feature_dim = max((int(b.feature_dim) for b in self.backbones.values()), default=0)
        self._norm = _NORM.get(cfg.image_norm)
        self.generator: torch.Generator | None = None  # optional RNG for the train-time augmentation

    @property
    def output_dim(self) -> int:
        d = sum(self.key_horizon[k] * self.feature_dim for k in self.rgb_keys)
        return d + sum(self.key_horizon[k] * int(torch.tensor(self.key_shape[k]).prod()) for k in self.lowdim_keys)

    def backbone_parameters(self) -> list[nn.Parameter]:
        return list(self.backbones.parameters())

    def preprocess(self, img: torch.Tensor) -> torch.Tensor:
        """[B, T, 3, S, S] in [0, 1] → cropped (random in training, centred in evaluation: the same scale),
        jittered and blurred (training only, when configured) and normalised images."""
        if self.cfg.crop_ratio < 1.0:
            img = (random_crop_resize(img, self.cfg.crop_ratio, self.generator) if self.training
                   else center_crop_resize(img, self.cfg.crop_ratio))
        if self.training and self.cfg.color_jitter:
            img = color_jitter(img, *self.cfg.color_jitter, generator=self.generator)
        if self.training and self.cfg.blur_sigma_max > 0:
            img = random_gaussian_blur(img, self.cfg.blur_sigma_max, generator=self.generator)
        if self._norm is not None:
            img = normalize_image(img, *self._norm)
        return img

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        feats = []
        B = None
        for k in self.rgb_keys + self.lowdim_keys:
            if k not in obs:
                raise PolicyError(f"ObsEncoder: observation key {k!r} missing; got {sorted(obs)}")
            x = obs[k]
            want = (self.key_horizon[k],) + self.key_shape[k]
            if tuple(x.shape[1:]) != want or (B is not None and x.shape[0] != B):
                raise PolicyError(f"ObsEncoder: {k!r} must be [B, {', '.join(map(str, want))}], got {tuple(x.shape)}")
            B = x.shape[0]
        for k in self.rgb_keys:
            img = self.preprocess(obs[k])
            Bk, T = img.shape[:2]
            f = self.backbones[k](img.reshape(Bk * T, *img.shape[2:]))
            feats.append(f.reshape(Bk, -1))
        for k in self.lowdim_keys:
            feats.append(obs[k].reshape(obs[k].shape[0], -1))
        return torch.cat(feats, dim=-1)
