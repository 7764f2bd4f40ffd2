"""Scan and demo trajectories: smooth, start overhead, grasp at the handle, mug placed on the plate."""

from __future__ import annotations

import numpy as np

from umi_aug.geometry import so3_log
from umi_aug.geometry.umi import umi_T_cam_tcp
from umi_aug.sim.trajectories import UMI_FPS, min_jerk, plan_demo, scan_trajectory


def test_min_jerk_endpoints():
    s = np.linspace(0, 1, 101)
    y = min_jerk(s)
    assert y[0] == 0 and y[-1] == 1 and np.all(np.diff(y) >= 0)
    dy = np.gradient(y, s)
    assert abs(dy[0]) < 1e-3 and abs(dy[-1]) < 1e-3


def test_demo_plan(scene0):
    L = scene0.layout
    p = plan_demo(L, np.random.default_rng(0))
    n = len(p)
    assert 300 < n < 700 and p.fps == UMI_FPS
    np.testing.assert_allclose(p.timestamp, np.arange(n) / UMI_FPS)
    np.testing.assert_allclose(p.T_world_tcp, p.T_world_cam @ umi_T_cam_tcp(), atol=1e-12)
    ev = p.events
    assert 0 < ev["pregrasp"] < ev["contact"] < ev["grasped"] < ev["lifted"] < ev["above_plate"] < ev["placed"] \
        < ev["release"] < ev["end"] == n - 1
    # upright overhead start: looking down, image "up" (−y_cam) towards the far side (+y world)
    R0 = p.T_world_cam[0, :3, :3]
    assert R0[2, 2] < -0.85 and (-R0[:, 1])[1] > 0.3
    # contact: TCP exactly at the grasp pose, fingers still open; grasped: closed on the handle
    np.testing.assert_allclose(p.T_world_tcp[ev["contact"] - 1], L.T_world_grasp, atol=1e-9)
    assert p.gripper_width[ev["contact"] - 1] > 0.07
    assert abs(p.gripper_width[ev["grasped"]] - L.mug.handle_thickness) < 1e-3
    # mug static before grasp, held rigidly while attached, placed upright on the plate with the handle left
    np.testing.assert_allclose(p.T_world_mug[: ev["contact"]], np.broadcast_to(L.T_world_mug, (ev["contact"], 4, 4)))
    T_tcp_mug = np.linalg.inv(p.T_world_tcp[p.attached]) @ p.T_world_mug[p.attached]
    np.testing.assert_allclose(T_tcp_mug, np.broadcast_to(T_tcp_mug[0], T_tcp_mug.shape), atol=1e-9)
    end = p.T_world_mug[-1]
    np.testing.assert_allclose(end[:2, 3], L.T_world_mug_place[:2, 3], atol=1e-3)
    assert 0 <= end[2, 3] - L.plate.top_z < 2e-3
    assert np.degrees(np.linalg.norm(so3_log(L.T_world_mug_place[:3, :3].T @ end[:3, :3]))) < 1.0
    # smooth: bounded speed and no jumps
    v = np.linalg.norm(np.diff(p.T_world_tcp[:, :3, 3], axis=0), axis=1) * UMI_FPS
    assert v.max() < 1.0
    assert np.abs(np.diff(v)).max() * UMI_FPS < 10.0  # m/s² (no velocity jumps)


def test_scan_is_smooth_and_looks_at_table(scene0):
    T = scan_trajectory(scene0.layout, 200, np.random.default_rng(1))
    assert T.shape == (200, 4, 4)
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert step.max() < 0.05 and step.min() > 0
    heights = T[:, 2, 3]
    assert heights.min() > 0.15 and heights.max() - heights.min() > 0.1
    # optical axes point down towards the table
    assert (T[:, 2, 2] < -0.3).all()
    ang = [np.linalg.norm(so3_log(T[i, :3, :3].T @ T[i + 1, :3, :3])) for i in range(199)]
    assert np.degrees(max(ang)) < 5.0
