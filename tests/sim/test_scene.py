"""The built-in tabletop scene: deterministic per seed, compiles, gripper at the bottom of every frame, grasp."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.errors import SimError


def test_same_seed_same_bytes_different_seed_different_layout(scene0):
    from umi_aug.sim.scene import build_tabletop_scene

    again = build_tabletop_scene(0)
    assert again.xml == scene0.xml and again.assets == scene0.assets
    other = build_tabletop_scene(1)
    assert not np.allclose(other.layout.T_world_mug, scene0.layout.T_world_mug)
    with pytest.raises(SimError):
        build_tabletop_scene(-1)


def test_layout_is_sane(scene0):
    L = scene0.layout
    mug_xy, plate_xy = L.T_world_mug[:2, 3], L.T_world_plate[:2, 3]
    assert np.linalg.norm(mug_xy - plate_xy) > L.plate.radius + L.mug.handle_outer_x
    # handle points roughly left (−x), the place pose exactly left, upright on the plate surface
    assert L.T_world_mug[0, 0] < -0.6
    np.testing.assert_allclose(L.T_world_mug_place[:3, 0], [-1.0, 0.0, 0.0], atol=1e-12)
    assert L.T_world_mug_place[2, 3] == pytest.approx(L.plate.top_z)
    np.testing.assert_allclose(L.T_world_grasp, L.T_world_mug @ L.T_mug_grasp)
    # the grasp TCP sits on the handle's outer bar, fingers closing across the handle plane (mug y)
    R = L.T_mug_grasp[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [0, 1, 0], atol=1e-12)
    d = L.to_dict()
    assert d["tag"]["id"] == 13 and len(d["distractors"]) == len(L.distractors) >= 2


def test_compiles_with_expected_bodies(model0, tmp_path, scene0):
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.scene import CAMERA_NAME, FINGER_JOINTS, GRIPPER_BODY, MUG_BODY, PLATE_BODY

    mujoco = import_mujoco()
    for name in (GRIPPER_BODY, MUG_BODY, PLATE_BODY):
        assert mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_BODY, name) >= 0
    for j in FINGER_JOINTS:
        assert mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_JOINT, j) >= 0
    assert mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME) >= 0
    xml_path = scene0.write(tmp_path / "scene")
    m2 = mujoco.MjModel.from_xml_path(str(xml_path))
    assert m2.ngeom == model0.ngeom


def test_fingers_pinch_the_handle_at_the_grasp_pose(model0, scene0):
    """At the grasp pose with the closing width, both fingers touch the handle (distance ~0) without deep
    penetration, and the gripper clears the table."""
    from umi_aug.geometry.umi import camera_poses_from_tcp_poses
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.tabletop_state import TabletopState

    mujoco = import_mujoco()
    L = scene0.layout
    st = TabletopState(model0)
    w = L.mug.handle_thickness
    st.set(camera_poses_from_tcp_poses(L.T_world_grasp), w)
    gid = lambda n: mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    handle = [gid(f"mug_handle_{i}") for i in range(L.mug.handle_segments)]
    fromto = np.zeros(6)
    for side in ("left", "right"):
        dist = min(mujoco.mj_geomDistance(model0, st.data, gid(f"gripper_pad_{side}"), h, 0.05, fromto)
                   for h in handle)
        assert -1.5e-3 < dist < 1.5e-3, (side, dist)
    # every gripper geom's bounding box (geom frame) stays above the table top (z = 0)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    for g in st.gripper_geom_ids:
        c, h = model0.geom_aabb[g, :3], model0.geom_aabb[g, 3:]
        corners = (c + signs * h) @ st.data.geom_xmat[g].reshape(3, 3).T + st.data.geom_xpos[g]
        assert corners[:, 2].min() > 0.005


def test_gripper_appears_at_bottom_and_width_moves_fingers(model0, gopro224, gl):
    from umi_aug.camera.masks import predefined_mask
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer, RasterOptions
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.tabletop_state import TabletopState

    st = TabletopState(model0)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.0, 0.2, 0.45]
    masks = {}
    with FisheyeRenderer(model0, gopro224, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as r:
        for w in (0.0, 0.085):
            st.set(T, w)
            masks[w] = st.gripper_mask(r.render(T, st.data, rgb=False, depth=False, segmentation=True).geom_id)
    m = masks[0.085]
    rows = np.nonzero(m)[0]
    assert 0.05 < m.mean() < 0.35
    assert rows.min() > 0.5 * 224  # only in the bottom half, as in real UMI frames
    # mostly inside UMI's predefined gripper+finger masks
    umi = predefined_mask(224, 224, mirror=True, gripper=True, finger=True)
    assert (m & umi).sum() / m.sum() > 0.9
    # opening the gripper moves the fingers apart: the centre column between the tips clears
    assert (masks[0.0] != m).sum() > 100
    assert m[140:160, 108:116].mean() < masks[0.0][140:160, 108:116].mean()


def test_aruco_tag_13_defines_the_world_frame(model0, gl):
    import cv2

    from umi_aug.sim.raster import PinholeRasterizer, RasterOptions
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR, TAG_SIZE
    from umi_aug.sim.tabletop_state import TabletopState

    st = TabletopState(model0)
    far = np.eye(4)
    far[:3, 3] = [0.0, 0.0, 1.5]
    st.set(far, 0.05)  # gripper out of the way
    S = 400
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.03, 0.02, 0.45]
    with PinholeRasterizer(model0, S, RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as r:
        r.update_scene(st.data, T)
        rgb, _ = r.render(T, 60.0, depth=False)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
                                  cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert ids is not None and 13 in ids.ravel()
    c = corners[list(ids.ravel()).index(13)][0]
    f = (S / 2) / np.tan(np.radians(30))
    h = TAG_SIZE / 2
    obj = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])  # OpenCV ArUco corner order (z up)
    p_cam = (obj - T[:3, 3]) @ T[:3, :3]  # world → camera (tag top at z ≈ 0)
    uv = f * p_cam[:, :2] / p_cam[:, 2:] + (S - 1) / 2
    assert np.abs(uv - c).max() < 1.5  # corners in ArUco order land where the world frame says
