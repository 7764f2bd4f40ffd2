"""Damped-least-squares inverse kinematics of a MuJoCo arm: one solver for the simulator arms.

:class:`ArmIK` places a site of a compiled ``mujoco.MjModel`` at a target pose by moving a named chain of hinge
joints inside their limits. It works on its own private ``MjData`` (the caller's simulation state is never
changed): the joints of the chain are set, everything else comes from an optional ``qpos`` (default: the model's
``qpos0``), and only the kinematics (``mj_kinematics`` + ``mj_comPos``) are recomputed.

Frames and units: poses are ``T_world_site`` [4, 4] in MuJoCo's world frame (metres); joint angles radians. The
pose error is ``e = (p_goal − p, log(R_goal · Rᵀ))`` [6] — position (m) and the world-frame rotation vector
(rad) that turns the site onto the goal; an iteration steps ``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ e`` with ``J`` [6, n] the
site Jacobian (``mj_jacSite``: linear rows, then angular rows, world frame) over the chain's DoFs.

Two callers, two parameter sets (:class:`DLSParams`; both kept exactly as they were before the solvers merged):

* the square benchmark's Panda (:class:`umi_aug.square.ik.PandaIK`): step limited in 2-norm (0.2 rad),
  rotation error by :func:`umi_aug.geometry.so3_log`, up to 200 iterations; its path tracking
  (``PandaIK.refine``) also releases joints at a bound (``release_bounds``) and adds a null-space pull;
* deploy's simulated UR5e (:class:`umi_aug.deploy.sim_arm.UR5eSim`, 500 Hz servo loop): step limited per joint
  (max-norm, 0.05 rad), rotation error by :func:`rodrigues_log` (OpenCV, faster), a few warm-started iterations
  per control period.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Literal, Sequence

import cv2
import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import so3_log
from umi_aug.sim.gl import import_mujoco

__all__ = ["ArmIK", "DLSParams", "rodrigues_log", "site_pose"]


def rodrigues_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector [3] (rad) of a 3×3 rotation by OpenCV's Rodrigues (C; the same as
    :func:`umi_aug.geometry.so3_log` up to rounding, several times faster for one matrix)."""
    return cv2.Rodrigues(np.ascontiguousarray(R, dtype=np.float64))[0].reshape(3)


def site_pose(data: Any, site: int) -> np.ndarray:
    """``T_world_site`` [4, 4] (m) of site id ``site`` from ``data``'s current kinematics."""
    T = np.eye(4)
    T[:3, :3] = data.site_xmat[site].reshape(3, 3)
    T[:3, 3] = data.site_xpos[site]
    return T


@dataclass(frozen=True)
class DLSParams:
    """Parameters of :meth:`ArmIK.solve_dls`.

    Attributes:
        max_step: largest joint step per iteration (rad), measured by ``step_norm``.
        step_norm: ``"l2"`` (the whole step vector's length; the square Panda) or ``"max"`` (the largest single
            joint change; the simulated UR5e). A longer step is scaled down, keeping its direction.
        damping: λ of ``(J Jᵀ + λ² I)`` (m, and rad for the rotation rows).
        tol_pos_m, tol_rot_rad: the iteration stops once the position error (m) and the rotation error (rad,
            geodesic) are both below these.
        rot_log: rotation matrix → rotation vector of the orientation error (:func:`umi_aug.geometry.so3_log` for
            the square Panda, :func:`rodrigues_log` for the simulated UR5e).
    """

    max_step: float
    step_norm: Literal["l2", "max"] = "l2"
    damping: float = 1e-2
    tol_pos_m: float = 1e-6
    tol_rot_rad: float = 1e-5
    rot_log: Callable[[np.ndarray], np.ndarray] = so3_log


class ArmIK:
    """Kinematics and DLS inverse kinematics of one joint chain of a MuJoCo model.

    Args:
        model: compiled ``mujoco.MjModel``.
        site: name of the site to place (e.g. a TCP or grip site).
        joints: names of the chain's hinge/slide joints, in the order of ``q``.
        owner: names the caller in error messages. joints_label: how the messages name the joints (default: the
            names).

    Attributes:
        site: the site id. qadr, dadr: [n] ``qpos`` / DoF addresses of the joints. lo, hi: [n] joint ranges
        (rad). data: the private ``MjData``.

    Raises:
        SimError: the site or a joint is not in the model.
    """

    def __init__(self, model: Any, site: str, joints: Sequence[str], *, owner: str = "ArmIK",
                 joints_label: str | None = None) -> None:
        mj = self._mj = import_mujoco()
        self.model = model
        self.site = mj.mj_name2id(model, mj.mjtObj.mjOBJ_SITE, site)
        if self.site < 0:
            raise SimError(f"{owner}: no site {site!r} in the model")
        jids = [mj.mj_name2id(model, mj.mjtObj.mjOBJ_JOINT, n) for n in joints]
        if min(jids) < 0:
            raise SimError(f"{owner}: joints {joints_label or tuple(joints)} not all found")
        self.qadr = np.array([model.jnt_qposadr[j] for j in jids])
        self.dadr = np.array([model.jnt_dofadr[j] for j in jids])
        self.lo = np.array([model.jnt_range[j][0] for j in jids])
        self.hi = np.array([model.jnt_range[j][1] for j in jids])
        self.data = mj.MjData(model)
        self._jacp, self._jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))

    # ------------------------------------------------------------------ kinematics
    def load(self, q: np.ndarray, qpos: np.ndarray | None = None) -> None:
        """Set the chain's joints to ``q`` [n] (rad) — and first every joint to ``qpos`` [nq] with zero velocity,
        when given — and recompute the kinematics of the private data."""
        d = self.data
        if qpos is not None:
            d.qpos[:] = qpos
            d.qvel[:] = 0.0
        d.qpos[self.qadr] = q
        self._mj.mj_kinematics(self.model, d)
        self._mj.mj_comPos(self.model, d)

    def site_T(self) -> np.ndarray:
        """``T_world_site`` [4, 4] (m) at the joints last loaded."""
        return site_pose(self.data, self.site)

    def fk(self, q: np.ndarray, qpos: np.ndarray | None = None) -> np.ndarray:
        """``T_world_site`` [4, 4] (m) with the chain at ``q`` [n] rad (the rest from ``qpos``, see :meth:`load`)."""
        self.load(q, qpos)
        return self.site_T()

    def jacobian(self) -> np.ndarray:
        """Site Jacobian [6, n] at the joints last loaded: linear rows (m/rad), then angular rows (rad/rad), world
        frame."""
        self._mj.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site)
        return np.vstack([self._jacp[:, self.dadr], self._jacr[:, self.dadr]])

    def pose_error(self, T_goal: np.ndarray, rot_log: Callable[[np.ndarray], np.ndarray] = so3_log) -> np.ndarray:
        """``(p_goal − p, rot_log(R_goal · Rᵀ))`` [6] (m, rad) of the site at the joints last loaded."""
        T = self.site_T()
        return np.concatenate([T_goal[:3, 3] - T[:3, 3], rot_log(T_goal[:3, :3] @ T[:3, :3].T)])

    # ------------------------------------------------------------------ inverse kinematics
    def solve_dls(self, T_goal: np.ndarray, q0: np.ndarray, params: DLSParams, *, max_iters: int,
                  qpos: np.ndarray | None = None, lo: np.ndarray | None = None, hi: np.ndarray | None = None,
                  release_bounds: bool = False, q_rest: np.ndarray | None = None,
                  null_gain: float = 0.0) -> tuple[np.ndarray, float, float, int]:
        """Damped least squares from ``q0`` towards the site pose ``T_goal``, one descent (no restarts).

        Each iteration: stop if converged (:class:`DLSParams` tolerances), else ``dq`` from the DLS step, scaled to
        ``params.max_step``, ``q ← clip(q + dq, lo, hi)``. ``q0`` itself is not clipped.

        Args:
            T_goal: np.ndarray,  # [4, 4] target T_world_site, metres
            q0: np.ndarray,  # [n] start joints, rad
            params: step, damping, tolerances, rotation error (:class:`DLSParams`).
            max_iters: most iterations.
            qpos: np.ndarray,  # [nq] the other joints (default: the private data's, initially ``qpos0``)
            lo, hi: np.ndarray,  # [n] joint bounds, rad (default: the model's joint ranges)
            release_bounds: a joint held at a bound whose step points outward is dropped from the Jacobian for
                that step (the pseudo-inverse is recomputed without it, up to n times), so redundant joints take
                over instead of the iteration stalling there (the Panda's path tracking).
            q_rest: np.ndarray,  # [n] null-space attractor, rad (with ``release_bounds`` and null_gain > 0)
            null_gain: fraction of ``q_rest − q`` added per iteration, projected into the task's null space.
        Returns:
            (q [n] rad, position error m, rotation error rad, iterations)
        """
        lo = self.lo if lo is None else lo
        hi = self.hi if hi is None else hi
        q = np.array(q0, dtype=np.float64)
        self.load(q, qpos)
        err = self.pose_error(T_goal, params.rot_log)
        eye6, it = np.eye(6), 0
        for it in range(1, int(max_iters) + 1):
            if np.linalg.norm(err[:3]) < params.tol_pos_m and np.linalg.norm(err[3:]) < params.tol_rot_rad:
                break
            J = self.jacobian()
            if release_bounds:
                dq = self._released_step(J, err, q, lo, hi, params.damping, q_rest, null_gain)
            else:
                dq = J.T @ np.linalg.solve(J @ J.T + params.damping**2 * eye6, err)
            n = np.linalg.norm(dq) if params.step_norm == "l2" else np.abs(dq).max()
            if n > params.max_step:
                dq *= params.max_step / n
            q = np.clip(q + dq, lo, hi)
            self.load(q)
            err = self.pose_error(T_goal, params.rot_log)
        return q, float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:])), it

    @staticmethod
    def _released_step(J: np.ndarray, err: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                       damping: float, q_rest: np.ndarray | None, null_gain: float) -> np.ndarray:
        """DLS step [n] without the joints that sit at a bound and would step outward (see
        :meth:`solve_dls`'s ``release_bounds``), plus the null-space pull towards ``q_rest``."""
        nq, eye6 = J.shape[1], np.eye(6)
        free = np.ones(nq, dtype=bool)
        for _ in range(nq):
            Jf = J * free
            J_pinv = Jf.T @ np.linalg.solve(Jf @ Jf.T + damping**2 * eye6, eye6)  # [n, 6]
            dq = J_pinv @ err
            if null_gain > 0.0 and q_rest is not None:
                dq += (np.eye(nq) - J_pinv @ Jf) @ (null_gain * (np.asarray(q_rest) - q) * free)
            out = free & (((q <= lo) & (dq < 0.0)) | ((q >= hi) & (dq > 0.0)))
            if not out.any():
                break
            free &= ~out
        return dq

    def null_space_step(self, q: np.ndarray, q_rest: np.ndarray, gain: float, max_abs: np.ndarray,
                        qpos: np.ndarray | None = None) -> np.ndarray:
        """``q`` [n] moved by ``gain · (q_rest − q)`` projected into the null space of the site Jacobian at ``q``
        (the site pose stays put to first order; a redundant arm's elbow swivels towards ``q_rest``), the step
        scaled down so no joint moves more than ``max_abs`` [n] rad, and clipped into the joint ranges. Rows of J
        with singular values below 1e-3 of the largest count as null space (near a singularity the pose moves;
        re-solve after)."""
        q = np.asarray(q, dtype=np.float64)
        self.load(q, qpos)
        J = self.jacobian()
        dq = (np.eye(len(q)) - np.linalg.pinv(J, rcond=1e-3) @ J) @ (gain * (np.asarray(q_rest) - q))
        big = np.abs(dq) / np.maximum(np.asarray(max_abs, dtype=np.float64), 1e-12)
        if big.max() > 1.0:
            dq /= big.max()
        return np.clip(q + dq, self.lo, self.hi)
