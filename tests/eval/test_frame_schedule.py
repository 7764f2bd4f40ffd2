"""The harness renders only the wrist frames a checkpoint policy will look at (PolicyDriver.wants_image): the skipped
frames are exactly the ones no inference window uses, and a rollout with skipping equals one rendering every step."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests.eval.conftest import CONFIGS_FILE


class _FakePolicy:
    """Stands in for umi_aug.policy.Policy: records which frames (tagged by step index) each inference saw."""

    def __init__(self, To: int, down: int, action_horizon: int, n_action_steps: int, img_To: int | None = None
                 ) -> None:
        self.task = SimpleNamespace(n_robots=1, n_cameras=1, image_size=8, obs_down_sample_steps=down,
                                    img_obs_horizon=To if img_To is None else img_To, low_dim_obs_horizon=To,
                                    action_horizon=action_horizon)
        self.n_action_steps = n_action_steps
        self.seen: list[list[int]] = []

    def reset(self) -> None:
        self.seen = []

    def predict_action(self, obs, n_steps, generator=None):
        self.seen.append([int(img[0]) for img in obs["camera0_rgb"]])
        return {"action": np.zeros((n_steps, 7))}


def _run(To, down, horizon, n_exec, steps, skip, img_To=None):
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.eval.rollout import PolicyDriver

    fake = _FakePolicy(To, down, horizon, n_exec, img_To)
    driver = PolicyDriver(CheckpointEvalPolicy(fake))
    driver.reset(0)
    rendered = []
    obs = {"robot0_eef_pos": np.zeros(3), "robot0_eef_rot_axis_angle": np.zeros(3), "robot0_gripper_width": 0.04}
    for t in range(steps):
        want = driver.wants_image() if skip else True
        obs["camera0_rgb"] = np.full(1, t) if want else None
        if want:
            rendered.append(t)
        driver.act(obs, lambda target, close_below_m: target)
    return fake.seen, rendered


@pytest.mark.parametrize("trial", range(40))
def test_skipped_frames_are_never_used(trial):
    rng = np.random.default_rng([trial, 12345])
    To, down = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    img_To = int(rng.integers(1, To + 1))  # image frames: the window's newest img_To (e.g. 1 image, 2 poses)
    horizon = int(rng.integers(2, 17))
    n_exec = int(rng.integers(1, horizon))
    steps = int(rng.integers(1, 90))
    seen_all, _ = _run(To, down, horizon, n_exec, steps, skip=False, img_To=img_To)
    seen_skip, rendered = _run(To, down, horizon, n_exec, steps, skip=True, img_To=img_To)  # a needed None raises
    assert seen_skip == seen_all
    used = {t for window in seen_all for t in window}
    assert used <= set(rendered)
    # nothing rendered in vain, except frames whose window lies beyond the last step
    last_inference = max(t for t in range(steps) if t in rendered)
    assert set(rendered) - used <= set(range(last_inference - (img_To - 1) * down, steps))


def test_umi_schedule_renders_two_frames_in_eight():
    seen, rendered = _run(To=2, down=1, horizon=16, n_exec=8, steps=64, skip=True)
    assert len(seen) == 8 and len(rendered) == 16


def test_one_image_frame_renders_one_frame_in_eight():
    """One image frame and two low-dim rows (the study's recipe): the older pose needs no picture."""
    seen, rendered = _run(To=2, down=1, horizon=16, n_exec=8, steps=64, skip=True, img_To=1)
    assert len(seen) == 8 and rendered == list(range(0, 64, 8))
    assert seen == [[t] for t in range(0, 64, 8)]


def test_skipping_gives_the_same_rollout(square_env, tiny_checkpoint):
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.eval.rollout import rollout_config
    from umi_aug.eval.runner import load_eval_configs, rollout_seed
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.eval import SceneProbe

    configs = load_eval_configs(CONFIGS_FILE)
    probe = SceneProbe(square_env)
    pol = CheckpointEvalPolicy.from_checkpoint(tiny_checkpoint, n_action_steps=4)
    cam = WristFisheyeCamera(square_env.model, pol.image_size)
    try:
        recs = [rollout_config(square_env, probe, pol, configs["states"][7], 7, rollout_seed(0, 7), horizon=13,
                               camera=cam, render_every_step=every) for every in (True, False)]
    finally:
        cam.close()
    strip = ("time_s", "wall_s")
    assert {k: v for k, v in recs[0].items() if k not in strip} == {k: v for k, v in recs[1].items() if k not in strip}
