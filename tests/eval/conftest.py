"""Fixtures of the evaluation-harness tests: one SquareEnv-backed harness per session (in this process), a tiny
random-weight checkpoint, a recorded expert episode. Everything is generated here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

CONFIGS_FILE = Path(__file__).resolve().parents[2] / "eval" / "square_init_configs_1000.npz"


@pytest.fixture(autouse=True)
def _one_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def square_env():
    import importlib.util

    if importlib.util.find_spec("robosuite") is None:  # not importorskip: MuJoCo must be imported via sim.gl
        pytest.skip("robosuite not installed (pip install 'umi-aug[robomimic]')")
    from umi_aug.eval.runner import _worker_state, load_eval_configs

    # the harness's own per-process env (shared with in-process run_eval calls: one env for the whole session)
    spec = {"env_meta": load_eval_configs(CONFIGS_FILE)["env_args"], "key": "hold", "policy": "hold"}
    yield _worker_state(spec)["env"]


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """A random-weight checkpoint of a tiny policy (32² images, ResNet width 8) with a normaliser fitted on a
    synthetic dataset — enough to run the closed loop (it will not solve the task)."""
    from umi_aug.policy.checkpoint import save_checkpoint
    from umi_aug.policy.config import config_to_dict, shape_meta
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy
    from tests.policy.helpers import make_dataset, tiny_config

    tmp = tmp_path_factory.mktemp("ckpt")
    ds = make_dataset(tmp / "d.zarr.zip", np.random.default_rng(0), n_episodes=2, length=40)
    cfg = tiny_config(ds, tmp, obs_down_sample_steps=1, val_ratio=0.0)
    model = DiffusionUnetPolicy(shape_meta(cfg.task), cfg.policy, warn_random_init=False)
    model.set_normalizer(UmiPolicyDataset(ds, cfg.task, split="all").fit_normalizer())
    return save_checkpoint(tmp / "tiny.ckpt", {"cfg": config_to_dict(cfg), "state_dicts": {"model": model.state_dict()},
                                               "pickles": {"global_step": 0, "epoch": 0, "epoch_done": True}})
