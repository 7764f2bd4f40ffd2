"""Fixtures of the policy tests: a small UMI dataset written once per module (smooth poses, 32² images).

The tests need the ``policy`` extra (diffusers, transformers, hydra-core); without it they are not collected.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

_MISSING = [m for m in ("diffusers", "transformers", "hydra", "omegaconf") if importlib.util.find_spec(m) is None]
if _MISSING:  # pragma: no cover - depends on the environment
    collect_ignore_glob = ["test_*.py"]


@pytest.fixture(autouse=True)
def _torch_threads():
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def dataset_path(tmp_path_factory):
    """4 episodes × 40 frames, one camera (32²): ``dataset.zarr.zip``."""
    from tests.policy.helpers import make_dataset

    path = tmp_path_factory.mktemp("policy_data") / "dataset.zarr.zip"
    return make_dataset(path, np.random.default_rng(1234))
