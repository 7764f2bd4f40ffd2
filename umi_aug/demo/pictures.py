"""Pictures the demo writes: lens geometry, sampled start-pose cone, contact sheet of original and new episodes.

All figures are PNG files written atomically (temporary file, then rename). matplotlib runs headless (Agg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from umi_aug.augment.pictures import contact_sheet, pyplot, save_figure  # noqa: F401  (contact_sheet: demo API)


def lens_figure(intr, path: Path) -> Path:
    """Three panels: ray angle θ per pixel (with 90° and image-circle contours and UMI's gripper mask),
    the Kannala–Brandt curve θ_d(θ) with its fold-over, and which cube face feeds each pixel."""
    # lazy, start-up: cv2
    from umi_aug.camera.cubemap import CubemapFisheyeRemap
    from umi_aug.camera.kb import kb_theta_d, unproject
    from umi_aug.camera.masks import predefined_mask

    remapper = CubemapFisheyeRemap(intr)

    plt = pyplot()
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
    return save_figure(fig, path)


def comparison_sheet(
    ground_truth: np.ndarray,  # [K, S, S, 3] uint8 simulator renders
    augmented: np.ndarray,  # [K, S, S, 3] uint8 augmented frames at the same poses
    valid: np.ndarray,  # [S, S] bool pixels that count (inside the lens, outside the gripper overlay)
    path: Path,
    n_rows: int = 4,
) -> Path:
    """Rows of ground truth | augmented | absolute error (x4, invalid pixels grey) for ``n_rows`` evenly spaced
    frames, each titled with its PSNR over the valid pixels."""
    plt = pyplot()
    k = len(ground_truth)
    rows = np.unique(np.linspace(0, k - 1, min(n_rows, k)).round().astype(int))
    fig, axes = plt.subplots(len(rows), 3, figsize=(6.3, 2.1 * len(rows)), squeeze=False)
    for r, i in enumerate(rows):
        gt, aug = ground_truth[i].astype(np.float64), augmented[i].astype(np.float64)
        err = np.abs(gt - aug).mean(-1)
        mse = float(np.mean((gt - aug)[valid] ** 2))
        psnr = 10 * np.log10(255.0 ** 2 / mse) if mse > 0 else float("inf")
        shown = np.where(valid, np.clip(4 * err, 0, 255), 128).astype(np.uint8)
        for c, (img, title) in enumerate(((ground_truth[i], "ground truth (sim)"),
                                          (augmented[i], f"augmented (3DGS) {psnr:.1f} dB"),
                                          (shown, "|error| x4"))):
            a = axes[r, c]
            a.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=255)
            a.set_xticks([])
            a.set_yticks([])
            a.set_title(title, fontsize=7)
    fig.suptitle("augmented frames vs simulator ground truth at the same poses", fontsize=9)
    return save_figure(fig, path)
