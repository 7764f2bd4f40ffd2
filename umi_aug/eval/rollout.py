"""One evaluation rollout from a stored start configuration, with its record — for any simulated task.

The policy is driven through the one policy contract only (:mod:`umi_aug.policy.contract`), by a
:class:`PolicyDriver` as Diffusion Policy's env runner drives its policies: per control step observe (low-dim
always; the fisheye wrist image only when the policy's :class:`~umi_aug.eval.policies.RolloutSpec` has an
``image_size``, and only at the steps whose frame a coming inference will look at: :meth:`PolicyDriver.wants_image`)
→ when the queue of actions is empty, ``policy.predict_action(obs_dict)`` on the observation window → the next
queued row as the environment's action → ``env.step``. Time is split into ``sim`` (``env.step`` incl. the
simulator's observation), ``render`` (fisheye wrist image), ``policy`` (the driver, incl. inference) and
``other`` (the task's sub-goal and contact checks, reset).

The environment and what the record says about the task come from the benchmark (:mod:`umi_aug.eval.task`:
:class:`~umi_aug.eval.task.SimEnv`, :class:`~umi_aug.eval.task.TaskProbe`; the square's in
:mod:`umi_aug.square.eval`). Recorded: ``config``, ``seed``, ``success`` — the environment's task success at ANY
step, as Diffusion Policy scores it (max reward over the episode) — and ``steps_to_success`` (first such step,
1-based), then the task's fields (:meth:`~umi_aug.eval.task.TaskProbe.start`), ``steps``, ``final_state_sha1``,
``policy_info`` (a scripted control's report), ``time_s`` and ``wall_s``; with a :class:`Handover`, also
``handover_step``, ``handover_reason`` and ``handover_info``.
"""

from __future__ import annotations

import hashlib
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from umi_aug.data.video import VideoWriter
from umi_aug.errors import PolicyError
from umi_aug.eval.policies import PRIVILEGED_KEY, RolloutSpec
from umi_aug.eval.task import SimEnv, TaskProbe, WristCamera
from umi_aug.policy.contract import PolicyLike, SeedablePolicy, action_chunk
from umi_aug.sim.raster import PinholeRasterizer, RasterOptions

__all__ = ["LOW_DIM_KEYS", "Handover", "PolicyDriver", "rollout_config", "VideoSpec"]

#: the low-dim observation keys a policy gets (UMI's training keys; the width as [1])
LOW_DIM_KEYS: tuple[str, ...] = ("robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width")


class PolicyDriver:
    """Drives one policy through the contract during a rollout, as Diffusion Policy's env runner with its
    multi-step wrapper does: observation history → obs_dict window → ``predict_action`` when the queue of actions
    is empty → one queued row per control step as the environment's action.

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
        every ``L = n_action_steps · obs_down_sample_steps`` steps; each looks at the images at offsets
        ``0, down, …, (img_obs_horizon−1)·down`` (the window's newest ``img_obs_horizon`` frames; the low-dim rows
        further back need no image). The very first frame is always kept (early windows pad with it); with no
        fixed ``n_action_steps`` every frame is. With UMI's two image frames, 8 executed targets and ``down = 1``
        this renders 2 frames in 8; with one image frame (and two low-dim rows), 1 in 8.
        """
        q = len(self._queue)
        if q == 0 or not self._hist or self.spec.n_action_steps is None:
            return True
        L = self.spec.n_action_steps * self._down
        return any(k * self._down >= q and (k * self._down - q) % L == 0 for k in range(self.spec.img_obs_horizon))

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

    def act(self, obs: Mapping[str, Any], env_action: Callable[[np.ndarray, float | None], np.ndarray],
            privileged: Callable[[], Any] | None = None) -> np.ndarray:
        """The environment's action of this control step.

        Args:
            obs: this step's env observation (``robot0_eef_pos``, ``robot0_eef_rot_axis_angle``,
                ``robot0_gripper_width``; ``camera0_rgb`` when the spec has an ``image_size``: the rendered image,
                or ``None`` where :meth:`wants_image` said no).
            env_action: ``env_action(target, gripper_close_below_m)`` turns an absolute TCP target ``[7]`` into
                the environment's action from the current pose (:meth:`~umi_aug.eval.task.TaskProbe.env_action`;
                not called for a spec with ``env_actions``).
            privileged: reads the task's privileged snapshot (privileged controls only).
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
        return a if s.env_actions else env_action(a, s.gripper_close_below_m)


@dataclass
class Handover:
    """A second policy that finishes a rollout (:func:`rollout_config`'s ``handover``).

    Attributes:
        policy: the policy that takes over (any :class:`~umi_aug.policy.contract.PolicyLike`, run by its own
            :class:`PolicyDriver`: a privileged scripted control reads the simulator from then on).
        subgoal: the task record's boolean sub-goal field whose first ``True`` hands over (the square's
            ``pregrasp_reached``); None: only the step limit.
        step_limit: hand over after this many control steps even without the sub-goal; None: never.
    """

    policy: Any
    subgoal: str | None = None
    step_limit: int | None = None

    def due(self, rec: Mapping[str, Any], steps: int) -> str | None:
        """``"subgoal"`` / ``"step_limit"`` when the rollout's first ``steps`` control steps call for the
        handover, else None."""
        if self.subgoal is not None and rec.get(self.subgoal):
            return "subgoal"
        if self.step_limit is not None and steps >= self.step_limit:
            return "step_limit"
        return None


@dataclass
class VideoSpec:
    """Videos of one rollout: ``wrist`` fisheye and ``external`` pinhole (fixed scene camera) mp4 paths."""

    wrist_path: str
    external_path: str
    size: int = 224
    every: int = 2  # write every n-th control step (20 Hz / 2 = 10 fps, as DP's runner)


class _Videos:
    def __init__(self, env: SimEnv, spec: VideoSpec, camera_factory: Callable[[int], WristCamera],
                 T_ext: np.ndarray) -> None:
        self.spec = spec
        self.env = env
        self.wrist = camera_factory(spec.size)
        self.ext = PinholeRasterizer(env.model, spec.size, RasterOptions(near=0.01, far=10.0))
        fps = 20.0 / spec.every
        self.w_wrist = VideoWriter(spec.wrist_path, spec.size, spec.size, fps)
        self.w_ext = VideoWriter(spec.external_path, spec.size, spec.size, fps)
        self.T_ext = np.asarray(T_ext, np.float64)

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


def rollout_config(env: SimEnv, probe: TaskProbe, policy: Any, state: np.ndarray, config: int, seed: int,
                   horizon: int = 400, camera: WristCamera | None = None, stop_on_success: bool = True,
                   video: VideoSpec | None = None, camera_factory: Callable[[int], WristCamera] | None = None,
                   render_every_step: bool = False, handover: Handover | None = None) -> dict[str, Any]:
    """Run ``policy`` from the flattened simulator ``state`` for up to ``horizon`` control steps.

    The environment is first reset (fixed seed 0: clears the gripper's integrated command and the controller, so a
    rollout never depends on the previous one), then the stored state is restored as an episode start (the
    controller's null-space posture reference = its arm joints, as when the environment was reset into it).

    Args:
        env: the task's environment (:class:`~umi_aug.eval.task.SimEnv`; the square's
            :class:`~umi_aug.square.env.SquareEnv` created with ``image_size=None``: step renders nothing).
        probe: the task's :class:`~umi_aug.eval.task.TaskProbe` of ``env`` (the square's
            :class:`~umi_aug.square.eval.SceneProbe`).
        policy: any :class:`~umi_aug.policy.contract.PolicyLike`, run as its
            :class:`~umi_aug.eval.policies.RolloutSpec` says (:class:`PolicyDriver`).
        state: float64 [S] flattened simulator state of the start configuration (the square's: robomimic's [45]).
        config, seed: configuration index (privileged controls read it) and rollout seed (seeds a
            :class:`~umi_aug.policy.contract.SeedablePolicy`).
        camera: the wrist camera at the policy's image size (needed iff the spec has an ``image_size``).
        stop_on_success: end at the first successful step (robomimic's ``terminate_on_success``; the score —
            success at any step — is the same as running on).
        video: write videos of this rollout (``camera_factory(size)`` gives the wrist camera of the video size).
        render_every_step: render the wrist image at every step, not only the frames the policy will look at
            (reference path of the tests; same outcome, ~4× the rendering).
        handover: a second policy that takes over from ``policy`` for the rest of the rollout once the task's
            sub-goal ``handover.subgoal`` is first reached or after ``handover.step_limit`` control steps
            (e.g. a learned approach finished by the scripted expert); recorded as ``handover_step`` (control
            steps the first policy drove) and ``handover_reason`` (``"subgoal"``, ``"step_limit"`` or None).
    Returns:
        JSON-able record (see module docstring).
    """
    t_start = time.perf_counter()
    tm = {"sim": 0.0, "render": 0.0, "policy": 0.0, "other": 0.0}
    env.reset(seed=0)
    obs = env.reset_to(state, initial=True)
    driver = PolicyDriver(policy)
    driver.reset(seed)
    rec: dict[str, Any] = {"config": int(config), "seed": int(seed), "success": False, "steps_to_success": None,
                           **probe.start()}
    if handover is not None:
        rec |= {"handover_step": None, "handover_reason": None}
    videos = _Videos(env, video, camera_factory, probe.video_camera()) if video is not None else None
    tm["other"] += time.perf_counter() - t_start
    steps = 0
    try:
        for t in range(int(horizon)):
            if driver.spec.image_size:  # only the frames the policy will look at (PolicyDriver.wants_image)
                t0 = time.perf_counter()
                obs["camera0_rgb"] = (camera.render(env.data, env.wrist_pose())
                                      if render_every_step or driver.wants_image() else None)
                tm["render"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            action = driver.act(obs, probe.env_action, lambda: probe.privileged(config))
            t1 = time.perf_counter()
            obs, _, _, _ = env.step(action)
            t2 = time.perf_counter()
            tm["policy"] += t1 - t0
            tm["sim"] += t2 - t1
            steps = t + 1
            probe.observe(rec, steps)  # the task's sub-goals and contacts of the state after this step
            if handover is not None and rec["handover_reason"] is None:
                why = handover.due(rec, steps)
                if why:
                    rec["handover_step"], rec["handover_reason"] = steps, why
                    driver = PolicyDriver(handover.policy)
                    driver.reset(seed)
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
    probe.finish(rec)
    rec["steps"] = steps
    rec["final_state_sha1"] = hashlib.sha1(np.ascontiguousarray(env.get_state()).tobytes()).hexdigest()
    if hasattr(policy, "info"):  # optional report of a scripted control (the expert's final phase)
        rec["policy_info"] = policy.info()
    if handover is not None and rec["handover_reason"] and hasattr(handover.policy, "info"):
        rec["handover_info"] = handover.policy.info()
    rec["time_s"] = tm
    rec["wall_s"] = time.perf_counter() - t_start
    return rec
