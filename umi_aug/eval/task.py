"""What the evaluation harness needs from a simulated benchmark, as three protocols.

The harness (:mod:`umi_aug.eval.runner`, :mod:`umi_aug.eval.rollout`) knows policies, observation windows,
seeds, records and summaries; a benchmark brings the rest:

- :class:`SimEnv` — the simulated environment a rollout resets into a stored start state and steps;
- :class:`TaskProbe` — one per environment: the task's fields of the rollout record (sub-goals, contacts), the
  privileged snapshot scripted controls read, the conversion of an absolute TCP target into the environment's
  action, the external video camera;
- :class:`SimTask` — builds environments, probes and wrist cameras in each worker, its scripted controls and its
  recorded episodes for ``policy=replay``, and names the record fields the summary counts.

The square benchmark's is :data:`umi_aug.square.eval.SQUARE_TASK` (``eval/eval_sim.py`` passes it to
:func:`umi_aug.eval.runner.run_eval`). A task object is handed to spawned worker processes, so it must pickle
(a module-level instance of a plain class does).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from umi_aug.policy.contract import PolicyLike

__all__ = ["SimEnv", "TaskProbe", "WristCamera", "SimTask"]


class SimEnv(Protocol):
    """A simulated environment as the rollout drives it (MuJoCo underneath: ``model`` / ``data``)."""

    @property
    def model(self) -> Any:
        """The MuJoCo ``MjModel`` (the external video camera renders it)."""
        ...

    @property
    def data(self) -> Any:
        """The MuJoCo ``MjData`` of the current state (the wrist camera renders it)."""
        ...

    def reset(self, seed: int | None = None) -> Mapping[str, Any]:
        """A seeded reset (the rollout resets with seed 0 first, so no rollout depends on the one before)."""
        ...

    def reset_to(self, states: np.ndarray, model_xml: str | None = None, initial: bool = False
                 ) -> Mapping[str, Any]:
        """Restore a flattened simulator state (``initial``: as an episode start); returns the observation."""
        ...

    def step(self, action: np.ndarray) -> tuple[Mapping[str, Any], float, bool, dict]:
        """One control step with the environment's own action; ``(observation, reward, done, info)``. The
        observation holds ``robot0_eef_pos`` [3] (m), ``robot0_eef_rot_axis_angle`` [3] (rad) and
        ``robot0_gripper_width`` (m), world frame."""
        ...

    def is_success(self) -> bool:
        """The task's success in the current state."""
        ...

    def get_state(self) -> np.ndarray:
        """The flattened simulator state (hashed into the record)."""
        ...

    def wrist_pose(self) -> np.ndarray:
        """``T_world_cam`` [4, 4] of the wrist camera (OpenCV axes, metres)."""
        ...

    def close(self) -> None:
        ...


class WristCamera(Protocol):
    """The policy's wrist camera at one image size."""

    def render(self, data: Any, T_world_cam: np.ndarray) -> np.ndarray:
        """uint8 [S, S, 3] RGB of the state ``data`` seen from ``T_world_cam`` (OpenCV axes, metres)."""
        ...

    def close(self) -> None:
        ...


class TaskProbe(Protocol):
    """Reads one environment's task state for the rollout (built once per environment, reused by its rollouts)."""

    def start(self) -> dict[str, Any]:
        """After the reset into a start configuration: the task's record fields with their initial values (they
        follow ``config, seed, success, steps_to_success`` in the record, in this order)."""
        ...

    def observe(self, rec: dict[str, Any], steps: int) -> None:
        """After control step ``steps`` (1-based): update the task's fields of ``rec`` from the new state."""
        ...

    def finish(self, rec: dict[str, Any]) -> None:
        """After the last step: the task's final values (e.g. flags from step counts; JSON-able)."""
        ...

    def privileged(self, config: int) -> Any:
        """The snapshot of the simulator a privileged control reads (``obs_dict["privileged"]``) in the current
        state of a rollout from configuration ``config``; plain data, not a view of the environment."""
        ...

    def env_action(self, target: np.ndarray, gripper_close_below_m: float | None) -> np.ndarray:
        """An absolute TCP target ``[7]`` (position m, rotation vector rad, gripper width m; world frame) → the
        environment's action from the current TCP pose (``gripper_close_below_m``: width targets below it close
        the gripper; None: the environment's own threshold). Raises :class:`~umi_aug.errors.PolicyError` for a
        bad target."""
        ...

    def video_camera(self) -> np.ndarray:
        """``T_world_cam`` [4, 4] (OpenCV axes, metres) of the fixed external camera of the rollout videos."""
        ...


class SimTask(Protocol):
    """A simulated benchmark the runner evaluates policies on (``checkpoint`` policies are the harness's own)."""

    #: the scripted policy kinds the task offers besides ``checkpoint`` (values of ``policy=``)
    controls: tuple[str, ...]
    #: record fields the summary reports as sub-goal rates / collision rates (booleans)
    subgoals: tuple[str, ...]
    collisions: tuple[str, ...]

    def make_env(self, env_meta: dict[str, Any] | None) -> SimEnv:
        """The environment of a configuration file's ``env_args`` (None: the task's default), rendering nothing
        on its own (the rollout renders the wrist images it needs)."""
        ...

    def probe(self, env: SimEnv) -> TaskProbe:
        ...

    def camera(self, env: SimEnv, size: int) -> WristCamera:
        """The wrist camera of ``env`` at ``size``² pixels (the policy's image size)."""
        ...

    def control(self, kind: str, spec: dict[str, Any]) -> PolicyLike:
        """The scripted policy ``kind`` (one of :attr:`controls`); ``spec`` holds its settings
        (``random_scale``, ``replay_actions``)."""
        ...

    def replay_configs(self, replay_dir: str | Path
                       ) -> tuple[dict[str, Any], Sequence[np.ndarray], list[str]]:
        """``policy=replay``: the start configurations of the recorded episodes in ``replay_dir`` (the dict of
        :func:`umi_aug.eval.runner.load_eval_configs`), their actions and their file names."""
        ...

    def summary_info(self) -> dict[str, Any]:
        """Task facts written into ``summary.json`` after ``seed`` (e.g. the sub-goals' tolerances)."""
        ...
