"""Damped-least-squares inverse kinematics of the Panda arm in MuJoCo (plain DLS; no extra IK library).

Solves for the 7 arm joints that put a site (default: robosuite's grip site) at a target world pose, inside
the joint limits, with seeded random restarts; then reports the residual and any penetrating contact of the
robot with the scene at the solution. Works on a private ``MjData``: the caller's state is never changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import so3_log
from umi_aug.sim.gl import import_mujoco

__all__ = ["IKResult", "PandaIK", "POS_TOL_M", "ROT_TOL_RAD"]

#: Acceptance thresholds of a solution: 10× tighter than the required 1 mm / 0.5°, so an accepted pose is the
#: sampled pose (a looser residual means the arm stopped at a joint limit short of the target).
POS_TOL_M: float = 1e-4
ROT_TOL_RAD: float = float(np.deg2rad(0.05))
#: Convergence thresholds of the iteration.
_CONV_POS, _CONV_ROT = 1e-6, 1e-5
_DAMPING = 1e-2        # λ of (J Jᵀ + λ² I)
_MAX_STEP = 0.2        # rad, largest joint change per iteration
_MAX_ITERS = 200
_PENETRATION_M = 1e-3  # a contact deeper than this counts as a collision


@dataclass
class IKResult:
    """Result of :meth:`PandaIK.solve`.

    Attributes:
        q: float64 [7] arm joint angles (radians).
        pos_err: metres; rot_err: radians (geodesic) between the site pose reached and the target.
        reachable: residual within :data:`POS_TOL_M` / :data:`ROT_TOL_RAD`.
        collisions: "geom_a/geom_b" pairs of the robot penetrating something at ``q`` (empty = free).
        iters: iterations of the accepted attempt; attempts: restarts used.
    """

    q: np.ndarray
    pos_err: float
    rot_err: float
    reachable: bool
    collisions: list[str] = field(default_factory=list)
    iters: int = 0
    attempts: int = 0

    @property
    def ok(self) -> bool:
        return self.reachable and not self.collisions


class PandaIK:
    """IK for ``robot0``'s 7 arm joints.

    Args:
        model: raw ``mujoco.MjModel`` of the square environment.
        site: site to place.
        prefix: joint name prefix (``robot0_joint1`` … ``robot0_joint7``).
    """

    def __init__(self, model, site: str = "gripper0_grip_site", prefix: str = "robot0_joint") -> None:
        mj = self._mj = import_mujoco()
        self.model = model
        self.site = mj.mj_name2id(model, mj.mjtObj.mjOBJ_SITE, site)
        if self.site < 0:
            raise SimError(f"PandaIK: no site {site!r} in the model")
        jids = [mj.mj_name2id(model, mj.mjtObj.mjOBJ_JOINT, f"{prefix}{i}") for i in range(1, 8)]
        if min(jids) < 0:
            raise SimError(f"PandaIK: joints {prefix}1..7 not all found")
        self.qadr = np.array([model.jnt_qposadr[j] for j in jids])
        self.dadr = np.array([model.jnt_dofadr[j] for j in jids])
        self.lo = np.array([model.jnt_range[j][0] for j in jids])
        self.hi = np.array([model.jnt_range[j][1] for j in jids])
        self.data = mj.MjData(model)
        robot_bodies = [b for b in range(model.nbody)
                        if mj.mj_id2name(model, mj.mjtObj.mjOBJ_BODY, b).startswith(("robot0_", "gripper0_"))]
        self._robot_body = np.zeros(model.nbody, dtype=bool)
        self._robot_body[robot_bodies] = True
        # the static pedestal: a robot contact with it counts as self-collision
        self._mount_body = np.array([(mj.mj_id2name(model, mj.mjtObj.mjOBJ_BODY, b) or "").startswith("mount0_")
                                     for b in range(model.nbody)], dtype=bool)

    def site_pose(self, q: np.ndarray, data_src) -> np.ndarray:
        """Site pose ``[4, 4]`` with arm joints ``q`` and everything else from ``data_src``."""
        self._load(data_src, q)
        return self._site_T()

    def _load(self, data_src, q: np.ndarray) -> None:
        d = self.data
        d.qpos[:] = data_src.qpos
        d.qvel[:] = 0.0
        d.qpos[self.qadr] = q
        self._mj.mj_kinematics(self.model, d)
        self._mj.mj_comPos(self.model, d)

    def _site_T(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[self.site].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[self.site]
        return T

    def _error(self, T_goal: np.ndarray) -> np.ndarray:
        T = self._site_T()
        return np.concatenate([T_goal[:3, 3] - T[:3, 3], so3_log(T_goal[:3, :3] @ T[:3, :3].T)])

    def _iterate(self, data_src, T_goal: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        mj, m, d = self._mj, self.model, self.data
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        self._load(data_src, q)
        err = self._error(T_goal)
        it = 0
        for it in range(1, _MAX_ITERS + 1):
            if np.linalg.norm(err[:3]) < _CONV_POS and np.linalg.norm(err[3:]) < _CONV_ROT:
                break
            mj.mj_jacSite(m, d, jacp, jacr, self.site)
            J = np.vstack([jacp[:, self.dadr], jacr[:, self.dadr]])  # [6, 7]
            dq = J.T @ np.linalg.solve(J @ J.T + _DAMPING**2 * np.eye(6), err)
            n = np.linalg.norm(dq)
            if n > _MAX_STEP:
                dq *= _MAX_STEP / n
            q = np.clip(q + dq, self.lo, self.hi)
            d.qpos[self.qadr] = q
            mj.mj_kinematics(m, d)
            mj.mj_comPos(m, d)
            err = self._error(T_goal)
        return q, err, it

    def refine(self, data_src, T_world_site: np.ndarray, q_start: np.ndarray, *, lo: np.ndarray | None = None,
               hi: np.ndarray | None = None, q_rest: np.ndarray | None = None, null_gain: float = 0.0,
               max_iters: int = _MAX_ITERS) -> tuple[np.ndarray, float, float, int]:
        """One damped-least-squares descent from ``q_start`` (no restarts), for tracking a path.

        Unlike :meth:`solve`'s iteration, a joint held at a bound whose step points outward is dropped from the
        Jacobian for that step, so the redundant 7th DoF takes over instead of the iteration stalling there.

        Args:
            data_src: ``mujoco.MjData`` giving the rest of the scene (not modified).
            T_world_site: np.ndarray,  # [4, 4] target, metres
            q_start: np.ndarray,  # [7] start joints, rad (clipped into [lo, hi])
            lo, hi: np.ndarray,  # [7] joint bounds, rad (default: the model's joint ranges)
            q_rest: np.ndarray,  # [7] null-space attractor, rad (used when null_gain > 0)
            null_gain: fraction of ``q_rest - q`` added per iteration, projected into the task's null space.
        Returns:
            (q [7] rad, position error m, rotation error rad (geodesic), iterations)
        """
        mj, m, d = self._mj, self.model, self.data
        lo = self.lo if lo is None else np.asarray(lo, dtype=np.float64)
        hi = self.hi if hi is None else np.asarray(hi, dtype=np.float64)
        T_goal = np.asarray(T_world_site, dtype=np.float64)
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        q = np.clip(np.asarray(q_start, dtype=np.float64), lo, hi)
        self._load(data_src, q)
        err = self._error(T_goal)
        eye6, it = np.eye(6), 0
        for it in range(1, int(max_iters) + 1):
            if np.linalg.norm(err[:3]) < _CONV_POS and np.linalg.norm(err[3:]) < _CONV_ROT:
                break
            mj.mj_jacSite(m, d, jacp, jacr, self.site)
            J = np.vstack([jacp[:, self.dadr], jacr[:, self.dadr]])  # [6, 7]
            free = np.ones(7, dtype=bool)
            for _ in range(7):
                Jf = J * free
                J_pinv = Jf.T @ np.linalg.solve(Jf @ Jf.T + _DAMPING**2 * eye6, eye6)  # [7, 6]
                dq = J_pinv @ err
                if null_gain > 0.0 and q_rest is not None:
                    dq += (np.eye(7) - J_pinv @ Jf) @ (null_gain * (np.asarray(q_rest) - q) * free)
                out = free & (((q <= lo) & (dq < 0.0)) | ((q >= hi) & (dq > 0.0)))
                if not out.any():
                    break
                free &= ~out
            n = np.linalg.norm(dq)
            if n > _MAX_STEP:
                dq *= _MAX_STEP / n
            q = np.clip(q + dq, lo, hi)
            d.qpos[self.qadr] = q
            mj.mj_kinematics(m, d)
            mj.mj_comPos(m, d)
            err = self._error(T_goal)
        return q, float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:])), it

    def posture_step(self, data_src, q: np.ndarray, q_rest: np.ndarray, gain: float,
                     max_abs: np.ndarray) -> np.ndarray:
        """``q`` moved by ``gain · (q_rest − q)`` projected into the null space of the site Jacobian at ``q`` (the
        site pose stays put to first order; the arm's elbow swivels towards ``q_rest``), the step scaled down so no
        joint moves more than ``max_abs`` [7] rad, and clipped into the joint ranges. Rows of J with singular values
        below 1e-3 of the largest count as null space (near a singularity the pose moves; re-solve after)."""
        mj, m, d = self._mj, self.model, self.data
        q = np.asarray(q, dtype=np.float64)
        self._load(data_src, q)
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mj.mj_jacSite(m, d, jacp, jacr, self.site)
        J = np.vstack([jacp[:, self.dadr], jacr[:, self.dadr]])
        dq = (np.eye(7) - np.linalg.pinv(J, rcond=1e-3) @ J) @ (gain * (np.asarray(q_rest) - q))
        big = np.abs(dq) / np.maximum(np.asarray(max_abs, dtype=np.float64), 1e-12)
        if big.max() > 1.0:
            dq /= big.max()
        return np.clip(q + dq, self.lo, self.hi)

    def contacts(self, data_src, q: np.ndarray, max_penetration_m: float = _PENETRATION_M,
                 self_collision: bool = True) -> list[tuple[str, str, float]]:
        """Contacts of the moving robot (arm + gripper) penetrating deeper than ``max_penetration_m`` (metres)
        with arm joints ``q``, fingers and everything else from ``data_src``: with the scene (table, pegs, nuts)
        and, when ``self_collision``, with itself or its mount. Returns ``(geom_a, geom_b, distance m)`` (< 0)."""
        mj, m, d = self._mj, self.model, self.data
        self._load(data_src, q)
        mj.mj_collision(m, d)
        out = []
        for c in d.contact[: d.ncon]:
            if c.dist >= -max_penetration_m:
                continue
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            arm1, arm2 = self._robot_body[b1], self._robot_body[b2]
            if not (arm1 or arm2):
                continue
            own = (arm1 or self._mount_body[b1]) and (arm2 or self._mount_body[b2])
            if own and not self_collision:
                continue
            out.append((mj.mj_id2name(m, mj.mjtObj.mjOBJ_GEOM, c.geom1) or str(c.geom1),
                        mj.mj_id2name(m, mj.mjtObj.mjOBJ_GEOM, c.geom2) or str(c.geom2), float(c.dist)))
        return out

    def collisions(self, data_src, q: np.ndarray) -> list[str]:
        """Robot contacts penetrating deeper than 1 mm with arm joints ``q`` (state of ``data_src`` otherwise)."""
        mj, m, d = self._mj, self.model, self.data
        self._load(data_src, q)
        mj.mj_forward(m, d)
        out = []
        for c in d.contact[: d.ncon]:
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            if c.dist < -_PENETRATION_M and (self._robot_body[b1] or self._robot_body[b2]) \
                    and not (self._robot_body[b1] and self._robot_body[b2]):
                out.append(f"{mj.mj_id2name(m, mj.mjtObj.mjOBJ_GEOM, c.geom1)}/"
                           f"{mj.mj_id2name(m, mj.mjtObj.mjOBJ_GEOM, c.geom2)}")
        return out

    def solve(self, data_src, T_world_site: np.ndarray, rng: np.random.Generator | int = 0,
              restarts: int = 4, restart_std: float = 0.3) -> IKResult:
        """Arm joints placing the site at ``T_world_site``.

        Args:
            data_src: ``mujoco.MjData`` giving the start joints and the rest of the scene (not modified).
            T_world_site: np.ndarray,  # [4, 4] target, metres
            rng: restarts perturb the start joints by N(0, restart_std²) rad from this generator/seed.
            restarts: extra attempts after the first (from the current joints) fails.
        Returns:
            :class:`IKResult` of the best attempt.
        """
        T_goal = np.asarray(T_world_site, dtype=np.float64)
        if T_goal.shape != (4, 4) or not np.all(np.isfinite(T_goal)):
            raise SimError(f"PandaIK.solve: target must be a finite [4, 4] pose, got shape {T_goal.shape}")
        gen = np.random.default_rng(rng)
        q0 = np.asarray(data_src.qpos[self.qadr], dtype=np.float64).copy()
        best = None
        for attempt in range(restarts + 1):
            start = q0 if attempt == 0 else np.clip(q0 + gen.normal(0.0, restart_std, 7), self.lo, self.hi)
            q, err, it = self._iterate(data_src, T_goal, start)
            pe, re = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
            res = IKResult(q=q, pos_err=pe, rot_err=re, reachable=pe < POS_TOL_M and re < ROT_TOL_RAD,
                           iters=it, attempts=attempt + 1)
            if res.reachable:
                res.collisions = self.collisions(data_src, q)
                if not res.collisions:
                    return res
            if best is None or (res.ok, -res.pos_err) > (best.ok, -best.pos_err):
                best = res
        return best
