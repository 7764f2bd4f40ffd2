"""The square task's scripted policies for the evaluation harness, each a :class:`umi_aug.policy.contract.PolicyLike`
(``reset()``, ``predict_action(obs_dict) -> {"action": chunk}``) outputting the square env's 7-D OSC_POSE delta
action (``[dx, dy, dz] / 0.05 m, axis-angle / 0.5 rad`` in the world frame, gripper ``−1`` open … ``+1`` close; what
:meth:`umi_aug.square.env.SquareEnv.step` takes), one per call (:data:`umi_aug.eval.policies.CONTROL_SPEC`):

* :class:`ExpertEvalPolicy` — adapter of the privileged-state scripted expert (needs no images: nothing is rendered).
* :class:`ReplayEvalPolicy` — replays recorded actions open loop (control: must succeed from the recording's state).
* :class:`HoldStillEvalPolicy`, :class:`RandomEvalPolicy` — controls that must never succeed.

The expert and the replay read the simulator through one documented entry of their obs_dict,
:data:`~umi_aug.eval.policies.PRIVILEGED_KEY` (a :class:`PrivilegedState` snapshot the rollout takes before each
call, :meth:`umi_aug.square.eval.SceneProbe.privileged`), never through the environment: the snapshot is plain
data (the policy cannot step, reset or read anything else of the simulation), the privileged information any
control uses is listed in one dataclass, and a learned policy's obs_dict never has the entry.

A trained checkpoint's absolute TCP targets become the same OSC_POSE deltas through :func:`abs_tcp_to_osc_delta`
(the square policies are trained on the targets the expert COMMANDED, ``task.action_key: action``;
:mod:`umi_aug.square.commands`): exactly the demo's action when the arm is where the demo's was (issue #29 B2:
labels of REACHED poses executed this way moved the arm only 0.64–0.66 of the demo's way per chunk). The gripper
width target becomes the Panda's command: close below ``gripper_close_below_m`` (half its opening), open otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import Any, Mapping, Sequence

import numpy as np

from umi_aug.errors import PolicyError, SimError
from umi_aug.eval.policies import CONTROL_SPEC, PRIVILEGED_KEY, one_action_chunk
from umi_aug.square.commands import GRIPPER_CLOSE_BELOW_M, osc_delta_from_target
from umi_aug.square.env import GRIP_SITE, NUT_BODY, PEG_BODY
from umi_aug.square.expert import ExpertConfig, SquareExpert

__all__ = ["PrivilegedState", "ExpertEvalPolicy", "HoldStillEvalPolicy", "RandomEvalPolicy", "ReplayEvalPolicy",
           "abs_tcp_to_osc_delta", "CONTROLS"]

#: the square task's scripted kinds of ``policy=`` (``configs/eval_sim.yaml``), besides ``checkpoint``
CONTROLS: tuple[str, ...] = ("expert", "replay", "hold", "random")

_HOLD_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)  # OSC_POSE: no motion, gripper open


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
        """The current state of ``env`` (a :class:`~umi_aug.square.env.SquareEnv`); a copy, not a view."""
        return cls(int(config), env.site_pose(GRIP_SITE), env.body_pose(NUT_BODY), env.body_pose(PEG_BODY),
                   float(env.rs.table_offset[2]))


def _privileged(obs_dict: Mapping[str, Any], who: str) -> PrivilegedState:
    state = obs_dict.get(PRIVILEGED_KEY)
    if not isinstance(state, PrivilegedState):
        raise PolicyError(f"{who}: obs_dict has no {PRIVILEGED_KEY!r} entry (a privileged control runs only in the "
                          f"simulated evaluation)")
    return state


def abs_tcp_to_osc_delta(T_world_tcp: np.ndarray, target: np.ndarray,
                         gripper_close_below_m: float = GRIPPER_CLOSE_BELOW_M) -> np.ndarray:
    """An absolute TCP target ``[7]`` → the square env's OSC_POSE delta action
    (:func:`umi_aug.square.commands.osc_delta_from_target`; a bad target raises :class:`PolicyError`)."""
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
    """Adapter of the scripted privileged-state expert (:class:`~umi_aug.square.expert.SquareExpert`): its
    next action from ``obs_dict["privileged"]``."""

    name = "expert"
    rollout_spec = replace(CONTROL_SPEC, privileged=True)

    def __init__(self, cfg: ExpertConfig | None = None) -> None:
        self.expert = SquareExpert(cfg)

    def reset(self) -> None:
        self.expert.reset()

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return one_action_chunk(self.expert.act(_ExpertView(_privileged(obs_dict, "ExpertEvalPolicy"))))

    def info(self) -> dict[str, Any]:
        """Final expert phase (for failure analysis)."""
        return {"expert_phase": self.expert.phase}


class HoldStillEvalPolicy:
    """Zero motion, gripper open: the arm holds its start pose (a control that must never succeed)."""

    name = "hold"
    rollout_spec = CONTROL_SPEC

    def reset(self) -> None:
        pass

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return one_action_chunk(np.array(_HOLD_ACTION))


class RandomEvalPolicy:
    """Uniform random actions in ``[−scale, scale]⁷`` from a generator seeded per rollout (a control)."""

    name = "random"
    rollout_spec = CONTROL_SPEC

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = float(scale)
        self.rng = np.random.default_rng(0)

    def seed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def predict_action(self, obs_dict: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return one_action_chunk(self.rng.uniform(-self.scale, self.scale, 7))


class ReplayEvalPolicy:
    """Replays recorded OSC actions open loop; configuration ``i`` (``obs_dict["privileged"].config``) replays
    ``actions[i]``, then holds still.

    Args:
        actions: per configuration, float [T_i, 7] recorded actions.
    """

    name = "replay"
    rollout_spec = replace(CONTROL_SPEC, privileged=True)

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
        return one_action_chunk(a)
