"""`python eval/eval_sim.py` as a user runs it: spawned workers, videos, a clean console."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_cli_two_spawned_workers_videos_and_clean_console(tmp_path, tiny_checkpoint, square_env):
    out = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "eval" / "eval_sim.py"), f"checkpoint={tiny_checkpoint}", "configs='3,4'",  # a list: quoted, as on a shell
           "workers=2", "horizon=6", "video_every=1", "video_size=64", f"out_dir={out}", "progress=false"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=500)
    console = proc.stdout + proc.stderr
    assert proc.returncode == 0, console[-3000:]
    # MuJoCo's EGL teardown used to print a traceback per GL context of every worker at exit
    assert "Traceback" not in console and "EGLError" not in console, console[-3000:]
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(r["config"] for r in rows) == [3, 4] and all(r["steps"] == 6 for r in rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n"] == 2 and summary["workers"] == 2
    from umi_aug.data.video import probe_video, read_video_frames

    for i in (3, 4):
        for kind in ("wrist", "external"):
            path = out / "videos" / f"config_{i:04d}_{kind}.mp4"
            info = probe_video(path)  # every 2nd of 6 control steps → 3 frames, 64² RGB, not blank
            assert (info.n_frames, info.width, info.height) == (3, 64, 64), (path, info)
            frames = read_video_frames(path, range(info.n_frames))
            assert np.ptp(frames) > 30, path
