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
            # a 1 Hz robot-side watchdog: this real-time child on a loaded machine may miss ur-rtde's default 0.1 s
            "robot": {"robot_ip": f"fake?log={log}", "rtde_modules": FAKE, "max_pos_speed": 0.25,
                      "watchdog_min_frequency": 1.0},
            "gripper": {"gripper_ip": "127.0.0.1", "gripper_port": wsg_port},
            "camera": {"device": str(video), "width": 128, "height": 72, "fps": 60.0, "latency": 0.17,
                       "realtime": True},
            "safety": {"workspace_min": [-0.6, -0.8, -0.05], "workspace_max": [0.6, 0.2, 0.55]},
        },
        "policy": {"kind": "reach", "target": [0.4, -0.05, 0.28, np.pi, 0.0, 0.0], "speed": 0.05, "dt": 0.1},
        "out_dir": str(tmp_path / "run"), "start_delay": 0.3, "max_duration": 15.0, "reach_tolerance_m": 0.005,
        "confirm": True,
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
    """#31 item 3: a dry run (with joints_init set, which a real run would moveJ to) connects read-only: the fake
    robot's call log and the gripper server's command log hold reads only; the would-be commands are recorded."""
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log, dry_run=True, n_cycles=2, confirm=False)  # no prompt needed
    cfg["robot"]["robot"]["joints_init"] = [0, -90, -90, -90, 90, 0]
    s = run_deploy(cfg, ask=lambda text: pytest.fail("a dry run must not ask"))
    assert s["cycles"] == 2 and s["dry_run"] and s["dry_run_would_stop"]["n_commands"] == 0
    assert [c[0] for c in map(json.loads, open(log))] == ["receive.__init__", "receive.disconnect"]
    srv.thread.join(5)
    assert srv.ids() and set(srv.ids()) <= {0xB0, 0x07}  # measure (a read) and the protocol goodbye only
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(tmp_path / "run" / "episode.zarr.zip") as rb:  # the would-be commands, recorded
        a = np.asarray(rb["action"][:])
    assert a.shape == (2, 7) and np.isfinite(a).all()
    assert (tmp_path / "run" / "tcp_commanded_vs_reached.png").exists()


@pytest.mark.slow
def test_dry_run_records_why_it_would_have_stopped(tmp_path, video):
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log, dry_run=True, n_cycles=2)
    cfg["policy"].update({"target": [0.4, 0.3, 0.28, np.pi, 0.0, 0.0], "speed": 0.2})  # y = 0.3 > box max 0.2
    s = run_deploy(cfg)
    w = s["dry_run_would_stop"]
    assert s["cycles"] == 2 and s["stop_reason"] == "2 cycles done"  # the dry run went on
    assert w["n_commands"] > 0 and w["first_cycle"] == 0 and "outside the workspace box" in w["reasons"][0]
    assert json.loads((tmp_path / "run" / "timing.json").read_text())["dry_run_would_stop"] == w
    assert [c[0] for c in map(json.loads, open(log))] == ["receive.__init__", "receive.disconnect"]
    srv.thread.join(5)
    assert set(srv.ids()) <= {0xB0, 0x07}


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
    """Independent of machine load (#31 item 8): one action per cycle whatever the inference time
    (``late_actions: next_slot``), a 0.25 s policy step, and the run ends after 2 cycles (``n_cycles``), not on a
    clock: ``max_duration`` is only a hang guard (a 3 s run once gave 1 cycle with 5 busy processes beside it)."""
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log, checkpoint=str(tiny_ckpt), dt=0.25, steps_per_inference=2,
               n_cycles=2, max_duration=300.0, late_actions="next_slot")
    cfg["policy"] = {"kind": "checkpoint"}
    cfg["robot"]["safety"] = {"workspace_min": [-0.1, -0.35, -0.05], "workspace_max": [0.7, 0.35, 0.6],
                              "max_step_m": 0.5, "max_step_rad": np.pi, "height_threshold": -0.1}
    s = run_deploy(cfg)
    assert s["stop_reason"] == "2 cycles done", s
    assert s["cycles"] == 2 and s["policy"] == "Policy" and s["dt"] == pytest.approx(0.25)
    assert s["late_actions"]["n_hold_cycles"] == 0
    calls = [json.loads(line) for line in open(log)]
    servo = np.array([c[2] for c in calls if c[0] == "servoL"])
    assert np.abs(servo - fake_rtde.POSE0).max() > 1e-6  # the policy's commands moved the (fake) arm
    srv.thread.join(5)


# ------------------------------------------------------------------ #31 item 4: a real arm needs an explicit yes
def _control_calls(log):
    """Calls that command the robot (anything beyond the receive interface's reads)."""
    return [c[0] for c in map(json.loads, open(log)) if not c[0].startswith("receive.")]


def test_default_robot_is_the_simulation_and_confirm_is_off():
    import yaml
    from pathlib import Path

    cfg = yaml.safe_load((Path(__file__).resolve().parents[2] / "configs" / "deploy_ur.yaml").read_text())
    assert {"robot": "sim_ur5e"} in cfg["defaults"] and cfg["confirm"] is False and cfg["dry_run"] is False


@pytest.mark.parametrize("answer, match", [
    ("no", r"not confirmed \(answer 'no', expected 'yes'\); nothing was sent to the arm"),
    (None, r"robot.backend=rtde moves a real arm: confirm at the interactive prompt, or pass confirm=true"),
])
def test_real_arm_moves_only_after_an_explicit_yes(tmp_path, video, answer, match):
    from umi_aug.errors import DeployError

    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    shown: list[str] = []

    def ask(text):
        shown.append(text)
        return answer

    with pytest.raises(DeployError, match=match):
        run_deploy(_cfg(tmp_path, video, srv.port, log, confirm=False), ask=ask)
    assert _control_calls(log) == []  # the control interface was never opened
    srv.thread.join(5)
    assert set(srv.ids()) <= {0xB0, 0x07}  # gripper: measured only (and the protocol goodbye)
    text = shown[0]
    for part in ("robot_ip=fake?log=", "setTcp([0, 0, 0.235, 0, 0, 0])", "[-0.6, -0.8, -0.05] .. [0.6, 0.2, 0.55]",
                 "max_pos_speed 0.25 m/s", "max_rot_speed 0.6 rad/s", "current TCP: [0.4, 0.0, 0.3, 3.142, 0.0, 0.0]",
                 "first target: [", "reach target: [0.4, -0.05, 0.28, 3.142, 0.0, 0.0], 0.054 m"):
        assert part in text, (part, text)


def test_real_arm_moves_after_yes(tmp_path, video):
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    s = run_deploy(_cfg(tmp_path, video, srv.port, log, confirm=False, n_cycles=1), ask=lambda text: "yes")
    assert s["cycles"] == 1
    names = _control_calls(log)
    assert names[:3] == ["control.__init__", "setTcp", "setWatchdog"] and "servoL" in names
    srv.thread.join(5)
    assert 0x20 in srv.ids() and 0xB1 in srv.ids()  # homed and position-controlled after the yes


def test_reach_refuses_a_far_target_before_anything_moves(tmp_path, video):
    from umi_aug.deploy.policies import ReachPolicy
    from umi_aug.errors import DeployError

    with pytest.raises(DeployError, match=r"policy.max_distance_m=0.9 must be in \(0, 0.85\]"):
        ReachPolicy([0.4, 0, 0.3, np.pi, 0, 0], max_distance_m=0.9)
    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log)  # confirm=True: the refusal does not depend on the prompt
    cfg["policy"].update({"target": [0.1, -0.4, 0.3, np.pi, 0.0, 0.0], "max_distance_m": 0.4})  # 0.5 m away
    with pytest.raises(DeployError, match=r"is 0.500 m from the current TCP \[0.4, 0.0, 0.3\] m > "
                                          r"policy.max_distance_m=0.4"):
        run_deploy(cfg)
    assert _control_calls(log) == []
    srv.thread.join(5)
    assert set(srv.ids()) <= {0xB0, 0x07}


# ------------------------------------------------------------------ #31 item 5: bounded limits, start-up check
@pytest.mark.parametrize("block, key, value", [
    ("robot", "max_pos_speed", 100.0), ("robot", "watchdog_s", 1e6), ("safety", "max_step_m", 50.0),
    ("safety", "max_obs_age_s", 1e9), ("safety", "height_threshold", -1e9),
    ("safety", "workspace_max", [100.0, 100.0, 100.0]),
])
def test_a_limit_out_of_bounds_is_one_error_before_any_device_starts(tmp_path, video, block, key, value):
    from umi_aug.errors import DeployError

    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, 1, log)  # gripper port 1: nothing listens (it must not be reached)
    cfg["robot"][block][key] = value
    with pytest.raises(DeployError, match=rf"robot\.{block}\.{key.replace('_max', '_min/max')}") as ei:
        run_deploy(cfg)
    assert "\n" not in str(ei.value)
    assert not log.exists()  # the robot was never contacted


@pytest.mark.parametrize("safety, match", [
    ({"workspace_min": [-0.6, 0.05, -0.05], "workspace_max": [0.6, 0.6, 0.55]},
     r"start-up check: the current TCP \[0.4, 0.0, 0.3\] m is outside the workspace box"),
    ({"height_threshold": 0.35, "workspace_max": [0.6, 0.2, 0.55]},
     r"start-up check: the fingers of the current TCP \[0.4, 0.0, 0.3\] m are 50.0 mm below "
     r"safety.height_threshold=0.35"),
])
def test_start_up_check_stops_before_the_first_command(tmp_path, video, safety, match):
    from umi_aug.deploy.safety import SafetyStop

    srv = FakeWSG()
    log = tmp_path / "calls.jsonl"
    cfg = _cfg(tmp_path, video, srv.port, log)
    cfg["robot"]["safety"].update(safety)
    with pytest.raises(SafetyStop, match=match):
        run_deploy(cfg)
    assert _control_calls(log) == []  # no command reached the robot
    srv.thread.join(5)
    assert set(srv.ids()) <= {0xB0, 0x07}
