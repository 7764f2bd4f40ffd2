"""Pictures the demo writes: lens geometry, sampled start-pose cone, contact sheet of original and new episodes.

All figures are PNG files written atomically (temporary file, then rename). matplotlib runs headless (Agg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from umi_aug.io_utils import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def lens_figure(intr, path: Path) -> Path:
    """Three panels: ray angle θ per pixel (with 90° and image-circle contours and UMI's gripper mask),
    the Kannala–Brandt curve θ_d(θ) with its fold-over, and which cube face feeds each pixel."""
    from umi_aug.camera.cubemap import CubemapFisheyeRemap
    from umi_aug.camera.kb import kb_theta_d, unproject
    from umi_aug.camera.masks import predefined_mask

    remapper = CubemapFisheyeRemap(intr)

    plt = _pyplot()
    h, w = intr.height, intr.width
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays, valid = unproject(np.stack([u, v], axis=-1), intr)
    theta = np.degrees(np.arccos(np.clip(rays[..., 2], -1.0, 1.0)))
    theta_img = np.where(valid, theta, np.nan)

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    im = ax[0].imshow(theta_img, cmap="viridis")
    ax[0].contour(np.where(valid, theta, 0.0), levels=[90.0], colors="w", linewidths=1.2)
    ax[0].contour(predefined_mask(h, w, mirror=True, gripper=True).astype(float), levels=[0.5], colors="r")
    ax[0].set_title(f"ray angle θ [deg] at {w}×{h}\nwhite: θ = 90°, red: UMI gripper/mirror masks", fontsize=9)
    fig.colorbar(im, ax=ax[0], fraction=0.046)

    th = np.linspace(0.0, min(np.pi, intr.theta_fold * 1.3 if np.isfinite(intr.theta_fold) else np.pi), 400)
    ax[1].plot(np.degrees(th), kb_theta_d(th, np.asarray(intr.k)), label="θ_d(θ) Kannala–Brandt")
    ax[1].plot(np.degrees(th), th, "--", color="grey", label="equidistant θ_d = θ")
    ax[1].axvline(np.degrees(intr.theta_max), color="r", label=f"valid limit {np.degrees(intr.theta_max):.1f}°")
    ax[1].axvline(90.0, color="k", lw=0.8, ls=":")
    corner_r = np.hypot((0 - intr.cx) / intr.fx, (0 - intr.cy) / intr.fy)
    ax[1].axhline(corner_r, color="orange", lw=0.8, label="image corner θ_d")
    ax[1].set_xlabel("θ [deg]")
    ax[1].set_ylabel("θ_d [rad]")
    ax[1].legend(fontsize=8)
    ax[1].set_title("Kannala–Brandt lens model", fontsize=9)

    faces = remapper.face_of_pixel.astype(float)
    faces[faces < 0] = np.nan
    ax[2].imshow(faces, cmap="tab10", vmin=0, vmax=9)
    ax[2].set_title("cube face sampled per pixel\n(" + ", ".join(remapper.faces_needed) + ")", fontsize=9)
    for a in (ax[0], ax[2]):
        a.set_xticks([])
        a.set_yticks([])
    return _save(fig, path)


def cone_figure(
    T_world_ref: np.ndarray,  # [4, 4]
    pivot: np.ndarray,  # [3]
    T_world_goal: np.ndarray,  # [4, 4]
    starts: np.ndarray,  # [N, 4, 4]
    paths: np.ndarray,  # [N, T, 4, 4]
    path: Path,
    axis_len: float = 0.08,
    demo_path: np.ndarray | None = None,  # [T, 4, 4] original demo camera poses
) -> Path:
    """3-D view of the sampled start poses (optical axes as arrows), the reference and goal views and the
    straight-line camera paths."""
    plt = _pyplot()
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    p = starts[:, :3, 3]
    z = starts[:, :3, 2]
    ax.scatter(*p.T, c="tab:blue", s=18, label="sampled starts")
    ax.quiver(*p.T, *(axis_len * z).T, color="tab:blue", lw=0.8)
    for i, traj in enumerate(paths):
        ax.plot(*traj[:, :3, 3].T, color="tab:gray", lw=0.7, label="new camera paths" if i == 0 else None)
    if demo_path is not None:
        ax.plot(*demo_path[:, :3, 3].T, color="tab:green", lw=1.5, label="original demo")
    for T, c, name in ((T_world_ref, "tab:green", "demo start"), (T_world_goal, "tab:red", "splice (pre-grasp) pose")):
        ax.scatter(*T[:3, 3], c=c, s=40, label=name)
        ax.quiver(*T[:3, 3], *(axis_len * T[:3, 2]), color=c, lw=1.5)
    ax.scatter(*pivot, c="k", marker="x", s=50, label="cone pivot (grasp point)")
    pts = np.concatenate([p, paths[..., :3, 3].reshape(-1, 3), pivot[None], T_world_ref[None, :3, 3]]
                         + ([demo_path[:, :3, 3]] if demo_path is not None else []))
    span = np.ptp(pts, axis=0).max() / 2 + axis_len
    mid = (pts.max(axis=0) + pts.min(axis=0)) / 2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[1] - span, mid[1] + span)
    ax.set_zlim(mid[2] - span, mid[2] + span)
    ax.set_box_aspect((1, 1, 1))  # equal metric scale on all axes
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("start poses in the quaternion cone (arrows: optical axis)")
    return _save(fig, path)


def contact_sheet(
    frames: np.ndarray,  # [E, T, H, W, 3] uint8
    path: Path,
    n_cols: int = 7,
    splice_index: int | None = None,
    row_names: list[str] | None = None,
) -> Path:
    """Grid of fisheye frames: one row per episode, ``n_cols`` frames evenly spaced in time up to and
    including ``splice_index`` (frames after it are the original ones), then the last frame."""
    plt = _pyplot()
    n_ep, n_t = frames.shape[:2]
    last_new = n_t - 1 if splice_index is None else splice_index
    cols = list(np.linspace(0, last_new, min(n_cols - 1, last_new + 1)).round().astype(int)) + [n_t - 1]
    fig, axes = plt.subplots(n_ep, len(cols), figsize=(1.9 * len(cols), 1.9 * n_ep), squeeze=False)
    for e in range(n_ep):
        for j, k in enumerate(cols):
            axes[e, j].imshow(frames[e, k])
            axes[e, j].set_xticks([])
            axes[e, j].set_yticks([])
            if e == 0:
                tag = " (splice)" if k == splice_index else (" (end)" if k == n_t - 1 else "")
                axes[e, j].set_title(f"t={k}{tag}", fontsize=8)
        axes[e, 0].set_ylabel(row_names[e] if row_names else f"ep {e}", fontsize=8)
    fig.suptitle("policy images (224², UMI layout): original demo and new episodes from cone-sampled starts",
                 fontsize=9)
    return _save(fig, path)
