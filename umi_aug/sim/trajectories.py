"""Hand-held camera trajectories of the synthetic session: the mapping scan and the mug→plate demos.

All poses are 4×4 in the world (= table-tag) frame, metres; camera poses have OpenCV axes; TCP poses follow
UMI's ``T_world_tcp = T_world_cam @ T_cam_tcp``. Motions are smooth: demos interpolate waypoints with
minimum-jerk timing (zero velocity and acceleration at each waypoint) plus a small hand tremor that vanishes at
the waypoints (so grasp and placement are exact); the scan is a sum of slow sinusoids.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import make_pose, so3_exp
from umi_aug.geometry.cone import look_at_rotation
from umi_aug.geometry.interp import interpolate_pose
from umi_aug.geometry.umi import camera_poses_from_tcp_poses, tcp_poses_from_camera_poses, umi_T_cam_tcp
from umi_aug.sim.scene import OBJECT_REGION, SceneLayout

__all__ = ["UMI_FPS", "min_jerk", "scan_trajectory", "DemoPlan", "plan_demo"]

#: UMI's GoPro frame rate (59.94 fps = 60000/1001).
UMI_FPS: float = 60000.0 / 1001.0
#: Hand tremor amplitude of demo motions (position m, rotation rad); zero at every waypoint.
TREMOR_POS_M: float = 0.0025
TREMOR_ROT_RAD: float = math.radians(0.6)
#: Gripper opening before grasping / after releasing, metres (UMI's teleop range is 0..0.09).
OPEN_WIDTH_RANGE: tuple[float, float] = (0.075, 0.085)


def min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk time scaling ``10 s^3 − 15 s^4 + 6 s^5`` on ``s ∈ [0, 1]`` (clipped): 0→1 with zero
    velocity and acceleration at both ends."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def _workspace_centre(layout: SceneLayout) -> np.ndarray:
    (x0, x1), (y0, y1) = OBJECT_REGION
    return np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0])


def _look(pos: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Upright OpenCV camera pose at ``pos`` looking at ``target`` (image up ≈ world +z, or +y when looking
    straight down), rolled by ``roll`` radians about the optical axis."""
    fwd = target - pos
    fwd = fwd / np.linalg.norm(fwd)
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.97 else np.array([0.0, 1.0, 0.0])
    R = look_at_rotation(pos, target, up)
    if roll:
        R = R @ so3_exp(np.array([0.0, 0.0, roll]))
    return make_pose(R, pos)


def scan_trajectory(layout: SceneLayout, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """A hand-held mapping sweep: arcs around the workspace from the user's side at varying heights and
    distances, looking at (jittered) points on the table, with a little roll — like a UMI mapping video.

    Args:
        layout: scene layout (the workspace centre is derived from the object region).
        n_frames: number of frames (>= 2).
        rng: random generator (phases and amplitudes).

    Returns:
        T_world_cam: np.ndarray,  # [n_frames, 4, 4] OpenCV axes
    """
    if n_frames < 2:
        raise SimError(f"scan_trajectory: need >= 2 frames, got {n_frames}")
    c = _workspace_centre(layout)
    s = np.linspace(0.0, 1.0, int(n_frames))
    ph = rng.uniform(0.0, 2.0 * math.pi, 6)
    sweep = rng.uniform(1.7, 2.0)
    out = np.empty((n_frames, 4, 4))
    for i, si in enumerate(s):
        az = -math.pi / 2 + sweep * math.sin(2.0 * math.pi * si)  # around the front (user) side
        rho = 0.40 + 0.10 * math.cos(2.0 * math.pi * 2.0 * si + ph[0])
        h = 0.34 + 0.12 * math.cos(2.0 * math.pi * 1.5 * si + ph[1])
        pos = c + np.array([rho * math.cos(az), rho * math.sin(az), h])
        tgt = c + np.array([0.10 * math.sin(2 * math.pi * 2.0 * si + ph[2]),
                            0.07 * math.sin(2 * math.pi * 3.0 * si + ph[3]), 0.0])
        roll = math.radians(10.0) * math.sin(2 * math.pi * 2.5 * si + ph[4])
        out[i] = _look(pos, tgt, roll)
    return out


@dataclass
class DemoPlan:
    """One demonstration, sampled at ``fps``.

    Attributes:
        timestamp: [T] seconds from the first frame (``frame_idx / fps``).
        T_world_tcp: [T, 4, 4] TCP poses (UMI TCP axes = OpenCV camera axes).
        T_world_cam: [T, 4, 4] camera poses (``T_world_tcp @ inv(T_cam_tcp)``).
        gripper_width: [T] metres, 0 = closed.
        T_world_mug: [T, 4, 4] mug pose (bottom centre).
        attached: [T] bool, mug rigidly held by the gripper.
        events: frame indices of the phase boundaries: ``pregrasp`` (arrival above the handle),
            ``contact`` (TCP at the handle, fingers start closing: the first contact frame), ``grasped``
            (closed, mug attached), ``lifted``, ``above_plate``, ``placed`` (mug on the plate),
            ``release`` (fingers open, mug detached), ``end``.
        phases: [T] phase name of every frame.
    """

    fps: float
    timestamp: np.ndarray
    T_world_tcp: np.ndarray
    T_world_cam: np.ndarray
    gripper_width: np.ndarray
    T_world_mug: np.ndarray
    attached: np.ndarray
    events: dict[str, int] = field(default_factory=dict)
    phases: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.timestamp.shape[0])


def _translate(T: np.ndarray, d_world: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, 3] = out[:3, 3] + d_world
    return out


def _tremor(n: int, rng: np.random.Generator) -> np.ndarray:
    """[n, 6] smooth small perturbation (pos m, rotvec rad), zero at both ends of the segment."""
    if n <= 1:
        return np.zeros((max(n, 0), 6))
    t = np.linspace(0.0, 1.0, n)
    env = np.sin(math.pi * t) ** 2
    out = np.zeros((n, 6))
    for k in range(6):
        amp = TREMOR_POS_M if k < 3 else TREMOR_ROT_RAD
        f1, f2 = rng.uniform(1.0, 3.0), rng.uniform(3.0, 6.0)
        p1, p2 = rng.uniform(0, 2 * math.pi, 2)
        out[:, k] = amp * env * (0.7 * np.sin(2 * math.pi * f1 * t + p1) + 0.3 * np.sin(2 * math.pi * f2 * t + p2))
    return out


def plan_demo(layout: SceneLayout, rng: np.random.Generator, fps: float = UMI_FPS,
              T_cam_tcp: np.ndarray | None = None) -> DemoPlan:
    """Plan "grasp the mug by its handle and place it upright on the plate, handle left".

    Starts from an upright overhead view (camera looking down at the workspace, image top towards the far
    side of the table), approaches the handle from outside, closes the fingers on the handle's outer bar,
    lifts, carries the mug over the plate while turning it so the handle points left (−x), lowers it onto the
    plate, opens and retreats. Durations and the start pose are jittered by ``rng``.

    Args:
        layout: the scene layout (mug, plate, grasp pose).
        rng: random generator.
        fps: sampling rate, frames per second (UMI: 59.94).
        T_cam_tcp: [4, 4] camera→TCP offset (default UMI's).

    Returns:
        :class:`DemoPlan`.
    """
    T_cam_tcp = umi_T_cam_tcp() if T_cam_tcp is None else np.asarray(T_cam_tcp, dtype=np.float64)
    mug = layout.mug
    T_grasp = layout.T_world_grasp
    # start: upright overhead camera, between the user and the objects
    mid = 0.5 * (layout.T_world_mug[:3, 3] + layout.T_world_plate[:3, 3])
    cam0 = mid + np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.16, -0.10), rng.uniform(0.42, 0.50)])
    tgt0 = mid + np.array([rng.uniform(-0.04, 0.04), rng.uniform(0.02, 0.08), 0.0])
    R0 = look_at_rotation(cam0, tgt0, np.array([0.0, 1.0, 0.0]))  # image up ≈ +y (far side)
    T_start = tcp_poses_from_camera_poses(make_pose(R0, cam0), T_cam_tcp)

    z_tcp = T_grasp[:3, 2]
    T_pre = _translate(T_grasp, -rng.uniform(0.06, 0.08) * z_tcp + np.array([0.0, 0.0, rng.uniform(0.04, 0.06)]))
    lift = rng.uniform(0.10, 0.13)
    T_lift = _translate(T_grasp, np.array([0.0, 0.0, lift]))
    T_mug_grasp = layout.T_mug_grasp
    place_clear = 0.0005  # mug bottom this far above the plate surface when released
    T_mug_place = _translate(layout.T_world_mug_place, np.array([0.0, 0.0, place_clear]))
    T_place = T_mug_place @ T_mug_grasp
    T_above = _translate(T_place, np.array([0.0, 0.0, lift]))
    T_retreat = _translate(T_place, -0.08 * T_place[:3, 2] + np.array([0.0, 0.0, 0.08]))

    w_open = rng.uniform(*OPEN_WIDTH_RANGE)
    w_closed = mug.handle_thickness + 0.0005
    jit = lambda d: d * rng.uniform(0.85, 1.15)  # noqa: E731
    # (name, target TCP pose, duration s, width at the end, mug attached during the segment)
    segments = [
        ("hold", T_start, jit(0.35), w_open, False),
        ("approach", T_pre, jit(1.7), w_open, False),
        ("descend", T_grasp, jit(0.9), w_open, False),
        ("close", T_grasp, jit(0.5), w_closed, False),
        ("lift", T_lift, jit(0.8), w_closed, True),
        ("transport", T_above, jit(1.6), w_closed, True),
        ("lower", T_place, jit(0.9), w_closed, True),
        ("open", T_place, jit(0.4), w_open, False),
        ("retreat", T_retreat, jit(0.9), w_open, False),
    ]
    poses, widths, att, phases = [], [], [], []
    events: dict[str, int] = {}
    T_prev, w_prev = T_start, w_open
    for name, T_tgt, dur, w_tgt, attached in segments:
        n = max(2, int(round(dur * fps)))
        s = min_jerk((np.arange(n) + 1) / n)  # excludes the segment start (= previous segment's end)
        seg = interpolate_pose(T_prev, T_tgt, s)
        trem = _tremor(n + 1, rng)[1:] if name not in ("hold", "close", "open") else np.zeros((n, 6))
        for k in range(n):
            dT = make_pose(so3_exp(trem[k, 3:]), trem[k, :3])
            seg[k] = seg[k] @ dT
        events_before = len(poses)
        poses.extend(seg)
        widths.extend(w_prev + (w_tgt - w_prev) * s)
        att.extend([attached] * n)
        phases.extend([name] * n)
        if name == "approach":
            events["pregrasp"] = events_before + n - 1
        elif name == "descend":
            events["contact"] = events_before + n  # first frame of closing: TCP at the handle
        elif name == "close":
            events["grasped"] = events_before + n - 1
        elif name == "lift":
            events["lifted"] = events_before + n - 1
        elif name == "transport":
            events["above_plate"] = events_before + n - 1
        elif name == "lower":
            events["placed"] = events_before + n - 1
        elif name == "open":
            events["release"] = events_before + n - 1
        T_prev, w_prev = T_tgt, w_tgt
    # first frame: the start pose itself
    T_world_tcp = np.concatenate([T_start[None], np.stack(poses)], axis=0)
    widths_a = np.concatenate([[w_open], np.asarray(widths)])
    attached_a = np.concatenate([[False], np.asarray(att, dtype=bool)])
    phases = ["hold"] + phases
    events = {k: v + 1 for k, v in events.items()}
    events["end"] = len(T_world_tcp) - 1
    # the mug: static until attached; follows the TCP rigidly while attached; stays where released
    T_tcp_mug = np.linalg.inv(T_mug_grasp)
    T_mug = np.empty_like(T_world_tcp)
    cur = layout.T_world_mug.copy()
    for i in range(len(T_world_tcp)):
        if attached_a[i]:
            cur = T_world_tcp[i] @ T_tcp_mug
        T_mug[i] = cur
    n_total = len(T_world_tcp)
    return DemoPlan(
        fps=float(fps),
        timestamp=np.arange(n_total, dtype=np.float64) / float(fps),
        T_world_tcp=T_world_tcp,
        T_world_cam=camera_poses_from_tcp_poses(T_world_tcp, T_cam_tcp),
        gripper_width=widths_a,
        T_world_mug=T_mug,
        attached=attached_a,
        events=events,
        phases=phases,
    )
