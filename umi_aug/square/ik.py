"""Inverse kinematics of the square benchmark's Panda arm: the simulator arms' DLS solver
(:class:`umi_aug.sim.ik.ArmIK`) with the Panda's parameters (:data:`PANDA_DLS`).

Solves for the 7 arm joints that put a site (default: robosuite's grip site) at a target world pose, inside
the joint limits, with seeded random restarts; then reports the residual and any penetrating contact of the
robot with the scene at the solution. Works on a private ``MjData``: the caller's state is never changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import so3_log
from umi_aug.sim.ik import ArmIK, DLSParams

__all__ = ["IKResult", "PandaIK", "PANDA_DLS", "POS_TOL_M", "ROT_TOL_RAD"]

#: Acceptance thresholds of a solution: 10× tighter than the required 1 mm / 0.5°, so an accepted pose is the
#: sampled pose (a looser residual means the arm stopped at a joint limit short of the target).
POS_TOL_M: float = 1e-4
ROT_TOL_RAD: float = float(np.deg2rad(0.05))
#: The Panda's DLS: λ = 1e-2, steps of at most 0.2 rad in 2-norm, converged below 1e-6 m / 1e-5 rad, rotation
#: error by ``so3_log``.
PANDA_DLS = DLSParams(max_step=0.2, step_norm="l2", damping=1e-2, tol_pos_m=1e-6, tol_rot_rad=1e-5, rot_log=so3_log)
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


class PandaIK(ArmIK):
    """IK for ``robot0``'s 7 arm joints: :class:`~umi_aug.sim.ik.ArmIK` with the square's DLS parameters
    (:data:`PANDA_DLS`), seeded restarts and the robot's contacts with the scene.

    Args:
        model: raw ``mujoco.MjModel`` of the square environment.
        site: site to place.
        prefix: joint name prefix (``robot0_joint1`` … ``robot0_joint7``).
    """

    def __init__(self, model, site: str = "gripper0_grip_site", prefix: str = "robot0_joint") -> None:
        super().__init__(model, site, [f"{prefix}{i}" for i in range(1, 8)], owner="PandaIK",
                         joints_label=f"{prefix}1..7")
        mj = self._mj
        robot_bodies = [b for b in range(model.nbody)
                        if mj.mj_id2name(model, mj.mjtObj.mjOBJ_BODY, b).startswith(("robot0_", "gripper0_"))]
        self._robot_body = np.zeros(model.nbody, dtype=bool)
        self._robot_body[robot_bodies] = True
        # the static pedestal: a robot contact with it counts as self-collision
        self._mount_body = np.array([(mj.mj_id2name(model, mj.mjtObj.mjOBJ_BODY, b) or "").startswith("mount0_")
                                     for b in range(model.nbody)], dtype=bool)

    def site_pose(self, q: np.ndarray, data_src) -> np.ndarray:
        """Site pose ``[4, 4]`` with arm joints ``q`` and everything else from ``data_src``."""
        return self.fk(q, data_src.qpos)

    def refine(self, data_src, T_world_site: np.ndarray, q_start: np.ndarray, *, lo: np.ndarray | None = None,
               hi: np.ndarray | None = None, q_rest: np.ndarray | None = None, null_gain: float = 0.0,
               max_iters: int = _MAX_ITERS) -> tuple[np.ndarray, float, float, int]:
        """One damped-least-squares descent from ``q_start`` (no restarts), for tracking a path.

        Unlike :meth:`solve`'s iteration, a joint held at a bound whose step points outward is dropped from the
        Jacobian for that step, so the redundant 7th DoF takes over instead of the iteration stalling there
        (:meth:`~umi_aug.sim.ik.ArmIK.solve_dls` with ``release_bounds``).

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
        lo = self.lo if lo is None else np.asarray(lo, dtype=np.float64)
        hi = self.hi if hi is None else np.asarray(hi, dtype=np.float64)
        q = np.clip(np.asarray(q_start, dtype=np.float64), lo, hi)
        return self.solve_dls(np.asarray(T_world_site, dtype=np.float64), q, PANDA_DLS, max_iters=max_iters,
                              qpos=data_src.qpos, lo=lo, hi=hi, release_bounds=True, q_rest=q_rest,
                              null_gain=null_gain)

    def posture_step(self, data_src, q: np.ndarray, q_rest: np.ndarray, gain: float,
                     max_abs: np.ndarray) -> np.ndarray:
        """:meth:`~umi_aug.sim.ik.ArmIK.null_space_step` with the rest of the scene from ``data_src``: ``q`` [7]
        moved towards ``q_rest`` in the null space of the site Jacobian (the grip site stays put to first order),
        no joint more than ``max_abs`` [7] rad, inside the joint ranges."""
        return self.null_space_step(q, q_rest, gain, max_abs, data_src.qpos)

    def contacts(self, data_src, q: np.ndarray, max_penetration_m: float = _PENETRATION_M,
                 self_collision: bool = True) -> list[tuple[str, str, float]]:
        """Contacts of the moving robot (arm + gripper) penetrating deeper than ``max_penetration_m`` (metres)
        with arm joints ``q``, fingers and everything else from ``data_src``: with the scene (table, pegs, nuts)
        and, when ``self_collision``, with itself or its mount. Returns ``(geom_a, geom_b, distance m)`` (< 0)."""
        mj, m, d = self._mj, self.model, self.data
        self.load(q, data_src.qpos)
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
        self.load(q, data_src.qpos)
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
            q, pe, re, it = self.solve_dls(T_goal, start, PANDA_DLS, max_iters=_MAX_ITERS, qpos=data_src.qpos)
            res = IKResult(q=q, pos_err=pe, rot_err=re, reachable=pe < POS_TOL_M and re < ROT_TOL_RAD,
                           iters=it, attempts=attempt + 1)
            if res.reachable:
                res.collisions = self.collisions(data_src, q)
                if not res.collisions:
                    return res
            if best is None or (res.ok, -res.pos_err) > (best.ok, -best.pos_err):
                best = res
        return best
