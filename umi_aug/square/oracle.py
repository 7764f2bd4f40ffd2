"""The replay oracle of the square task's train/eval contract (issue #29): a demo's OWN action chunks, cut and
re-anchored exactly as the network outputs them, replayed through ``eval_sim``'s policy interface from that demo's
start state (``python eval/square_oracle.py``).

A policy that imitated its data perfectly would output, at each inference, the chunk its training sample at that
step holds. :class:`DemoChunkModel` is that perfect imitator: it stands in for the network inside
:class:`umi_aug.policy.Policy` (so observations go through ``Policy.obs_to_model`` and its chunk through
``model_actions_to_abs``, re-anchored on the CURRENT observed pose), and :class:`CheckpointEvalPolicy` executes it
as it executes a trained checkpoint. The chunk is time-indexed (the k-th inference reads the sample at step
``k · n_action_steps · obs_down_sample_steps``). If the labels and the controller agree, the rollout reproduces the
demo and succeeds; labels of reached poses executed by the expert's delta rule do not (0/3 in the issue).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from umi_aug.data import make_umi_episode
from umi_aug.eval.policies import CheckpointEvalPolicy
from umi_aug.eval.rollout import rollout_config
from umi_aug.policy import Policy
from umi_aug.policy.config import TrainConfig, structured_config
from umi_aug.policy.dataset import lowdim_from_rows, window_rows
from umi_aug.square.commands import commanded_targets

__all__ = ["DemoChunkModel", "demo_chunks", "oracle_policy", "oracle_config", "OracleDemo", "run_oracle", "LABELS"]


def demo_chunks(task, pose6: np.ndarray, gripper: np.ndarray, start_pose: np.ndarray,
                action7: np.ndarray | None) -> np.ndarray:
    """The model-space action window (what a training sample's ``action`` holds) at EVERY step of one episode.

    Args:
        task: the policy's :class:`~umi_aug.policy.config.TaskConfig` (its ``action_key`` says which labels).
        pose6: np.ndarray,  # [T, 6] TCP pos (m) + rotvec (rad), as the replay buffer stores them
        gripper: np.ndarray,  # [T, 1] widths (m)
        start_pose: np.ndarray,  # [T, 6] the demo start pose on every row
        action7: np.ndarray | None,  # [T, 7] commanded targets (used iff ``task.action_key``)
    Returns:
        np.ndarray,  # [T, H, 10] float64; windows past the end repeat the last row (``action_padding``)
    """
    t = copy.copy(task)
    t.action_padding = True
    T = len(pose6)
    cur = np.arange(T, dtype=np.int64)
    low, a_rows = window_rows(t, cur, np.zeros(T, np.int64), np.full(T, T, np.int64))
    use = action7 if task.action_key is not None else None
    out = lowdim_from_rows(t, [np.asarray(pose6, np.float64)], [np.asarray(gripper, np.float64)],
                           [np.asarray(start_pose, np.float64)], low, a_rows, cur,
                           action7=None if use is None else [np.asarray(use, np.float64)])
    return out["action"]


class DemoChunkModel(torch.nn.Module):
    """Stands in for the Diffusion Policy network: the k-th call returns the demo's window at step ``k · every``
    (clamped to the last step), ignoring the observation — a perfect, time-indexed imitator."""

    def __init__(self, chunks: np.ndarray, every: int) -> None:
        super().__init__()
        self.chunks = np.asarray(chunks, np.float64)
        self.every = int(every)
        self.calls = 0

    @torch.no_grad()
    def predict_action(self, obs: dict[str, torch.Tensor], generator: torch.Generator | None = None
                       ) -> dict[str, torch.Tensor]:
        step = min(self.calls * self.every, len(self.chunks) - 1)
        self.calls += 1
        B = next(iter(obs.values())).shape[0]
        a = torch.as_tensor(self.chunks[step], dtype=torch.float32)
        return {"action": a[None].expand(B, *a.shape)}


def oracle_policy(cfg: TrainConfig, chunks: np.ndarray, n_action_steps: int | None = None) -> CheckpointEvalPolicy:
    """The eval harness's checkpoint policy with :class:`DemoChunkModel` in place of the network."""
    n = int(n_action_steps or cfg.policy.n_action_steps)
    model = DemoChunkModel(chunks, n * int(cfg.task.obs_down_sample_steps))
    return CheckpointEvalPolicy(Policy(model, cfg), n_action_steps=n)


@dataclass
class OracleDemo:
    """One recorded demo as the oracle needs it: its start ``state`` [45] and its replay-buffer rows."""

    state: np.ndarray
    pose6: np.ndarray
    gripper: np.ndarray
    start_pose: np.ndarray
    action7: np.ndarray | None
    seed: int = -1

    @classmethod
    def from_episode(cls, ep: Any) -> "OracleDemo":
        """From a :class:`umi_aug.square.episode.Episode` (rows rounded to float32, as the zarr stores them)."""
        u = make_umi_episode(ep.T_world_tcp, ep.gripper_width)
        pose6 = np.concatenate([u["robot0_eef_pos"], u["robot0_eef_rot_axis_angle"]], 1).astype(np.float64)
        act = commanded_targets(ep.T_world_tcp, ep.actions).astype(np.float32).astype(np.float64)
        return cls(np.asarray(ep.states[0]), pose6, u["robot0_gripper_width"].astype(np.float64),
                   u["robot0_demo_start_pose"], act, int(ep.seed))

    def chunks(self, task) -> np.ndarray:
        return demo_chunks(task, self.pose6, self.gripper, self.start_pose, self.action7)


class _BlankCamera:
    """A wrist camera that renders nothing (the oracle never looks at images): black ``S×S`` frames."""

    def __init__(self, size: int) -> None:
        self.size = int(size)

    def render(self, data: Any, T_world_cam: np.ndarray) -> np.ndarray:
        return np.zeros((self.size, self.size, 3), np.uint8)


#: label kinds of :func:`run_oracle`: the commanded targets (``task.action_key: action``) or the reached poses
LABELS: tuple[str, ...] = ("commanded", "reached")


def oracle_config(labels: str = "commanded", image_size: int = 84) -> TrainConfig:
    """The square task's training config (``configs/task/square.yaml`` values that matter here), with the labels
    taken from the commanded targets or, for the contrast, the reached poses (UMI's rule)."""
    if labels not in LABELS:
        raise ValueError(f"labels = {labels!r}: expected one of {LABELS}")
    return structured_config({"task": {"name": "square", "image_size": image_size, "obs_down_sample_steps": 1,
                                       "val_ratio": 0.0, "action_key": "action" if labels == "commanded" else None},
                              "policy": {"encoder": {"name": "resnet"}}})


def run_oracle(seeds: list[int], labels: str = "commanded", progress: bool = False,
               horizon: int = 400) -> list[dict[str, Any]]:
    """Record the scripted expert from reset seed ``s`` (no images), then replay its own chunks through the eval
    harness (:func:`umi_aug.eval.rollout.rollout_config`, the checkpoint policy's path) from its first state.

    Returns:
        one record per seed: ``seed``, ``demo_steps``, ``demo_success`` and the rollout record's ``success``,
        ``steps_to_success``, ``pregrasp_reached``, ``steps``, ``wall_s``.
    """
    # lazy, start-up: cv2
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.episode import rollout_expert
    from umi_aug.square.eval import SceneProbe

    cfg = oracle_config(labels)
    env = SquareEnv(image_size=None)
    try:
        probe, cam = SceneProbe(env), _BlankCamera(cfg.task.image_size)
        out = []
        for s in tqdm(seeds, desc=f"oracle ({labels} labels)", unit="demo", disable=not progress):
            ep = rollout_expert(env, seed=int(s), render=False, horizon=horizon)
            demo = OracleDemo.from_episode(ep)
            rec = rollout_config(env, probe, oracle_policy(cfg, demo.chunks(cfg.task)), demo.state, int(s), 0,
                                 horizon=horizon, camera=cam)
            out.append({"seed": int(s), "demo_steps": len(ep), "demo_success": bool(ep.success),
                        **{k: rec[k] for k in ("success", "steps_to_success", "pregrasp_reached", "steps",
                                               "wall_s")}})
        return out
    finally:
        env.close()
