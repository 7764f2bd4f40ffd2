"""Tiny hand-built inputs for the bad-input suite (no MuJoCo, no rendering: each builds in well under a second).

:func:`build_session` writes a minimal UMI session in the real layout (``demos/mapping`` + one demo with
``raw_video.mp4`` and trajectory CSVs, ``calibration/gopro_intrinsics_<w>x<h>.json``, ``dataset.zarr.zip``);
:func:`snapshot` records every file's bytes so a test can assert that inputs and previous outputs are unchanged.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")

W, H, FPS = 64, 48, 30.0
N_MAP, N_DEMO, S = 6, 8, 32


def _write_video(path: Path, n: int) -> None:
    from umi_aug.data.video import VideoWriter

    path.parent.mkdir(parents=True, exist_ok=True)
    with VideoWriter(path, W, H, FPS) as vw:
        for i in range(n):
            vw.write(np.full((H, W, 3), 20 * i % 255, np.uint8))


def _write_csv(path: Path, n: int) -> None:
    from umi_aug.data.trajectory_csv import CameraTrajectory, write_camera_trajectory_csv

    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    T[:, 0, 3] = np.linspace(0.0, 0.1, n)
    T[:, 2, 3] = 0.4
    write_camera_trajectory_csv(path, CameraTrajectory(
        frame_idx=np.arange(n), timestamp=np.arange(n) / FPS, state=np.full(n, 2), is_lost=np.zeros(n, bool),
        is_keyframe=np.zeros(n, bool), T_world_cam=T))


def write_dataset(path: Path, lengths=(N_DEMO,), seed: int = 0) -> Path:
    """A UMI ``.zarr.zip`` (or directory) with one episode per length, ``S x S`` JPEG-XL frames."""
    from tests.data.helpers import random_episode
    from umi_aug.data import ReplayBuffer

    rng = np.random.default_rng(seed)
    buf = ReplayBuffer.create()
    for n in lengths:
        buf.add_episode(random_episode(rng, n, images=True, size=S))
    buf.save(path)
    return path


def build_session(root: Path) -> Path:
    """A minimal valid UMI session folder (see the module doc)."""
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json

    _write_video(root / "demos" / "mapping" / "raw_video.mp4", N_MAP)
    _write_csv(root / "demos" / "mapping" / "mapping_camera_trajectory.csv", N_MAP)
    (root / "demos" / "mapping" / "tx_slam_tag.json").write_text(json.dumps({"tx_slam_tag": np.eye(4).tolist()}))
    _write_video(root / "demos" / "demo_00" / "raw_video.mp4", N_DEMO)
    _write_csv(root / "demos" / "demo_00" / "camera_trajectory.csv", N_DEMO)
    (root / "calibration").mkdir(parents=True, exist_ok=True)
    save_umi_intrinsics_json(gopro_intrinsics_2_7k().scaled(W, H),
                             root / "calibration" / f"gopro_intrinsics_{W}x{H}.json")
    write_dataset(root / "dataset.zarr.zip")
    return root


def snapshot(*roots: Path) -> dict[str, str]:
    """``{path: sha256}`` of every file under (or at) ``roots``."""
    out = {}
    for r in roots:
        r = Path(r)
        files = [r] if r.is_file() else sorted(p for p in r.rglob("*") if p.is_file())
        for p in files:
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="session")
def _session_template(tmp_path_factory):
    return build_session(tmp_path_factory.mktemp("robust_template") / "session")


@pytest.fixture
def session(_session_template, tmp_path):
    """A fresh copy of the minimal session for one test."""
    import shutil

    return Path(shutil.copytree(_session_template, tmp_path / "session"))


class Reached(Exception):
    """Raised by a stubbed ``prepare_session``: the run got past every up-front check."""


@pytest.fixture
def stop_before_stages(monkeypatch):
    """Make ``export`` stop where the stages would start (raises :class:`Reached`)."""
    import importlib

    ex = importlib.import_module("umi_aug.augment.exporter")

    def stop(*a, **k):
        raise Reached()

    monkeypatch.setattr(importlib.import_module("umi_aug.augment.sources.session"), "prepare_session", stop)
    return ex


def small_cfg(**kw):
    from umi_aug.augment import AugmentConfig

    base = dict(mode="freespace", n_per_demo=2, seed=1, image_size=S)
    base.update(kw)
    return AugmentConfig(**base)
