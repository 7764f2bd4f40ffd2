"""Absolute commanded targets of the square env's OSC_POSE controller, and the exact way back to its delta actions.

The square env's controller (robosuite OSC_POSE, delta input, 20 Hz) takes at step ``t`` a world-frame delta
``a = [dp / 0.05 m, rotvec / 0.5 rad, gripper]`` (each in [−1, 1]) and drives the grip site towards the ABSOLUTE
goal ``p_t + 0.05·a_pos``, ``exp(0.5·a_rot) · R_t`` (``robosuite.utils.control_utils.set_goal_position`` /
``set_goal_orientation``: the rotation delta left-multiplies the current orientation, so it moves every frame
fixed to the hand, the TCP's camera axes included, the same way; a rotation delta of exactly zero keeps the
previous orientation goal). Within one step the arm covers only part of the
way (about 11 % of a step from rest, ~1/3 in steady motion), so the poses an arm REACHED are not what it was TOLD:
a policy that outputs reached poses and is executed by turning each into a delta with the same rule runs ~35 %
slower than its data (issue #29, B2). Labels are therefore the commanded targets (what Diffusion Policy's
``abs_action`` does for robomimic), and :func:`osc_delta_from_target` turns a target back into exactly the delta
that produced it.

Layout (one arm): ``[x, y, z, rx, ry, rz, w]`` = grip-site position (m), TCP rotation vector (rad, world frame,
OpenCV camera axes as ``T_world_tcp``), gripper width target (m: 0 = the close command, :data:`GRIPPER_OPEN_M`
= the open command). Row ``t`` of an episode's targets is the target commanded at step ``t − 1`` (the pose the arm
was driven towards for time ``t``; row 0 = the start pose with the first gripper command), so — as with UMI's
pose labels — row ``t`` is near the observed pose ``t`` and a policy executes rows ``1 … n`` of its chunk.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import pos_rotvec_to_pose, pose_to_pos_rotvec, so3_exp, so3_log

__all__ = ["POS_SCALE_M", "ROT_SCALE_RAD", "GRIPPER_OPEN_M", "GRIPPER_CLOSE_BELOW_M", "PATH_COMMAND_LEAD_STEPS",
           "commanded_targets", "path_command_targets",
           "osc_delta_from_target", "gripper_width_target", "gripper_command"]

#: OSC_POSE output_max of robomimic's square env_meta: metres / radians per unit action.
POS_SCALE_M: float = 0.05
ROT_SCALE_RAD: float = 0.5
#: the Panda's finger separation when fully open (two slide joints of 0 … 0.04 m each): the open command's width
GRIPPER_OPEN_M: float = 0.08
#: a width target below this is the close command (+1), at or above it the open command (−1)
GRIPPER_CLOSE_BELOW_M: float = 0.5 * GRIPPER_OPEN_M


def gripper_width_target(command: np.ndarray) -> np.ndarray:
    """Gripper commands (+1 / >0 close, −1 / ≤0 open; robosuite's Panda integrates their sign) → width targets
    (0 m closed, :data:`GRIPPER_OPEN_M` open)."""
    return np.where(np.asarray(command, np.float64) > 0, 0.0, GRIPPER_OPEN_M)


def gripper_command(width_target: float, close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> float:
    """A width target → the Panda gripper command: +1 (close) below ``close_below_m``, −1 (open) otherwise.
    The inverse of :func:`gripper_width_target` for every command the scripted expert gives (it gives ±1 only)."""
    return 1.0 if float(width_target) < close_below_m else -1.0


def commanded_targets(T_world_tcp: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The absolute targets an episode's OSC_POSE delta actions commanded, one row per step (module docstring).

    Args:
        T_world_tcp: np.ndarray,  # [T, 4, 4] TCP poses observed before each action (grip site, OpenCV axes), m
        actions: np.ndarray,  # [T, 7] the delta actions (clipped to [−1, 1] as the controller clips them)
    Returns:
        np.ndarray,  # [T, 7] float64: row 0 = [pose 0, width target of action 0]; row t = the target of action
                     # t − 1 (position, rotation vector, width target)
    Raises:
        SimError: shapes that differ, non-finite values.
    """
    T = np.asarray(T_world_tcp, np.float64)
    a = np.asarray(actions, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or a.shape != (len(T), 7) or len(T) < 1:
        raise SimError(f"commanded_targets: need T_world_tcp [T, 4, 4] and actions [T, 7], got {T.shape}, {a.shape}")
    if not (np.isfinite(T).all() and np.isfinite(a).all()):
        raise SimError("commanded_targets: poses or actions hold NaN/Inf")
    a = np.clip(a, -1.0, 1.0)
    out = np.empty((len(T), 7))
    out[0, :6] = pose_to_pos_rotvec(T[0])
    goal = np.empty((len(T) - 1, 4, 4))
    goal[:] = np.eye(4)
    goal[:, :3, 3] = T[:-1, :3, 3] + POS_SCALE_M * a[:-1, :3]
    rot = so3_exp(ROT_SCALE_RAD * a[:-1, 3:6]) @ T[:-1, :3, :3]
    # robosuite's OSC keeps its previous orientation goal when the rotation delta is exactly zero (set_goal:
    # "only update goal orientation if there is a valid delta ori value"); the goal after a reset is the start pose
    prev = T[0, :3, :3]
    for t in range(len(T) - 1):
        if not np.any(a[t, 3:6] != 0.0):
            rot[t] = prev
        prev = rot[t]
    goal[:, :3, :3] = rot
    out[1:, :6] = pose_to_pos_rotvec(goal)
    out[0, 6] = gripper_width_target(a[0, 6])
    out[1:, 6] = gripper_width_target(a[:-1, 6])
    return out


def osc_delta_from_target(T_world_tcp: np.ndarray, target: np.ndarray,
                          close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> np.ndarray:
    """An absolute target ``[7]`` → the OSC_POSE delta action that commands it from the current TCP pose (the
    exact inverse of :func:`commanded_targets` for an unclipped command; clipped to [−1, 1] otherwise).

    Args:
        T_world_tcp: np.ndarray,  # [4, 4] current TCP pose (grip site, OpenCV camera axes), metres
        target: np.ndarray,  # [7] position (m), rotation vector (rad), gripper width target (m)
    Returns:
        np.ndarray,  # [7] in [−1, 1]: world position delta / 0.05 m, world axis-angle delta / 0.5 rad, gripper ±1
    Raises:
        SimError: a target that is not a finite [7] vector.
    """
    t = np.asarray(target, dtype=np.float64)
    if t.shape != (7,) or not np.isfinite(t).all():
        raise SimError(f"osc_delta_from_target: target must be finite [7], got {t.shape} {t}")
    T_t = pos_rotvec_to_pose(t[:6])
    dp = (T_t[:3, 3] - T_world_tcp[:3, 3]) / POS_SCALE_M
    dr = so3_log(T_t[:3, :3] @ T_world_tcp[:3, :3].T) / ROT_SCALE_RAD
    return np.concatenate([np.clip(dp, -1, 1), np.clip(dr, -1, 1), [gripper_command(t[6], close_below_m)]])


#: Lead (control steps) of the commanded target ahead of the pose on a smooth path: in steady motion the square
#: env's OSC trails its goal by ~3 steps of motion (a least-squares fit of the expert demos' free-space steps,
#: Δp_{t+1} = A·u_t + B·Δp_t + C·u_{t−1}, gives u = Δp·(1 − B)/(A + C) ≈ 3.1·Δp at constant velocity).
PATH_COMMAND_LEAD_STEPS: float = 3.0


def _interp_pose(T: np.ndarray, s: float) -> np.ndarray:
    """Pose at fractional index ``s`` of ``T`` [N, 4, 4] (linear position, geodesic rotation; clamped)."""
    s = float(np.clip(s, 0.0, len(T) - 1))
    i = min(int(np.floor(s)), len(T) - 2) if len(T) > 1 else 0
    f = s - i
    if len(T) == 1 or f <= 0.0:
        return T[i].copy()
    out = np.eye(4)
    out[:3, 3] = (1.0 - f) * T[i, :3, 3] + f * T[i + 1, :3, 3]
    out[:3, :3] = so3_exp(f * so3_log(T[i + 1, :3, :3] @ T[i, :3, :3].T)) @ T[i, :3, :3]
    return out


def path_command_targets(T_world_tcp: np.ndarray, gripper_width: np.ndarray,
                         lead_steps: float = PATH_COMMAND_LEAD_STEPS) -> np.ndarray:
    """Commanded targets (module layout) that drive the OSC along a KINEMATIC path (an augmented episode's new,
    planned frames, never executed): row 0 = the start pose, row t = the path's pose ``lead_steps`` after
    ``t − 1`` (clamped at the path's end, where the target then rests — as the expert's P-law commands its goal
    once within reach). The gripper keeps the path's state: the close command where its width is below
    :data:`GRIPPER_CLOSE_BELOW_M`, the open command otherwise.

    An approximation of the commands a real execution would have needed (the lead is the controller's steady-state
    lag; accelerations are not modelled): ``tests/square/test_commands.py`` measures how closely the simulated
    arm follows a demo's own approach when driven by these targets.

    Args:
        T_world_tcp: np.ndarray,  # [N, 4, 4] planned TCP poses at the control rate (20 Hz)
        gripper_width: np.ndarray,  # [N] metres
    Returns:
        np.ndarray,  # [N, 7] float64
    """
    T = np.asarray(T_world_tcp, np.float64)
    w = np.asarray(gripper_width, np.float64).reshape(-1)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) < 1 or w.shape != (len(T),):
        raise SimError(f"path_command_targets: need T_world_tcp [N, 4, 4] and gripper_width [N], got {T.shape}, "
                       f"{w.shape}")
    if not (np.isfinite(T).all() and np.isfinite(w).all() and lead_steps >= 0):
        raise SimError(f"path_command_targets: NaN/Inf poses or widths, or lead_steps = {lead_steps} < 0")
    goals = np.stack([T[0]] + [_interp_pose(T, t - 1 + lead_steps) for t in range(1, len(T))])
    out = np.empty((len(T), 7))
    out[:, :6] = pose_to_pos_rotvec(goals)
    out[:, 6] = np.where(w < GRIPPER_CLOSE_BELOW_M, 0.0, GRIPPER_OPEN_M)
    return out
