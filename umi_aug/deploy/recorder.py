"""Episode recording: a UMI zarr replay buffer, a CPU (libx264) mp4, a commanded-vs-reached TCP plot and timing
statistics (control-loop period jitter, observation-to-action latency)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.data import ReplayBuffer
from umi_aug.data.video import VideoWriter
from umi_aug.deploy.runner import CycleLog

__all__ = ["EpisodeRecorder", "timing_stats"]


def timing_stats(x: np.ndarray) -> dict[str, float]:
    """p50 / p99 / max of a sample (seconds → milliseconds)."""
    x = np.asarray(x, np.float64) * 1000.0
    if len(x) == 0:
        return {"n": 0}
    return {"n": int(len(x)), "p50_ms": float(np.percentile(x, 50)), "p99_ms": float(np.percentile(x, 99)),
            "max_ms": float(x.max())}


class EpisodeRecorder:
    """Collects one record per inference cycle (``on_cycle`` hook of the runner) plus the robot's state stream.

    Args:
        robot, gripper, camera: the runner's backends (read only).
    """

    def __init__(self, robot: Any, gripper: Any, camera: Any) -> None:
        self.robot, self.gripper, self.camera = robot, gripper, camera
        self.rows: list[dict[str, np.ndarray]] = []
        self.commands: list[tuple[float, np.ndarray]] = []
        self.robot_t: list[np.ndarray] = []
        self.robot_pose: list[np.ndarray] = []
        self._last_t = -np.inf

    def on_cycle(self, c: CycleLog) -> None:
        cam = self.camera.get_frames(1)
        g = self.gripper.get_states(1)
        # a held cycle (nothing sent: every action late, or a stale chunk) records the hold: current pose + width
        first = c.commands[0] if len(c.commands) else np.concatenate([c.tcp_pose, [g["width"][-1]]])
        self.rows.append({"timestamp": np.float64(c.obs_timestamps[-1]), "camera0_rgb": cam["rgb"][-1],
                          "robot0_eef_pos": c.tcp_pose[:3], "robot0_eef_rot_axis_angle": c.tcp_pose[3:],
                          "robot0_gripper_width": np.array([g["width"][-1]]), "action": first,
                          "obs_to_action_latency": np.float64(c.obs_to_action_latency)})
        self.commands += [(float(t), a) for t, a in zip(c.action_timestamps, c.commands)]
        self._pull_states()

    def _pull_states(self) -> None:
        s = self.robot.get_states(100000)
        new = s["timestamp"] > self._last_t
        if new.any():
            self.robot_t.append(s["timestamp"][new])
            self.robot_pose.append(s["tcp_pose"][new])
            self._last_t = float(s["timestamp"][new][-1])

    def save(self, out_dir: str | Path, fps: float, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write ``episode.zarr.zip``, ``episode.mp4``, ``tcp_commanded_vs_reached.png``, ``timing.json``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        try:
            self._pull_states()
        except Exception:  # noqa: BLE001 - backend may already be closed
            pass
        stats: dict[str, Any] = dict(extra or {})
        if self.rows:
            data = {k: np.stack([r[k] for r in self.rows]) for k in self.rows[0]}
            data["robot0_gripper_width"] = data["robot0_gripper_width"].reshape(-1, 1)
            rb = ReplayBuffer.create()
            rb.add_episode({k: v for k, v in data.items() if k != "obs_to_action_latency"})
            rb.save(out / "episode.zarr.zip")
            with VideoWriter(out / "episode.mp4", data["camera0_rgb"].shape[2], data["camera0_rgb"].shape[1],
                             fps=fps) as vw:
                for f in data["camera0_rgb"]:
                    vw.write(f)
            stats["obs_to_action_latency"] = timing_stats(data["obs_to_action_latency"])
            cyc = np.diff(data["timestamp"])
            stats["inference_cycle_period"] = timing_stats(cyc)
        if self.robot_t:
            rt = np.concatenate(self.robot_t)
            stats["control_period"] = timing_stats(np.diff(rt))
            rp = np.concatenate(self.robot_pose)
            stats["tcp_displacement_m"] = float(np.linalg.norm(rp[-1, :3] - rp[0, :3]))  # first → last state
            self._plot(out / "tcp_commanded_vs_reached.png", rt, rp)
        (out / "timing.json").write_text(json.dumps(stats, indent=2))
        return stats

    def _plot(self, path: Path, rt: np.ndarray, rp: np.ndarray) -> None:
        import matplotlib  # lazy, start-up: matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

        fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        t0 = rt[0]
        ct = np.array([t for t, _ in self.commands])
        cp = np.array([a for _, a in self.commands]) if self.commands else np.zeros((0, 7))
        for i, (ax, name) in enumerate(zip(axes, "xyz")):
            ax.plot(rt - t0, rp[:, i], "-", lw=1.2, label="reached (robot state)")
            if len(ct):
                ax.plot(ct - t0, cp[:, i], ".", ms=4, label="commanded (due time)")
            ax.set_ylabel(f"TCP {name} [m]")
            ax.grid(alpha=0.3)
        axes[0].legend(loc="best", fontsize=8)
        axes[-1].set_xlabel("time [s]")
        fig.suptitle("Commanded vs reached TCP position (robot base frame)")
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
