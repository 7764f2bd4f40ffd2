"""The one policy contract of evaluation and deployment: Diffusion Policy's ``BaseImagePolicy`` interface.

Diffusion Policy's env runners only ever call ``policy.reset()`` and ``policy.predict_action(obs_dict)``; so do
this project's simulated evaluation (:func:`umi_aug.eval.rollout.rollout_config`) and the robot runner
(:class:`umi_aug.deploy.runner.PolicyRunner`). Anything with these two methods is a policy to both:

* ``obs_dict``: the keys and per-frame formats the policy was trained on, the last ``To`` observations oldest
  first (one policy step = ``task.obs_down_sample_steps`` control steps apart)::

      camera{j}_rgb               [To, H, W, 3] uint8 RGB
      robot{i}_eef_pos            [To, 3] float64, m (TCP in the world / robot base frame)
      robot{i}_eef_rot_axis_angle [To, 3] float64, rotation vector (rad)
      robot{i}_gripper_width      [To, 1] float64, m

  A learned policy gets exactly these. The simulated evaluation adds one documented entry for its scripted
  controls only (``privileged``: the task's snapshot, e.g. the square's ``PrivilegedState``), never for a learned
  policy.
* result: a mapping with at least :data:`ACTION_KEY` (``"action"``), the action chunk ``[n, Da]`` (Diffusion
  Policy's output dict; extra keys are allowed). For a robot arm ``Da = 7·R``: per arm the absolute TCP target
  ``[x, y, z, rx, ry, rz, gripper_width]`` (m, rotation vector in rad, m), row 0 at the current step, the rows one
  policy step apart (UMI's action window). The simulated evaluation also drives scripted controls whose rows are
  the square environment's own OSC_POSE deltas; they say so in their :class:`~umi_aug.eval.policies.RolloutSpec`.

Optional: :class:`SeedablePolicy` (``seed(seed)``) for a policy whose randomness an evaluation fixes per rollout.
"""

from __future__ import annotations

from typing import Any, Mapping, Protocol, runtime_checkable

from umi_aug.errors import PolicyError

__all__ = ["PolicyLike", "SeedablePolicy", "ACTION_KEY", "action_chunk"]

#: the result entry that holds the action chunk (Diffusion Policy's ``action``)
ACTION_KEY = "action"


@runtime_checkable
class PolicyLike(Protocol):
    """What evaluation and deployment call: ``reset()`` at the start of an episode, then ``predict_action``."""

    def predict_action(self, obs_dict: Mapping[str, Any]) -> Mapping[str, Any]:
        """The observation window (module docstring) → ``{"action": [n, Da], ...}``."""
        ...

    def reset(self) -> None:
        """Start a new episode (clear any state kept between calls)."""
        ...


@runtime_checkable
class SeedablePolicy(PolicyLike, Protocol):
    """A policy with randomness (sampling noise, random actions) that a caller can fix for one episode."""

    def seed(self, seed: int) -> None:
        """Make the coming episode's randomness a function of ``seed`` alone (call before the first
        :meth:`predict_action` of the episode)."""
        ...


def action_chunk(result: Any) -> Any:
    """The action chunk of a ``predict_action`` result (``result["action"]``; its shape is the caller's to check).

    Raises:
        PolicyError: the result is not a mapping with an ``"action"`` entry.
    """
    if not isinstance(result, Mapping) or ACTION_KEY not in result:
        got = sorted(map(str, result)) if isinstance(result, Mapping) else type(result).__name__
        raise PolicyError(f"predict_action must return a dict with {ACTION_KEY!r} (Diffusion Policy's output), "
                          f"got {got}")
    return result[ACTION_KEY]
