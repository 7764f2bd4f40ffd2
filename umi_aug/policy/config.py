"""Typed training/inference configuration (OmegaConf dataclasses; Hydra YAML groups in ``configs/`` merge onto them).

Layout follows UMI's ``train_diffusion_unet_timm_umi_workspace.yaml`` + ``task/umi.yaml`` (umi_stack.md §4): the
top-level :class:`TrainConfig` names the workspace class in ``_target_``; ``task`` describes the dataset and the
UMI sampling (horizons, down-sampling, pose representation); ``policy`` the U-Net, the noise scheduler (its
``_target_`` is a diffusers scheduler class) and the observation encoder; ``aug`` the augmentation stage
(``none``, or on-the-fly ``freespace`` / ``obstacle`` / ``both``); ``device`` where and how fast to run. Code
reads these dataclasses, never raw dicts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, List, Optional

from umi_aug.data.schema import is_image_key
from umi_aug.errors import PolicyError

#: Names accepted by ``aug.name``: no augmentation, or on-the-fly augmentation in these modes.
AUG_NAMES: tuple[str, ...] = ("none", "freespace", "obstacle", "both")
#: The augmentation modes each ``aug.name`` draws from.
AUG_MODES: dict[str, tuple[str, ...]] = {"none": (), "freespace": ("freespace",), "obstacle": ("obstacle",),
                                         "both": ("freespace", "obstacle")}
#: Observation-encoder backbones (``policy.encoder.name``).
ENCODER_NAMES: tuple[str, ...] = ("clip_vit", "resnet")
#: Pooling of the ResNet's last feature map (``policy.encoder.resnet_pool``).
RESNET_POOLS: tuple[str, ...] = ("avg", "spatial_softmax")
#: Action heads (``policy.action_head``): Diffusion Policy's U-Net, or deterministic chunk regression (issue #29).
ACTION_HEADS: tuple[str, ...] = ("diffusion", "regression")
#: Losses of the regression head (``policy.regression_loss``), on normalised actions.
REGRESSION_LOSSES: tuple[str, ...] = ("l1", "mse")
#: ``task.make_if_missing`` values: build the dataset when ``dataset_path`` does not exist.
MAKE_IF_MISSING: tuple[str, ...] = ("", "demo", "session")


@dataclass
class TaskConfig:
    """Dataset + UMI sampling (``task/umi.yaml``). One arm = ``robot0_*`` keys, one camera = ``camera0_rgb``."""

    name: str = "umi"
    #: UMI replay buffer (``.zarr.zip`` or zarr directory); required for training
    dataset_path: str = ""
    #: build the dataset when missing: "" (no: error), "demo" (``umi-aug demo`` data), "session" (synthetic session)
    make_if_missing: str = ""
    n_robots: int = 1
    n_cameras: int = 1
    image_size: int = 224
    img_obs_horizon: int = 2
    low_dim_obs_horizon: int = 2
    action_horizon: int = 16
    #: frames between samples; 3 at 59.94 fps gives UMI's ≈20 Hz
    obs_down_sample_steps: int = 3
    obs_pose_repr: str = "relative"
    action_pose_repr: str = "relative"
    #: add ``robot{i}_eef_rot_axis_angle_wrt_start`` (rot6d of the pose relative to the demo start pose)
    use_wrt_start: bool = True
    #: std of the N(0, σ) noise UMI adds to all 6 components of the start pose (training set only here)
    start_pose_noise: float = 0.05
    val_ratio: float = 0.05
    split_seed: int = 42
    #: UMI default False: windows whose 16 actions cross the episode end are skipped
    action_padding: bool = False
    #: drop proprioception from the policy input (UMI's ``ignore_by_policy``)
    ignore_proprioception: bool = False
    #: where the action labels come from: None = the future TCP poses and gripper widths (UMI's rule: the arm's
    #: controller tracks poses); a replay-buffer key (``action``) = stored ABSOLUTE COMMANDED targets
    #: [N, 7·R] (per arm pos m, rotvec rad, gripper width m; row t = the target commanded for step t, row 0 the
    #: start pose) — for robots whose controller lags its targets (the square env's OSC: issue #29 B2)
    action_key: Optional[str] = None
    #: False: an augmented episode (``meta/aug_id`` >= 0) whose source demo is an episode of the same buffer gives
    #: samples only where a row it reads lies at or before its splice (``meta/aug_splice_index``); its later samples
    #: repeat the source episode's own (same frames, poses and labels; only ``wrt_start`` differs), so 20 augmented
    #: episodes per demo spend ~75 % of a fixed step budget on copies of the demos' tails (issue #29). True = UMI's
    #: rule, every step a sample. Buffers without augmented episodes are unaffected.
    sample_replayed_tails: bool = True


@dataclass
class SchedulerConfig:
    """A diffusers scheduler, built by class name with these kwargs (those it does not take are dropped).
    Defaults = UMI's DDIM (50 train steps, squaredcos_cap_v2, clip_sample, epsilon)."""

    _target_: str = "diffusers.DDIMScheduler"
    num_train_timesteps: int = 50
    beta_start: float = 0.0001
    beta_end: float = 0.02
    beta_schedule: str = "squaredcos_cap_v2"
    clip_sample: bool = True
    set_alpha_to_one: bool = True
    steps_offset: int = 0
    prediction_type: str = "epsilon"
    variance_type: str = "fixed_small"


@dataclass
class EncoderConfig:
    """Observation encoder: a backbone per camera (CLS token of a CLIP ViT, or a GroupNorm ResNet) + flattened
    low-dim obs. Defaults = OpenAI CLIP ViT-B/16 vision tower."""

    name: str = "clip_vit"
    #: local HF CLIP folder (CLIPModel/CLIPVisionModel) or a file (.safetensors/.bin/.pt/.pth/.ckpt; HF, timm or
    #: UMI checkpoint keys); None = random init (with a warning)
    pretrained_path: Optional[str] = None
    frozen: bool = False
    share_rgb_model: bool = False
    #: "clip" (OpenAI CLIP mean/std), "imagenet" or "none" — applied in train AND eval (UMI applies none)
    image_norm: str = "clip"
    #: random crop side as a fraction of the image (UMI: 0.95), resized back; evaluation takes the centred crop of
    #: the same side (the same scale as training); 1.0 = off
    crop_ratio: float = 0.95
    #: train-only colour jitter (brightness, contrast, saturation, hue) as torchvision's ColorJitter; [] = off
    color_jitter: List[float] = field(default_factory=lambda: [0.3, 0.4, 0.5, 0.08])
    #: train-only Gaussian blur, std uniform in [0, blur_sigma_max] pixels per sample (image_aug.random_gaussian_blur:
    #: 3DGS renders are softer than camera frames, issue #29); 0 = off (UMI). On square at 84², 1.0 made the
    #: policy grasp worse (15/100 against 32 in distribution, docs/square_learning.md §2e)
    blur_sigma_max: float = 0.0
    # ---- CLIP ViT (ignored for resnet); defaults = ViT-B/16 ----
    vit_hidden_size: int = 768
    vit_layers: int = 12
    vit_heads: int = 12
    vit_mlp_size: int = 3072
    vit_patch_size: int = 16
    # ---- ResNet (ignored for clip_vit); [2,2,2,2] with width 64 = ResNet-18 ----
    resnet_width: int = 64
    resnet_blocks: List[int] = field(default_factory=lambda: [2, 2, 2, 2])
    #: "avg" (global average pooling → 8·width features) or "spatial_softmax" (keypoint coordinates, robomimic)
    resnet_pool: str = "avg"
    #: keypoints K of the spatial softmax (2K features; robomimic: 32)
    spatial_softmax_keypoints: int = 32
    #: ResNet activations and weights channels-last (NHWC): ~1.2x (fp32) / 1.3x (bf16) faster CPU convolutions
    #: than NCHW, the same features (tested); false = NCHW (the reference)
    channels_last: bool = True


@dataclass
class PolicyConfig:
    """Diffusion Policy with a 1-D temporal conditional U-Net (UMI's ``DiffusionUnetTimmPolicy`` settings), or
    (``action_head: regression``) the same encoder with an MLP that regresses the chunk."""

    name: str = "clip_vit_b16"
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    #: "diffusion" (the paper's: U-Net + scheduler below) or "regression" (MLP ``head_hidden_dims``, one pass)
    action_head: str = "diffusion"
    #: hidden widths of the regression MLP (robomimic BC: [1024, 1024])
    head_hidden_dims: List[int] = field(default_factory=lambda: [1024, 1024])
    #: "l1" (ACT) or "mse", on normalised actions
    regression_loss: str = "l1"
    noise_scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    num_inference_steps: int = 16
    diffusion_step_embed_dim: int = 128
    down_dims: List[int] = field(default_factory=lambda: [256, 512, 1024])
    kernel_size: int = 5
    n_groups: int = 8
    cond_predict_scale: bool = True
    #: DDPM-IP input perturbation (UMI: 0.1)
    input_pertub: float = 0.1
    #: how many of the predicted steps :meth:`Policy.predict_action` returns by default (DP: 8)
    n_action_steps: int = 8


@dataclass
class AugConfig:
    """Action-view augmentation (issue #9; :class:`umi_aug.policy.augmented_dataset.AugmentedUmiDataset`).

    ``none`` trains on the original data only. ``freespace`` / ``obstacle`` / ``both`` add on-the-fly augmented
    samples: the session holding ``task.dataset_path`` (its scan, demos, calibration) is prepared once
    (reconstruction, fisheye 3DGS, contact split; cached in ``work_dir``), then each augmented sample plans its
    episode and renders only the frames it needs. To train on an offline export (``umi-aug augment``) instead,
    use ``aug=none task.dataset_path=<export>.zarr.zip``.
    """

    name: str = "none"
    #: session folder (scan + demos + calibration); "" = the folder holding task.dataset_path
    session_dir: str = ""
    #: stage cache of the augmentation pipeline; "" = <session_dir>/augment
    work_dir: str = ""
    #: fraction of augmented samples per epoch, in [0, 1)
    ratio: float = 0.5
    #: distinct augmentations (start pose / obstacle) per demo
    n_aug_per_demo: int = 1000
    #: fraction in [0, 1) of the augmented samples that come from a demo's re-rendered copy (its own labels, its
    #: approach frames rendered by the scene model; ``umi-aug augment --rerender-originals`` offline)
    rerender_fraction: float = 0.0
    #: root seed of the augmentation (episodes) and of the slot draws
    seed: int = 0
    #: start-pose cone (paper: 50 deg, 0.15 m)
    cone_half_angle_deg: float = 50.0
    cone_radius_m: float = 0.15
    #: 3DGS training of the scene (steps, Gaussian budget); None = umi-aug's default for the input, as
    #: ``umi-aug augment`` trains it (a session: 1500 / 25000; a plain dataset: 550 / 30000 with the short schedule
    #: of ``umi_aug/augment/splat_defaults.py``)
    splat_iterations: Optional[int] = None
    splat_max_gaussians: Optional[int] = None
    #: 3DGS scale regulariser; None = umi-aug's default for the input (a session: 1.0, a plain dataset: 0.01)
    splat_scale_reg: Optional[float] = None
    #: 3DGS coarse-to-fine factor (first half of the steps at 1/F size); None = by input (a session: 1, a plain
    #: dataset: 2)
    splat_coarse_downscale: Optional[int] = None
    #: planned episodes kept per DataLoader worker (LRU)
    plan_cache_size: int = 256
    #: plain UMI dataset input (no session folder): UMI's camera→TCP ``tcp_offset`` (m) and episodes per scene:
    #: an int >= 1 (consecutive episodes), or "auto" (the episodes of one place, found from the data); typed Any
    #: so that OmegaConf takes either
    tcp_offset_m: float = 0.205
    scene_group: Any = 1


@dataclass
class DeviceConfig:
    name: str = "cpu"
    device: str = "cpu"
    #: None = all usable cores (umi_aug.runtime.configure_threads)
    threads: Optional[int] = None
    num_workers: int = 0
    pin_memory: bool = False
    #: "none" or "bf16" (autocast on CUDA)
    amp: str = "none"


@dataclass
class DataloaderConfig:
    batch_size: int = 64
    val_batch_size: int = 64
    shuffle: bool = True
    persistent_workers: bool = True
    #: decode every camera frame ONCE into RAM (uint8) when they take at most this many GB, then build batches
    #: by indexing (no per-sample JPEG-XL decode; issue #29); 0 = decode the frames each sample needs (reference)
    frames_in_memory_gb: float = 4.0


@dataclass
class TrainingConfig:
    seed: int = 42
    num_epochs: int = 120
    #: stop after this many optimiser steps in total (None: run all epochs)
    max_steps: Optional[int] = None
    #: stop (with a checkpoint) once this many steps are done WITHOUT changing the schedule, which ``max_steps`` /
    #: ``num_epochs`` define; rerun with a larger value to continue (time-sliced runs, learning curves)
    pause_at_step: Optional[int] = None
    lr: float = 3.0e-4
    betas: List[float] = field(default_factory=lambda: [0.95, 0.999])
    eps: float = 1.0e-8
    weight_decay: float = 1.0e-6
    #: lr multiplier of the encoder when it was initialised from pretrained weights (UMI: 0.1)
    pretrained_encoder_lr_scale: float = 0.1
    lr_scheduler: str = "cosine"
    lr_warmup_steps: int = 2000
    use_ema: bool = True
    ema_power: float = 0.75
    ema_inv_gamma: float = 1.0
    ema_min_value: float = 0.0
    ema_max_value: float = 0.9999
    ema_update_after_step: int = 0
    max_grad_norm: Optional[float] = None
    #: epochs between validation loss / sampled-action MSE / checkpoints (0 = never; checkpoints also at the end)
    val_every: int = 1
    sample_every: int = 5
    checkpoint_every: int = 10
    #: also checkpoint every this many optimiser steps, mid-epoch included (0 = off); a resumed run continues at
    #: the next batch of that epoch's order, so a run killed between epochs loses at most this many steps
    checkpoint_every_steps: int = 0
    max_val_steps: Optional[int] = None
    #: continue from ``<output_dir>/checkpoints/latest.ckpt`` when it exists
    resume: bool = True
    progress_bar: bool = True


@dataclass
class TrainConfig:
    _target_: str = "umi_aug.policy.workspace.TrainWorkspace"
    name: str = "train_diffusion_unet_clip"
    #: where checkpoints/ and logs go; None = Hydra's run dir (or the current directory outside Hydra)
    output_dir: Optional[str] = None
    task: TaskConfig = field(default_factory=TaskConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    aug: AugConfig = field(default_factory=AugConfig)
    device: DeviceConfig = field(default_factory=DeviceConfig)
    dataloader: DataloaderConfig = field(default_factory=DataloaderConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)


def scene_group_ok(value: Any) -> bool:
    """``aug.scene_group``: an int >= 1 or ``"auto"``."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value >= 1
    from umi_aug.augment.dataset_source import parse_scene_group  # only for a string: the augment stage

    return parse_scene_group(value) is not None


def check_aug(aug: AugConfig) -> None:
    """Raise :class:`PolicyError` naming the field unless ``aug`` is a valid augmentation setting."""
    if aug.name not in AUG_NAMES:
        raise PolicyError(f"aug.name={aug.name!r} is not an augmentation; expected one of {list(AUG_NAMES)}")
    if not scene_group_ok(aug.scene_group):
        raise PolicyError(f"config `aug.scene_group` = {aug.scene_group!r}: expected an int >= 1 or 'auto'")
    if not 0.0 <= aug.ratio < 1.0:
        raise PolicyError(f"config `aug.ratio` = {aug.ratio!r}: expected a fraction in [0, 1)")
    if aug.n_aug_per_demo < 1:
        raise PolicyError(f"config `aug.n_aug_per_demo` = {aug.n_aug_per_demo!r}: must be >= 1")
    if not 0.0 <= aug.rerender_fraction < 1.0:  # NaN fails too
        raise PolicyError(f"config `aug.rerender_fraction` = {aug.rerender_fraction!r}: expected a fraction in "
                          f"[0, 1)")


def check_config(cfg: TrainConfig) -> None:
    """Validate value ranges the dataclass types cannot express; raise :class:`PolicyError` naming the field."""
    t, p = cfg.task, cfg.policy

    def bad(name: str, value: Any, want: str) -> None:
        raise PolicyError(f"config `{name}` = {value!r}: {want}")

    for name in ("img_obs_horizon", "low_dim_obs_horizon", "action_horizon", "obs_down_sample_steps",
                 "n_robots", "image_size"):
        if getattr(t, name) < 1:
            bad(f"task.{name}", getattr(t, name), "must be >= 1")
    if t.n_cameras < 0:
        bad("task.n_cameras", t.n_cameras, "must be >= 0")
    for name in ("obs_pose_repr", "action_pose_repr"):
        if getattr(t, name) not in ("relative", "abs"):
            bad(f"task.{name}", getattr(t, name), "expected 'relative' or 'abs'")
    if not 0.0 <= t.val_ratio < 1.0:
        bad("task.val_ratio", t.val_ratio, "must be in [0, 1)")
    if t.action_key is not None and (not t.action_key or is_image_key(t.action_key) or
                                     any(t.action_key == f"robot{i}_{k}" for i in range(t.n_robots)
                                         for k in ("eef_pos", "eef_rot_axis_angle", "gripper_width"))):
        bad("task.action_key", t.action_key, "expected null (labels = future TCP poses) or the replay-buffer key "
            "of stored absolute commanded targets, e.g. 'action'")
    if t.make_if_missing not in MAKE_IF_MISSING:
        bad("task.make_if_missing", t.make_if_missing, f"expected one of {list(MAKE_IF_MISSING)}")
    if p.encoder.name not in ENCODER_NAMES:
        bad("policy.encoder.name", p.encoder.name, f"expected one of {list(ENCODER_NAMES)}")
    if p.encoder.image_norm not in ("clip", "imagenet", "none"):
        bad("policy.encoder.image_norm", p.encoder.image_norm, "expected 'clip', 'imagenet' or 'none'")
    if not 0.0 < p.encoder.crop_ratio <= 1.0:
        bad("policy.encoder.crop_ratio", p.encoder.crop_ratio, "must be in (0, 1]")
    if not 0.0 <= float(p.encoder.blur_sigma_max) <= 4.0:
        bad("policy.encoder.blur_sigma_max", p.encoder.blur_sigma_max, "must be in [0, 4] pixels")
    if len(p.encoder.color_jitter) not in (0, 4):
        bad("policy.encoder.color_jitter", p.encoder.color_jitter, "expected [] or [brightness, contrast, saturation, hue]")
    if p.encoder.resnet_pool not in RESNET_POOLS:
        bad("policy.encoder.resnet_pool", p.encoder.resnet_pool, f"expected one of {list(RESNET_POOLS)}")
    if p.encoder.spatial_softmax_keypoints < 1:
        bad("policy.encoder.spatial_softmax_keypoints", p.encoder.spatial_softmax_keypoints, "must be >= 1")
    if p.action_head not in ACTION_HEADS:
        bad("policy.action_head", p.action_head, f"expected one of {list(ACTION_HEADS)}")
    if p.regression_loss not in REGRESSION_LOSSES:
        bad("policy.regression_loss", p.regression_loss, f"expected one of {list(REGRESSION_LOSSES)}")
    if p.action_head == "regression" and any(int(d) < 1 for d in p.head_hidden_dims):
        bad("policy.head_hidden_dims", list(p.head_hidden_dims), "every width must be >= 1")
    if p.action_head == "diffusion":  # the U-Net halves the horizon len(down_dims)-1 times, in GroupNorm groups
        n_down = len(p.down_dims) - 1
        if not p.down_dims or t.action_horizon % (2 ** n_down):
            bad("task.action_horizon", t.action_horizon,
                f"must be divisible by 2^(len(policy.down_dims)-1) = {2 ** n_down} (the U-Net halves it {n_down} "
                "times)")
        if any(d % p.n_groups for d in p.down_dims):
            bad("policy.down_dims", list(p.down_dims), f"every entry must be divisible by n_groups={p.n_groups}")
    if not 1 <= p.n_action_steps <= t.action_horizon:
        bad("policy.n_action_steps", p.n_action_steps, f"must be in [1, task.action_horizon={t.action_horizon}]")
    if p.noise_scheduler.prediction_type != "epsilon":
        bad("policy.noise_scheduler.prediction_type", p.noise_scheduler.prediction_type,
            "only 'epsilon' prediction is supported")
    if not (cfg.dataloader.frames_in_memory_gb >= 0.0 and math.isfinite(cfg.dataloader.frames_in_memory_gb)):
        bad("dataloader.frames_in_memory_gb", cfg.dataloader.frames_in_memory_gb, "must be a finite number >= 0")
    if cfg.training.pause_at_step is not None and cfg.training.pause_at_step < 1:
        bad("training.pause_at_step", cfg.training.pause_at_step, "must be >= 1 (or null)")
    if cfg.device.amp not in ("none", "bf16"):
        bad("device.amp", cfg.device.amp, "expected 'none' or 'bf16'")
    if cfg.dataloader.batch_size < 1:
        bad("dataloader.batch_size", cfg.dataloader.batch_size, "must be >= 1")


def shape_meta(task: TaskConfig) -> dict:
    """UMI's ``shape_meta`` for ``task``: ``{'obs': {key: {shape, horizon, type}}, 'action': {shape, horizon}}``.

    Keys (single arm): ``camera0_rgb`` [3, S, S] rgb; ``robot0_eef_pos`` [3]; ``robot0_eef_rot_axis_angle`` [6]
    (rot6d); ``robot0_gripper_width`` [1]; ``robot0_eef_rot_axis_angle_wrt_start`` [6]; action [10 · n_robots].
    """
    obs: dict[str, dict] = {}
    for j in range(task.n_cameras):
        obs[f"camera{j}_rgb"] = {"shape": [3, task.image_size, task.image_size], "horizon": task.img_obs_horizon,
                                 "type": "rgb", "down_sample_steps": task.obs_down_sample_steps}
    for i in range(task.n_robots):
        for key, dim in (("eef_pos", 3), ("eef_rot_axis_angle", 6), ("gripper_width", 1)):
            obs[f"robot{i}_{key}"] = {"shape": [dim], "horizon": task.low_dim_obs_horizon, "type": "low_dim",
                                      "down_sample_steps": task.obs_down_sample_steps,
                                      "ignore_by_policy": task.ignore_proprioception}
        if task.use_wrt_start:
            obs[f"robot{i}_eef_rot_axis_angle_wrt_start"] = {
                "shape": [6], "horizon": task.low_dim_obs_horizon, "type": "low_dim",
                "down_sample_steps": task.obs_down_sample_steps, "ignore_by_policy": task.ignore_proprioception}
    return {"obs": obs, "action": {"shape": [10 * task.n_robots], "horizon": task.action_horizon,
                                   "down_sample_steps": task.obs_down_sample_steps}}


def structured_config(overrides: Any = None) -> TrainConfig:
    """A :class:`TrainConfig` from defaults merged with ``overrides`` (dict / DictConfig / dataclass), type-checked.

    Raises:
        PolicyError: unknown key or wrong type (OmegaConf's message included).
    """
    # lazy, optional dependency: omegaconf
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        base = OmegaConf.structured(TrainConfig)
        if overrides is not None:
            base = OmegaConf.merge(base, overrides)
        return OmegaConf.to_object(base)  # type: ignore[return-value]
    except OmegaConfBaseException as exc:
        raise PolicyError(f"bad training config: {exc}") from exc


def config_to_dict(cfg: TrainConfig) -> dict:
    """Plain nested dict of ``cfg`` (for checkpoints and logs)."""
    from omegaconf import OmegaConf  # lazy, optional dependency: omegaconf

    return OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True)  # type: ignore[return-value]
