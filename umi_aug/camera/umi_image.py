"""UMI's image path from a raw fisheye frame to the policy image (UMI ``07_generate_replay_buffer``, after decoding):
gripper mask painted black (mirrors kept), full-height centre crop, ``cv2.resize`` with INTER_AREA.

The geometry of the result is ``intr.umi_policy(size)`` (``pixel_centre="exact"``).
"""

from __future__ import annotations

import cv2
import numpy as np

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.masks import draw_predefined_mask
from umi_aug.errors import CameraError


def umi_policy_image(
    img: np.ndarray,  # [H, W, 3] uint8 RGB, H × W == intr.height × intr.width
    intr: FisheyeIntrinsics,
    size: int = 224,
    mask_gripper: bool = True,
) -> np.ndarray:
    """Return the ``[size, size, 3]`` uint8 policy image UMI would store for the raw frame ``img``.

    Raises:
        CameraError: the frame's size does not match ``intr`` or the frame is narrower than the square crop.
    """
    intr.check_image_shape(img.shape)
    if mask_gripper:
        img = draw_predefined_mask(img, color=(0, 0, 0), mirror=False, gripper=True, finger=False)
    x0, y0, cw, ch = intr.crop_geometry(size, size)
    if x0 < 0 or y0 < 0:
        raise CameraError(f"frame {intr.width}x{intr.height} is narrower than the {cw}x{ch} policy crop")
    crop = img[y0 : y0 + ch, x0 : x0 + cw]
    return cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)
