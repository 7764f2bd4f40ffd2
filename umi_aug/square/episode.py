"""One episode of the square task as arrays in robomimic's layout (+ the UMI pose/gripper channels).

Row ``t`` of ``states`` / ``obs`` is the state before ``actions[t]``; ``rewards[t]`` / ``dones[t]`` follow it.
The episode of :func:`rollout_expert` ends at the first step after which the task is successful and the expert
has retreated (or at ``horizon``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from umi_aug.square.env import FISHEYE_KEY, LOW_DIM_KEYS, SquareEnv
from umi_aug.square.expert import ExpertConfig, SquareExpert

__all__ = ["Episode", "rollout_expert", "HORIZON"]

#: robomimic's evaluation horizon for square PH.
HORIZON: int = 400


@dataclass
class Episode:
    """Arrays of one episode (T steps).

    Attributes:
        states: float64 [T, 45] flattened MuJoCo states (robomimic ``states``).
        actions: float64 [T, 7] OSC_POSE delta actions.
        rewards: float64 [T]; dones: int64 [T] (1 at the final step of a successful episode).
        obs: {key: [T, ...]}: :data:`LOW_DIM_KEYS` float64 and ``FISHEYE_KEY`` uint8 [T, S, S, 3] (if rendered).
        T_world_tcp: float64 [T, 4, 4] TCP poses (OpenCV camera axes at the grip site).
        gripper_width: float64 [T] metres.
        success: the task succeeded; seed: reset seed (or −1); model_xml: the MJCF; seconds: wall time.
    """

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    obs: dict[str, np.ndarray]
    T_world_tcp: np.ndarray
    gripper_width: np.ndarray
    success: bool
    seed: int = -1
    model_xml: str = ""
    seconds: float = 0.0
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.actions.shape[0])


class _Recorder:
    def __init__(self, render: bool) -> None:
        self.render = render
        self.rows: dict[str, list] = {k: [] for k in ("states", "actions", "rewards", "dones", "tcp", "width")}
        self.obs: dict[str, list] = {}

    def observe(self, env: SquareEnv, obs: dict[str, np.ndarray]) -> None:
        self.rows["states"].append(env.get_state())
        self.rows["tcp"].append(env.tcp_pose())
        self.rows["width"].append(env.gripper_width())
        keys = LOW_DIM_KEYS + ((FISHEYE_KEY,) if self.render else ())
        for k in keys:
            self.obs.setdefault(k, []).append(np.asarray(obs[k]).copy())

    def stack(self, **kw) -> Episode:
        r = self.rows
        return Episode(
            states=np.asarray(r["states"]), actions=np.asarray(r["actions"], dtype=np.float64),
            rewards=np.asarray(r["rewards"], dtype=np.float64), dones=np.asarray(r["dones"], dtype=np.int64),
            obs={k: np.stack(v) for k, v in self.obs.items()}, T_world_tcp=np.asarray(r["tcp"]),
            gripper_width=np.asarray(r["width"]), **kw)


def rollout_expert(
    env: SquareEnv,
    seed: int,
    horizon: int = HORIZON,
    expert_cfg: ExpertConfig | None = None,
    render: bool = True,
    states0: np.ndarray | None = None,
) -> Episode:
    """Run the scripted expert from ``env.reset(seed)`` (or from the flattened state ``states0``).

    Args:
        env: a :class:`SquareEnv` (with ``image_size`` set when ``render``).
        seed: reset seed (numpy global generator; ignored for the state when ``states0`` is given).
        horizon: maximum number of steps.
        render: record the fisheye wrist image in ``obs``.
    Returns:
        :class:`Episode`; ``success`` says whether the task was solved within the horizon.
    """
    t0 = time.perf_counter()
    saved_size = env.image_size
    if not render:
        env.image_size = None
    try:
        obs = env.reset(seed=seed) if states0 is None else env.reset_to(states0, initial=True)
        expert = SquareExpert(expert_cfg)
        rec = _Recorder(render)
        success = False
        for _ in range(int(horizon)):
            rec.observe(env, obs)
            action = expert.act(env)
            obs, reward, _, _ = env.step(action)
            success = env.is_success()
            finished = success and expert.phase == "done"
            rec.rows["actions"].append(action)
            rec.rows["rewards"].append(float(reward))
            rec.rows["dones"].append(int(finished))
            if finished:
                break
    finally:
        env.image_size = saved_size
    return rec.stack(success=bool(success), seed=int(seed), model_xml=env.model_xml(),
                     seconds=time.perf_counter() - t0, info={"final_phase": expert.phase})
