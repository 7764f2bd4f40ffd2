"""The square task in the evaluation harness (``eval/eval_sim.py``): :data:`SQUARE_TASK`, the
:class:`umi_aug.eval.task.SimTask` that :func:`umi_aug.eval.runner.run_eval` runs on, and :class:`SceneProbe`, its
record of one rollout.

The environment is :class:`~umi_aug.square.env.SquareEnv` (robosuite NutAssemblySquare, Panda, OSC_POSE at
20 Hz), the wrist camera :class:`~umi_aug.square.camera.WristFisheyeCamera`, the scripted controls those of
:mod:`umi_aug.square.controls`; ``policy=replay`` replays episode shards of ``umi-aug square-demos``. Recorded per
rollout besides the harness's ``success`` (robosuite's task success — nut on the square peg AND gripper ≥ ~4 cm
away — at ANY step) and ``steps_to_success`` (all world frame, metres):

* ``pregrasp_reached`` — the grip site came within :data:`PREGRASP_POS_TOL_M` and :data:`PREGRASP_ROT_TOL_DEG`
  of the configuration's expert pre-grasp pose (:func:`~umi_aug.square.expert.expert_pregrasp_pose`: the scripted
  expert's ``approach`` goal — hover point above the handle, z down, fingers closing across the handle — computed
  from the nut as it lies, i.e. after it settled from its spawn height, until a finger first touches the nut;
  rotation error taken modulo the gripper's 180° symmetry about its approach axis);
* ``lifted`` — the nut was at least :data:`LIFT_HEIGHT_M` above its resting height (before first touched) while a
  finger touched it;
* ``inserted`` — the nut was on the square peg (robosuite's ``on_peg``: xy within 3 cm, below table + 5 cm),
  released or not;
* ``collision_table`` / ``collision_peg`` — any gripper (hand or finger) geom in contact with the table /
  either peg; counted in steps.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import EvalError, UmiAugError
from umi_aug.eval.task import SimEnv, TaskProbe
from umi_aug.geometry import pose_inverse
from umi_aug.policy.contract import PolicyLike
from umi_aug.sim.gl import import_mujoco
from umi_aug.square.camera import T_CAM_TCP, WristFisheyeCamera
from umi_aug.square.commands import GRIPPER_CLOSE_BELOW_M
from umi_aug.square.controls import (CONTROLS, ExpertEvalPolicy, HoldStillEvalPolicy, PrivilegedState,
                                     RandomEvalPolicy, ReplayEvalPolicy, abs_tcp_to_osc_delta)
from umi_aug.square.env import GRIP_SITE, NUT_BODY, SquareEnv
from umi_aug.square.expert import PREGRASP_POS_TOL_M, PREGRASP_ROT_TOL_DEG, expert_pregrasp_pose, pregrasp_error
from umi_aug.square.writers import load_episode

__all__ = ["SQUARE_TASK", "SquareTask", "SceneProbe", "POLICY_KINDS", "LIFT_HEIGHT_M", "PREGRASP_POS_TOL_M",
           "PREGRASP_ROT_TOL_DEG"]

#: nut lift sub-goal: nut centre this far above its start height (m) with a finger touching it
LIFT_HEIGHT_M: float = 0.03

#: values of ``policy=`` in ``configs/eval_sim.yaml`` for the square task
POLICY_KINDS: tuple[str, ...] = ("checkpoint", *CONTROLS)


class SceneProbe:
    """The square task's :class:`~umi_aug.eval.task.TaskProbe`: geom/body ids of the square scene for the
    sub-goal and contact checks (built once per environment) and the rollout's per-step bookkeeping."""

    def __init__(self, env: SquareEnv) -> None:
        mujoco = import_mujoco()
        m = env.model
        self.env = env
        self.nut_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, NUT_BODY)
        self.grip_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, GRIP_SITE)
        names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(m.ngeom)]
        bnames = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(b)) or "" for b in m.geom_bodyid]
        self.gripper = np.array([n.startswith("gripper0_") or b.startswith("gripper0_")
                                 for n, b in zip(names, bnames)])
        self.fingers = np.array([("finger" in n or "finger" in b) and g for n, b, g in
                                 zip(names, bnames, self.gripper)])
        self.table = np.array(["table" in n and not n.startswith("gripper0_") for n in names])
        self.peg = np.array([b in ("peg1", "peg2") for b in bnames])
        self.nut = np.array([b.startswith("SquareNut") for b in bnames])
        self.table_z = float(env.rs.table_offset[2])
        self._nut_rest = np.eye(4)  # the nut's pose before a finger first touched it
        self._T_pre = np.eye(4)  # the expert's pre-grasp pose for that nut pose
        self._touched = False  # a finger has touched the nut (from then on the pre-grasp goal and rest are frozen)

    def contacts(self) -> tuple[bool, bool, bool]:
        """(gripper–table, gripper–peg, finger–nut) contact in the current state."""
        d = self.env.data
        n = int(d.ncon)
        if n == 0:
            return False, False, False
        g1 = np.asarray(d.contact.geom1[:n])
        g2 = np.asarray(d.contact.geom2[:n])
        gg1, gg2 = self.gripper[g1], self.gripper[g2]
        table = bool(np.any((gg1 & self.table[g2]) | (gg2 & self.table[g1])))
        peg = bool(np.any((gg1 & self.peg[g2]) | (gg2 & self.peg[g1])))
        nut = bool(np.any((self.fingers[g1] & self.nut[g2]) | (self.fingers[g2] & self.nut[g1])))
        return table, peg, nut

    def nut_pose(self) -> np.ndarray:
        d = self.env.data
        T = np.eye(4)
        T[:3, :3] = np.asarray(d.xmat[self.nut_body]).reshape(3, 3)
        T[:3, 3] = d.xpos[self.nut_body]
        return T

    def site_pose(self) -> np.ndarray:
        d = self.env.data
        T = np.eye(4)
        T[:3, :3] = np.asarray(d.site_xmat[self.grip_site]).reshape(3, 3)
        T[:3, 3] = d.site_xpos[self.grip_site]
        return T

    def on_peg(self) -> bool:
        return bool(self.env.rs.on_peg(self.nut_pose()[:3, 3], 0))

    def start(self) -> dict[str, Any]:
        """The record's square fields at the start (the nut as it lies after the reset)."""
        self._nut_rest = self.nut_pose()
        self._T_pre = expert_pregrasp_pose(self._nut_rest, self.table_z)
        self._touched = False
        return {"pregrasp_reached": False, "pregrasp_step": None, "pregrasp_min_pos_err_m": math.inf,
                "pregrasp_min_rot_err_deg": math.inf, "lifted": False, "lifted_step": None, "max_nut_rise_m": 0.0,
                "inserted": False, "inserted_step": None, "collision_table": False, "collision_table_steps": 0,
                "collision_peg": False, "collision_peg_steps": 0}

    def observe(self, rec: dict[str, Any], steps: int) -> None:
        """Sub-goals and contacts of the state after control step ``steps``."""
        c_table, c_peg, c_nut = self.contacts()
        rec["collision_table_steps"] += int(c_table)
        rec["collision_peg_steps"] += int(c_peg)
        nut = self.nut_pose()
        self._touched = self._touched or c_nut
        if not self._touched:  # the nut settles after the reset (spawned 2 cm up): follow it until first touched
            self._nut_rest = nut
            self._T_pre = expert_pregrasp_pose(nut, self.table_z)
        if not self._touched:  # min errors over the approach; reached = first step within tolerance
            dp, dr = pregrasp_error(self.site_pose(), self._T_pre)
            rec["pregrasp_min_pos_err_m"] = min(rec["pregrasp_min_pos_err_m"], dp)
            rec["pregrasp_min_rot_err_deg"] = min(rec["pregrasp_min_rot_err_deg"], math.degrees(dr))
            near = dp <= PREGRASP_POS_TOL_M and dr <= math.radians(PREGRASP_ROT_TOL_DEG)
            if near and not rec["pregrasp_reached"]:
                rec["pregrasp_reached"], rec["pregrasp_step"] = True, steps
        rise = float(nut[2, 3] - self._nut_rest[2, 3])
        rec["max_nut_rise_m"] = max(rec["max_nut_rise_m"], rise)
        if not rec["lifted"] and rise >= LIFT_HEIGHT_M and c_nut:
            rec["lifted"], rec["lifted_step"] = True, steps
        if not rec["inserted"] and self.on_peg():
            rec["inserted"], rec["inserted_step"] = True, steps

    def finish(self, rec: dict[str, Any]) -> None:
        """Closest approaches never measured → None; collision flags from their step counts."""
        for k in ("pregrasp_min_pos_err_m", "pregrasp_min_rot_err_deg"):
            rec[k] = None if not math.isfinite(rec[k]) else float(rec[k])
        rec["collision_table"] = rec["collision_table_steps"] > 0
        rec["collision_peg"] = rec["collision_peg_steps"] > 0

    def privileged(self, config: int) -> PrivilegedState:
        """The controls' snapshot of the current state (grip site, nut, peg, table height)."""
        return PrivilegedState.read(self.env, config)

    def env_action(self, target: np.ndarray, gripper_close_below_m: float | None) -> np.ndarray:
        """An absolute TCP target → the OSC_POSE delta from the current TCP pose (:func:`abs_tcp_to_osc_delta`;
        None: the Panda's threshold, half its opening)."""
        close = GRIPPER_CLOSE_BELOW_M if gripper_close_below_m is None else gripper_close_below_m
        return abs_tcp_to_osc_delta(self.env.tcp_pose(), target, close)

    def video_camera(self) -> np.ndarray:
        """A fixed camera 1.0 m in front of / 0.6 m above the table centre looking at it (OpenCV axes)."""
        eye = np.array([1.0, 0.0, self.table_z + 0.6])
        target = np.array([-0.05, 0.1, self.table_z + 0.05])
        z = (target - eye) / np.linalg.norm(target - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, z], axis=1)
        T[:3, 3] = eye
        return T


class SquareTask:
    """The square benchmark as the harness's :class:`~umi_aug.eval.task.SimTask` (stateless: pickles by name)."""

    name = "square"
    controls: tuple[str, ...] = CONTROLS
    subgoals: tuple[str, ...] = ("pregrasp_reached", "lifted", "inserted")
    collisions: tuple[str, ...] = ("collision_table", "collision_peg")

    def make_env(self, env_meta: dict[str, Any] | None) -> SquareEnv:
        """A :class:`SquareEnv` of ``env_meta`` (None: robomimic's square PH) that renders nothing itself."""
        return SquareEnv(env_meta=env_meta, image_size=None)

    def probe(self, env: SimEnv) -> TaskProbe:
        return SceneProbe(env)

    def camera(self, env: SimEnv, size: int) -> WristFisheyeCamera:
        return WristFisheyeCamera(env.model, size)

    def control(self, kind: str, spec: dict[str, Any]) -> PolicyLike:
        """``expert``, ``hold``, ``random`` (``spec["random_scale"]``) or ``replay`` (``spec["replay_actions"]``).

        Raises:
            EvalError: another kind.
        """
        if kind == "expert":
            return ExpertEvalPolicy()
        if kind == "hold":
            return HoldStillEvalPolicy()
        if kind == "random":
            return RandomEvalPolicy(spec["random_scale"])
        if kind == "replay":
            return ReplayEvalPolicy(spec["replay_actions"])
        raise EvalError(f"policy={kind!r}: expected one of {list(POLICY_KINDS)}")

    def replay_configs(self, replay_dir: str | Path) -> tuple[dict[str, Any], list[np.ndarray], list[str]]:
        """Start configurations + actions of recorded episode shards (``seed_*.npz`` in ``replay_dir``, sorted):
        configuration ``i`` is shard ``i``'s own start state ``states[0]``.

        Raises:
            EvalError: no shard, or an unreadable one.
        """
        d = Path(replay_dir)
        files = sorted(d.glob("seed_*.npz")) if d.is_dir() else []
        if not files:
            raise EvalError(f"replay_dir={str(replay_dir)!r}: no episode shards seed_*.npz (umi-aug square-demos "
                            f"writes them to <out>/shards/)")
        states, T_cam, actions = [], [], []
        for f in files:
            try:
                ep = load_episode(f)
            except UmiAugError as exc:
                raise EvalError(f"replay_dir: {exc}") from exc
            states.append(ep.states[0])
            T_cam.append(ep.T_world_tcp[0] @ pose_inverse(np.asarray(T_CAM_TCP)))
            actions.append(ep.actions)
        return ({"states": np.stack(states), "T_world_cam": np.stack(T_cam), "source_index": None,
                 "env_args": None}, actions, [f.name for f in files])

    def summary_info(self) -> dict[str, Any]:
        """The pre-grasp sub-goal's tolerances."""
        return {"pregrasp_tolerance": {"pos_m": PREGRASP_POS_TOL_M, "rot_deg": PREGRASP_ROT_TOL_DEG}}


#: the square benchmark of ``eval/eval_sim.py``
SQUARE_TASK = SquareTask()
