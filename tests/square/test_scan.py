"""Square scan (umi_aug.square.scan): robot never rendered, nut hidden / alone, poses, depth points, errors."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("robosuite")  # the robomimic extra; CI installs it (README)

from umi_aug.errors import SimError  # noqa: E402
from umi_aug.square import scan as S  # noqa: E402
from umi_aug.square.camera import wrist_intrinsics  # noqa: E402


@pytest.fixture(scope="module")
def env():
    from umi_aug.square.env import SquareEnv

    e = SquareEnv(image_size=None)
    e.reset(seed=3)
    yield e
    e.close()


def _geoms_of(model, prefixes: tuple[str, ...]) -> set[int]:
    from umi_aug.sim.gl import import_mujoco

    mj = import_mujoco()
    return {g for g in range(model.ngeom)
            if (mj.mj_id2name(model, mj.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g])) or "").startswith(prefixes)}


def test_robot_absent_from_every_scan_kind_and_present_without_hiding(gl, env):
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer

    state = env.get_state()
    T = env.wrist_pose()  # the wrist camera: the fingers fill the bottom of its image
    robot = _geoms_of(env.model, S.ROBOT_BODY_PREFIXES)
    nut = _geoms_of(env.model, ("SquareNut",))
    groups = env.model.geom_group.copy()
    intr = wrist_intrinsics(48)
    with FisheyeRenderer(env.model, intr) as r:  # the unmodified model does see the robot (the test can fail)
        seen = set(np.unique(r.render(T, env.data, rgb=False, depth=False, segmentation=True).geom_id).tolist())
    assert seen & robot and seen & nut
    for kind in S.SCAN_KINDS:
        fr = S.render_scan(env.model, state, T[None], intr, kind)
        ids = set(np.unique(fr.geom_id[fr.mask]).tolist())
        assert not ids & robot, kind
        if kind == "scene":
            assert ids & nut and ids - nut  # nut and table/pegs
        elif kind == "static":
            assert not ids & nut and ids
        else:
            assert ids and ids <= nut
    np.testing.assert_array_equal(env.model.geom_group, groups)  # the caller's model is untouched
    # the robot's sites (grip-site markers) are hidden too
    m = S.scan_model(env.model, "scene")
    assert np.all(m.site_group[np.isin(m.site_bodyid, S.robot_body_ids(m))] == S.HIDDEN_GROUP)


def test_state_of_wrong_length_is_one_clear_error(env):
    s = env.get_state()
    with pytest.raises(SimError, match=r"1 \+ nq \(23\) \+ nv \(21\) = 45"):
        S.data_at_state(env.model, s[:-1])
    with pytest.raises(SimError, match="non-finite"):
        S.data_at_state(env.model, np.where(np.arange(len(s)) == 3, np.nan, s))
    d = S.data_at_state(env.model, s)
    np.testing.assert_allclose(S.body_pose(env.model, d), env.body_pose("SquareNut_main"), atol=1e-12)


def test_scan_poses_deterministic_cover_the_cap_and_look_at_the_table():
    c = np.array([-0.08, 0.08, 0.82])
    P = S.scan_poses(c, 40, seed=7)
    np.testing.assert_array_equal(P, S.scan_poses(c, 40, seed=7))
    assert not np.allclose(P, S.scan_poses(c, 40, seed=8))
    R = P[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    d = P[:, :3, 3] - c
    r = np.linalg.norm(d, axis=1)
    assert r.min() >= 0.18 - 1e-9 and r.max() <= 0.40 + 1e-9 and r.max() - r.min() > 0.15
    polar = np.degrees(np.arccos(d[:, 2] / r))
    assert polar.max() <= 60.0 + 1e-9 and polar.max() > 50.0 and polar.min() < 10.0
    # optical axis hits the table plane within target_radius of the centre
    z = P[:, :3, 2]
    t = (c[2] - P[:, 2, 3]) / z[:, 2]
    hit = P[:, :3, 3] + t[:, None] * z
    assert np.all(t > 0) and np.linalg.norm(hit[:, :2] - c[:2], axis=1).max() <= 0.12 + 1e-9
    with pytest.raises(SimError, match="radius"):
        S.scan_poses(c, 4, 0, radius=(0.3, 0.2))


def test_nut_scan_points_lie_on_the_nut_in_its_body_frame(gl, env):
    from umi_aug.geometry import pose_inverse

    state = env.get_state()
    T_nut = env.body_pose("SquareNut_main")
    P = S.nut_orbit_poses(T_nut, 6, seed=0)
    np.testing.assert_allclose(np.linalg.norm(P[:, :3, 3] - T_nut[:3, 3], axis=1).clip(0.16, 0.26),
                               np.linalg.norm(P[:, :3, 3] - T_nut[:3, 3], axis=1), atol=1e-9)
    fr = S.render_scan(env.model, state, P, S.nut_orbit_intrinsics(48), "nut")
    assert fr.mask.any(axis=(1, 2)).all()  # the nut is in every orbit view
    xyz, rgb = S.scan_points(fr, 3000, seed=0, T_frame_world=pose_inverse(T_nut))
    assert xyz.shape == rgb.shape and len(xyz) > 500 and np.isfinite(xyz).all()
    # nut: a 9 cm square ring + handle, ~2 cm thick, handle along +x (robosuite SquareNut)
    assert np.all(np.abs(xyz[:, 2]) < 0.015) and np.all(np.abs(xyz[:, 1]) < 0.05)
    assert xyz[:, 0].min() > -0.05 and 0.06 < xyz[:, 0].max() < 0.09
    assert np.all((0 <= rgb) & (rgb <= 1))
