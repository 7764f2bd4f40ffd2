"""Fixtures shared by the deploy tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_ckpt(tmp_path_factory):
    """A random-weight tiny policy (as tests/eval's fixture) with a normaliser fitted on a synthetic dataset,
    trained once for the ur-rtde and the simulated-UR5e end-to-end tests."""
    from tests.policy.helpers import make_tiny_checkpoint

    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), length=60, obs_down_sample_steps=3)
