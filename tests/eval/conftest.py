"""Fixtures of the evaluation-harness tests (the square task is the harness's test bed): one SquareEnv-backed
harness per session (in this process), a tiny random-weight checkpoint, a recorded expert episode. Everything is
generated here."""

from __future__ import annotations

from pathlib import Path

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
def _square_env_spec():
    import importlib.util

    if importlib.util.find_spec("robosuite") is None:  # not importorskip: MuJoCo must be imported via sim.gl
        pytest.skip("robosuite not installed (pip install 'umi-aug[robomimic]')")
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.square.eval import SQUARE_TASK

    return {"env_meta": load_eval_configs(CONFIGS_FILE)["env_args"], "key": "hold", "policy": "hold",
            "task": SQUARE_TASK}


@pytest.fixture
def square_env(_square_env_spec):
    """The harness's own per-process env (shared with in-process run_eval calls: one env for the whole session).
    Looked up per test: a run_eval with another env_meta (policy=replay: none) closes and replaces the harness's
    env, so an env object held from an earlier test may be closed; this rebuilds it only in that case."""
    from umi_aug.eval.runner import _worker_state

    return _worker_state(_square_env_spec)["env"]


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """A random-weight checkpoint of a tiny policy (32² images, ResNet width 8) with a normaliser fitted on a
    synthetic dataset — enough to run the closed loop (it will not solve the task)."""
    from tests.policy.helpers import make_tiny_checkpoint

    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), length=40, obs_down_sample_steps=1)
