"""Shared fixtures of the reconstruction tests: one small synthetic session (built once per test session)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")

SCAN_FRAMES = 40


@pytest.fixture(scope="session")
def sim_session(tmp_path_factory):
    """A synthetic UMI session: 40 scan frames + 1 demo at 320x240 (~25 s to render on 2 cores)."""
    import importlib.util

    if importlib.util.find_spec("mujoco") is None:  # not importorskip: MuJoCo must be imported via umi_aug.sim.gl
        pytest.skip("mujoco (sim extra) not installed")
    from umi_aug.sim.session import make_session

    out = tmp_path_factory.mktemp("recon_session") / "session"
    make_session(out, 0, n_demos=1, scan_frames=SCAN_FRAMES, benchmark_frames=0, progress=False)
    return out


@pytest.fixture(scope="session")
def recon_known(sim_session, tmp_path_factory):
    """The pipeline in known-poses mode on the session (run once)."""
    pytest.importorskip("pycolmap")
    pytest.importorskip("open3d")
    from umi_aug.recon import ReconConfig, SfmConfig, reconstruct_session

    out = tmp_path_factory.mktemp("recon_known")
    return reconstruct_session(sim_session, out, ReconConfig(sfm=SfmConfig(mode="known_poses"), scan_stride=1))
