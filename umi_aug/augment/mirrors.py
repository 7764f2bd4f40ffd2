"""UMI's two side mirrors in augmented frames (issue #34 item 6).

A UMI gripper carries two side mirrors; UMI's dataset script keeps their pixels (a real reflection) unless run with
``--no_mirror`` (then they are painted black like the gripper), and ``--mirror_swap`` replaces them with the
horizontally flipped image's pixels. The 3DGS scene is trained with the mirror polygons masked out, so what it
renders there is neither a reflection nor black: the scene straight ahead, or nothing.

The export therefore takes the mirror pixels of an augmented frame from the same original frame as the gripper
overlay (the demo's frame with the closest gripper width, :func:`umi_aug.augment.overlay.source_frames_by_width`):
``overlay.mirrors = "source"`` adds the mirror polygons to the overlay mask. That follows whatever convention the
dataset was written with — black for ``--no_mirror``, the swapped pixels for ``--mirror_swap``, the real reflection
otherwise — at the price, for reflections, of showing what the mirror showed from the source frame's pose rather
than from the augmented pose (the mirrors face sideways and mostly reflect the fingers and the table next to the
gripper; rendering the mirrored virtual views from the 3DGS, with mirror planes fitted to the data, is not done).
``"scene"`` keeps the 3DGS render there (the behaviour before #34; right for a rig without mirrors).

:func:`detect_mirror_convention` tells the three cases apart from the frames: the mirror polygons reach below
UMI's image circle, so even with real reflections about 40 % of their pixels are black in every frame, while a
``--no_mirror`` dataset has them all black (``"masked"``); a physical mirror's outline is an edge in the image
(what the mirror reflects does not continue the scene around it: the real episode's frames change 3.3× more across
the outline than beside it), while a rig without mirrors — the synthetic sessions — shows the scene continuing
through the polygons (1.2×): ``"reflection"`` or ``"none"``. A swap and a true reflection both show a mirror image
of the symmetric rig and are not told apart; both take the source frame's pixels. ``overlay.mirrors = "auto"``
takes ``"source"`` for ``masked`` and ``reflection``, ``"scene"`` for ``none``.
"""

from __future__ import annotations

import cv2
import numpy as np

from umi_aug.camera.masks import predefined_mask
from umi_aug.errors import AugmentError

__all__ = ["MIRROR_MODES", "MASKED_BLACK_FRACTION", "MIRROR_EDGE_RATIO", "mirror_mask", "detect_mirror_convention",
           "mirror_pixels_from_source"]

#: ``OverlayConfig.mirrors`` values: chosen from the frames, mirror pixels from the overlay's original frame, or
#: the 3DGS render.
MIRROR_MODES: tuple[str, ...] = ("auto", "source", "scene")
#: Fraction of mirror pixels black in (nearly) every frame above which a dataset counts as ``--no_mirror``
#: (a dataset with visible mirrors: ~0.41 at any policy size, the part of the polygons outside the image circle).
MASKED_BLACK_FRACTION: float = 0.85
#: Frame change across the mirror outline / beside it above which the mirrors are physical (real episode 3.3,
#: synthetic session without mirrors 1.2).
MIRROR_EDGE_RATIO: float = 2.0
#: A pixel is black when its largest channel is below this (JPEG-XL keeps painted black within a few levels).
_BLACK_LEVEL = 16
#: ... in at least this fraction of the frames.
_BLACK_FRAMES = 0.95


def mirror_mask(size: int) -> np.ndarray:
    """UMI's two mirror polygons at ``size x size`` (full-height centre crop) → ``[S, S]`` bool."""
    return predefined_mask(size, size, mirror=True, gripper=False, finger=False)


def detect_mirror_convention(frames: np.ndarray) -> tuple[str, dict]:
    """How a UMI dataset's frames show the side mirrors (module docstring).

    Args:
        frames: ``[N, S, S, 3]`` uint8 policy frames of the dataset (N >= 2; a few dozen spread over the demos).

    Returns:
        ``(convention, evidence)``: ``"masked"`` (black, UMI's ``--no_mirror``), ``"reflection"`` (a physical mirror
        — or ``--mirror_swap``'s copy of one) or ``"none"`` (no mirror: the scene continues through the polygons);
        ``evidence`` = ``black_fraction`` (mirror pixels black in ≥ 95 % of the frames), ``edge_ratio`` (mean
        absolute change between horizontal neighbours across the outline / beside it, 0..255 levels), the
        thresholds and ``n_frames``.

    Raises:
        AugmentError: not uint8 ``[N >= 2, S, S, 3]`` frames.
    """
    f = np.asarray(frames)
    if f.ndim != 4 or f.shape[-1] != 3 or f.shape[1] != f.shape[2] or f.dtype != np.uint8 or f.shape[0] < 2:
        raise AugmentError(f"detect_mirror_convention: need uint8 frames [N >= 2, S, S, 3], got {f.dtype} {f.shape}")
    m = mirror_mask(f.shape[1])
    black_px = (f.max(axis=-1) < _BLACK_LEVEL).mean(axis=0) >= _BLACK_FRAMES  # [S, S] black in (nearly) every frame
    frac = float(black_px[m].mean())
    lit = ~black_px[:, 1:] & ~black_px[:, :-1]  # horizontal neighbour pairs, both lit
    across = (m[:, 1:] != m[:, :-1]) & lit
    band = cv2.dilate(m.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    beside = (m[:, 1:] == m[:, :-1]) & band[:, 1:] & band[:, :-1] & lit
    ratio = 0.0
    if across.any() and beside.any():
        dx = np.abs(np.diff(f.astype(np.float32), axis=2)).mean(axis=(0, 3))  # [S, S-1]
        ratio = float(dx[across].mean() / max(float(dx[beside].mean()), 1e-6))
    if frac >= MASKED_BLACK_FRACTION:
        conv = "masked"
    else:
        conv = "reflection" if ratio >= MIRROR_EDGE_RATIO else "none"
    return conv, {"black_fraction": round(frac, 4), "edge_ratio": round(ratio, 3),
                  "masked_black_fraction": MASKED_BLACK_FRACTION, "mirror_edge_ratio": MIRROR_EDGE_RATIO,
                  "n_frames": int(len(f))}


def mirror_pixels_from_source(mode: str, convention: str) -> bool:
    """Whether the overlay copies the mirror polygons from the source frame: ``mode`` (``OverlayConfig.mirrors``)
    with the detected ``convention`` for ``"auto"``.

    Raises:
        AugmentError: an unknown mode.
    """
    if mode not in MIRROR_MODES:
        raise AugmentError(f"overlay.mirrors={mode!r}: expected one of {list(MIRROR_MODES)}")
    if mode == "auto":
        return convention in ("masked", "reflection")
    return mode == "source"
