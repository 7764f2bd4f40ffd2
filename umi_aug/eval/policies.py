"""Policies the simulation harness drives, all behind one small interface (:class:`EvalPolicy`).

Every policy turns the current environment state / observation into ONE 7-D OSC_POSE delta action of the square
environment per 20 Hz control step (``[dx, dy, dz] / 0.05 m, axis-angle / 0.5 rad`` in the world frame, gripper
``−1`` open … ``+1`` close; what :meth:`umi_aug.sim.square.env.SquareEnv.step` takes).

* :class:`CheckpointEvalPolicy` — a trained Diffusion Policy (:class:`umi_aug.policy.Policy`). It outputs
  ABSOLUTE targets (position, rotation vector, gripper width). The square policies are trained on the targets the
  expert COMMANDED (``task.action_key: action``; :mod:`umi_aug.sim.square.commands`), and each is executed the way
  it was commanded when recorded: :func:`~umi_aug.sim.square.commands.osc_delta_from_target` turns it into the
  OSC_POSE delta from the current pose — exactly the demo's action when the arm is where the demo's was (issue #29
  B2: labels of REACHED poses executed this way moved the arm only 0.64–0.66 of the demo's way per chunk). The
  gripper width target becomes the Panda's command: close below ``gripper_close_below_m`` (half its opening),
  open otherwise.
* :class:`ExpertEvalPolicy` — the privileged-state scripted expert (needs no images: nothing is rendered).
* :class:`ReplayEvalPolicy` — replays recorded actions open loop (control: must succeed from the recording's state).
* :class:`HoldStillEvalPolicy`, :class:`RandomEvalPolicy` — controls that must never succeed.
"""

from __future__ import annotations

import os
from collections import deque
from typing import Any, Protocol, Sequence

import numpy as np

from umi_aug.errors import PolicyError, SimError
from umi_aug.sim.square.commands import GRIPPER_CLOSE_BELOW_M, osc_delta_from_target
from umi_aug.sim.square.expert import ExpertConfig, SquareExpert

__all__ = ["EvalPolicy", "ExpertEvalPolicy", "HoldStillEvalPolicy", "RandomEvalPolicy", "ReplayEvalPolicy",
           "CheckpointEvalPolicy", "abs_tcp_to_osc_delta", "POLICY_KINDS"]

#: values of ``policy=`` in ``configs/eval_sim.yaml``
POLICY_KINDS: tuple[str, ...] = ("checkpoint", "expert", "replay", "hold", "random")


class EvalPolicy(Protocol):
    """What the harness needs from a policy.

    Attributes:
        name: short label for reports.
        image_size: fisheye image size the policy observes (pixels), or ``None`` = no images (nothing rendered).
    """

    name: str
    image_size: int | None

    def reset(self, env: Any, config: int, seed: int) -> None:
        """Start a rollout of configuration ``config``; ``seed`` fixes all of the policy's randomness."""

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        """OSC_POSE delta action ``[7]`` for the current step (``obs``: env observation, + ``camera0_rgb`` when
        ``image_size`` is set: the rendered image, or ``None`` where :meth:`wants_image` said no)."""

    def wants_image(self) -> bool:
        """Whether the image of the coming :meth:`act` call will ever be looked at (policies with images only;
        the harness renders only those frames)."""


def abs_tcp_to_osc_delta(T_world_tcp: np.ndarray, target: np.ndarray,
                         gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> np.ndarray:
    """An absolute TCP target ``[7]`` → the square env's OSC_POSE delta action
    (:func:`umi_aug.sim.square.commands.osc_delta_from_target`; a bad target raises :class:`PolicyError`)."""
    try:
        return osc_delta_from_target(T_world_tcp, target, gripper_close_below_m)
    except SimError as exc:
        raise PolicyError(str(exc)) from None


class ExpertEvalPolicy:
    """The scripted privileged-state expert (:class:`~umi_aug.sim.square.expert.SquareExpert`)."""

    name = "expert"
    image_size = None

    def __init__(self, cfg: ExpertConfig | None = None) -> None:
        self.expert = SquareExpert(cfg)

    def reset(self, env: Any, config: int, seed: int) -> None:
        self.expert.reset()

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.expert.act(env)

    def info(self) -> dict[str, Any]:
        """Final expert phase (for failure analysis)."""
        return {"expert_phase": self.expert.phase}


class HoldStillEvalPolicy:
    """Zero motion, gripper open: the arm holds its start pose (a control that must never succeed)."""

    name = "hold"
    image_size = None

    def reset(self, env: Any, config: int, seed: int) -> None:
        pass

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])


class RandomEvalPolicy:
    """Uniform random actions in ``[−scale, scale]⁷`` from a generator seeded per rollout (a control)."""

    name = "random"
    image_size = None

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = float(scale)
        self.rng = np.random.default_rng(0)

    def reset(self, env: Any, config: int, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self.rng.uniform(-self.scale, self.scale, 7)


class ReplayEvalPolicy:
    """Replays recorded OSC actions open loop; configuration ``i`` replays ``actions[i]`` (then holds still).

    Args:
        actions: per configuration, float [T_i, 7] recorded actions.
    """

    name = "replay"
    image_size = None

    def __init__(self, actions: Sequence[np.ndarray]) -> None:
        self.actions = [np.asarray(a, dtype=np.float64) for a in actions]
        for i, a in enumerate(self.actions):
            if a.ndim != 2 or a.shape[1] != 7 or not np.isfinite(a).all():
                raise PolicyError(f"ReplayEvalPolicy: actions[{i}] must be finite [T, 7], got {a.shape}")
        self._cur: np.ndarray = np.zeros((0, 7))
        self._t = 0

    def reset(self, env: Any, config: int, seed: int) -> None:
        if not 0 <= config < len(self.actions):
            raise PolicyError(f"ReplayEvalPolicy: no recorded episode for configuration {config} "
                              f"({len(self.actions)} recorded)")
        self._cur, self._t = self.actions[config], 0

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        a = self._cur[self._t] if self._t < len(self._cur) else HoldStillEvalPolicy().act(env, obs)
        self._t += 1
        return a


class CheckpointEvalPolicy:
    """A trained checkpoint run closed loop: observation history → action chunk → per-step OSC deltas.

    At a step with no queued targets it calls :meth:`umi_aug.policy.Policy.predict_action` on the last ``To``
    observations (spaced ``obs_down_sample_steps`` apart, oldest first; the first step is padded by repetition as in
    training), takes the chunk's targets ``1 … n_action_steps`` (target 0 is the current pose: UMI's action window
    starts at the current step) and executes them one per control step (each held for ``obs_down_sample_steps``
    steps), converted by :func:`abs_tcp_to_osc_delta`. Sampling noise comes from a ``torch.Generator`` seeded with
    the rollout seed, so a rollout is a deterministic function of (checkpoint, configuration, seed).

    Args:
        policy: a :class:`umi_aug.policy.Policy` (:meth:`from_checkpoint` loads one from a training checkpoint).
        n_action_steps: executed targets per inference (default: the policy's ``policy.n_action_steps``).
        gripper_close_below_m: width targets below this close the gripper (:func:`abs_tcp_to_osc_delta`).
    """

    name = "checkpoint"

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, device: str = "cpu", n_action_steps: int | None = None,
                        gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> "CheckpointEvalPolicy":
        """Load a training checkpoint (``umi_aug.policy.checkpoint``; EMA weights when present).

        Raises:
            PolicyError: unreadable/malformed checkpoint, or one that does not fit the square env (names the file).
        """
        from umi_aug.policy import Policy

        try:
            return cls(Policy.from_checkpoint(path, device=device), n_action_steps, gripper_close_below_m)
        except PolicyError as exc:
            msg = str(exc)
            raise PolicyError(msg if str(path) in msg else f"checkpoint {path}: {msg}") from exc

    def __init__(self, policy: Any, n_action_steps: int | None = None,
                 gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> None:
        self.policy = policy
        task = self.policy.task
        if task.n_robots != 1 or task.n_cameras != 1:
            raise PolicyError(f"the square env has one arm and one camera; the policy expects "
                              f"n_robots={task.n_robots}, n_cameras={task.n_cameras}")
        self.image_size: int | None = int(task.image_size)
        self.down = int(task.obs_down_sample_steps)
        self.To = max(int(task.img_obs_horizon), int(task.low_dim_obs_horizon))
        n = int(n_action_steps or self.policy.n_action_steps)
        if not 1 <= n <= task.action_horizon - 1:
            raise PolicyError(f"n_action_steps={n} must be in [1, {task.action_horizon - 1}] (target 0 is the "
                              f"current pose)")
        self.n_exec = n
        self.close_below_m = float(gripper_close_below_m)
        self._hist: deque = deque(maxlen=(self.To - 1) * self.down + 1)
        self._queue: list[np.ndarray] = []
        self._gen = None
        self.n_inferences = 0

    def reset(self, env: Any, config: int, seed: int) -> None:
        import torch

        self.policy.reset()
        self._hist.clear()
        self._queue = []
        self._gen = torch.Generator().manual_seed(int(seed))

    def _obs_dict(self) -> dict[str, np.ndarray]:
        h = list(self._hist)
        idx = [max(0, len(h) - 1 - k * self.down) for k in range(self.To)][::-1]
        rows = [h[i] for i in idx]
        if any(r["camera0_rgb"] is None for r in rows):  # wants_image() said no to a frame used here: a bug
            raise PolicyError(f"observation frames {idx} of {len(h)}: an image the schedule skipped is needed")
        return {k: np.stack([r[k] for r in rows]) for k in rows[0]}

    def wants_image(self) -> bool:
        """True iff the frame of the coming :meth:`act` enters some future inference's observation window.

        Inferences happen when the queue runs empty: in ``q`` steps (``q`` = targets still queued; now if 0), then
        every ``L = n_action_steps · obs_down_sample_steps`` steps; each looks back at offsets
        ``0, down, …, (To−1)·down``. The very first frame is always kept (early windows pad with it). With UMI's
        ``To = 2``, 8 executed targets and ``down = 1`` this renders 2 frames in 8.
        """
        q = len(self._queue)
        if q == 0 or not self._hist:
            return True
        L = self.n_exec * self.down
        return any(k * self.down >= q and (k * self.down - q) % L == 0 for k in range(self.To))

    def act(self, env: Any, obs: dict[str, np.ndarray]) -> np.ndarray:
        self._hist.append({"robot0_eef_pos": np.asarray(obs["robot0_eef_pos"], np.float64),
                           "robot0_eef_rot_axis_angle": np.asarray(obs["robot0_eef_rot_axis_angle"], np.float64),
                           "robot0_gripper_width": np.asarray(obs["robot0_gripper_width"], np.float64).reshape(1),
                           "camera0_rgb": obs["camera0_rgb"]})
        if not self._queue:
            chunk = self.policy.predict_action(self._obs_dict(), n_steps=self.n_exec + 1, generator=self._gen)
            self.n_inferences += 1
            self._queue = [row for row in chunk[1:] for _ in range(self.down)]
        target = self._queue.pop(0)
        return abs_tcp_to_osc_delta(env.tcp_pose(), target, self.close_below_m)
