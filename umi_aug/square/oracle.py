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

:func:`run_export_oracle` asks the same of an augmented export's episodes (:mod:`umi_aug.augment`, square demos):
each episode's own chunks replayed from its own start — the source demo's objects, the arm placed by IK at the
episode's first TCP pose — under the training recipe's pose representations. The new, planned frames were never
executed: their labels lead along the path (:func:`~umi_aug.square.commands.path_command_targets`), and the arm
driven by them lags the plan while it accelerates, so whether a perfect imitator of them succeeds depends on how
its actions are anchored (measured in eval/README.md, check (e)).
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

__all__ = ["DemoChunkModel", "demo_chunks", "oracle_policy", "oracle_config", "OracleDemo", "run_oracle", "LABELS",
           "episode_start_state", "run_export_oracle"]


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

    @classmethod
    def from_buffer(cls, buf: Any, episode: int, state: np.ndarray) -> "OracleDemo":
        """Episode ``episode`` of a square replay buffer (UMI keys + ``action``) that starts from ``state``."""
        e = buf.get_episode(int(episode), ["robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width",
                                           "robot0_demo_start_pose", "action"])
        pose6 = np.concatenate([e["robot0_eef_pos"], e["robot0_eef_rot_axis_angle"]], 1).astype(np.float64)
        return cls(np.asarray(state, np.float64), pose6, e["robot0_gripper_width"].astype(np.float64),
                   e["robot0_demo_start_pose"].astype(np.float64), e["action"].astype(np.float64))

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


def oracle_config(labels: str = "commanded", image_size: int = 84, obs_pose_repr: str = "relative",
                  action_pose_repr: str = "abs") -> TrainConfig:
    """The square task's training config (``configs/task/square.yaml`` values that matter here: absolute action
    targets since session 29), with the labels taken from the commanded targets or, for the contrast, the reached
    poses (UMI's rule), and the given pose representations (``task.obs_pose_repr`` / ``task.action_pose_repr``:
    ``relative`` or ``abs``)."""
    if labels not in LABELS:
        raise ValueError(f"labels = {labels!r}: expected one of {LABELS}")
    return structured_config({"task": {"name": "square", "image_size": image_size, "obs_down_sample_steps": 1,
                                       "val_ratio": 0.0, "action_key": "action" if labels == "commanded" else None,
                                       "obs_pose_repr": obs_pose_repr, "action_pose_repr": action_pose_repr},
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


def episode_start_state(env: Any, ik: Any, source_state: np.ndarray, T_world_tcp: np.ndarray, ik_seed: int = 0
                        ) -> tuple[np.ndarray | None, Any]:
    """The start state of an augmented episode: ``source_state`` (its source demo's first state: nut, pegs,
    fingers) with the arm joints set by IK (:class:`~umi_aug.square.ik.PandaIK` ``ik``) so that the TCP is at
    ``T_world_tcp`` [4, 4] (world frame, OpenCV axes as the replay buffer stores it; the grip site follows from the
    hand's fixed TCP→site transform), the arm at rest. ``ik_seed`` seeds the IK's restarts.

    Returns:
        (state [S] ready for ``rollout_config``, or None when the pose is out of reach; the IK result).
    """
    from umi_aug.geometry import pose_inverse
    from umi_aug.square.env import GRIP_SITE
    from umi_aug.square.init_configs import place_arm

    env.reset_to(np.asarray(source_state, np.float64))
    T_tcp_site = pose_inverse(env.tcp_pose()) @ env.site_pose(GRIP_SITE)
    res = ik.solve(env.data, np.asarray(T_world_tcp, np.float64) @ T_tcp_site, rng=ik_seed)
    if not res.reachable:
        return None, res
    place_arm(env, res.q, ik.qadr)
    return env.get_state(), res


def run_export_oracle(export: Any, demos_hdf5: Any, episodes: list[int] | None = None,
                      cfg: TrainConfig | None = None, progress: bool = False, horizon: int = 400
                      ) -> list[dict[str, Any]]:
    """Replay the episodes of an augmented square export through the eval harness, each from its own start, each
    with its own action chunks (time-indexed, re-anchored as ``cfg``'s representations say).

    Args:
        export: the export's ``.zarr.zip`` (``umi-aug augment`` / the study's export or variants, with ``action``
            and the per-episode records ``meta/aug_*``).
        demos_hdf5: the source demos' robomimic hdf5 (``umi-aug square-demos``): demo ``d``'s first state is the
            start of every episode whose ``aug_source_episode`` is ``d``.
        episodes: episode indices (default: all).
        cfg: the training config whose task representations the chunks are cut and re-anchored with (default
            :func:`oracle_config`: commanded targets, absolute action targets as ``configs/task/square.yaml``).
    Returns:
        one record per episode: ``episode``, ``source``, ``aug_id`` (−1: an original demo), ``length``,
        ``ik_pos_err_m``, and the rollout's ``success``, ``pregrasp_reached``, ``lifted``, ``steps``,
        ``pregrasp_min_pos_err_m``, ``collision_table``.
    """
    # lazy, start-up: cv2 / robosuite
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.data import ReplayBuffer
    from umi_aug.errors import SimError
    from umi_aug.geometry import pos_rotvec_to_pose
    from umi_aug.square.env import GRIP_SITE, SquareEnv
    from umi_aug.square.eval import SceneProbe
    from umi_aug.square.ik import PandaIK
    from umi_aug.square.init_configs import source_states_from_hdf5

    cfg = cfg or oracle_config()
    rec = read_episode_records(export)
    sources, _ = source_states_from_hdf5(demos_hdf5)
    episodes = list(range(len(rec["aug_id"]))) if episodes is None else [int(e) for e in episodes]
    bad = [e for e in episodes if not 0 <= e < len(rec["aug_id"])]
    if bad:
        raise SimError(f"{export}: episodes {bad[:5]} out of range (the export has {len(rec['aug_id'])})")
    env = SquareEnv(image_size=None)
    try:
        probe, cam, ik = SceneProbe(env), _BlankCamera(cfg.task.image_size), PandaIK(env.model, GRIP_SITE)
        out = []
        with ReplayBuffer.open(export) as buf:
            for e in tqdm(episodes, desc="export oracle", unit="episode", disable=not progress):
                d = int(rec["aug_source_episode"][e])
                if not 0 <= d < len(sources):
                    raise SimError(f"{export}: episode {e} comes from source demo {d}, but {demos_hdf5} holds "
                                   f"{len(sources)} demos")
                demo = OracleDemo.from_buffer(buf, e, sources[d])
                state, ik_res = episode_start_state(env, ik, sources[d], pos_rotvec_to_pose(demo.pose6[0]))
                if state is None:
                    raise SimError(f"{export}: episode {e}'s first pose is out of the Panda's reach (IK error "
                                   f"{1000 * ik_res.pos_err:.1f} mm / {np.degrees(ik_res.rot_err):.1f}°)")
                r = rollout_config(env, probe, oracle_policy(cfg, demo.chunks(cfg.task)), state, e, 0,
                                   horizon=horizon, camera=cam)
                out.append({"episode": e, "source": d, "aug_id": int(rec["aug_id"][e]), "length": len(demo.pose6),
                            "ik_pos_err_m": float(ik_res.pos_err),
                            **{k: r[k] for k in ("success", "pregrasp_reached", "lifted", "steps",
                                                 "pregrasp_min_pos_err_m", "collision_table")}})
        return out
    finally:
        env.close()
