"""The whole runner (run_deploy) closing the loop with the real backends' code against a fake rtde module (the
TCP follows servoL), the loopback WSG-50 server and a video-file camera: scripted reach, dry run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.deploy import fake_rtde
from tests.deploy.wsg_server import FakeWSG
from umi_aug.deploy.app import run_deploy

FAKE = ["tests.deploy.fake_rtde", "tests.deploy.fake_rtde"]


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    from umi_aug.data.video import VideoWriter

    path = tmp_path_factory.mktemp("vid") / "cam.mp4"
    rng = np.random.default_rng(1)
    base = rng.integers(0, 255, (72, 128, 3), dtype=np.uint8)
    with VideoWriter(path, 128, 72, fps=60.0, crf=30) as vw:
        for i in range(60 * 20):
            vw.write(np.roll(base, i, axis=1))
    return path


def _cfg(tmp_path, video, wsg_port, log, **kw):
    cfg = {
        "robot": {
            "robot": {"robot_ip": f"fake?log={log}", "rtde_modules": FAKE, "max_pos_speed": 0.25},
            "gripper": {"gripper_ip": "127.0.0.1", "gripper_port": wsg_port},
            "camera": {"device": str(video), "width": 128, "height": 72, "fps": 60.0, "latency": 0.17,
                       "realtime": True},
            "safety": {"workspace_min": [-0.6, -0.8, -0.05], "workspace_max": [0.6, 0.2, 0.6]},
        },
        "policy": {"kind": "reach", "target": [0.4, -0.05, 0.28, np.pi, 0.0, 0.0], "speed": 0.05, "dt": 0.1},
        "out_dir": str(tmp_path / "run"), "start_delay": 0.3, "max_duration": 15.0, "reach_tolerance_m": 0.005,
    }
    cfg.update(kw)
    return cfg


@pytest.mark.slow
def test_reach_closes_the_loop_and_records(tmp_path, video):
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    s = run_deploy(_cfg(tmp_path, video, srv.port, log))
    assert s["stop_reason"] == "done", s
    assert s["final_error_m"] < 0.005 and s["cycles"] >= 2
    out = tmp_path / "run"
    for f in ("episode.zarr.zip", "episode.mp4", "tcp_commanded_vs_reached.png", "timing.json"):
        assert (out / f).stat().st_size > 0, f
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(out / "episode.zarr.zip") as rb:
        assert rb.n_episodes == 1 and rb.n_steps == s["cycles"]
        assert rb["camera0_rgb"].shape[1:] == (224, 224, 3) and rb["action"].shape[1] == 7
    t = json.loads((out / "timing.json").read_text())
    assert t["control_period"]["n"] > 100 and t["obs_to_action_latency"]["p50_ms"] >= 170.0  # camera latency
    calls = [json.loads(line) for line in open(log)]
    assert [c[0] for c in calls][-4:] == ["servoStop", "stopScript", "control.disconnect", "receive.disconnect"]
    srv.thread.join(5)
    assert srv.ids()[-2:] == [0x22, 0x07]  # gripper stopped and disconnected
    assert any(c == 0xB1 and abs(np.frombuffer(p[1:5], "<f4")[0] - 50.0) < 0.5 for c, p in srv.received)


@pytest.mark.slow
def test_dry_run_sends_no_motion(tmp_path, video):
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    s = run_deploy(_cfg(tmp_path, video, srv.port, log, dry_run=True, n_cycles=2))
    assert s["cycles"] == 2 and s["dry_run"]
    servo = np.array([c[2] for c in map(json.loads, open(log)) if c[0] == "servoL"])
    assert len(servo) > 10 and np.allclose(servo, fake_rtde.POSE0)  # held the start pose throughout
    assert (tmp_path / "run" / "tcp_commanded_vs_reached.png").exists()
    srv.thread.join(5)


@pytest.mark.slow
def test_command_outside_workspace_halts_and_still_records(tmp_path, video):
    from umi_aug.deploy.safety import SafetyStop

    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log)
    cfg["policy"]["target"] = [0.4, 0.3, 0.28, np.pi, 0.0, 0.0]  # y = 0.3 > workspace_max y = 0.2
    cfg["policy"]["speed"] = 0.2
    with pytest.raises(SafetyStop, match=r"outside the workspace box"):
        run_deploy(cfg)
    calls = [json.loads(line) for line in open(log)]
    assert [c[0] for c in calls][-4:] == ["servoStop", "stopScript", "control.disconnect", "receive.disconnect"]
    servo_y = np.array([c[2][1] for c in calls if c[0] == "servoL"])
    assert servo_y.max() <= 0.2 + 1e-9  # never commanded outside the box
    assert (tmp_path / "run" / "timing.json").exists()
    srv.thread.join(5)


def test_cli_bad_checkpoint_is_one_clear_error(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, str(root / "eval" / "deploy_ur.py"), "checkpoint=/nonexistent.ckpt",
                        f"out_dir={tmp_path / 'o'}", f"hydra.run.dir={tmp_path / 'h'}"],
                       capture_output=True, text=True, timeout=120, cwd=root)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == ["error: checkpoint='/nonexistent.ckpt': not a file; pass "
                                             "checkpoint=PATH (or policy=reach)"]


@pytest.mark.slow
def test_checkpoint_policy_closes_the_loop(tmp_path, video, tiny_ckpt):
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log, checkpoint=str(tiny_ckpt), n_cycles=3,
               action_exec_latency=0.3)  # slack for a loaded CI machine (CPU inference, busy child process)
    cfg["policy"] = {"kind": "checkpoint"}
    cfg["robot"]["safety"] = {"workspace_min": [-2, -2, -2], "workspace_max": [2, 2, 2], "max_step_m": 2.0,
                              "max_step_rad": 3.2, "height_threshold": -2.0}
    s = run_deploy(cfg)
    assert s["cycles"] == 3 and s["policy"] == "Policy" and s["dt"] == pytest.approx(3 / 60)
    calls = [json.loads(line) for line in open(log)]
    servo = np.array([c[2] for c in calls if c[0] == "servoL"])
    assert np.abs(servo - fake_rtde.POSE0).max() > 1e-6  # the policy's commands moved the (fake) arm
    srv.thread.join(5)
