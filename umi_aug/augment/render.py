"""Frames of a planned episode (paper §3.3 + the §3.4 gripper overlay).

Frames before the splice are new views: the scene's fisheye 3DGS (plus, in obstacle mode, the obstacle's Gaussians
composited by :func:`umi_aug.splat.compose.render_composed`), then the real gripper pixels of the original frame
with the closest gripper width (:mod:`umi_aug.augment.overlay`). Frames from the splice on replay the original
motion, so they are the original frames read from the session's dataset (not re-rendered); in obstacle mode the
obstacle is composited onto them where it is in front of the scene (depth test against the scene's 3DGS ray
depth), and the gripper pixels are restored on top, so the obstacle does not vanish at the splice.

Rendering resolution: directly at the policy resolution with ``intr.umi_policy(S)`` — the intrinsics of UMI's
full-height centre crop resized to ``S x S`` — instead of rendering the raw frame and resizing. The EWA splats are
already band-limited at the output pixel grid (the screen-space filter), so a downscale would only cost
(raw/policy)² more rasterisation for the same geometry; and the crop's outside is never rendered.

Background: black. The scene surrounds the camera, so it only shows where no Gaussian covers a ray (outside the
reconstructed region, or beyond the lens' valid angle); UMI's frames are dark there too (vignette, painted jaws).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

from umi_aug.augment.overlay import composite_overlay, source_frames_by_width
from umi_aug.errors import AugmentError

__all__ = ["render_episode_frames", "overlay_originals", "overlay_source_rows", "overlay_sources", "placed_obstacles",
           "render_view"]

if TYPE_CHECKING:  # pragma: no cover
    from umi_aug.augment.plan import PlannedEpisode
    from umi_aug.augment.session_assets import SessionAssets

#: Obstacle pixels with alpha below this are not composited onto original frames.
OBSTACLE_ALPHA_MIN: float = 1.0 / 255.0


def placed_obstacles(assets: SessionAssets, planned: PlannedEpisode) -> list:
    """The episode's obstacle as ``[PlacedGaussians]`` (scaled in the object frame), or ``[]``."""
    import torch  # lazy, start-up: torch

    # lazy, start-up: torch
    from umi_aug.splat import Gaussians
    from umi_aug.splat.compose import PlacedGaussians

    ob = planned.obstacle
    if ob is None:
        return []
    g = assets.obstacle_gaussians(ob.asset)
    s = float(ob.scale)
    gs = Gaussians(g.means * s, g.log_scales + math.log(s), g.quats_wxyz, g.logit_opacities, g.sh0, g.sh_rest)
    key = f"{ob.asset}@{s:.9f}"
    return [PlacedGaussians(gs.to(dtype=torch.float32), np.asarray(ob.T_world_obj, np.float64), key)]


def render_view(assets: SessionAssets, T_world_cam: np.ndarray, obstacles: Sequence = (),
                pixels: np.ndarray | None = None) -> np.ndarray:
    """The 3DGS scene (+ placed obstacles) at the policy intrinsics → ``[S, S, 3]`` uint8 (no overlay);
    ``pixels`` ``[S, S]`` bool: only these are rendered, the others are black (None: all)."""
    from umi_aug.splat.compose import render_composed, rgb_to_uint8  # lazy, start-up: torch

    cfg = assets.cfg
    out = render_composed(assets.gaussians, list(obstacles), np.asarray(T_world_cam, np.float64),
                          assets.policy_intrinsics, background=(0.0, 0.0, 0.0), near=cfg.render_near_m,
                          far=cfg.render_far_m, min_transmittance=cfg.render_min_transmittance, pixels=pixels)
    return rgb_to_uint8(out.rgb)


def _obstacle_over_original(assets: SessionAssets, T_world_cam: np.ndarray, obstacles_world: Sequence,
                            original: np.ndarray, scene_tiles: bool = True) -> np.ndarray:
    """Composite the obstacles (world-frame Gaussians) onto an original frame where they are in front of the
    scene's 3DGS surface (ray-depth test; where the scene has alpha < 0.5 the obstacle always shows).

    ``scene_tiles``: the scene is rasterised only in the 16x16 tiles where an obstacle has alpha >=
    :data:`OBSTACLE_ALPHA_MIN` (the only pixels the test reads; ~4 % of a 224² frame), and not at all when no
    obstacle shows; False: the whole scene frame (the reference path). Same pixels either way."""
    import torch  # lazy, start-up: torch

    # lazy, start-up: numba, scipy, torch
    from umi_aug.splat import render
    from umi_aug.splat.renderer import tiles_covering

    cfg = assets.cfg
    intr = assets.policy_intrinsics
    T = np.asarray(T_world_cam, np.float64)
    kw = dict(near=cfg.render_near_m, far=cfg.render_far_m, min_transmittance=cfg.render_min_transmittance)
    with torch.no_grad():
        obstacle = [render(g, T, intr, **kw) for g in obstacles_world]
        if scene_tiles:
            shows = np.zeros((intr.height, intr.width), dtype=bool)
            for r in obstacle:
                shows |= r.alpha.numpy() >= OBSTACLE_ALPHA_MIN
            if not shows.any():
                return original.copy()
            scene = render(assets.gaussians, T, intr, tiles=tiles_covering(shows), **kw)
        else:
            scene = render(assets.gaussians, T, intr, **kw)
        out = original.astype(np.float32) / 255.0
        for r in obstacle:
            a = r.alpha.numpy().astype(np.float32)
            front = (r.ray_depth.numpy() < scene.ray_depth.numpy()) | (scene.alpha.numpy() < 0.5)
            a = np.where(front & (a >= OBSTACLE_ALPHA_MIN), a, 0.0)[..., None]
            rgb = r.rgb.numpy().astype(np.float32)  # premultiplied (black background)
            out = out * (1.0 - a) + np.where(a > 0, rgb, 0.0)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def overlay_source_rows(demo_gripper_width: np.ndarray, contact_index: int, episode_gripper_width: np.ndarray,
                        splice_index: int, frame_indices: np.ndarray) -> np.ndarray:
    """The demo frame whose gripper is overlaid on each new frame ``frame_indices`` ``[K]`` of an episode spliced
    at ``splice_index``: among the demo's frames ``0..contact_index`` (widths ``demo_gripper_width``, metres), the
    one with the closest gripper width to the episode's (``episode_gripper_width`` [N], metres), ties broken by
    the closest normalised time."""
    c = int(contact_index)
    idx = np.asarray(frame_indices, dtype=np.int64)
    return source_frames_by_width(np.asarray(demo_gripper_width)[: c + 1], np.asarray(episode_gripper_width)[idx],
                                  np.linspace(0.0, 1.0, c + 1), idx / max(1, int(splice_index)))


def overlay_sources(assets: SessionAssets, planned: PlannedEpisode, frame_indices: np.ndarray) -> np.ndarray:
    """Original frame (index into the demo) whose gripper is overlaid on each new frame ``[K]`` of ``planned``
    (:func:`overlay_source_rows`)."""
    d = assets.demo(planned.demo_index)
    ep = planned.episode
    return overlay_source_rows(d.gripper_width, d.contact_index, ep.gripper_width, ep.splice_index, frame_indices)


def overlay_originals(assets: SessionAssets, demo_index: int, src: np.ndarray) -> np.ndarray:
    """Original frames ``src`` (``[K]`` indices ``<= contact_index``) of demo ``demo_index`` for the gripper
    overlay, decoded once per demo: the demo's whole pre-contact range is decoded on first use by a call that
    spans at least half of it, and kept (one demo at a time per process — export jobs run demo by demo), so an
    episode costs no JPEG-XL decodes. Same pixels as
    ``assets.original_frames(demo_index, src)`` (the reference path)."""
    src = np.asarray(src, dtype=np.int64)
    c = int(assets.demo(demo_index).contact_index)
    if src.size and (src.min() < 0 or src.max() > c):
        return assets.original_frames(demo_index, src)
    ident = (assets.cache_id, int(demo_index), c)
    slot = assets.memo.get("overlay_originals")
    if slot is None or slot[0] != ident:
        span = int(src.max()) - int(src.min()) + 1 if src.size else 0
        if 2 * span < c + 1:  # a few frames (an on-the-fly sample): decoding them directly is cheaper
            return assets.original_frames(demo_index, src)
        slot = (ident, assets.original_frames(demo_index, np.arange(c + 1), shared=True))
        assets.memo["overlay_originals"] = slot
    return slot[1][src]


def render_episode_frames(assets: SessionAssets, planned: PlannedEpisode, frame_indices: Sequence[int], *,
                          cache_originals: bool = True, obstacle_tiles: bool = True,
                          overlay_pixels: bool = True) -> np.ndarray:
    """Policy frames ``[K, S, S, 3]`` uint8 of ``planned`` at ``frame_indices`` (only those are made).

    Frames ``k < splice_index``: 3DGS render (+ obstacle) with the gripper overlay. Frames ``k >= splice_index``:
    original frame ``source_contact_index + (k − splice_index)`` of the demo (+ obstacle composited in obstacle
    mode, gripper restored). ``cache_originals``: the overlay's original frames come from
    :func:`overlay_originals` (decoded once per demo); False: decoded for this call (the reference path).
    ``obstacle_tiles``: on replayed frames of an obstacle episode the scene's depth is rendered only where the
    obstacle shows (:func:`_obstacle_over_original`); False: the whole frame (the reference path).
    ``overlay_pixels``: the new frames' pixels that the gripper overlay covers completely (alpha 1:
    :meth:`SessionAssets.rendered_pixels`) are not rasterised; False: every pixel (the reference path). Same
    frames either way.

    Raises:
        AugmentError: an index outside ``[0, n_frames)``.
    """
    ep = planned.episode
    S = assets.cfg.image_size
    idx = np.asarray(list(frame_indices), dtype=np.int64).reshape(-1)
    N, n = len(ep.timestamps), int(ep.splice_index)
    if idx.size and (idx.min() < 0 or idx.max() >= N):
        raise AugmentError(f"render_episode_frames: frame indices {idx.min()}..{idx.max()} outside [0, {N})")
    out = np.zeros((idx.size, S, S, 3), np.uint8)
    if idx.size == 0:
        return out
    alpha = assets.overlay_alpha
    obstacles = placed_obstacles(assets, planned)
    new = idx < n
    if new.any():
        k_new = idx[new]
        src = overlay_sources(assets, planned, k_new)
        originals = (overlay_originals(assets, planned.demo_index, src) if cache_originals
                     else assets.original_frames(planned.demo_index, src))
        pixels = assets.rendered_pixels if overlay_pixels else None
        rendered = np.stack([render_view(assets, ep.T_world_cam[k], obstacles, pixels) for k in k_new])
        out[new] = composite_overlay(rendered, originals, alpha)
    if (~new).any():
        k_old = idx[~new]
        src = int(ep.source_contact_index) + (k_old - n)
        originals = assets.original_frames(planned.demo_index, src)
        if obstacles:
            from umi_aug.splat.compose import transform_gaussians  # lazy, start-up: torch

            world = [transform_gaussians(o.gaussians, o.T_world_obj) for o in obstacles]
            withobs = np.stack([_obstacle_over_original(assets, ep.T_world_cam[k], world, o, obstacle_tiles)
                                for k, o in zip(k_old, originals)])
            originals = composite_overlay(withobs, originals, alpha)
        out[~new] = originals
    return out
