"""Policies the simulation harness drives — every one through the one policy contract
(:class:`umi_aug.policy.contract.PolicyLike`: ``reset()``, ``predict_action(obs_dict) -> {"action": chunk}``).

The rollout (:mod:`umi_aug.eval.rollout`) is the environment runner, as in Diffusion Policy: it keeps the
observation history, builds the ``obs_dict`` window, calls ``predict_action`` when its queue of actions is empty
and executes the chunk one row per control step as the environment's action. How it runs a policy — window,
image size, rows executed, action kind — is the policy's :class:`RolloutSpec` (eval-side facts, not part of the
contract): its ``rollout_spec`` attribute, else one read from its training ``task`` (a
:class:`umi_aug.policy.Policy`), else the defaults (any object with ``predict_action`` / ``reset`` runs).

* :class:`CheckpointEvalPolicy` — a trained Diffusion Policy (:class:`umi_aug.policy.Policy`) with a fixed chunk
  length and sampling noise seeded per rollout (:class:`~umi_aug.policy.contract.SeedablePolicy`). Its obs_dict is
  exactly the training sample's observation; it outputs ABSOLUTE targets (position, rotation vector, gripper
  width), which the task's probe turns into the environment's action from the current pose
  (:meth:`umi_aug.eval.task.TaskProbe.env_action`; the square env: an OSC_POSE delta,
  :func:`umi_aug.square.controls.abs_tcp_to_osc_delta`).
* Scripted controls (a benchmark's own, :meth:`umi_aug.eval.task.SimTask.control`; the square's expert, replay,
  hold-still and random in :mod:`umi_aug.square.controls`) output the environment's own actions, one per call
  (:data:`CONTROL_SPEC`). Privileged ones read the simulator through one documented entry of their obs_dict,
  :data:`PRIVILEGED_KEY` (the snapshot :meth:`~umi_aug.eval.task.TaskProbe.privileged` takes before each call),
  never through the environment; a learned policy's obs_dict never has the entry.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from umi_aug.errors import PolicyError
from umi_aug.policy.contract import ACTION_KEY

__all__ = ["RolloutSpec", "CONTROL_SPEC", "PRIVILEGED_KEY", "one_action_chunk", "CheckpointEvalPolicy"]

#: the obs_dict entry of the privileged controls (the task's snapshot); never given to a learned policy
PRIVILEGED_KEY = "privileged"


@dataclass(frozen=True)
class RolloutSpec:
    """How the rollout runs a policy (eval-side facts; the policy itself only answers ``predict_action``).

    Attributes:
        img_obs_horizon: camera frames per obs_dict (the newest of the window), if ``image_size`` is set.
        low_dim_obs_horizon: low-dim rows per obs_dict (the newest of the window).
        obs_down_sample_steps: control steps between consecutive observations of a window; each executed row is
            held this many control steps (one policy step).
        image_size: fisheye wrist image size (pixels), or ``None``: no ``camera0_rgb``, nothing rendered.
        n_action_steps: rows executed per call (``None``: every row from ``first_action`` on).
        first_action: index of the first executed row (1: row 0 is the current step, UMI's action window).
        env_actions: the rows are the environment's own actions, executed as they are; otherwise absolute TCP
            targets, converted by the task's :meth:`~umi_aug.eval.task.TaskProbe.env_action` with the TCP pose of
            the step executing them.
        gripper_close_below_m: width targets below this close the gripper (absolute targets only), m; None: the
            environment's own threshold (the square Panda's: half its opening).
        privileged: the obs_dict gets :data:`PRIVILEGED_KEY` (scripted controls only).
    """

    img_obs_horizon: int = 1
    low_dim_obs_horizon: int = 2
    obs_down_sample_steps: int = 1
    image_size: int | None = None
    n_action_steps: int | None = None
    first_action: int = 1
    env_actions: bool = False
    gripper_close_below_m: float | None = None
    privileged: bool = False

    @property
    def obs_horizon(self) -> int:
        """Observations kept per window (``To``): the longer of the two horizons."""
        return max(self.img_obs_horizon if self.image_size else 1, self.low_dim_obs_horizon)

    @classmethod
    def of(cls, policy: Any) -> "RolloutSpec":
        """``policy.rollout_spec``, else the window of its training ``task`` (``policy.task``: image size and
        horizons, every row after the current one executed), else the defaults."""
        spec = getattr(policy, "rollout_spec", None)
        if spec is not None:
            return spec
        task = getattr(policy, "task", None)
        if task is None:
            return cls()
        return cls(int(task.img_obs_horizon), int(task.low_dim_obs_horizon), int(task.obs_down_sample_steps),
                   int(task.image_size))


#: the spec of a scripted control: one environment action per call and control step, no images
CONTROL_SPEC = RolloutSpec(img_obs_horizon=1, low_dim_obs_horizon=1, n_action_steps=1, first_action=0,
                           env_actions=True)


def one_action_chunk(a: np.ndarray) -> dict[str, np.ndarray]:
    """One environment action ``[7]`` as the contract's result: a chunk of one row."""
    return {ACTION_KEY: np.asarray(a)[None]}


class CheckpointEvalPolicy:
    """A trained checkpoint run closed loop: ``predict_action`` of :class:`umi_aug.policy.Policy` with the chunk
    length fixed and the sampling noise seeded per rollout.

    The rollout calls it when its queue is empty, with the last ``To`` observations (spaced
    ``obs_down_sample_steps`` apart, oldest first; the first step is padded by repetition as in training), takes
    the chunk's targets ``1 … n_action_steps`` (target 0 is the current pose: UMI's action window starts at the
    current step) and executes them one per policy step, converted by the task's
    :meth:`~umi_aug.eval.task.TaskProbe.env_action`. Sampling noise comes from a ``torch.Generator`` seeded by
    :meth:`seed` with the rollout seed, so a rollout is a deterministic function of (checkpoint, configuration,
    seed).

    Args:
        policy: a :class:`umi_aug.policy.Policy` (:meth:`from_checkpoint` loads one from a training checkpoint).
        n_action_steps: executed targets per inference (default: the policy's ``policy.n_action_steps``).
        gripper_close_below_m: width targets below this close the gripper (m; None: the environment's own).
    """

    name = "checkpoint"

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, device: str = "cpu", n_action_steps: int | None = None,
                        gripper_close_below_m: float | None = None) -> "CheckpointEvalPolicy":
        """Load a training checkpoint (``umi_aug.policy.checkpoint``; EMA weights when present).

        Raises:
            PolicyError: unreadable/malformed checkpoint, or one for more than one arm or camera (names the file).
        """
        from umi_aug.policy import Policy  # lazy: torch and the network code load only for a checkpoint

        try:
            return cls(Policy.from_checkpoint(path, device=device), n_action_steps, gripper_close_below_m)
        except PolicyError as exc:
            msg = str(exc)
            raise PolicyError(msg if str(path) in msg else f"checkpoint {path}: {msg}") from exc

    def __init__(self, policy: Any, n_action_steps: int | None = None,
                 gripper_close_below_m: float | None = None) -> None:
        self.policy = policy
        task = self.policy.task
        if task.n_robots != 1 or task.n_cameras != 1:
            raise PolicyError(f"the square env has one arm and one camera; the policy expects "
                              f"n_robots={task.n_robots}, n_cameras={task.n_cameras}")
        self.image_size: int | None = int(task.image_size)
        n = int(n_action_steps or self.policy.n_action_steps)
        if not 1 <= n <= task.action_horizon - 1:
            raise PolicyError(f"n_action_steps={n} must be in [1, {task.action_horizon - 1}] (target 0 is the "
                              f"current pose)")
        self.n_exec = n
        self.rollout_spec = RolloutSpec(int(task.img_obs_horizon), int(task.low_dim_obs_horizon),
                                        int(task.obs_down_sample_steps), self.image_size, n, 1, False,
                                        None if gripper_close_below_m is None else float(gripper_close_below_m))
        self._gen = None
        self.n_inferences = 0

    def seed(self, seed: int) -> None:
        import torch  # lazy: only a checkpoint needs torch

        self._gen = torch.Generator().manual_seed(int(seed))

    def reset(self) -> None:
        self.policy.reset()

    def predict_action(self, obs_dict: Mapping[str, Any]) -> Mapping[str, Any]:
        out = self.policy.predict_action(obs_dict, n_steps=self.n_exec + 1, generator=self._gen)
        self.n_inferences += 1
        return out
