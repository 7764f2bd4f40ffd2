"""UMI's raw-frame → policy-image path: geometry matches ``intr.umi_policy`` and sizes are checked."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.camera import gopro_intrinsics_2_7k, predefined_mask, project
from umi_aug.camera.umi_image import umi_policy_image
from umi_aug.errors import CameraError


def test_dot_lands_where_policy_intrinsics_project_it(rng):
    intr = gopro_intrinsics_2_7k().scaled(640, 480)
    pol = intr.umi_policy(224)
    for _ in range(5):
        # a bright 3-D point in view, away from the gripper mask
        p = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.4, 0.05), 1.0])
        uv, ok = project(p, intr)
        assert ok
        img = np.zeros((480, 640, 3), np.uint8)
        u, v = np.rint(uv).astype(int)
        img[v - 3 : v + 4, u - 3 : u + 4] = 255  # 7x7 block centred on the rounded pixel
        out = umi_policy_image(img, intr, 224).astype(float)[..., 0]
        ys, xs = np.nonzero(out)
        w = out[ys, xs]
        centroid = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
        expected, ok2 = project(p, pol)
        # the block was centred on the rounded pixel: shift the expectation by the same rounding
        expected = expected + (np.rint(uv) - uv) * pol.fx / intr.fx
        assert ok2 and np.abs(centroid - expected).max() < 0.1


def test_gripper_masked_black_and_shape_checked():
    intr = gopro_intrinsics_2_7k().scaled(320, 240)
    out = umi_policy_image(np.full((240, 320, 3), 200, np.uint8), intr, 224)
    assert out.shape == (224, 224, 3) and out.dtype == np.uint8
    mask = predefined_mask(224, 224, mirror=False, gripper=True)
    assert (out[mask] < 60).mean() > 0.95 and (out[~mask] == 200).mean() > 0.95
    with pytest.raises(CameraError, match="does not match intrinsics"):
        umi_policy_image(np.zeros((224, 320, 3), np.uint8), intr, 224)
