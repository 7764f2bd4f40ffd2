"""The one OpenCV↔MuJoCo camera-axis conversion, checked against MuJoCo's own cameras."""

from __future__ import annotations

import numpy as np
import pytest

from tests.sim.conftest import random_rotation
from umi_aug.errors import SimError
from umi_aug.sim.camera_frames import mujoco_camera_vectors, mujoco_to_opencv_camera, opencv_to_mujoco_camera


def test_identity_and_involution(rng):
    T = np.eye(4)
    np.testing.assert_array_equal(opencv_to_mujoco_camera(T)[:3, :3], np.diag([1.0, -1.0, -1.0]))
    Ts = np.tile(np.eye(4), (5, 1, 1))
    Ts[:, :3, :3] = [random_rotation(rng) for _ in range(5)]
    Ts[:, :3, 3] = rng.normal(size=(5, 3))
    M = opencv_to_mujoco_camera(Ts)
    np.testing.assert_array_equal(M[:, :3, 3], Ts[:, :3, 3])
    np.testing.assert_allclose(np.linalg.det(M[:, :3, :3]), 1.0, atol=1e-12)
    np.testing.assert_array_equal(mujoco_to_opencv_camera(M), Ts)


def test_forward_up_vectors(rng):
    R = random_rotation(rng)
    fwd, up = mujoco_camera_vectors(R)
    np.testing.assert_allclose(fwd, R[:, 2])  # optical axis = OpenCV +z
    np.testing.assert_allclose(up, -R[:, 1])  # image up = OpenCV −y


def test_bad_input():
    with pytest.raises(SimError):
        opencv_to_mujoco_camera(np.eye(5))
    with pytest.raises(SimError):
        opencv_to_mujoco_camera(np.full((4, 4), np.nan))


def test_matches_mujoco_camera_in_scene(model0, rng):
    """The scene's MJCF camera (MuJoCo axes) rides on the gripper body (OpenCV axes): MuJoCo's own cam_xmat must
    equal our conversion of the body pose."""
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.scene import CAMERA_NAME
    from umi_aug.sim.tabletop_state import TabletopState

    mujoco = import_mujoco()
    st = TabletopState(model0)
    cam = mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
    for _ in range(3):
        T = np.eye(4)
        T[:3, :3] = random_rotation(rng)
        T[:3, 3] = rng.uniform(-0.3, 0.3, 3) + [0, 0.2, 0.4]
        st.set(T, 0.05)
        M = opencv_to_mujoco_camera(T)
        np.testing.assert_allclose(st.data.cam_xmat[cam].reshape(3, 3), M[:3, :3], atol=1e-9)
        np.testing.assert_allclose(st.data.cam_xpos[cam], T[:3, 3], atol=1e-12)


def test_pinhole_render_matches_mujoco_renderer(model0, gl):
    """Our free-pose rasteriser at an OpenCV pose renders the same image as mujoco.Renderer through the model's
    own fixed camera (fovy 90) at that pose."""
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.raster import PinholeRasterizer, RasterOptions
    from umi_aug.sim.scene import CAMERA_NAME, SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.tabletop_state import TabletopState

    mujoco = import_mujoco()
    st = TabletopState(model0)
    T = np.eye(4)
    from umi_aug.geometry.cone import look_at_rotation

    T[:3, 3] = [0.25, -0.25, 0.35]
    T[:3, :3] = look_at_rotation(T[:3, 3], np.array([0.0, 0.3, 0.0]), np.array([0.0, 0.0, 1.0]))
    st.set(T, 0.06)
    S = 96
    with mujoco.Renderer(model0, S, S) as ref:
        ref.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        ref.update_scene(st.data, CAMERA_NAME)
        img_ref = ref.render()
    with PinholeRasterizer(model0, S, RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as r:
        r.update_scene(st.data, T)
        img, _ = r.render(T, 90.0, depth=False)
    diff = np.abs(img.astype(int) - img_ref.astype(int))
    assert diff.mean() < 2.0, diff.mean()
    # a 1-pixel shift or a flip would give a large difference on this textured scene
    assert np.abs(np.roll(img, 1, axis=0).astype(int) - img_ref.astype(int)).mean() > 4 * max(diff.mean(), 1.0)
