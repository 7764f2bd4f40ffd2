"""One evaluation rollout of the square task from a stored start configuration, with its record.

The policy is driven through the one policy contract only (:mod:`umi_aug.policy.contract`), by a
:class:`PolicyDriver` as Diffusion Policy's env runner drives its policies: per control step (20 Hz) observe
(low-dim always; the fisheye wrist image only when the policy's :class:`~umi_aug.eval.policies.RolloutSpec` has an
``image_size``, and only at the steps whose frame a coming inference will look at: :meth:`PolicyDriver.wants_image`)
→ when the queue of actions is empty, ``policy.predict_action(obs_dict)`` on the observation window → the next
queued row as the env's OSC_POSE delta → ``env.step``. Time is split into ``sim`` (``env.step`` incl. robosuite's
observation), ``render`` (fisheye wrist image), ``policy`` (the driver, incl. inference) and ``other`` (sub-goal
and contact checks, reset). Recorded (all world frame, metres):

* ``success`` — robosuite's task success (nut on the square peg AND gripper ≥ ~4 cm away) at ANY step, as
  Diffusion Policy scores it (max reward over the episode); ``steps_to_success`` = first such step (1-based);
* ``pregrasp_reached`` — the grip site came within :data:`PREGRASP_POS_TOL_M` and :data:`PREGRASP_ROT_TOL_DEG`
  of the configuration's expert pre-grasp pose (:func:`expert_pregrasp_pose`: the scripted expert's ``approach``
  goal — hover point above the handle, z down, fingers closing across the handle — computed from the nut as it
  lies, i.e. after it settled from its spawn height, until a finger first touches the nut; rotation error taken
  modulo the gripper's 180° symmetry about its approach axis);
* ``lifted`` — the nut was at least :data:`LIFT_HEIGHT_M` above its resting height (before first touched) while a
  finger touched it;
* ``inserted`` — the nut was on the square peg (robosuite's ``on_peg``: xy within 3 cm, below table + 5 cm),
  released or not;
* ``collision_table`` / ``collision_peg`` — any gripper (hand or finger) geom in contact with the table /
  either peg; counted in steps.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from umi_aug.errors import PolicyError
from umi_aug.eval.policies import PRIVILEGED_KEY, PrivilegedState, RolloutSpec, abs_tcp_to_osc_delta
from umi_aug.policy.contract import PolicyLike, SeedablePolicy, action_chunk
from umi_aug.sim.square.expert import (PREGRASP_POS_TOL_M, PREGRASP_ROT_TOL_DEG, expert_pregrasp_pose,
                                       pregrasp_error)

__all__ = ["PREGRASP_POS_TOL_M", "PREGRASP_ROT_TOL_DEG", "LIFT_HEIGHT_M", "expert_pregrasp_pose",
           "SceneProbe", "PolicyDriver", "rollout_config", "VideoSpec"]

#: the low-dim observation keys of the square env a policy gets (training's keys; the width as [1])
LOW_DIM_KEYS: tuple[str, ...] = ("robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width")

#: nut lift sub-goal: nut centre this far above its start height (m) with a finger touching it
LIFT_HEIGHT_M: float = 0.03


class SceneProbe:
    """Geom/body ids of the square scene for sub-goal and contact checks (built once per environment)."""

    def __init__(self, env: Any) -> None:
        import mujoco

        from umi_aug.sim.square.env import GRIP_SITE, NUT_BODY

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


class PolicyDriver:
    """Drives one policy through the contract during a rollout, as Diffusion Policy's env runner with its
    multi-step wrapper does: observation history → obs_dict window → ``predict_action`` when the queue of actions
    is empty → one queued row per control step as the square env's OSC_POSE delta.

    The window holds the last ``To`` observations spaced ``obs_down_sample_steps`` control steps apart, oldest
    first (early windows pad with the first); ``camera0_rgb`` holds its newest ``img_obs_horizon`` frames,
    the low-dim keys their newest ``low_dim_obs_horizon`` rows — a training sample's observation. The rows
    ``first_action …`` of each chunk are queued, each held for ``obs_down_sample_steps`` control steps.

    Args:
        policy: any :class:`~umi_aug.policy.contract.PolicyLike`.
        spec: how to run it (default :meth:`RolloutSpec.of(policy) <umi_aug.eval.policies.RolloutSpec.of>`).
    """

    def __init__(self, policy: PolicyLike, spec: RolloutSpec | None = None) -> None:
        self.policy = policy
        self.spec = spec or RolloutSpec.of(policy)
        self._To = self.spec.obs_horizon
        self._down = int(self.spec.obs_down_sample_steps)
        self._hist: deque = deque(maxlen=(self._To - 1) * self._down + 1)
        self._queue: list[np.ndarray] = []

    def reset(self, seed: int) -> None:
        """Start a rollout: ``policy.reset()``; a :class:`~umi_aug.policy.contract.SeedablePolicy` is seeded with
        ``seed`` (its randomness is then a function of the rollout seed alone)."""
        self.policy.reset()
        if isinstance(self.policy, SeedablePolicy):
            self.policy.seed(seed)
        self._hist.clear()
        self._queue = []

    def wants_image(self) -> bool:
        """True iff the frame of the coming :meth:`act` enters some future inference's observation window.

        Inferences happen when the queue runs empty: in ``q`` steps (``q`` = rows still queued; now if 0), then
        every ``L = n_action_steps · obs_down_sample_steps`` steps; each looks back at offsets
        ``0, down, …, (To−1)·down``. The very first frame is always kept (early windows pad with it); with no fixed
        ``n_action_steps`` every frame is. With UMI's ``To = 2``, 8 executed targets and ``down = 1`` this renders
        2 frames in 8.
        """
        q = len(self._queue)
        if q == 0 or not self._hist or self.spec.n_action_steps is None:
            return True
        L = self.spec.n_action_steps * self._down
        return any(k * self._down >= q and (k * self._down - q) % L == 0 for k in range(self._To))

    def _obs_dict(self) -> dict[str, Any]:
        h = list(self._hist)
        idx = [max(0, len(h) - 1 - k * self._down) for k in range(self._To)][::-1]
        rows = [h[i] for i in idx]
        low = rows[self._To - self.spec.low_dim_obs_horizon:]
        out: dict[str, Any] = {k: np.stack([r[k] for r in low]) for k in LOW_DIM_KEYS}
        if self.spec.image_size:
            cam = rows[self._To - self.spec.img_obs_horizon:]
            if any(r["camera0_rgb"] is None for r in cam):  # wants_image() said no to a frame used here: a bug
                raise PolicyError(f"observation frames {idx} of {len(h)}: an image the schedule skipped is needed")
            out["camera0_rgb"] = np.stack([r["camera0_rgb"] for r in cam])
        return out

    def act(self, obs: Mapping[str, Any], tcp_pose: Callable[[], np.ndarray],
            privileged: Callable[[], PrivilegedState] | None = None) -> np.ndarray:
        """The OSC_POSE delta ``[7]`` of this control step.

        Args:
            obs: this step's env observation (``robot0_eef_pos``, ``robot0_eef_rot_axis_angle``,
                ``robot0_gripper_width``; ``camera0_rgb`` when the spec has an ``image_size``: the rendered image,
                or ``None`` where :meth:`wants_image` said no).
            tcp_pose: reads the current ``T_world_tcp`` [4, 4] (converting an absolute target).
            privileged: reads the :class:`~umi_aug.eval.policies.PrivilegedState` (privileged controls only).
        Raises:
            PolicyError: a result without ``"action"``, or a chunk with no row to execute.
        """
        s = self.spec
        row = {"robot0_eef_pos": np.asarray(obs["robot0_eef_pos"], np.float64),
               "robot0_eef_rot_axis_angle": np.asarray(obs["robot0_eef_rot_axis_angle"], np.float64),
               "robot0_gripper_width": np.asarray(obs["robot0_gripper_width"], np.float64).reshape(1)}
        if s.image_size:
            row["camera0_rgb"] = obs["camera0_rgb"]
        self._hist.append(row)
        if not self._queue:
            obs_dict = self._obs_dict()
            if s.privileged:
                if privileged is None:
                    raise PolicyError("a privileged control needs the simulator's state; none was given")
                obs_dict[PRIVILEGED_KEY] = privileged()
            chunk = np.asarray(action_chunk(self.policy.predict_action(obs_dict)), np.float64)
            stop = None if s.n_action_steps is None else s.first_action + s.n_action_steps
            todo = chunk[s.first_action:stop] if chunk.ndim == 2 and chunk.shape[1] == 7 else chunk[:0]
            if len(todo) == 0:
                raise PolicyError(f"predict_action returned an action chunk of shape {chunk.shape}; the square env "
                                  f"executes rows {s.first_action} … of an [n, 7] chunk")
            self._queue = [a for a in todo for _ in range(self._down)]
        a = self._queue.pop(0)
        return a if s.env_actions else abs_tcp_to_osc_delta(tcp_pose(), a, s.gripper_close_below_m)


@dataclass
class VideoSpec:
    """Videos of one rollout: ``wrist`` fisheye and ``external`` pinhole (fixed scene camera) mp4 paths."""

    wrist_path: str
    external_path: str
    size: int = 224
    every: int = 2  # write every n-th control step (20 Hz / 2 = 10 fps, as DP's runner)


class _Videos:
    def __init__(self, env: Any, spec: VideoSpec, camera_factory) -> None:
        from umi_aug.data.video import VideoWriter
        from umi_aug.sim.raster import PinholeRasterizer, RasterOptions

        self.spec = spec
        self.env = env
        self.wrist = camera_factory(spec.size)
        self.ext = PinholeRasterizer(env.model, spec.size, RasterOptions(near=0.01, far=10.0))
        fps = 20.0 / spec.every
        self.w_wrist = VideoWriter(spec.wrist_path, spec.size, spec.size, fps)
        self.w_ext = VideoWriter(spec.external_path, spec.size, spec.size, fps)
        # a fixed camera 1.0 m in front of / 0.6 m above the table centre looking at it (OpenCV axes)
        tz = float(env.rs.table_offset[2])
        eye = np.array([1.0, 0.0, tz + 0.6])
        target = np.array([-0.05, 0.1, tz + 0.05])
        z = (target - eye) / np.linalg.norm(target - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        self.T_ext = np.eye(4)
        self.T_ext[:3, :3] = np.stack([x, y, z], axis=1)
        self.T_ext[:3, 3] = eye

    def frame(self, t: int) -> None:
        if t % self.spec.every:
            return
        self.w_wrist.write(self.wrist.render(self.env.data, self.env.wrist_pose()))
        self.ext.update_scene(self.env.data, self.T_ext)
        rgb, _ = self.ext.render(self.T_ext, 55.0, rgb=True, depth=False)
        self.w_ext.write(rgb)

    def close(self) -> None:
        self.w_wrist.close()
        self.w_ext.close()
        self.ext.close()


def rollout_config(env: Any, probe: SceneProbe, policy: Any, state: np.ndarray, config: int, seed: int,
                   horizon: int = 400, camera=None, stop_on_success: bool = True,
                   video: VideoSpec | None = None, camera_factory=None,
                   render_every_step: bool = False) -> dict[str, Any]:
    """Run ``policy`` from the flattened MuJoCo ``state`` for up to ``horizon`` control steps.

    The environment is first reset (fixed seed 0: clears the gripper's integrated command and the controller, so a
    rollout never depends on the previous one), then the stored state is restored as an episode start (the
    controller's null-space posture reference = its arm joints, as when the environment was reset into it).

    Args:
        env: :class:`~umi_aug.sim.square.env.SquareEnv` created with ``image_size=None`` (step renders nothing).
        probe: :class:`SceneProbe` of ``env``.
        policy: any :class:`~umi_aug.policy.contract.PolicyLike`, run as its
            :class:`~umi_aug.eval.policies.RolloutSpec` says (:class:`PolicyDriver`).
        state: float64 [45] robomimic flattened state of the start configuration.
        config, seed: configuration index (privileged controls read it) and rollout seed (seeds a
            :class:`~umi_aug.policy.contract.SeedablePolicy`).
        camera: :class:`~umi_aug.sim.square.camera.WristFisheyeCamera` at the policy's image size (needed iff
            the spec has an ``image_size``).
        stop_on_success: end at the first successful step (robomimic's ``terminate_on_success``; the score —
            success at any step — is the same as running on).
        video: write videos of this rollout.
        render_every_step: render the wrist image at every step, not only the frames the policy will look at
            (reference path of the tests; same outcome, ~4× the rendering).
    Returns:
        JSON-able record (see module docstring).
    """
    t_start = time.perf_counter()
    tm = {"sim": 0.0, "render": 0.0, "policy": 0.0, "other": 0.0}
    env.reset(seed=0)
    obs = env.reset_to(state, initial=True)
    driver = PolicyDriver(policy)
    driver.reset(seed)
    nut_rest = probe.nut_pose()
    T_pre = expert_pregrasp_pose(nut_rest, probe.table_z)
    rec: dict[str, Any] = {
        "config": int(config), "seed": int(seed), "success": False, "steps_to_success": None,
        "pregrasp_reached": False, "pregrasp_step": None, "pregrasp_min_pos_err_m": math.inf,
        "pregrasp_min_rot_err_deg": math.inf, "lifted": False, "lifted_step": None, "max_nut_rise_m": 0.0,
        "inserted": False, "inserted_step": None, "collision_table": False, "collision_table_steps": 0,
        "collision_peg": False, "collision_peg_steps": 0,
    }
    videos = _Videos(env, video, camera_factory) if video is not None else None
    tm["other"] += time.perf_counter() - t_start
    steps = 0
    touched = False  # a finger has touched the nut (from then on the pre-grasp goal and rest height are frozen)
    try:
        for t in range(int(horizon)):
            if driver.spec.image_size:  # only the frames the policy will look at (PolicyDriver.wants_image)
                t0 = time.perf_counter()
                obs["camera0_rgb"] = (camera.render(env.data, env.wrist_pose())
                                      if render_every_step or driver.wants_image() else None)
                tm["render"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            action = driver.act(obs, env.tcp_pose, lambda: PrivilegedState.read(env, config))
            t1 = time.perf_counter()
            obs, _, _, _ = env.step(action)
            t2 = time.perf_counter()
            tm["policy"] += t1 - t0
            tm["sim"] += t2 - t1
            steps = t + 1
            # ---- sub-goals and contacts of the state after this step
            c_table, c_peg, c_nut = probe.contacts()
            rec["collision_table_steps"] += int(c_table)
            rec["collision_peg_steps"] += int(c_peg)
            nut = probe.nut_pose()
            touched = touched or c_nut
            if not touched:  # the nut settles after the reset (spawned 2 cm up): follow it until first touched
                nut_rest = nut
                T_pre = expert_pregrasp_pose(nut, probe.table_z)
            if not touched:  # min errors over the approach; reached = first step within tolerance
                dp, dr = pregrasp_error(probe.site_pose(), T_pre)
                rec["pregrasp_min_pos_err_m"] = min(rec["pregrasp_min_pos_err_m"], dp)
                rec["pregrasp_min_rot_err_deg"] = min(rec["pregrasp_min_rot_err_deg"], math.degrees(dr))
                near = dp <= PREGRASP_POS_TOL_M and dr <= math.radians(PREGRASP_ROT_TOL_DEG)
                if near and not rec["pregrasp_reached"]:
                    rec["pregrasp_reached"], rec["pregrasp_step"] = True, steps
            rise = float(nut[2, 3] - nut_rest[2, 3])
            rec["max_nut_rise_m"] = max(rec["max_nut_rise_m"], rise)
            if not rec["lifted"] and rise >= LIFT_HEIGHT_M and c_nut:
                rec["lifted"], rec["lifted_step"] = True, steps
            if not rec["inserted"] and probe.on_peg():
                rec["inserted"], rec["inserted_step"] = True, steps
            success = env.is_success()
            if videos is not None:
                videos.frame(t)
            tm["other"] += time.perf_counter() - t2
            if success and not rec["success"]:
                rec["success"], rec["steps_to_success"] = True, steps
                if stop_on_success:
                    break
    finally:
        if videos is not None:
            videos.close()
    for k in ("pregrasp_min_pos_err_m", "pregrasp_min_rot_err_deg"):
        rec[k] = None if not math.isfinite(rec[k]) else float(rec[k])
    rec["collision_table"] = rec["collision_table_steps"] > 0
    rec["collision_peg"] = rec["collision_peg_steps"] > 0
    rec["steps"] = steps
    rec["final_state_sha1"] = hashlib.sha1(np.ascontiguousarray(env.get_state()).tobytes()).hexdigest()
    if hasattr(policy, "info"):  # optional report of a scripted control (the expert's final phase)
        rec["policy_info"] = policy.info()
    rec["time_s"] = tm
    rec["wall_s"] = time.perf_counter() - t_start
    return rec
