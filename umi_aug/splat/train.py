"""Fisheye 3DGS trainer on the CPU (paper §3.1 "Fisheye 3D Gaussians"; issue #4 item 4).

Per step: one training view (shuffled epochs), :func:`umi_aug.splat.render` with gradients (KB EWA projection and
numba rasteriser, both numba with hand-written backwards; ``fast_projection=False`` runs the torch-autograd
reference projection instead), the masked ``(1 - w) L1 + w D-SSIM`` loss
(:mod:`umi_aug.splat.losses`; gripper/mirror pixels and pixels outside the image circle excluded), opacity and
scale regularisers, Adam (:mod:`umi_aug.splat.optim`), then 3DGS-MCMC position noise and, every
``refine_every`` steps, relocation of dead Gaussians and growth up to the budget ``max_gaussians``
(:mod:`umi_aug.splat.densify`). SH degree rises by one every ``sh_increase_every`` steps. Every
``holdout_every``-th view (index 0, 8, 16, ...) is held out: never trained on, evaluated (masked PSNR / SSIM).

Why MCMC rather than clone/split/prune: on the CPU the step time is proportional to the number of Gaussians
(projection and rasteriser both scale with it), so a hard, smoothly growing budget gives a predictable run time;
MCMC needs no screen-space gradient statistics or opacity resets (which cost several hundred steps to recover
each, a large share of a 3-5k-step CPU run) and works from random initialisation.

Outputs in ``out_dir``: ``scene.ply`` (INRIA layout), ``checkpoint.pt`` (atomic; resumable), ``metrics.json``,
``contact_sheet.png`` (held-out GT | render | |error|), ``curve.png`` (PSNR / SSIM vs iteration and seconds; a run
evaluated at two iterations or more).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SplatError
from umi_aug.io_utils import atomic_path
from umi_aug.splat.densify import grow, inject_noise, relocate_dead
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.losses import masked_psnr, photometric_loss_fused, ssim_target_stats
from umi_aug.splat.optim import GaussianAdam
from umi_aug.splat.ply import write_ply
from umi_aug.splat.train_report import config_dict, write_outputs

__all__ = [
    "SplatTrainConfig", "TrainView", "SplatTrainResult", "train_splat",
    "split_views", "scene_scale", "init_gaussians", "CHECKPOINT_NAME",
]

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
#: Accumulated seconds in ``SplatTrainResult.timings``: the step's stages (render, loss, backward, step, densify)
#: and, inside them, the projection / rasteriser forward (render) and backward (backward).
TIMING_KEYS = ("render", "loss", "backward", "step", "densify", "project", "raster", "project_backward",
               "raster_backward")
CHECKPOINT_VERSION = 1
#: Config fields that may change between a checkpoint and a resumed run.
RESUMABLE_CHANGES = frozenset({"iterations", "eval_every", "eval_at_start", "checkpoint_every", "sheet_views",
                               "fast_projection", "loss_pixels_only"})


@dataclass(frozen=True)
class SplatTrainConfig:
    """Trainer settings (defaults: the synthetic 320x240 session in ~15 min on 2 shared CPU cores).

    Attributes:
        iterations: training steps (one view each).
        max_gaussians: Gaussian budget (MCMC growth cap; never exceeded).
        sh_degree: largest SH degree; the rendered degree rises by 1 every ``sh_increase_every`` steps.
        holdout_every: every n-th view (index % n == 0) is held out and evaluated; 0 = none held out.
        ssim_weight: ``w`` in ``(1 - w) L1 + w (1 - SSIM)``.
        seed: all randomness (view order, relocation sampling, noise).
        lr_means: position learning rate per metre of scene scale, decayed exponentially to
            ``lr_means * lr_means_final`` at the last step; ``lr_*``: Adam learning rates of the other parameters.
        init_opacity, init_scale: initial opacity and scale (x mean distance to the 3 nearest init points).
        refine_start, refine_stop, refine_every: MCMC relocation / growth window and period (steps);
            ``refine_stop`` None = 80 % of ``iterations``.
        growth_factor: N grows by this factor per refinement up to ``max_gaussians``.
        min_opacity: Gaussians at or below this opacity are dead (relocated).
        noise_lr: position-noise multiplier (x the current ``lr_means`` x scene scale).
        opacity_reg, scale_reg: weights of ``mean(opacity)`` and ``mean(scale / scene_scale)`` added to the loss.
        filter: screen-space filter of the renderer (``"inria"`` | ``"mip"`` | ``"none"``).
        background: RGB behind the Gaussians in [0, 1].
        eval_every: evaluate held-out and (up to ``train_eval_views``) training views every n steps (and at the end);
            0 = at the last step only.
        eval_at_start: also evaluate the initial Gaussians (the curve's step 0). Evaluations read the scene and
            draw no random numbers: neither setting changes the trained scene.
        checkpoint_every: write ``checkpoint.pt`` every n steps (and at the end).
        sheet_views: held-out views in the contact sheet.
        fast_projection: numba projection with its hand-written backward
            (:class:`umi_aug.splat.project.ProjectGaussians`); False: the torch-autograd reference (same results
            up to rounding, slower).
        coarse_downscale, coarse_fraction: coarse-to-fine training. The first ``round(coarse_fraction x
            iterations)`` steps train on the views downscaled by the integer ``coarse_downscale`` (the mean of each
            ``f x f`` block; a coarse pixel is in the loss only if all its full pixels are), rendered with the
            matching intrinsics (``FisheyeIntrinsics.scaled``, exact for that block mean); the rest at full
            resolution. At f = 2 a coarse step's rasteriser costs 40-60 % of a full one, not 1/4 (measured on the
            real episode: per-Gaussian work such as binning does not shrink with the image), the loss ~1/f^2; the
            projection, the optimiser step and the densifier are per Gaussian and cost the same
            (docs/real_scale.md section 1b). Evaluation and outputs are always at full resolution.
            ``coarse_downscale = 1``: full resolution throughout.
        loss_pixels_only: training steps and evaluations rasterise only the pixels of the view's loss mask
            (``render(pixels=)``): the loss, every gradient and every metric are exactly those of rendering the whole
            view (the masked loss composites the target outside the mask before anything reads it), while the
            gripper, mirrors and the corners outside the image circle (43 % of a UMI policy frame) cost nothing
            where they fill whole 16x16 tiles. False: every pixel is rendered (the reference; same results).
    """

    iterations: int = 3000
    max_gaussians: int = 60_000
    sh_degree: int = 3
    holdout_every: int = 8
    ssim_weight: float = 0.2
    seed: int = 0
    sh_increase_every: int = 500
    lr_means: float = 1.6e-4
    lr_means_final: float = 0.01
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    init_opacity: float = 0.5
    init_scale: float = 0.5
    refine_start: int = 300
    refine_stop: int | None = None
    refine_every: int = 100
    growth_factor: float = 1.05
    min_opacity: float = 0.005
    noise_lr: float = 5e5
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    filter: str = "inria"
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    eval_every: int = 500
    eval_at_start: bool = True
    train_eval_views: int = 8
    checkpoint_every: int = 500
    sheet_views: int = 4
    fast_projection: bool = True
    coarse_downscale: int = 1
    coarse_fraction: float = 0.5
    loss_pixels_only: bool = True

    def check(self) -> None:
        """Raise :class:`SplatError` naming the first invalid field."""
        def bad(name: str, why: str) -> SplatError:
            return SplatError(f"SplatTrainConfig.{name} = {getattr(self, name)!r}: {why}")

        for name in ("iterations", "max_gaussians", "refine_every", "checkpoint_every", "sh_increase_every"):
            if int(getattr(self, name)) < 1:
                raise bad(name, "must be >= 1")
        if int(self.eval_every) < 0:
            raise bad("eval_every", "must be >= 1, or 0 (at the last step only)")
        if not 0 <= self.sh_degree <= 3:
            raise bad("sh_degree", "must be in 0..3")
        if self.holdout_every < 0 or self.holdout_every == 1:
            raise bad("holdout_every", "must be 0 (no hold-out) or >= 2")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise bad("ssim_weight", "must be in [0, 1]")
        if not 0.0 < self.init_opacity < 1.0:
            raise bad("init_opacity", "must be in (0, 1)")
        if self.growth_factor < 1.0:
            raise bad("growth_factor", "must be >= 1")
        if int(self.coarse_downscale) != self.coarse_downscale or self.coarse_downscale < 1:
            raise bad("coarse_downscale", "must be an integer >= 1")
        if not 0.0 <= float(self.coarse_fraction) <= 1.0:
            raise bad("coarse_fraction", "must be in [0, 1]")
        if self.filter not in ("inria", "mip", "none"):
            raise bad("filter", "must be 'inria', 'mip' or 'none'")
        if len(self.background) != 3:
            raise bad("background", "must be 3 floats")
        for name in ("lr_means", "lr_scales", "lr_quats", "lr_opacities", "lr_sh0", "lr_sh_rest", "init_scale",
                     "lr_means_final"):
            if not (float(getattr(self, name)) > 0 and math.isfinite(float(getattr(self, name)))):
                raise bad(name, "must be positive and finite")

    @property
    def refine_stop_step(self) -> int:
        return int(0.8 * self.iterations) if self.refine_stop is None else int(self.refine_stop)

    @property
    def coarse_stop_step(self) -> int:
        """Last step trained at the coarse resolution (0: none)."""
        return int(round(self.coarse_fraction * self.iterations)) if self.coarse_downscale > 1 else 0


@dataclass
class TrainView:
    """One training image.

    Attributes:
        name: identifier (e.g. ``mapping/000012``).
        image: np.ndarray,  # [H, W, 3] uint8 RGB, H x W = the intrinsics' size
        T_world_cam: np.ndarray,  # [4, 4] OpenCV camera pose, metres
        loss_mask: np.ndarray,  # [H, W] bool, True = pixel used in the loss
    """

    name: str
    image: np.ndarray
    T_world_cam: np.ndarray
    loss_mask: np.ndarray


@dataclass
class SplatTrainResult:
    """What :func:`train_splat` returns.

    Attributes:
        gaussians: the trained scene (float32, detached).
        out_dir, ply_path: output folder and ``out_dir/scene.ply`` (None without ``out_dir``).
        heldout_psnr, heldout_ssim: final masked metrics over the held-out views (nan if none held out, or if a run
            stopped by ``stop_at`` has evaluated nothing yet).
        history: one dict per evaluation: iteration, seconds (training time, evaluation excluded), cpu_seconds
            (the process's CPU time over the same steps, all threads), wall_seconds, n_gaussians, loss,
            train_psnr, train_ssim, heldout_psnr, heldout_ssim.
    """

    gaussians: Gaussians
    out_dir: Path | None
    ply_path: Path | None
    heldout_psnr: float
    heldout_ssim: float
    history: list[dict] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------- helpers
def split_views(n_views: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """``(train, heldout)`` indices: index ``i`` is held out iff ``holdout_every > 0 and i % holdout_every == 0``
    (INRIA's ``llffhold``); everything is trained on when that would leave no training view."""
    held = [i for i in range(n_views) if holdout_every > 0 and i % holdout_every == 0]
    train = [i for i in range(n_views) if i not in set(held)]
    if not train:
        return list(range(n_views)), []
    return train, held


def scene_scale(T_world_cam: np.ndarray) -> float:
    """``1.1 x`` the largest distance of a camera centre from their mean (gsplat), metres; 1 for < 2 cameras."""
    c = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    if len(c) < 2:
        return 1.0
    r = float(np.linalg.norm(c - c.mean(0), axis=1).max()) * 1.1
    return r if r > 1e-6 else 1.0


def init_gaussians(xyz: np.ndarray, rgb: np.ndarray | None, cfg: SplatTrainConfig, scale_ref: float,
                   rng: np.random.Generator) -> Gaussians:
    """Isotropic Gaussians at ``xyz [N, 3]`` (world, metres) with colours ``rgb [N, 3]`` in [0, 1] (random when
    None), scale = ``cfg.init_scale`` x RMS distance to the 3 nearest points (at least ``1e-4 scale_ref``)."""
    from scipy.spatial import cKDTree  # lazy, start-up: scipy

    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) < 1 or not np.isfinite(xyz).all():
        raise SplatError(f"train_splat: init_xyz must be a finite [N, 3] array with N >= 1, got shape {xyz.shape}")
    if rgb is None:
        rgb = rng.uniform(0.0, 1.0, size=xyz.shape)
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape != xyz.shape or not np.isfinite(rgb).all():
        raise SplatError(f"train_splat: init_rgb must be finite [N, 3] like init_xyz {xyz.shape}, got {rgb.shape}")
    k = min(4, len(xyz))
    if k > 1:
        d, _ = cKDTree(xyz).query(xyz, k=k)
        dist = np.sqrt((d[:, 1:] ** 2).mean(axis=1))
    else:
        dist = np.full(len(xyz), 0.01 * scale_ref)
    dist = np.maximum(dist, 1e-4 * scale_ref)
    return Gaussians.from_points(xyz, np.clip(rgb, 0.0, 1.0), dist * cfg.init_scale, cfg.init_opacity,
                                 sh_degree=cfg.sh_degree, dtype=torch.float32)


def _check_views(views: Sequence[TrainView], intr: FisheyeIntrinsics) -> None:
    if len(views) == 0:
        raise SplatError("train_splat: no views")
    for v in views:
        img = np.asarray(v.image)
        if img.dtype != np.uint8 or img.shape != (intr.height, intr.width, 3):
            raise SplatError(f"train_splat: view {v.name!r}: image must be uint8 [{intr.height}, {intr.width}, 3] "
                             f"(the intrinsics' size), got {img.dtype} {list(img.shape)}")
        m = np.asarray(v.loss_mask)
        if m.dtype != np.bool_ or m.shape != (intr.height, intr.width):
            raise SplatError(f"train_splat: view {v.name!r}: loss_mask must be bool [{intr.height}, {intr.width}], "
                             f"got {m.dtype} {list(m.shape)}")
        if not m.any():
            raise SplatError(f"train_splat: view {v.name!r}: loss_mask selects no pixel")
        T = np.asarray(v.T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise SplatError(f"train_splat: view {v.name!r}: T_world_cam must be a finite [4, 4] pose")


#: Memory for the training views' SSIM window statistics kept between steps (bytes; 256 MiB = ~220 views at 224^2).
SSIM_STATS_CACHE_BYTES = 256 * 2**20


class _Data:
    """Views as tensors (images float32 [H, W, 3] in [0, 1], masks bool [H, W])."""

    def __init__(self, views: Sequence[TrainView]):
        self.names = [v.name for v in views]
        self.images = [torch.from_numpy(np.asarray(v.image, dtype=np.float32) / 255.0) for v in views]
        self.masks = [torch.from_numpy(np.ascontiguousarray(v.loss_mask)) for v in views]
        self.poses = [torch.as_tensor(np.asarray(v.T_world_cam, dtype=np.float64)) for v in views]
        self._ssim_stats: dict[int, torch.Tensor] = {}

    def ssim_stats(self, i: int) -> torch.Tensor:
        """:func:`ssim_target_stats` of view ``i``, computed on first use and kept while the kept ones stay within
        ``SSIM_STATS_CACHE_BYTES`` (24 bytes per pixel in float32; beyond it they are computed each time)."""
        st = self._ssim_stats.get(i)
        if st is None:
            st = ssim_target_stats(self.images[i])
            kept = sum(t.numel() * t.element_size() for t in self._ssim_stats.values())
            if kept + st.numel() * st.element_size() <= SSIM_STATS_CACHE_BYTES:
                self._ssim_stats[i] = st
        return st

    def downscaled(self, intr: FisheyeIntrinsics, factor: int) -> tuple["_Data", FisheyeIntrinsics]:
        """The views at ``1/factor`` resolution (``f x f`` block means; a coarse pixel keeps its mask only if all its
        full pixels have it) and their intrinsics (``intr.scaled``, exact for the block mean)."""
        f = int(factor)
        H, W = intr.height, intr.width
        if H % f or W % f:
            raise SplatError(f"SplatTrainConfig.coarse_downscale = {f}: the image size {W}x{H} is not a multiple "
                             f"of it")
        out = _Data([])
        out.names, out.poses = list(self.names), list(self.poses)
        out.images = [img.reshape(H // f, f, W // f, f, 3).mean(dim=(1, 3)) for img in self.images]
        out.masks = [m.reshape(H // f, f, W // f, f).all(dim=3).all(dim=1) for m in self.masks]
        for name, m in zip(out.names, out.masks):
            if not bool(m.any()):
                raise SplatError(f"train_splat: view {name!r}: its loss_mask keeps no pixel at 1/{f} resolution "
                                 f"(SplatTrainConfig.coarse_downscale); use a smaller factor")
        return out, intr.scaled(W // f, H // f, "exact")


def _lrs(cfg: SplatTrainConfig, step: int, scale: float) -> dict[str, float]:
    t = min(max(step, 0), cfg.iterations) / max(cfg.iterations, 1)
    return {
        "means": cfg.lr_means * scale * cfg.lr_means_final**t,
        "log_scales": cfg.lr_scales,
        "quats_wxyz": cfg.lr_quats,
        "logit_opacities": cfg.lr_opacities,
        "sh0": cfg.lr_sh0,
        "sh_rest": cfg.lr_sh_rest,
    }


def _render(g: Gaussians, data: _Data, i: int, intr: FisheyeIntrinsics, cfg: SplatTrainConfig, deg: int):
    """View ``i`` rendered for the masked metrics (only its loss mask's pixels when ``cfg.loss_pixels_only``)."""
    from umi_aug.splat.renderer import render  # lazy, start-up: numba, scipy

    return render(g, data.poses[i], intr, torch.tensor(cfg.background, dtype=torch.float32), deg,
                  filter=cfg.filter, pixels=data.masks[i] if cfg.loss_pixels_only else None)


@torch.no_grad()
def _evaluate(g: Gaussians, data: _Data, idx: Sequence[int], intr, cfg, deg) -> tuple[float, float]:
    """Mean masked PSNR (dB) and SSIM over views ``idx`` (nan when empty). The SSIM is the fused loss's
    (:func:`photometric_loss_fused` with weight 1: :func:`masked_ssim`'s value, within float rounding, with the view's
    kept target statistics), ~2.5x less blurring than :func:`masked_ssim` on 2 cores."""
    if not idx:
        return float("nan"), float("nan")
    ps, ss = [], []
    for i in idx:
        rgb = _render(g, data, i, intr, cfg, deg).rgb.clamp(0.0, 1.0)
        ps.append(masked_psnr(rgb, data.images[i], data.masks[i]))
        _, parts = photometric_loss_fused(rgb, data.images[i], data.masks[i], 1.0, target_stats=data.ssim_stats(i))
        ss.append(float(parts["ssim"]))
    return float(np.mean(ps)), float(np.mean(ss))


def _cfg_dict(cfg: SplatTrainConfig) -> dict[str, Any]:
    return config_dict(cfg)


# --------------------------------------------------------------------------------------------- checkpointing
def _save_checkpoint(path: Path, state: dict) -> None:
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _load_checkpoint(path: Path, cfg: SplatTrainConfig, names: list[str]) -> dict | None:
    if not path.is_file():
        return None
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001  (any unreadable file: say which)
        raise SplatError(f"{path}: unreadable checkpoint ({exc}); rerun with --restart to start over "
                         f"(umi-aug train-splat), or delete it") from exc
    if ck.get("version") != CHECKPOINT_VERSION:
        raise SplatError(f"{path}: checkpoint version {ck.get('version')!r}, expected {CHECKPOINT_VERSION}")
    defaults = _cfg_dict(SplatTrainConfig())  # a field added since the checkpoint was written had its default
    old = {**defaults, **ck["cfg"]}
    new = _cfg_dict(cfg)
    diff = [k for k in new if k not in RESUMABLE_CHANGES and old.get(k) != new[k]]
    if diff:
        changes = ", ".join(f"{k}: {old.get(k)!r} -> {new[k]!r}" for k in diff)
        raise SplatError(f"{path}: checkpoint was trained with other settings ({changes}); use the same config "
                         f"or rerun with --restart to start over (umi-aug train-splat)")
    if ck["views"] != names:
        raise SplatError(f"{path}: checkpoint was trained on other views ({len(ck['views'])} vs {len(names)}); "
                         f"rerun with --restart to start over (umi-aug train-splat)")
    return ck


# ---------------------------------------------------------------------------------------------------- training
def train_splat(
    views: Sequence[TrainView],
    intr: FisheyeIntrinsics,
    init_xyz: np.ndarray,  # [N, 3] world, metres
    init_rgb: np.ndarray | None = None,  # [N, 3] in [0, 1]
    cfg: SplatTrainConfig = SplatTrainConfig(),
    out_dir: str | Path | None = None,
    *,
    resume: bool = True,
    progress: bool = True,
    stop_at: int | None = None,
) -> SplatTrainResult:
    """Train a fisheye 3DGS scene from posed, masked images.

    Args:
        views: training + held-out images (every ``cfg.holdout_every``-th is held out), size = ``intr``'s.
        intr: KB fisheye intrinsics of the images.
        init_xyz: initial Gaussian centres (SfM points, or random in a box), world frame, metres.
        init_rgb: their colours in [0, 1] (random when None).
        cfg: :class:`SplatTrainConfig`.
        out_dir: output folder (scene.ply, checkpoint.pt, metrics.json, contact_sheet.png, curve.png when evaluated
            at two iterations or more); None = nothing written, no resume.
        resume: continue from ``out_dir/checkpoint.pt`` if present (to ``cfg.iterations``; a finished run
            returns at once; raising ``cfg.iterations`` continues a finished run, the position learning-rate
            decay is then re-based on the new count; other config changes raise). False: start over (an existing
            checkpoint is overwritten).
        progress: tqdm progress bar.
        stop_at: stop after this iteration (checkpoint written, no final outputs), as if interrupted; for
            time-sliced runs and tests.

    Returns:
        :class:`SplatTrainResult`.

    Raises:
        SplatError: invalid views / init / config, or an incompatible checkpoint.
    """
    cfg.check()
    _check_views(views, intr)
    out = Path(out_dir) if out_dir is not None else None
    data = _Data(views)
    coarse, coarse_intr = data.downscaled(intr, cfg.coarse_downscale) if cfg.coarse_stop_step > 0 else (data, intr)
    train_idx, held_idx = split_views(len(views), cfg.holdout_every)
    train_eval_idx = train_idx[:: max(1, math.ceil(len(train_idx) / max(cfg.train_eval_views, 1)))]
    scale = scene_scale(np.stack([np.asarray(v.T_world_cam) for v in views]))
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(int(cfg.seed))

    ck = _load_checkpoint(out / CHECKPOINT_NAME, cfg, data.names) if (out is not None and resume) else None
    if ck is not None:
        params = {k: v.clone().requires_grad_(True) for k, v in ck["params"].items()}
        opt = GaussianAdam(params)
        opt.load_state_dict(ck["opt"])
        gen.set_state(ck["torch_gen"])
        rng.bit_generator.state = ck["np_rng"]
        start, order, pos = int(ck["iteration"]), list(ck["order"]), int(ck["order_pos"])
        history, seconds, timings = list(ck["history"]), float(ck["seconds"]), dict(ck["timings"])
        cpu_seconds = float(ck.get("cpu_seconds", 0.0))
        loss_sum, loss_n = float(ck["loss_acc"][0]), int(ck["loss_acc"][1])
        log.info("resuming %s at iteration %d (%d Gaussians)", out, start, params["means"].shape[0])
    else:
        g0 = init_gaussians(init_xyz, init_rgb, cfg, scale, rng)
        if g0.n > cfg.max_gaussians:
            keep = np.sort(rng.choice(g0.n, cfg.max_gaussians, replace=False))
            g0 = g0.select(keep)
        params = {k: v.detach().clone().requires_grad_(True) for k, v in g0.tensors().items()}
        opt = GaussianAdam(params)
        start, order, pos, history, seconds, cpu_seconds = 0, [], 0, [], 0.0, 0.0
        loss_sum, loss_n = 0.0, 0
        timings = {k: 0.0 for k in TIMING_KEYS}

    def deg_at(step: int) -> int:
        return min(cfg.sh_degree, step // cfg.sh_increase_every)

    def snapshot() -> Gaussians:
        return Gaussians(**{k: v.detach().clone() for k, v in params.items()})

    def checkpoint(it: int) -> None:
        if out is None:
            return
        out.mkdir(parents=True, exist_ok=True)
        _save_checkpoint(out / CHECKPOINT_NAME, {
            "version": CHECKPOINT_VERSION, "iteration": it, "cfg": _cfg_dict(cfg), "views": data.names,
            "params": {k: v.detach().clone() for k, v in params.items()}, "opt": opt.state_dict(),
            "torch_gen": gen.get_state(), "np_rng": rng.bit_generator.state, "order": order, "order_pos": pos,
            "history": history, "seconds": seconds, "cpu_seconds": cpu_seconds, "timings": timings,
            "scene_scale": scale,
            "loss_acc": (loss_sum, loss_n),
        })

    def evaluate(it: int, loss_avg: float) -> dict:
        g = snapshot()
        deg = deg_at(it)
        tp, ts = _evaluate(g, data, train_eval_idx, intr, cfg, deg)
        hp, hs = _evaluate(g, data, held_idx, intr, cfg, deg)
        rec = {"iteration": it, "seconds": seconds, "cpu_seconds": cpu_seconds,
               "wall_seconds": time.perf_counter() - t_wall0 + wall_offset,
               "n_gaussians": g.n, "loss": loss_avg, "train_psnr": tp, "train_ssim": ts,
               "heldout_psnr": hp, "heldout_ssim": hs}
        log.info("it %d: %d Gaussians, held-out %.2f dB / %.4f, train %.2f dB (%.0f s)", it, g.n, hp, hs, tp, seconds)
        return rec

    t_wall0 = time.perf_counter()
    wall_offset = history[-1]["wall_seconds"] if history else 0.0
    end = cfg.iterations if stop_at is None else min(cfg.iterations, int(stop_at))
    if start == 0 and not history and cfg.eval_at_start:
        history.append(evaluate(0, float("nan")))
    pbar = None
    if progress and end > start:
        pbar = tqdm(total=cfg.iterations, initial=start, desc="train-splat", unit="it")
    bg = torch.tensor(cfg.background, dtype=torch.float32)
    try:
        for it in range(start + 1, end + 1):
            t0 = time.perf_counter()
            c0 = time.process_time()
            if pos >= len(order):
                order, pos = [int(i) for i in rng.permutation(train_idx)], 0
            i = order[pos]
            pos += 1
            g = Gaussians(**params)
            from umi_aug.splat.renderer import render

            d, d_intr = (coarse, coarse_intr) if it <= cfg.coarse_stop_step else (data, intr)
            r = render(g, d.poses[i], d_intr, bg, deg_at(it), filter=cfg.filter,
                       projection="auto" if cfg.fast_projection else "torch",
                       pixels=d.masks[i] if cfg.loss_pixels_only else None)
            t1 = time.perf_counter()
            loss, _parts = photometric_loss_fused(r.rgb, d.images[i], d.masks[i], cfg.ssim_weight,
                                                  target_stats=d.ssim_stats(i) if cfg.ssim_weight > 0 else None)
            if cfg.opacity_reg > 0:
                loss = loss + cfg.opacity_reg * torch.sigmoid(params["logit_opacities"]).mean()
            if cfg.scale_reg > 0:
                loss = loss + cfg.scale_reg * torch.exp(params["log_scales"]).mean() / scale
            t2 = time.perf_counter()
            loss.backward()
            t3 = time.perf_counter()
            lrs = _lrs(cfg, it, scale)
            opt.step(lrs, active={"sh_rest": (deg_at(it) + 1) ** 2 - 1})
            opt.zero_grad()
            inject_noise(params, cfg.noise_lr * lrs["means"], gen)
            t4 = time.perf_counter()
            if cfg.refine_start < it < cfg.refine_stop_step and it % cfg.refine_every == 0:
                relocate_dead(params, opt, gen, cfg.min_opacity)
                grow(params, opt, gen, cfg.max_gaussians, cfg.growth_factor, cfg.min_opacity)
            t5 = time.perf_counter()
            seconds += t5 - t0
            cpu_seconds += time.process_time() - c0
            for k, dt in (("render", t1 - t0), ("loss", t2 - t1), ("backward", t3 - t2), ("step", t4 - t3),
                          ("densify", t5 - t4)):
                timings[k] += dt
            for k in ("project", "raster", "project_backward", "raster_backward"):
                timings[k] = timings.get(k, 0.0) + r.meta["timings"].get(k, 0.0)
            lv = float(loss.detach())
            if not math.isfinite(lv):
                raise SplatError(f"train_splat: loss became {lv} at iteration {it} (view {data.names[i]!r}); "
                                 f"lower the learning rates")
            loss_sum, loss_n = loss_sum + lv, loss_n + 1
            if (cfg.eval_every and it % cfg.eval_every == 0) or it == cfg.iterations:
                history.append(evaluate(it, loss_sum / max(loss_n, 1)))
                loss_sum, loss_n = 0.0, 0
                if pbar is not None:
                    pbar.set_postfix(n=params["means"].shape[0], heldout_psnr=f"{history[-1]['heldout_psnr']:.2f}")
            if it % cfg.checkpoint_every == 0 or it == end:
                checkpoint(it)
            if pbar is not None:
                pbar.update(1)
    finally:
        if pbar is not None:
            pbar.close()

    g_final = snapshot()
    if ck is not None and start >= cfg.iterations and out is not None and (out / "metrics.json").is_file():
        m = json.loads((out / "metrics.json").read_text())
        return SplatTrainResult(g_final, out, out / "scene.ply", m["heldout_psnr"], m["heldout_ssim"],
                                m["history"], m.get("timings", {}))
    last = history[-1] if history else {"heldout_psnr": float("nan"), "heldout_ssim": float("nan")}  # stopped early
    result = SplatTrainResult(g_final, out, None, last["heldout_psnr"], last["heldout_ssim"], history, timings)
    if out is not None and end >= cfg.iterations:
        if start >= cfg.iterations:  # finished checkpoint without metrics.json: evaluate once more
            history.append(evaluate(cfg.iterations, float("nan")))
            result.heldout_psnr, result.heldout_ssim = history[-1]["heldout_psnr"], history[-1]["heldout_ssim"]
        result.ply_path = write_ply(out / "scene.ply", g_final)
        write_outputs(out, result, cfg, intr, data, held_idx if held_idx else train_eval_idx, deg_at(cfg.iterations),
                      scale, len(train_idx), len(held_idx))
    return result
