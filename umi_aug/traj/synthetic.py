"""A fixed analytic tabletop scene (mug / plate / distractors) with a synthetic mug-handle demo and scan views.

Used by the tests and ``benchmarks/traj.py`` while the reconstructed scene SDF (issue #5) is not available; it is
shaped like the project's sim scene (``umi_aug.sim``): world = table-tag frame, z up, table top at z = 0, the user
at −y. Everything is deterministic given ``seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from umi_aug.geometry import interpolate_pose, look_at_rotation, make_pose, so3_exp, umi_T_cam_tcp
from umi_aug.geometry.sdf import BoxSDF, CylinderSDF, HalfSpaceSDF, SphereSDF, UnionSDF
from umi_aug.traj.problem import Demonstration

__all__ = ["SyntheticTabletop", "tabletop_scene_sdf", "mug_handle_demo", "scan_views", "box_obstacle_points",
           "MUG_CENTER", "PLATE_CENTER"]

MUG_CENTER = np.array([0.05, 0.30, 0.0])  #: bottom centre of the mug, m
MUG_RADIUS, MUG_HEIGHT = 0.04, 0.095
PLATE_CENTER = np.array([-0.17, 0.28, 0.0])
PLATE_RADIUS, PLATE_THICKNESS = 0.10, 0.012
DEMO_FPS = 60000.0 / 1001.0


def tabletop_scene_sdf() -> UnionSDF:
    """Table half-space + mug (cylinder + handle box) + plate (flat cylinder) + a box and a ball distractor."""
    handle_x = MUG_CENTER[0] + MUG_RADIUS + 0.028
    parts = [
        HalfSpaceSDF([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
        CylinderSDF(MUG_CENTER + [0, 0, MUG_HEIGHT / 2], MUG_RADIUS, MUG_HEIGHT / 2),
        BoxSDF([handle_x, MUG_CENTER[1], MUG_HEIGHT / 2], [0.006, 0.006, 0.03]),
        CylinderSDF(PLATE_CENTER + [0, 0, PLATE_THICKNESS / 2], PLATE_RADIUS, PLATE_THICKNESS / 2),
        BoxSDF([0.28, 0.52, 0.06], [0.04, 0.05, 0.06], so3_exp(np.array([0.0, 0.0, 0.4]))),
        SphereSDF([-0.05, 0.55, 0.035], 0.035),
    ]
    return UnionSDF(parts)


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s * s)


def _grasp_camera_pose(tcp: np.ndarray, approach_dir: np.ndarray, pitch: float) -> np.ndarray:
    """Camera pose whose TCP is at ``tcp`` with the fingers pointing along ``approach_dir`` (horizontal unit
    vector), tilted down by ``pitch``; fingers close horizontally."""
    z = np.array([approach_dir[0] * math.cos(pitch), approach_dir[1] * math.cos(pitch), -math.sin(pitch)])
    R = look_at_rotation(np.zeros(3), z, np.array([0.0, 0.0, 1.0]))
    T = make_pose(R, np.zeros(3))
    T[:3, 3] = tcp - R @ umi_T_cam_tcp()[:3, 3]
    return T


def mug_handle_demo(seed: int = 0, tremor: float = 0.0) -> Demonstration:
    """A grasp-the-mug-handle-and-place-on-the-plate demo at UMI's 59.94 fps.

    Keyframes: start (camera ~0.45 m from the mug, looking at it) → pre-contact (TCP 6 cm out from the handle
    along the approach, clearance > 1.5 cm) → grasp (TCP at the handle) → lift → above the plate. Min-jerk
    timing between keyframes; optional hand tremor (metres, vanishing at keyframes); gripper closes at the grasp.
    The contact index is the pre-contact keyframe.
    """
    rng = np.random.default_rng(seed)
    handle = MUG_CENTER + np.array([MUG_RADIUS + 0.028, 0.0, MUG_HEIGHT / 2])
    approach = np.array([-1.0, 0.0, 0.0])
    pitch = math.radians(45)
    d = np.array([approach[0] * math.cos(pitch), approach[1] * math.cos(pitch), -math.sin(pitch)])
    grasp = _grasp_camera_pose(handle + 0.004 * d, approach, pitch)
    pre = _grasp_camera_pose(handle - 0.075 * d, approach, pitch)
    start_pos = np.array([0.32, -0.02, 0.40])
    start = make_pose(look_at_rotation(start_pos, MUG_CENTER + [0, 0, 0.05], np.array([0.0, 0.0, 1.0])), start_pos)
    lift = grasp.copy()
    lift[:3, 3] += [0.0, 0.0, 0.12]
    place = _grasp_camera_pose(PLATE_CENTER + [0.03, 0.0, MUG_HEIGHT / 2 + 0.03], approach, pitch)
    keys = [start, pre, grasp, lift, place]
    durations = [2.2, 0.8, 1.0, 1.6]
    poses, widths = [keys[0][None]], [np.array([0.085])]
    for i, dur in enumerate(durations):
        n = int(round(dur * DEMO_FPS))
        s = _min_jerk(np.arange(1, n + 1) / n)
        seg = interpolate_pose(keys[i], keys[i + 1], s)
        if tremor > 0:
            bump = np.sin(np.pi * np.arange(1, n + 1) / n)[:, None]
            seg[:, :3, 3] += tremor * bump * rng.standard_normal((n, 3)).cumsum(0) / np.sqrt(np.arange(1, n + 1))[:, None]
        poses.append(seg)
        w = np.full(n, 0.085) if i < 2 else np.full(n, 0.03)
        if i == 1:
            w = 0.085 - 0.055 * s  # closing while moving onto the handle
        widths.append(w)
    P = np.concatenate(poses)
    W = np.concatenate(widths)
    ts = np.arange(len(P)) / DEMO_FPS
    contact = int(round(durations[0] * DEMO_FPS))
    return Demonstration(P, ts, W, contact)


def scan_views(n: int = 160, seed: int = 0) -> np.ndarray:
    """A mapping sweep: cameras on arcs around the workspace (front side), heights 0.25–0.5 m, looking at
    jittered points near the objects → ``[n, 4, 4]``."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 0.32, 0.03])
    out = np.empty((n, 4, 4))
    for i, s in enumerate(np.linspace(0.0, 1.0, n)):
        az = -math.pi / 2 + 1.5 * math.sin(2 * math.pi * s)
        rho = 0.42 + 0.08 * math.cos(4 * math.pi * s)
        h = 0.36 + 0.1 * math.cos(3 * math.pi * s)
        pos = centre + [rho * math.cos(az), rho * math.sin(az), h]
        tgt = centre + rng.normal(0, 0.05, 3) * [1, 1, 0.3]
        out[i] = make_pose(look_at_rotation(pos, tgt, np.array([0.0, 0.0, 1.0])), pos)
    return out


def box_obstacle_points(center: np.ndarray, half_extents: np.ndarray, yaw: float = 0.0, n: int = 400,
                        seed: int = 0) -> np.ndarray:
    """Points sampled on the surface of a box (an "Objaverse object" stand-in) → ``[n + 8, 3]``."""
    rng = np.random.default_rng(seed)
    h = np.asarray(half_extents, dtype=np.float64)
    R = so3_exp(np.array([0.0, 0.0, yaw]))
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    pts = rng.uniform(-1, 1, (n, 3))
    ax = rng.integers(0, 3, n)
    pts[np.arange(n), ax] = np.sign(pts[np.arange(n), ax])
    pts = np.concatenate([corners, pts * h])
    return pts @ R.T + np.asarray(center, dtype=np.float64)


@dataclass(frozen=True)
class SyntheticTabletop:
    """Bundle: the fixed scene SDF, the demo, the scan views and a blocking box obstacle point cloud."""

    sdf: UnionSDF
    demo: Demonstration
    scan: np.ndarray
    obstacle_points: np.ndarray

    @classmethod
    def build(cls, seed: int = 0, tremor: float = 0.0) -> "SyntheticTabletop":
        demo = mug_handle_demo(seed, tremor)
        # a 12 cm tall box standing on the table between the start region and the mug: every straight-line
        # initial guess of the benchmark's θ = 50°, r = 0.15 m starts sweeps the gripper through it, and so does
        # the demo itself; the pre-contact pose keeps ~6 cm
        obs = box_obstacle_points([0.16, 0.08, 0.06], [0.04, 0.05, 0.06], yaw=0.3, seed=seed)
        return cls(tabletop_scene_sdf(), demo, scan_views(seed=seed), obs)

    @property
    def render_views(self) -> np.ndarray:
        return np.concatenate([self.demo.T_world_cam, self.scan])
