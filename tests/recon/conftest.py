"""Shared fixtures of the reconstruction tests: one small synthetic session (the suite's demo run renders it) and
the known-poses pipeline run on it once per test session."""

from __future__ import annotations

import json
import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="session")
def sim_session(demo_run):
    """A synthetic UMI session: 40 scan frames + 1 demo at 320x240, seed 0 (``make_session(out, 0, n_demos=1,
    scan_frames=40)``). Not rendered again here: it is the session the suite's ``umi-aug demo`` run rendered
    (tests/conftest.py ``demo_run``: seed 0, ``DEMO_SCAN_FRAMES`` = 40, UMI's 224² policy images), read only. Only
    the demo's session stage must have worked, not the rest of the demo."""
    from tests.conftest import DEMO_SCAN_FRAMES

    session = demo_run.out / "session"
    if not (session / "session.json").is_file():
        pytest.fail(f"the suite's `umi-aug demo` run (exit {demo_run.rc}) wrote no session at {session}: "
                    f"see tests/cli/test_cli.py::test_demo_runs_end_to_end")
    info = json.loads((session / "session.json").read_text())
    assert info["seed"] == 0 and info["config"]["scan_frames"] == DEMO_SCAN_FRAMES, info["config"]
    return session


@pytest.fixture(scope="session")
def recon_known(sim_session, tmp_path_factory):
    """The pipeline in known-poses mode on the session (run once)."""
    pytest.importorskip("pycolmap")
    pytest.importorskip("open3d")
    from umi_aug.recon import ReconConfig, SfmConfig, reconstruct_session

    out = tmp_path_factory.mktemp("recon_known")
    return reconstruct_session(sim_session, out, ReconConfig(sfm=SfmConfig(mode="known_poses"), scan_stride=1))
