"""The simulated arm (:class:`SimUR5eRobot`): robosuite 1.4.1's UR5e MJCF (kinematics, inertias, torque limits;
loaded with ``mujoco.MjSpec``, a TCP site added ``tcp_offset`` along the flange axis) stepped by MuJoCo in real time at the
e-Series controller rate (500 Hz, one 2 ms physics step per period; a late period catches up). Each period does
what the ur-rtde controller process does with ``servoL``: the same commands (``("waypoint", pose, t)``), the
same :class:`~umi_aug.deploy.interpolator.PoseTrajectoryInterpolator` with the speed limits, the same state
record (:data:`~umi_aug.deploy.arm_process.STATE_FIELDS`) and heartbeat watchdog. The sampled TCP pose becomes
joint targets by the simulator arms' damped-least-squares IK (:class:`umi_aug.sim.ik.ArmIK`, :data:`UR5E_DLS`;
warm-started from the last solution) ``response_latency`` later
(the real arm's response time, which the runner's ``action_latency`` compensates), tracked by joint PD control
with velocity feed-forward and gravity compensation within the UR5e's joint torque limits. The controller's protective stops are
mirrored: an unreachable target (IK residual) or a joint tracking error above the limit stop the arm with one
message. Every stop — the runner's, a ``("stop",)`` command, the heartbeat watchdog, the runner's death, a
protective stop — decelerates the TCP to rest as ur-rtde's ``servoStop(a)`` does (:class:`StopRamp`:
``stop_deceleration``, default servoStop's 10 m/s²), neither freezing it nor letting it run on to its target.
The robot base frame is the UR controller's (``getActualTCPPose``): the MJCF's base turned 180° about z and its
link offsets set to the UR5e DH parameters (:func:`ur5e_fk_dh`; checked at load), so a robot config
(box, ``joints_init``, reach target) means the same physical pose in simulation and on the arm.

The arm is one of the three roles of the simulated UR5e (:mod:`umi_aug.deploy.sim_ur5e`); it implements
:class:`~umi_aug.deploy.interfaces.RobotInterface` through the host side it shares with the ur-rtde backend
(:class:`~umi_aug.deploy.arm_process.ArmProcess`).

Every child process dies with the runner, also on SIGKILL (:func:`~umi_aug.deploy.device_process.child_setup`:
``PR_SET_PDEATHSIG``, plus a parent-alive check every loop period). The arm's process asks for SIGTERM as its
parent-death signal and handles it by decelerating to rest first (:func:`stop_on_signal`; a SIGALRM backstop ends
it if that hangs) — on the real arm the robot's own program does that stop when ur-rtde's watchdog fires.
"""

from __future__ import annotations

import collections
import importlib.util
import logging
import math
import os
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import cv2
import numpy as np

from umi_aug.config_check import reject_unknown_keys, require_positive
from umi_aug.deploy.arm_process import ArmProcess, drain_waypoint_commands
from umi_aug.deploy.clock import Clock, MonotonicClock
from umi_aug.deploy.device_process import child_setup, parent_alive, poll_enable
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator
from umi_aug.deploy.safety import SafetyStop, check_robot_limits
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError
from umi_aug.geometry.se3 import pos_rotvec_to_pose
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.ik import ArmIK, DLSParams, rodrigues_log, site_pose

__all__ = ["SimURConfig", "UR5eSim", "StopRamp", "SimServoLoop", "SimUR5eRobot", "ur5e_mjcf_path",
           "base_pose_matrix", "ur5e_fk_dh", "stop_time_bound", "stop_on_signal", "JOINT_NAMES", "TCP_SITE",
           "CONTROL_RATE_HZ", "UR5E_DLS"]

log = logging.getLogger(__name__)

JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
               "wrist_3_joint")
FLANGE_BODY = "right_hand"  # robosuite's UR5e: the tool flange frame, z out of the flange
TCP_SITE = "umi_tcp"
CONTROL_RATE_HZ = 500.0  # e-Series servoL rate
#: the servo loop's IK (:class:`~umi_aug.sim.ik.ArmIK`): λ = 1e-2, at most 0.05 rad per joint and iteration,
#: converged below 1e-6 m / 1e-5 rad, rotation error by OpenCV's Rodrigues (fast at 500 Hz)
UR5E_DLS = DLSParams(max_step=0.05, step_norm="max", damping=1e-2, tol_pos_m=1e-6, tol_rot_rad=1e-5,
                     rot_log=rodrigues_log)
_ARMATURE = 0.1  # kg·m², per joint (UR harmonic drives, ratio ~100, reflect ~0.1 kg·m²)
_MAX_CATCH_UP = 25  # physics steps one late period may add (50 ms); more is dropped (the sim slows down)
_REST_LIN_M_S = 1e-3  # a stop ends when the TCP moves slower than this (m/s) ...
_REST_ANG_RAD_S = 1e-2  # ... and turns slower than this (rad/s)
_STOP_SETTLE_MAX_S = 0.5  # after the stop ramp the arm has this long (physics time, s) to come to rest

#: UR5e Denavit–Hartenberg parameters (Universal Robots' published kinematics; base → tool0 flange), m / rad.
UR5E_DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
UR5E_DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
UR5E_DH_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
_DH_CHECK_TOL_M = 1e-4  # the corrected model must match the DH forward kinematics this closely (m)
#: the UR controller's base frame is the MJCF's ``base`` body turned 180° about z (wxyz quaternion)
_BASE_QUAT_UR = (0.0, 0.0, 0.0, 1.0)

def ur5e_fk_dh(q: np.ndarray, tcp_offset: float = 0.0) -> np.ndarray:
    """UR5e forward kinematics from the DH parameters: ``T_base_tcp`` [4, 4] in the UR controller's base frame
    (what ``getActualTCPPose`` reports) for joints ``q`` [6] (rad), the TCP ``tcp_offset`` m along the flange
    z axis (``setTcp([0, 0, tcp_offset, 0, 0, 0])``)."""
    T = np.eye(4)
    for qi, d, a, al in zip(np.asarray(q, float), UR5E_DH_D, UR5E_DH_A, UR5E_DH_ALPHA):
        ct, st, ca, sa = np.cos(qi), np.sin(qi), np.cos(al), np.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    tcp = np.eye(4)
    tcp[2, 3] = float(tcp_offset)
    return T @ tcp


def _to_ur_kinematics(spec: Any) -> None:
    """Make robosuite's UR5e MJCF the UR controller's kinematics: its base turned 180° about z (MuJoCo's world =
    the UR base frame) and its link offsets set to the DH values (robosuite's differ by up to 2 mm: shoulder
    0.163 m — the base is lowered 0.5 mm instead —, wrist 0.392 / 0.1 / 0.098 m, wrist offsets summing to
    0.134 m). Bodies missing in another MJCF are
    left alone; :class:`UR5eSim` then checks the result against :func:`ur5e_fk_dh`."""
    base, shoulder = spec.body("base"), spec.body("shoulder_link")
    if base is not None:
        base.quat = list(_BASE_QUAT_UR)
        if shoulder is not None:  # shoulder height d1: the whole arm moves (lowering the shoulder link inside its
            # base would make their collision geoms touch and brake the shoulder pan joint)
            base.pos = [float(base.pos[0]), float(base.pos[1]), UR5E_DH_D[0] - float(shoulder.pos[2])]
    up, fore = spec.body("upper_arm_link"), spec.body("forearm_link")
    fixes = {"forearm_link": lambda p: [p[0], p[1], -UR5E_DH_A[1]],
             "wrist_1_link": lambda p: [p[0], p[1], -UR5E_DH_A[2]],
             "wrist_3_link": lambda p: [p[0], p[1], UR5E_DH_D[4]],
             FLANGE_BODY: lambda p: [p[0], UR5E_DH_D[5], p[2]]}
    if up is not None and fore is not None:  # the y offsets of upper arm, forearm and wrist 2 sum to d4
        fixes["wrist_2_link"] = lambda p: [p[0], UR5E_DH_D[3] - float(up.pos[1]) - float(fore.pos[1]), p[2]]
    for name, fix in fixes.items():
        b = spec.body(name)
        if b is not None:
            b.pos = fix([float(v) for v in b.pos])


def ur5e_mjcf_path(path: str | None = None) -> Path:
    """The UR5e MJCF: ``path`` or robosuite 1.4.1's ``models/assets/robots/ur5e/robot.xml`` (found without
    importing robosuite).

    Raises:
        DeployError: the file does not exist / robosuite is not installed.
    """
    if path:
        p = Path(path)
    else:
        spec = importlib.util.find_spec("robosuite")
        if spec is None or not spec.submodule_search_locations:
            raise DeployError("robot.model=null needs robosuite's UR5e MJCF: pip install 'umi-aug[robomimic]' "
                              "(robosuite==1.4.1), or set robot.model to a UR5e MJCF file")
        p = Path(list(spec.submodule_search_locations)[0]) / "models/assets/robots/ur5e/robot.xml"
    if not p.is_file():
        raise DeployError(f"robot.model={str(p)!r}: no such MJCF file")
    return p


def base_pose_matrix(base_pose: list[float]) -> np.ndarray:
    """``[x, y, z, yaw_deg]`` of the robot base in the scene (table-tag) frame → ``T_world_base`` [4, 4]."""
    x, y, z, yaw = (float(v) for v in base_pose)
    c, s = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, z]
    return T


@dataclass
class SimURConfig:
    """The ``robot:`` block of ``configs/robot/sim_ur5e.yaml`` (the fields the runner shares with
    :class:`~umi_aug.deploy.ur_rtde.URConfig`, plus the simulation's).

    Attributes:
        robot_type: ``ur5e`` (500 Hz). tcp_offset: TCP along the flange axis (m).
        obs_latency, action_latency: as the real robot (s). max_pos_speed, max_rot_speed: interpolator limits.
        watchdog_s: stop when the runner has not beaten the heartbeat for this long (s).
        joints_init: start joint angles (deg). base_pose: ``[x, y, z, yaw_deg]`` of the base in the scene.
        response_latency: the arm follows the servo target this much later (s; the real arm's response, which
            ``action_latency`` compensates; 0 = immediately).
        max_joint_speed: joint target speed limit (rad/s; at most the UR5e's 180°/s).
        allow_fast_speeds: as :class:`~umi_aug.deploy.ur_rtde.URConfig` (speed bounds of UMI's eval instead of
            UR's defaults).
        kp: joint PD stiffness per joint (N·m/rad); damping is critical for the link inertia (``kd_ratio``).
        max_tracking_error_rad: joint tracking error that triggers the protective stop.
        max_ik_error_m: IK residual (m) that, held for ``unreachable_s``, triggers the protective stop.
        stop_deceleration: TCP deceleration of every stop (m/s²; :class:`StopRamp`): ur-rtde's ``servoStop(a)``,
            whose default ``a`` is 10 m/s² (``rtde_control_interface.h``; UMI's controller calls it without
            arguments). Bounded by :data:`~umi_aug.deploy.safety.BOUNDS`.
        stop_rot_deceleration: TCP angular deceleration of every stop (rad/s²): 10·π, so the rotation-speed bound
            (π rad/s) stops in the 0.1 s that 10 m/s² needs for the TCP-speed bound (1 m/s) (``servoStop`` has
            one linear rate; a pure rotation needs its own).
        model: UR5e MJCF path (null: robosuite's).
    """

    robot_type: str = "ur5e"
    tcp_offset: float = 0.235
    obs_latency: float = 0.0001
    action_latency: float = 0.1
    max_pos_speed: float = 0.25
    max_rot_speed: float = 0.6
    watchdog_s: float = 1.0
    joints_init: list[float] = field(default_factory=lambda: [72.77, -97.94, 90.45, -82.5, -90.0, 162.77])
    base_pose: list[float] = field(default_factory=lambda: [0.0, -0.35, 0.0, 180.0])
    kp: list[float] = field(default_factory=lambda: [3000.0, 3000.0, 2000.0, 400.0, 400.0, 200.0])
    kd_ratio: float = 1.0
    response_latency: float = 0.1
    max_joint_speed: float = float(np.pi)
    max_tracking_error_rad: float = 0.2
    max_ik_error_m: float = 0.005
    unreachable_s: float = 0.1
    stop_deceleration: float = 10.0
    stop_rot_deceleration: float = 10.0 * math.pi
    model: str | None = None
    allow_fast_speeds: bool = False

    @property
    def frequency(self) -> float:
        return CONTROL_RATE_HZ

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "robot") -> "SimURConfig":
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        c = cls(**{k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in m.items()})
        if c.robot_type != "ur5e":
            raise DeployError(f"{where}.robot_type={c.robot_type!r}; the simulation has the 'ur5e' only")
        require_positive(where, c, ("action_latency", "kd_ratio", "max_tracking_error_rad", "max_ik_error_m",
                             "unreachable_s"), DeployError)
        check_robot_limits(c, where)
        if not 0 <= c.tcp_offset < 0.5:
            raise DeployError(f"{where}.tcp_offset={c.tcp_offset} m must be in [0, 0.5)")
        if not 0 <= c.response_latency <= 1.0:
            raise DeployError(f"{where}.response_latency={c.response_latency} s must be in [0, 1]")
        for k, n in (("joints_init", 6), ("base_pose", 4), ("kp", 6)):
            v = getattr(c, k)
            if len(v) != n or not np.isfinite(np.asarray(v, float)).all():
                raise DeployError(f"{where}.{k} must be {n} finite numbers, got {v}")
        if min(c.kp) <= 0:
            raise DeployError(f"{where}.kp must be > 0, got {c.kp}")
        return c


class UR5eSim:
    """MuJoCo UR5e: joint PD control with gravity compensation, TCP pose/speed, DLS inverse kinematics.

    Args:
        cfg: :class:`SimURConfig` (model path, TCP offset, gains).
    """

    def __init__(self, cfg: SimURConfig) -> None:
        self._mj = mj = import_mujoco()
        path = ur5e_mjcf_path(cfg.model)
        try:
            spec = mj.MjSpec.from_file(str(path))
            spec.compiler.degree = False  # robosuite's MJCF gives radians (its arena's compiler setting)
            flange = spec.body(FLANGE_BODY)
            if flange is None:
                raise DeployError(f"robot.model={str(path)!r}: no body {FLANGE_BODY!r} (the UR5e tool flange)")
            flange.add_site(name=TCP_SITE, pos=[0.0, 0.0, float(cfg.tcp_offset)])
            _to_ur_kinematics(spec)
            for name in JOINT_NAMES:  # reflected motor/gearbox inertia (the MJCF has none): keeps PD stable
                j = spec.joint(name)
                if j is not None:
                    j.armature = _ARMATURE
            self.model = spec.compile()
        except ValueError as exc:
            raise DeployError(f"robot.model={str(path)!r}: MuJoCo cannot compile it ({exc})") from exc
        m = self.model
        jids = [mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, n) for n in JOINT_NAMES]
        if min(jids) < 0:
            raise DeployError(f"robot.model={str(path)!r}: joints {JOINT_NAMES} not all found")
        self._ik = ArmIK(m, TCP_SITE, JOINT_NAMES, owner="UR5eSim")  # its own MjData: IK leaves the state alone
        self.qadr, self.dadr, self.lo, self.hi, self.site = (self._ik.qadr, self._ik.dadr, self._ik.lo, self._ik.hi,
                                                             self._ik.site)
        act = {int(m.actuator_trnid[a][0]): a for a in range(m.nu)}
        self.tau_max = np.array([m.actuator_ctrlrange[act[j]][1] if j in act else 150.0 for j in jids])
        self.data = mj.MjData(m)
        self.kp = np.asarray(cfg.kp, float)
        self.kd_ratio = float(cfg.kd_ratio)
        self.dt = float(m.opt.timestep)
        self._jacp, self._jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        self._check_against_dh(str(path), float(cfg.tcp_offset))

    def _check_against_dh(self, path: str, tcp_offset: float) -> None:
        """The TCP of the model at a few fixed joint sets equals the UR5e DH forward kinematics (m)."""
        qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (8, 6))
        err = max(float(np.abs(self.fk(q)[:3, 3] - ur5e_fk_dh(q, tcp_offset)[:3, 3]).max()) for q in qs)
        if err > _DH_CHECK_TOL_M:
            raise DeployError(f"robot.model={path!r}: its TCP differs from the UR5e DH kinematics by {1000 * err:.1f} "
                              f"mm (the simulation must use the UR controller's base frame and link lengths)")

    # ------------------------------------------------------------------ state
    def reset(self, q: np.ndarray) -> None:
        d = self.data
        d.qpos[:] = 0.0
        d.qvel[:] = 0.0
        d.qpos[self.qadr] = q
        self._mj.mj_forward(self.model, d)

    def forward(self) -> None:
        """Recompute the kinematics for the current joints (after ``mj_step`` the site pose and Jacobian are those
        of the joints before the step's integration, 2 ms old)."""
        self._mj.mj_forward(self.model, self.data)

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[self.qadr].copy()

    @property
    def qd(self) -> np.ndarray:
        return self.data.qvel[self.dadr].copy()

    def tcp_T(self) -> np.ndarray:
        """[4, 4] TCP pose in the base frame (m), from the current kinematics."""
        return site_pose(self.data, self.site)

    def tcp_pose(self) -> np.ndarray:
        """[6] TCP pose in the base frame (m, rotation vector)."""
        d = self.data
        return np.concatenate([d.site_xpos[self.site], rodrigues_log(d.site_xmat[self.site].reshape(3, 3))])

    def tcp_speed(self) -> np.ndarray:
        """[6] TCP linear (m/s) and angular (rad/s) velocity in the base frame (as ``getActualTCPSpeed``)."""
        self._mj.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site)
        qd = self.data.qvel
        return np.concatenate([self._jacp @ qd, self._jacr @ qd])

    def fk(self, q: np.ndarray) -> np.ndarray:
        """[4, 4] TCP pose in the base frame (m) at joints ``q`` [6] rad (the IK's private data; the simulation state
        is not touched)."""
        return self._ik.fk(q)

    # ------------------------------------------------------------------ control
    def ik(self, T_goal: np.ndarray, q0: np.ndarray, iters: int = 5) -> tuple[np.ndarray, float, float]:
        """Damped least squares from ``q0`` [6] (rad) towards the TCP pose ``T_goal`` [4, 4] (base frame, m), at
        most ``iters`` iterations (:meth:`~umi_aug.sim.ik.ArmIK.solve_dls` with :data:`UR5E_DLS`; joints within
        limits). Returns ``(q, position residual m, rotation residual rad)``."""
        q, pos_err, rot_err, _ = self._ik.solve_dls(T_goal, q0, UR5E_DLS, max_iters=iters)
        return q, pos_err, rot_err

    def step(self, q_target: np.ndarray, qd_target: np.ndarray | None = None,
             qdd_target: np.ndarray | None = None) -> None:
        """One physics step with joint PD torques towards ``q_target`` / ``qd_target`` (rad, rad/s; velocity
        feed-forward) plus gravity/Coriolis compensation and, with ``qdd_target`` (rad/s²), the inertia
        feed-forward ``M·q̈`` (the stop ramp: the controller's own trajectory, tracked with its model), clipped to
        the joint torque limits."""
        m, d = self.model, self.data
        inertia = np.maximum(d.qM[m.dof_Madr[self.dadr]], 1e-3)
        kd = self.kd_ratio * 2.0 * np.sqrt(self.kp * inertia)
        qd_t = 0.0 if qd_target is None else qd_target
        tau = self.kp * (q_target - self.q) + kd * (qd_t - self.qd) + d.qfrc_bias[self.dadr]
        if qdd_target is not None:
            vec, res = np.zeros(m.nv), np.zeros(m.nv)
            vec[self.dadr] = qdd_target
            self._mj.mj_mulM(m, d, res, vec)
            tau = tau + res[self.dadr]
        d.qfrc_applied[self.dadr] = np.clip(tau, -self.tau_max, self.tau_max)
        self._mj.mj_step(m, d)


@dataclass
class StopRamp:
    """The stop of the simulated arm, as ur-rtde's ``servoStop(a)`` (the controller's ``stopl(a)``): from the TCP
    pose ``T0`` moving with ``twist``, the TCP keeps its direction of motion while its speed falls linearly to zero
    in ``duration`` s — neither an instant freeze nor a run to the last target.

    The displacement after ``τ`` s is ``g(τ)·twist`` with ``g(τ) = τ − τ²/(2·duration)`` (``duration/2`` once
    ``τ ≥ duration``): position ``p0 + v·g(τ)``, orientation ``exp(ω·g(τ))·R0``. ``duration = max(|v|/a_lin,
    |ω|/a_rot)``, so the linear deceleration is at most ``a_lin`` (m/s²) and the angular one at most ``a_rot``
    (rad/s²); the stop distance is ``|v|·duration/2`` (``|v|²/(2·a_lin)`` when the linear term decides).

    Attributes:
        T0: [4, 4] TCP pose in the robot base frame at the start of the stop (m).
        twist: [6] TCP velocity at the start, base frame: linear (m/s), angular (rad/s).
        duration: time to rest (s); 0 when the arm already stands.
    """

    T0: np.ndarray
    twist: np.ndarray
    duration: float

    @classmethod
    def start(cls, T0: np.ndarray, twist: np.ndarray, a_lin: float, a_rot: float) -> "StopRamp":
        """The ramp from pose ``T0`` [4, 4] and ``twist`` [6] with decelerations ``a_lin`` (m/s²), ``a_rot``
        (rad/s²)."""
        tw = np.asarray(twist, float).reshape(6)
        duration = max(float(np.linalg.norm(tw[:3])) / a_lin, float(np.linalg.norm(tw[3:])) / a_rot)
        return cls(np.asarray(T0, float).copy(), tw, duration)

    def g(self, tau: float) -> float:
        """Distance factor ``g(τ)`` (s): the displacement after ``tau`` s is ``g(τ)·twist``."""
        if self.duration <= 0.0:
            return 0.0
        tau = min(max(float(tau), 0.0), self.duration)
        return tau - tau * tau / (2.0 * self.duration)

    def pose(self, tau: float) -> np.ndarray:
        """[6] TCP target ``tau`` s after the start of the stop (base frame: m, rotation vector)."""
        g = self.g(tau)
        R = cv2.Rodrigues(np.ascontiguousarray(self.twist[3:] * g))[0] @ self.T0[:3, :3]
        return np.concatenate([self.T0[:3, 3] + self.twist[:3] * g, rodrigues_log(R)])


class SimServoLoop:
    """The simulated controller loop (the counterpart of :class:`~umi_aug.deploy.ur_rtde.URServoLoop`; runnable
    in-thread with a fake clock).

    Every way out decelerates the arm to rest first, as ``servoStop`` does on the real arm (:class:`StopRamp`,
    ``robot.stop_deceleration`` / ``stop_rot_deceleration``; physics keeps running, states keep being published):
    the runner's stop (``stop_event``), a ``("stop",)`` command, the heartbeat watchdog, the runner's death (parent
    check, or the parent-death signal through :meth:`request_stop`) and the simulated protective stops. The first
    two then return; the others raise :class:`SafetyStop` once the arm stands. :attr:`last_stop` describes the
    stop (for logs and tests).

    Args:
        cfg: :class:`SimURConfig`. commands: queue of ``("enable",)`` / ``("waypoint", pose[6], t)`` /
            ``("stop",)``; before ``enable`` the arm stands at ``joints_init`` (observe-only, as the real
            controller before its control interface is opened) and a waypoint is an error.
        state: ring buffer with :data:`~umi_aug.deploy.arm_process.STATE_FIELDS`. stop_event: set → leave.
        heartbeat: shared double, the runner's last heartbeat. clock: time base (``time.monotonic``).
        enabled: shared int set to 1 on ``enable``. parent_pid: the runner's pid (None: not checked).
    """

    def __init__(self, cfg: SimURConfig, commands: Any, state: SharedStateBuffer, stop_event: Any, heartbeat: Any,
                 clock: Clock | None = None, stats: Any = None, enabled: Any = None,
                 parent_pid: int | None = None) -> None:
        self.cfg, self.commands, self.state, self.stop_event = cfg, commands, state, stop_event
        self.heartbeat = heartbeat
        self.enabled, self.parent_pid = enabled, parent_pid
        self.clock = clock or MonotonicClock()
        self.n_periods = 0
        self.n_physics_steps = 0
        self.n_dropped_steps = 0
        self.stats = stats  # optional shared [periods, physics steps, dropped steps]
        self._requested: str | None = None
        #: the last stop: reason, fault (raised), clock time it began (s), speeds then (m/s, rad/s), ramp
        #: duration and physics time to rest (s), TCP travel from the start of the stop to rest (m)
        self.last_stop: dict[str, Any] | None = None

    def request_stop(self, reason: str) -> None:
        """Ask the loop to decelerate to rest and then raise :class:`SafetyStop` with ``reason`` (safe from a
        signal handler: it only records the request; the first one wins)."""
        if self._requested is None:
            self._requested = str(reason)

    def _stop_check(self, t_now: float) -> tuple[str, bool] | None:
        """Why the loop must stop now (start of a period at clock time ``t_now``, s): ``(reason, fault)`` or None."""
        if self._requested is not None:
            return self._requested, True
        if self.stop_event.is_set():
            return "stopped by the runner", False
        age = t_now - float(self.heartbeat.value)
        if age > self.cfg.watchdog_s:
            return (f"watchdog: no heartbeat from the runner for {age:.2f} s > robot.watchdog_s="
                    f"{self.cfg.watchdog_s}"), True
        if not parent_alive(self.parent_pid):
            return f"the runner process {self.parent_pid} died", True
        return None

    def _steps_due(self, sim: UR5eSim, t_now: float, t0: float, n_sub: int) -> int:
        """Physics steps this period: keep up with the clock (late periods catch up, at most ``_MAX_CATCH_UP``;
        more is dropped and counted)."""
        due = int((t_now - t0) / sim.dt) + n_sub - self.n_physics_steps - self.n_dropped_steps
        n = min(max(due, 1), _MAX_CATCH_UP)
        self.n_dropped_steps += max(due - n, 0)
        return n

    def _track(self, sim: UR5eSim, pose: np.ndarray, q_prev: np.ndarray, n: int, feed_forward: bool = True,
               qd_prev: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Servo the arm for ``n`` physics steps towards the TCP ``pose`` [6] (base frame): IK warm-started at the
        last joint target ``q_prev``, the joint speed limit (UR5e: 180°/s), then the joint target moves linearly
        from ``q_prev`` over the ``n`` steps (velocity feed-forward unless ``feed_forward`` is False; with
        ``qd_prev``, the last period's target velocity, also the inertia feed-forward of the change).

        Returns:
            (new joint target [6] rad, its velocity [6] rad/s, IK position residual m)
        """
        q_ik, pos_err, _ = sim.ik(pos_rotvec_to_pose(pose), q_prev)
        lim = self.cfg.max_joint_speed * n * sim.dt
        q_target = q_prev + np.clip(q_ik - q_prev, -lim, lim)
        qd_target = (q_target - q_prev) / (n * sim.dt) if feed_forward else np.zeros(6)
        qdd_target = None if qd_prev is None else (qd_target - qd_prev) / (n * sim.dt)
        for j in range(1, n + 1):
            sim.step(q_prev + (q_target - q_prev) * (j / n), qd_target, qdd_target)
        self.n_physics_steps += n
        return q_target, qd_target, pos_err

    def _publish(self, sim: UR5eSim, target: np.ndarray) -> None:
        """One state record (the joints, TCP pose and speed after this period's physics steps) and the counters."""
        sim.forward()  # TCP pose / speed of the joints now, not of the last step's start
        self.state.put({"timestamp": self.clock.now() - self.cfg.obs_latency, "tcp_pose": sim.tcp_pose(),
                        "tcp_speed": sim.tcp_speed(), "q": sim.q, "qd": sim.qd, "target_pose": target})
        self.n_periods += 1
        if self.stats is not None:
            self.stats[:] = [self.n_periods, self.n_physics_steps, self.n_dropped_steps]

    def run(self, sim: UR5eSim | None = None) -> None:
        """Observe until enabled, then servo until a stop; decelerate to rest (:meth:`_decelerate`); return, or
        raise :class:`SafetyStop` for a fault (watchdog, runner died, protective stop)."""
        cfg = self.cfg
        sim = sim or UR5eSim(cfg)
        sim.reset(np.deg2rad(cfg.joints_init))
        dt = 1.0 / cfg.frequency
        n_sub = max(1, int(round(dt / sim.dt)))
        t0 = self.clock.now()
        interp = PoseTrajectoryInterpolator([t0], [sim.tcp_pose()])
        q_target = sim.q
        last_wp: float | None = None
        t_bad: float | None = None
        delayed: collections.deque = collections.deque()
        armed = False
        while True:
            t_now = self.clock.now()
            stop = self._stop_check(t_now)
            if stop is not None:
                break
            pose = interp(t_now)
            delayed.append((t_now, pose))  # the arm acts on the servo target response_latency later
            while len(delayed) > 1 and delayed[1][0] <= t_now - cfg.response_latency:
                delayed.popleft()
            n = self._steps_due(sim, t_now, t0, n_sub)
            q_target, _, pos_err = self._track(sim, delayed[0][1], q_target, n, feed_forward=self.n_periods > 0)
            if pos_err > cfg.max_ik_error_m:
                t_bad = t_now if t_bad is None else t_bad
                if t_now - t_bad > cfg.unreachable_s:
                    stop = (f"protective stop (sim): target TCP pose {np.round(pose[:3], 4).tolist()} m is "
                            f"unreachable (IK residual {1000 * pos_err:.1f} mm for {t_now - t_bad:.2f} s)", True)
            else:
                t_bad = None
            track = float(np.abs(q_target - sim.q).max())
            if stop is None and track > cfg.max_tracking_error_rad:
                stop = (f"protective stop (sim): joint tracking error {track:.3f} rad > "
                        f"robot.max_tracking_error_rad={cfg.max_tracking_error_rad}", True)
            self._publish(sim, pose)
            if stop is None and not armed:
                cmd = poll_enable(self.commands)
                armed = cmd == "enable"
                if cmd == "stop":
                    stop = ("stop command", False)
                if armed and self.enabled is not None:
                    self.enabled.value = 1
            if stop is None and armed:
                interp, last_wp, got_stop = drain_waypoint_commands(self.commands, interp, last_wp, t_now + dt,
                                                                    cfg.max_pos_speed, cfg.max_rot_speed)
                if got_stop:
                    stop = ("stop command", False)
            self.clock.sleep_until(t_now + dt)  # as ur-rtde's waitPeriod: a late period is not made up
            if stop is not None:
                break
        self._decelerate(sim, t0, n_sub, *stop)
        if stop[1]:
            raise SafetyStop(stop[0])

    def _decelerate(self, sim: UR5eSim, t0: float, n_sub: int, reason: str, fault: bool) -> None:
        """Bring the TCP to rest as ``servoStop`` does: from the measured pose and velocity along
        :class:`StopRamp` (``robot.stop_deceleration`` m/s², ``stop_rot_deceleration`` rad/s²), timed by the
        physics steps (not the clock), servoed without the response latency (the controller acts at once); states
        are published every period. Ends when the ramp is over and the TCP speed is below ``_REST_LIN_M_S`` /
        ``_REST_ANG_RAD_S`` — or ``_STOP_SETTLE_MAX_S`` after the ramp (logged). Fills :attr:`last_stop`."""
        cfg = self.cfg
        dt = 1.0 / cfg.frequency
        sim.forward()  # the pose and speed of the joints now (the ramp starts from where the arm is)
        twist = sim.tcp_speed()
        ramp = StopRamp.start(sim.tcp_T(), twist, cfg.stop_deceleration, cfg.stop_rot_deceleration)
        p0, step0 = ramp.T0[:3, 3].copy(), self.n_physics_steps
        self.last_stop = {"reason": reason, "fault": fault, "t_clock": self.clock.now(),
                          "speed_m_s": float(np.linalg.norm(twist[:3])),
                          "rot_speed_rad_s": float(np.linalg.norm(twist[3:])), "ramp_s": ramp.duration,
                          "to_rest_s": 0.0, "distance_m": 0.0, "settled": True}
        # the PD target of a physics step is the pose due at the step's start (as in the servo loop, where the arm
        # at steady speed stands on its target when a step begins): the last target was one step back along the
        # current velocity — no jump in the PD error, the feed-forward carries the current speed into the ramp
        q_target, qd_target = sim.q - sim.qd * sim.dt, sim.qd
        settled = self._at_rest(sim)
        while not settled:
            t_now = self.clock.now()
            n = self._steps_due(sim, t_now, t0, n_sub)
            tau_last = (self.n_physics_steps + n - 1 - step0) * sim.dt  # start of this period's last step (s)
            pose = ramp.pose(tau_last)
            q_target, qd_target, _ = self._track(sim, pose, q_target, n, qd_prev=qd_target)
            self._publish(sim, pose)
            tau = (self.n_physics_steps - step0) * sim.dt
            settled = tau >= ramp.duration and self._at_rest(sim)
            if not settled and tau >= ramp.duration + _STOP_SETTLE_MAX_S:
                log.warning("simulated UR5e: not at rest %.2f s after the stop ramp (TCP %.4f m/s); stopping anyway",
                            _STOP_SETTLE_MAX_S, float(np.linalg.norm(sim.tcp_speed()[:3])))
                self.last_stop["settled"] = False
                break
            if not settled:
                self.clock.sleep_until(t_now + dt)
        self.last_stop["to_rest_s"] = (self.n_physics_steps - step0) * sim.dt
        self.last_stop["distance_m"] = float(np.linalg.norm(sim.tcp_pose()[:3] - p0))
        if self.last_stop["speed_m_s"] > _REST_LIN_M_S or self.last_stop["rot_speed_rad_s"] > _REST_ANG_RAD_S:
            log.info("simulated UR5e stop (%s): %.3f m/s → rest in %.3f s over %.1f mm", reason,
                     self.last_stop["speed_m_s"], self.last_stop["to_rest_s"], 1000 * self.last_stop["distance_m"])

    @staticmethod
    def _at_rest(sim: UR5eSim) -> bool:
        v = sim.tcp_speed()
        return bool(np.linalg.norm(v[:3]) < _REST_LIN_M_S and np.linalg.norm(v[3:]) < _REST_ANG_RAD_S)


def stop_time_bound(cfg: SimURConfig) -> float:
    """Longest stop the simulated arm can make (s): from the speed limits at the stop decelerations, plus the
    settling allowance."""
    return (max(cfg.max_pos_speed / cfg.stop_deceleration, cfg.max_rot_speed / cfg.stop_rot_deceleration)
            + _STOP_SETTLE_MAX_S)


def stop_on_signal(loop: SimServoLoop, parent_pid: int, backstop_s: float | None) -> Callable[[int, Any], None]:
    """SIGTERM handler of the simulated arm's process — the parent-death signal it asked for
    (:func:`~umi_aug.deploy.device_process.child_setup`) or a ``terminate()``: the loop decelerates to rest and
    stops (:meth:`SimServoLoop.request_stop`), as the real arm's program does when ur-rtde's watchdog fires.
    ``backstop_s`` s later SIGALRM (default action: terminate) ends the process whatever the loop does (None: no
    backstop; tests)."""
    armed = []

    def handler(signum: int, frame: Any) -> None:
        died = os.getppid() != parent_pid
        loop.request_stop(f"the runner process {parent_pid} died" if died else f"terminated (signal {signum})")
        if backstop_s is not None and not armed:
            armed.append(True)
            signal.alarm(max(1, int(math.ceil(backstop_s))))

    return handler


def _sim_robot_main(cfg: SimURConfig, heartbeat: Any, commands: Any, state: SharedStateBuffer, stop_event: Any,
                    errors: Any, enabled: Any, parent_pid: int) -> None:
    child_setup(parent_pid, death_signal=signal.SIGTERM)  # the runner's death: decelerate, then exit
    loop = SimServoLoop(cfg, commands, state, stop_event, heartbeat, stats=getattr(cfg, "_stats", None),
                        enabled=enabled, parent_pid=parent_pid)
    # the backstop leaves time for the model to load (a death during start-up) and for a loaded machine
    signal.signal(signal.SIGTERM, stop_on_signal(loop, parent_pid, backstop_s=stop_time_bound(cfg) + 10.0))
    try:
        loop.run()
    except BaseException as exc:  # noqa: BLE001 - reported to the runner
        errors.put(str(exc) if isinstance(exc, DeployError) else f"{type(exc).__name__}: {exc}")


class SimUR5eRobot(ArmProcess):
    """:class:`~umi_aug.deploy.interfaces.RobotInterface` of the simulated UR5e: :class:`SimServoLoop` in a child
    process behind the host side it shares with the ur-rtde backend (:class:`~umi_aug.deploy.arm_process.
    ArmProcess`: state ring buffer, command queue, heartbeat thread, error reporting).

    :meth:`sim_stats` reads the loop's counters (periods, physics steps, steps dropped when the machine could
    not keep real time)."""

    process_main = staticmethod(_sim_robot_main)

    def __init__(self, cfg: SimURConfig, ctx: Any = None, capacity: int = 2048, connect_timeout_s: float = 30.0):
        super().__init__(cfg, "simulated UR5e", ctx, capacity, connect_timeout_s)
        self._stats = self._ctx.Array("d", 3, lock=False)
        cfg._stats = self._stats  # travels to the child with the config

    def start(self) -> None:
        import_mujoco()  # chooses MUJOCO_GL once here; the controller process inherits it (no probe there)
        super().start()

    def sim_stats(self) -> dict[str, int]:
        p, n, drop = (int(v) for v in self._stats[:])
        return {"periods": p, "physics_steps": n, "dropped_physics_steps": drop}
