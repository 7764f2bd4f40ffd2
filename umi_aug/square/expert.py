"""Scripted expert for the square task from privileged state (nut pose incl. yaw, peg pose).

Phases: ``approach`` (above the handle, gripper vertical, fingers closing across the handle) → ``descend`` →
``grasp`` (close, hold) → ``lift`` → ``align`` (nut centre over the peg, nut yaw ≡ peg yaw mod 90°) → ``insert``
(lower, keep correcting) → ``release`` (open) → ``retreat`` (up) → ``done``. Each step is a P-controller on the
grip-site pose turned into robosuite's OSC_POSE delta action (world-frame position delta / 0.05 m, world-frame
axis-angle delta / 0.5 rad, clipped to [−1, 1]). Deterministic: no randomness inside the expert.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from umi_aug.geometry import so3_log
from umi_aug.square.commands import POS_SCALE_M, ROT_SCALE_RAD
from umi_aug.square.env import GRIP_SITE, NUT_BODY, PEG_BODY, SquareEnv

__all__ = ["ExpertConfig", "SquareExpert", "PHASES", "nut_yaw_error", "expert_pregrasp_pose", "pregrasp_error",
           "PREGRASP_POS_TOL_M", "PREGRASP_ROT_TOL_DEG"]

PHASES: tuple[str, ...] = ("approach", "descend", "grasp", "lift", "align", "insert", "release", "retreat", "done")


@dataclass(frozen=True)
class ExpertConfig:
    """Gains, heights (metres above the table top) and tolerances of :class:`SquareExpert`."""

    pos_gain: float = 1.0            # fraction of the position error commanded per step
    rot_gain: float = 1.0            # fraction of the rotation error commanded per step
    hover_height: float = 0.08       # above the handle before descending
    grasp_height: float = 0.017      # grip-site height above the table when closing (handle centre: 0.01)
    grasp_offset: float = 0.066      # grasp point along the handle, from the nut centre (handle: 0.029 … 0.079)
    carry_height: float = 0.20       # grip-site height while carrying (peg top is 0.13 above the table)
    insert_height: float = 0.13      # grip-site height to which the nut is lowered (nut ends on the table)
    pos_tol: float = 0.004           # position tolerance to leave approach/descend/lift
    align_pos_tol: float = 0.003     # nut-centre xy tolerance over the peg before inserting
    align_yaw_tol: float = math.radians(3.0)
    rot_tol: float = math.radians(4.0)
    grasp_steps: int = 10            # steps holding position with the gripper closing
    release_steps: int = 8
    retreat_height: float = 0.10     # retreat this far up after release
    phase_timeout: int = 80          # steps after which a phase is left anyway


#: pre-grasp sub-goal tolerance: grip-site position error (m) …
PREGRASP_POS_TOL_M: float = 0.02
#: … and rotation error (deg, modulo the 180° gripper symmetry)
PREGRASP_ROT_TOL_DEG: float = 15.0


def expert_pregrasp_pose(T_world_nut: np.ndarray, table_z: float, cfg: ExpertConfig | None = None) -> np.ndarray:
    """The scripted expert's pre-grasp grip-site pose for a nut pose (its ``approach`` goal).

    Args:
        T_world_nut: np.ndarray,  # [4, 4] nut body pose
        table_z: table-top height, metres.
    Returns:
        T_world_site: np.ndarray,  # [4, 4]: hover point ``hover_height`` above the handle point
                                   # (``grasp_offset`` along nut x), z axis down, x along nut y
    """
    cfg = cfg or ExpertConfig()
    handle = T_world_nut[:3, 3] + cfg.grasp_offset * T_world_nut[:3, 0]
    p = handle + np.array([0.0, 0.0, cfg.hover_height])
    p[2] = max(p[2], table_z + cfg.grasp_height + cfg.hover_height)
    z = np.array([0.0, 0.0, -1.0])
    x = T_world_nut[:3, 1] - z * float(T_world_nut[:3, 1] @ z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = p
    return T


def pregrasp_error(T_site: np.ndarray, T_goal: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad modulo a half turn about the goal's z) of a grip-site pose
    ``T_site`` [4, 4] against a pre-grasp pose ``T_goal`` [4, 4] (world frame)."""
    dp = float(np.linalg.norm(T_site[:3, 3] - T_goal[:3, 3]))
    flip = np.diag([-1.0, -1.0, 1.0])
    dr = min(float(np.linalg.norm(so3_log(T_goal[:3, :3] @ F @ T_site[:3, :3].T))) for F in (np.eye(3), flip))
    return dp, dr


def _wrap(a: float, period: float) -> float:
    """Angle wrapped into [−period/2, period/2)."""
    return (a + 0.5 * period) % period - 0.5 * period


def nut_yaw_error(R_world_nut: np.ndarray, peg_yaw: float = 0.0) -> float:
    """Yaw of the nut relative to the peg modulo the square's 90° symmetry, radians in [−π/4, π/4)."""
    yaw = math.atan2(R_world_nut[1, 0], R_world_nut[0, 0])
    return _wrap(yaw - peg_yaw, 0.5 * math.pi)


def _rotz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class SquareExpert:
    """Stateful scripted policy; call :meth:`reset` at the start of each episode, then :meth:`act` each step."""

    def __init__(self, cfg: ExpertConfig | None = None) -> None:
        self.cfg = cfg or ExpertConfig()
        self.reset()

    def reset(self) -> None:
        self.phase = "approach"
        self._t_phase = 0
        self._R_grasp: np.ndarray | None = None
        self._release_z: float | None = None

    def _next(self, phase: str) -> None:
        self.phase, self._t_phase = phase, 0

    # ------------------------------------------------------------------ helpers
    def _grasp_rotation(self, R_nut: np.ndarray, R_cur: np.ndarray) -> np.ndarray:
        """Grip-site rotation: z down, x (the closing axis) along ±nut y — the sign nearest ``R_cur``."""
        z = np.array([0.0, 0.0, -1.0])
        best, best_ang = None, np.inf
        for s in (1.0, -1.0):
            x = s * R_nut[:, 1]
            x = x - z * float(x @ z)
            x /= np.linalg.norm(x)
            R = np.stack([x, np.cross(z, x), z], axis=1)
            ang = float(np.linalg.norm(so3_log(R @ R_cur.T)))
            if ang < best_ang:
                best, best_ang = R, ang
        return best

    def _action(self, p_cur, R_cur, p_goal, R_goal, gripper: float) -> np.ndarray:
        cfg = self.cfg
        dp = (np.asarray(p_goal) - p_cur) * cfg.pos_gain / POS_SCALE_M
        dr = so3_log(R_goal @ R_cur.T) * cfg.rot_gain / ROT_SCALE_RAD
        a = np.concatenate([np.clip(dp, -1, 1), np.clip(dr, -1, 1), [gripper]])
        return a

    # ------------------------------------------------------------------ policy
    def act(self, env: SquareEnv) -> np.ndarray:
        """Next 7-D action from the privileged state of ``env``."""
        cfg = self.cfg
        G = env.site_pose(GRIP_SITE)
        p, R = G[:3, 3], G[:3, :3]
        nut = env.body_pose(NUT_BODY)
        handle = nut[:3, 3] + cfg.grasp_offset * nut[:3, 0]  # on the handle, clear of the ring
        peg = env.body_pose(PEG_BODY)
        table_z = float(env.rs.table_offset[2])
        peg_yaw = math.atan2(peg[1, 0], peg[0, 0])
        self._t_phase += 1
        timeout = self._t_phase > cfg.phase_timeout
        open_, close = -1.0, 1.0

        if self.phase == "approach":
            R_goal = self._grasp_rotation(nut[:3, :3], R)
            goal = handle + np.array([0.0, 0.0, cfg.hover_height])
            goal[2] = max(goal[2], table_z + cfg.grasp_height + cfg.hover_height)
            err_p = np.linalg.norm(goal - p)
            err_r = np.linalg.norm(so3_log(R_goal @ R.T))
            if (err_p < cfg.pos_tol and err_r < cfg.rot_tol) or timeout:
                self._R_grasp = R_goal
                self._next("descend")
            return self._action(p, R, goal, R_goal, open_)
        if self.phase == "descend":
            R_goal = self._grasp_rotation(nut[:3, :3], R)
            goal = handle.copy()
            goal[2] = table_z + cfg.grasp_height
            if np.linalg.norm(goal - p) < 0.5 * cfg.pos_tol or timeout:
                self._next("grasp")
            return self._action(p, R, goal, R_goal, open_)
        if self.phase == "grasp":
            goal = p.copy()
            if self._t_phase >= cfg.grasp_steps:
                self._next("lift")
            return self._action(p, R, goal, R, close)
        if self.phase == "lift":
            goal = p.copy()
            goal[2] = table_z + cfg.carry_height
            if abs(goal[2] - p[2]) < cfg.pos_tol or timeout:
                self._next("align")
            return self._action(p, R, goal, R, close)
        if self.phase in ("align", "insert"):
            dyaw = nut_yaw_error(nut[:3, :3], peg_yaw)
            R_goal = _rotz(-dyaw) @ R
            off = nut[:2, 3] - p[:2]  # nut centre relative to the grip site, carried along by the rotation
            off_after = (_rotz(-dyaw)[:2, :2] @ off)
            goal = p.copy()
            goal[:2] = peg[:2, 3] - off_after
            xy_err = float(np.linalg.norm(nut[:2, 3] - peg[:2, 3]))
            if self.phase == "align":
                goal[2] = table_z + cfg.carry_height
                if (xy_err < cfg.align_pos_tol and abs(dyaw) < cfg.align_yaw_tol) or timeout:
                    self._next("insert")
            else:
                goal[2] = table_z + cfg.insert_height
                if p[2] - goal[2] < cfg.pos_tol or timeout:
                    self._next("release")
            return self._action(p, R, goal, R_goal, close)
        if self.phase == "release":
            if self._t_phase >= cfg.release_steps:
                self._release_z = float(p[2])
                self._next("retreat")
            return self._action(p, R, p, R, open_)
        if self.phase == "retreat":
            goal = p.copy()
            goal[2] = (self._release_z or p[2]) + cfg.retreat_height
            if abs(goal[2] - p[2]) < cfg.pos_tol or timeout:
                self._next("done")
            return self._action(p, R, goal, R, open_)
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, open_])
