"""Policies the simulation harness drives — every one through the one policy contract
(:class:`umi_aug.policy.contract.PolicyLike`: ``reset()``, ``predict_action(obs_dict) -> {"action": chunk}``).

The rollout (:mod:`umi_aug.eval.rollout`) is the environment runner, as in Diffusion Policy: it keeps the
observation history, builds the ``obs_dict`` window, calls ``predict_action`` when its queue of actions is empty
and executes the chunk one row per 20 Hz control step as the square environment's 7-D OSC_POSE delta action
(``[dx, dy, dz] / 0.05 m, axis-angle / 0.5 rad`` in the world frame, gripper ``−1`` open … ``+1`` close; what
:meth:`umi_aug.sim.square.env.SquareEnv.step` takes). How it runs a policy — window, image size, rows executed,
action kind — is the policy's :class:`RolloutSpec` (eval-side facts, not part of the contract): its
``rollout_spec`` attribute, else one read from its training ``task`` (a :class:`umi_aug.policy.Policy`), else the
defaults (any object with ``predict_action`` / ``reset`` runs).

* :class:`CheckpointEvalPolicy` — a trained Diffusion Policy (:class:`umi_aug.policy.Policy`) with a fixed chunk
  length and sampling noise seeded per rollout (:class:`~umi_aug.policy.contract.SeedablePolicy`). Its obs_dict is
  exactly the training sample's observation; it outputs ABSOLUTE targets (position, rotation vector, gripper
  width). The square policies are trained on the targets the expert COMMANDED (``task.action_key: action``;
  :mod:`umi_aug.sim.square.commands`), and each is executed the way it was commanded when recorded:
  :func:`abs_tcp_to_osc_delta` turns it into the OSC_POSE delta from the current pose — exactly the demo's action
  when the arm is where the demo's was (issue #29 B2: labels of REACHED poses executed this way moved the arm only
  0.64–0.66 of the demo's way per chunk). The gripper width target becomes the Panda's command: close below
  ``gripper_close_below_m`` (half its opening), open otherwise.
* :class:`ExpertEvalPolicy` — adapter of the privileged-state scripted expert (needs no images: nothing is rendered).
* :class:`ReplayEvalPolicy` — replays recorded actions open loop (control: must succeed from the recording's state).
* :class:`HoldStillEvalPolicy`, :class:`RandomEvalPolicy` — controls that must never succeed.

The controls output the environment's own OSC_POSE deltas (``RolloutSpec.env_actions``), one per call. The expert
and the replay read the simulator through one documented entry of their obs_dict, :data:`PRIVILEGED_KEY`
(a :class:`PrivilegedState` snapshot the rollout takes before each call), never through the environment: the
snapshot is plain data (the policy cannot step, reset or read anything else of the simulation), the privileged
information any control uses is listed in one dataclass, and a learned policy's obs_dict never has the entry.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any, Mapping, Sequence

import numpy as np

from umi_aug.errors import PolicyError, SimError
from umi_aug.policy.contract import ACTION_KEY
from umi_aug.sim.square.commands import GRIPPER_CLOSE_BELOW_M, osc_delta_from_target
from umi_aug.sim.square.env import GRIP_SITE, NUT_BODY, PEG_BODY
from umi_aug.sim.square.expert import ExpertConfig, SquareExpert

__all__ = ["RolloutSpec", "PrivilegedState", "PRIVILEGED_KEY", "ExpertEvalPolicy", "HoldStillEvalPolicy",
           "RandomEvalPolicy", "ReplayEvalPolicy", "CheckpointEvalPolicy", "abs_tcp_to_osc_delta", "POLICY_KINDS"]

#: values of ``policy=`` in ``configs/eval_sim.yaml``
POLICY_KINDS: tuple[str, ...] = ("checkpoint", "expert", "replay", "hold", "random")

#: the obs_dict entry of the privileged controls (:class:`PrivilegedState`); never given to a learned policy
PRIVILEGED_KEY = "privileged"

_HOLD_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)  # OSC_POSE: no motion, gripper open


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
        env_actions: the rows are the square env's OSC_POSE deltas, executed as they are; otherwise absolute TCP
            targets, converted by :func:`abs_tcp_to_osc_delta` with the TCP pose of the step executing them.
        gripper_close_below_m: width targets below this close the gripper (absolute targets only), m.
        privileged: the obs_dict gets :data:`PRIVILEGED_KEY` (scripted controls only).
    """

    img_obs_horizon: int = 1
    low_dim_obs_horizon: int = 2
    obs_down_sample_steps: int = 1
    image_size: int | None = None
    n_action_steps: int | None = None
    first_action: int = 1
    env_actions: bool = False
    gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M
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


#: the spec of a control: one OSC_POSE delta per call and control step, no images
_CONTROL = RolloutSpec(img_obs_horizon=1, low_dim_obs_horizon=1, n_action_steps=1, first_action=0, env_actions=True)


@dataclass(frozen=True)
class PrivilegedState:
    """Simulator truth for scripted controls: ``obs_dict["privileged"]`` (world frame, metres).

    Attributes:
        config: index of the start configuration this rollout started from.
        T_world_grip: float64 [4, 4] pose of the gripper's grip site.
        T_world_nut: float64 [4, 4] pose of the square nut's body.
        T_world_peg: float64 [4, 4] pose of the square peg's body.
        table_z: height of the table top (m).
    """

    config: int
    T_world_grip: np.ndarray
    T_world_nut: np.ndarray
    T_world_peg: np.ndarray
    table_z: float

    @classmethod
    def read(cls, env: Any, config: int) -> "PrivilegedState":
        """The current state of ``env`` (a :class:`~umi_aug.sim.square.env.SquareEnv`); a copy, not a view."""
        return cls(int(config), env.site_pose(GRIP_SITE), env.body_pose(NUT_BODY), env.body_pose(PEG_BODY),
                   float(env.rs.table_offset[2]))


def _privileged(obs_dict: Mapping[str, Any], who: str) -> PrivilegedState:
    state = obs_dict.get(PRIVILEGED_KEY)
    if not isinstance(state, PrivilegedState):
        raise PolicyError(f"{who}: obs_dict has no {PRIVILEGED_KEY!r} entry (a privileged control runs only in the "
                          f"simulated evaluation)")
    return state


def _one_action(a: np.ndarray) -> dict[str, np.ndarray]:
    """One OSC_POSE delta [7] as a chunk of one row."""
    return {ACTION_KEY: np.asarray(a)[None]}


def abs_tcp_to_osc_delta(T_world_tcp: np.ndarray, target: np.ndarray,
                         gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> np.ndarray:
    """An absolute TCP target ``[7]`` → the square env's OSC_POSE delta action
    (:func:`umi_aug.sim.square.commands.osc_delta_from_target`; a bad target raises :class:`PolicyError`)."""
    try:
        return osc_delta_from_target(T_world_tcp, target, gripper_close_below_m)
    except SimError as exc:
        raise PolicyError(str(exc)) from None


class _ExpertView:
    """What :meth:`SquareExpert.act` reads of an environment (grip-site, nut and peg poses, table height),
    answered from a :class:`PrivilegedState`."""

    def __init__(self, state: PrivilegedState) -> None:
        self._bodies = {NUT_BODY: state.T_world_nut, PEG_BODY: state.T_world_peg}
        self._sites = {GRIP_SITE: state.T_world_grip}
        self.rs = SimpleNamespace(table_offset=(0.0, 0.0, state.table_z))

    def site_pose(self, name: str) -> np.ndarray:
        return self._sites[name]

    def body_pose(self, name: str) -> np.ndarray:
        return self._bodies[name]


class ExpertEvalPolicy:
    """Adapter of the scripted privileged-state expert (:class:`~umi_aug.sim.square.expert.SquareExpert`): its
    next action from ``obs_dict["privileged"]``."""

    name = "expert"
    rollout_spec = replace(_CONTROL, privileged=True)

    def __init__(self, cfg: ExpertConfig | None = None) -> None:
        self.expert = SquareExpert(cfg)

    def reset(self) -> None:
        self.expert.reset()

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return _one_action(self.expert.act(_ExpertView(_privileged(obs_dict, "ExpertEvalPolicy"))))

    def info(self) -> dict[str, Any]:
        """Final expert phase (for failure analysis)."""
        return {"expert_phase": self.expert.phase}


class HoldStillEvalPolicy:
    """Zero motion, gripper open: the arm holds its start pose (a control that must never succeed)."""

    name = "hold"
    rollout_spec = _CONTROL

    def reset(self) -> None:
        pass

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return _one_action(np.array(_HOLD_ACTION))


class RandomEvalPolicy:
    """Uniform random actions in ``[−scale, scale]⁷`` from a generator seeded per rollout (a control)."""

    name = "random"
    rollout_spec = _CONTROL

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = float(scale)
        self.rng = np.random.default_rng(0)

    def seed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return _one_action(self.rng.uniform(-self.scale, self.scale, 7))


class ReplayEvalPolicy:
    """Replays recorded OSC actions open loop; configuration ``i`` (``obs_dict["privileged"].config``) replays
    ``actions[i]``, then holds still.

    Args:
        actions: per configuration, float [T_i, 7] recorded actions.
    """

    name = "replay"
    rollout_spec = replace(_CONTROL, privileged=True)

    def __init__(self, actions: Sequence[np.ndarray]) -> None:
        self.actions = [np.asarray(a, dtype=np.float64) for a in actions]
        for i, a in enumerate(self.actions):
            if a.ndim != 2 or a.shape[1] != 7 or not np.isfinite(a).all():
                raise PolicyError(f"ReplayEvalPolicy: actions[{i}] must be finite [T, 7], got {a.shape}")
        self._t = 0

    def reset(self) -> None:
        self._t = 0

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        config = _privileged(obs_dict, "ReplayEvalPolicy").config
        if not 0 <= config < len(self.actions):
            raise PolicyError(f"ReplayEvalPolicy: no recorded episode for configuration {config} "
                              f"({len(self.actions)} recorded)")
        cur = self.actions[config]
        a = cur[self._t] if self._t < len(cur) else np.array(_HOLD_ACTION)
        self._t += 1
        return _one_action(a)


class CheckpointEvalPolicy:
    """A trained checkpoint run closed loop: ``predict_action`` of :class:`umi_aug.policy.Policy` with the chunk
    length fixed and the sampling noise seeded per rollout.

    The rollout calls it when its queue is empty, with the last ``To`` observations (spaced
    ``obs_down_sample_steps`` apart, oldest first; the first step is padded by repetition as in training), takes
    the chunk's targets ``1 … n_action_steps`` (target 0 is the current pose: UMI's action window starts at the
    current step) and executes them one per policy step, converted by :func:`abs_tcp_to_osc_delta`. Sampling noise
    comes from a ``torch.Generator`` seeded by :meth:`seed` with the rollout seed, so a rollout is a deterministic
    function of (checkpoint, configuration, seed).

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
        from umi_aug.policy import Policy  # lazy: torch and the network code load only for a checkpoint

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
        n = int(n_action_steps or self.policy.n_action_steps)
        if not 1 <= n <= task.action_horizon - 1:
            raise PolicyError(f"n_action_steps={n} must be in [1, {task.action_horizon - 1}] (target 0 is the "
                              f"current pose)")
        self.n_exec = n
        self.rollout_spec = RolloutSpec(int(task.img_obs_horizon), int(task.low_dim_obs_horizon),
                                        int(task.obs_down_sample_steps), self.image_size, n, 1, False,
                                        float(gripper_close_below_m))
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
