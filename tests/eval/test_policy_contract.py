"""One policy contract for evaluation and deployment (issue #33 item 3; umi_aug.policy.contract): every eval policy
kind, the deploy policies and the network wrapper are a PolicyLike; a plain object with only ``predict_action`` and
``reset`` runs in the simulated evaluation and in the robot runner alike; the rollout calls nothing else on a policy
(``seed`` only where the policy is seedable, ``info`` only to report), a learned policy's obs_dict holds exactly
the training sample's keys and windows, and only the privileged controls get the privileged entry."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests.eval.conftest import CONFIGS_FILE
from umi_aug.policy.contract import PolicyLike, SeedablePolicy, action_chunk

LOW_DIM = ("robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width")


class _Plain:
    """Only the contract: holds the observed pose (absolute targets), 4 rows; records what it saw."""

    def __init__(self) -> None:
        self.seen: list[dict] = []
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def predict_action(self, obs_dict):
        self.seen.append({k: np.shape(v) for k, v in obs_dict.items()})
        cur = np.concatenate([obs_dict["robot0_eef_pos"][-1], obs_dict["robot0_eef_rot_axis_angle"][-1],
                              np.reshape(obs_dict["robot0_gripper_width"][-1], 1)])
        return {"action": np.tile(cur, (4, 1))}


def _spy(pol) -> list[str]:
    """Record every call of ``pol``'s methods (instance attributes wrapping them); returns the list of names."""
    calls: list[str] = []
    for name in dir(pol):
        value = getattr(pol, name)
        if name.startswith("__") or not callable(value) or isinstance(value, type):
            continue

        def call(*a, _name=name, _value=value, **kw):
            calls.append(_name)
            return _value(*a, **kw)

        setattr(pol, name, call)
    return calls


class _Network:
    """Stands in for umi_aug.policy.Policy (image 1 frame, low-dim 2 rows, 8² images): records its obs_dicts."""

    def __init__(self) -> None:
        self.task = SimpleNamespace(n_robots=1, n_cameras=1, image_size=8, obs_down_sample_steps=1,
                                    img_obs_horizon=1, low_dim_obs_horizon=2, action_horizon=8)
        self.n_action_steps = 3
        self.seen: list[dict] = []

    def reset(self) -> None:
        pass

    def predict_action(self, obs_dict, n_steps=None, generator=None):
        self.seen.append({k: np.shape(v) for k, v in obs_dict.items()})
        cur = np.concatenate([obs_dict["robot0_eef_pos"][-1], obs_dict["robot0_eef_rot_axis_angle"][-1], [0.08]])
        return {"action": np.tile(cur, (n_steps, 1))}


class _BlankCamera:
    def __init__(self, size: int) -> None:
        self.size = size

    def render(self, data, T_world_cam):
        return np.zeros((self.size, self.size, 3), np.uint8)


def _eval_kinds():
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.square.controls import ExpertEvalPolicy, HoldStillEvalPolicy, RandomEvalPolicy, ReplayEvalPolicy

    return {"expert": ExpertEvalPolicy(), "hold": HoldStillEvalPolicy(), "random": RandomEvalPolicy(0.5),
            "replay": ReplayEvalPolicy([np.zeros((3, 7))] * 5), "checkpoint": CheckpointEvalPolicy(_Network())}


def test_every_policy_kind_is_the_one_contract():
    from umi_aug.deploy.policies import ReachPolicy
    from umi_aug.square.eval import POLICY_KINDS
    from umi_aug.square.oracle import oracle_config, oracle_policy

    kinds = _eval_kinds()
    assert set(kinds) == set(POLICY_KINDS)
    network = oracle_policy(oracle_config(image_size=16), np.zeros((4, 16, 10))).policy  # umi_aug.policy.Policy
    deploy = [ReachPolicy([0.4, 0.0, 0.3, np.pi, 0.0, 0.0]), network]
    for pol in [*kinds.values(), *deploy, _Plain()]:
        assert isinstance(pol, PolicyLike), type(pol).__name__
    seedable = {k for k, p in kinds.items() if isinstance(p, SeedablePolicy)}
    assert seedable == {"random", "checkpoint"}  # the two kinds with randomness


def test_results_are_diffusion_policys_dict():
    from umi_aug.deploy.policies import ReachPolicy
    from umi_aug.errors import PolicyError

    obs = {"robot0_eef_pos": np.array([[0.4, 0.0, 0.3]] * 2), "robot0_eef_rot_axis_angle": np.array([[np.pi, 0, 0]] * 2),
           "robot0_gripper_width": np.full((2, 1), 0.05)}
    assert action_chunk(ReachPolicy([0.41, 0.0, 0.3, np.pi, 0.0, 0.0]).predict_action(obs)).shape == (16, 7)
    with pytest.raises(PolicyError, match="must return a dict with 'action'"):
        action_chunk(np.zeros((4, 7)))
    with pytest.raises(PolicyError, match=r"got \['action_pred'\]"):
        action_chunk({"action_pred": np.zeros((4, 7))})


def test_a_plain_policy_runs_in_the_robot_runner():
    from tests.deploy.test_runner import make

    r, clock, robot, grip, cam, _ = make()
    plain = _Plain()
    r.policy = plain
    logs = r.run(n_cycles=3)
    assert plain.resets == 1 and len(plain.seen) == 3 and len(logs) == 3
    assert set(plain.seen[0]) == {"camera0_rgb", *LOW_DIM}
    assert all(len(c.commands) + c.n_dropped == 4 for c in logs)


def test_a_plain_policy_runs_in_the_simulated_evaluation(square_env):
    from umi_aug.eval.rollout import rollout_config
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.square.eval import SceneProbe

    state = load_eval_configs(CONFIGS_FILE)["states"][0]
    plain = _Plain()
    calls = _spy(plain)
    rec = rollout_config(square_env, SceneProbe(square_env), plain, state, 0, 5, horizon=9)
    assert rec["steps"] == 9 and not rec["success"] and plain.resets == 1
    # default window: 2 low-dim rows, no image; rows 1..3 of each 4-row chunk executed → an inference every 3 steps
    assert plain.seen == [{"robot0_eef_pos": (2, 3), "robot0_eef_rot_axis_angle": (2, 3),
                           "robot0_gripper_width": (2, 1)}] * 3
    assert calls == ["reset"] + ["predict_action"] * 3


@pytest.mark.parametrize("kind", ["expert", "hold", "random", "replay", "checkpoint"])
def test_the_rollout_calls_only_the_contract(square_env, kind):
    """Each eval kind is driven by reset / predict_action (+ seed where seedable); the network's obs_dict is the
    training sample's keys and windows, the privileged entry goes to the expert and the replay only."""
    from umi_aug.eval.policies import PRIVILEGED_KEY
    from umi_aug.eval.rollout import rollout_config
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.square.controls import PrivilegedState
    from umi_aug.square.eval import SceneProbe

    state = load_eval_configs(CONFIGS_FILE)["states"][2]
    pol = _eval_kinds()[kind]
    seen: list[dict] = []
    orig = pol.predict_action

    def recording(obs_dict):
        seen.append(dict(obs_dict))
        return orig(obs_dict)

    pol.predict_action = recording
    calls = _spy(pol)
    rollout_config(square_env, SceneProbe(square_env), pol, state, 2, 7, horizon=6, camera=_BlankCamera(8))
    assert calls[0] == "reset" and set(calls) <= {"reset", "seed", "predict_action", "info"}
    assert ("seed" in calls) == (kind in ("random", "checkpoint"))
    privileged = kind in ("expert", "replay")
    assert all((PRIVILEGED_KEY in o) == privileged for o in seen)
    if privileged:
        s = seen[0][PRIVILEGED_KEY]
        assert isinstance(s, PrivilegedState) and s.config == 2 and s.T_world_nut.shape == (4, 4)
    if kind == "checkpoint":
        net = pol.policy
        assert len(net.seen) == 2  # 3 targets per inference
        assert net.seen[0] == {"robot0_eef_pos": (2, 3), "robot0_eef_rot_axis_angle": (2, 3),
                               "robot0_gripper_width": (2, 1), "camera0_rgb": (1, 8, 8, 3)}
