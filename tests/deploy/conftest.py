"""Fixtures shared by the deploy tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_ckpt(tmp_path_factory):
    """A random-weight tiny policy (as tests/eval's fixture) with a normaliser fitted on a synthetic dataset,
    trained once for the ur-rtde and the simulated-UR5e end-to-end tests. Its dataset moves a quarter as far as the
    default (``motion_scale=0.25``): the sampler clips to the normaliser's range, so whatever the random weights
    and noise, every command stays within :func:`tests.policy.helpers.max_relative_step_m` of the pose it was predicted from (a
    full-scale dataset once gave a command 0.21 m above the start, out of the test's workspace box)."""
    from tests.policy.helpers import make_tiny_checkpoint

    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt"), length=60, obs_down_sample_steps=3,
                                motion_scale=0.25)
