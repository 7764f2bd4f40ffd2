"""Why does a square policy fail? Train/eval consistency and open-loop action error of a checkpoint on its demos.

Run: ``python benchmarks/square_policy_check.py --checkpoint CKPT --dataset square_demos/square_expert_fisheye84.zarr.zip
[--episodes 0 7 30] [--samples 3]``

For each listed demo episode (the demos of ``umi-aug square-demos`` start from seeded resets, seed = episode index
when every seed succeeded — ``report.json`` lists them): (1) the evaluation harness's observation at the demo's
start state — the env reset with that seed and eval's wrist camera — against the dataset's first row (image mean
absolute difference in grey levels, position / rotation-vector / width error); (2) the policy's action chunk
predicted from the dataset's own first observation (``--samples`` noise seeds) against the demo's next labels (the
commanded targets with ``task.action_key``, else the poses):
position error per target (mm), and how far the demo itself moves over the chunk. Large open-loop errors on the
policy's own training data mean an under-trained policy, not a harness fault.

With ``--along-frames``, for one or more checkpoints instead: the open-loop chunk error ALONG the listed demos, at
the listed frames (each frame's own observation, the episode's first pose as the ``wrt_start`` start pose): mean
position error (mm) and rotation error (degrees) of targets 1…n against the labels, averaged over the episodes —
where along the demo each policy has learned its data (issue #29: ``ours_n50`` is 58 mm / 26° off at the demos'
first frame, where ``none_n50`` is 16 mm / 4°):

    python benchmarks/square_policy_check.py --checkpoint A.ckpt B.ckpt --episodes 0 5 10 15 20 \
        --along-frames 0 8 16 24 32 48 64 96
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, nargs="+", help="one checkpoint (several with --along-frames)")
    ap.add_argument("--dataset", default="square_demos/square_expert_fisheye84.zarr.zip")
    ap.add_argument("--episodes", type=int, nargs="+", default=[0, 7, 30])
    ap.add_argument("--samples", type=int, default=3, help="noise seeds per chunk")
    ap.add_argument("--along-frames", type=int, nargs="+", default=None,
                    help="open-loop error along the demos at these frames, per checkpoint")
    args = ap.parse_args()
    if args.along_frames:
        along_the_demos(args.checkpoint, args.dataset, args.episodes, args.along_frames)
        return
    if len(args.checkpoint) != 1:
        ap.error("several checkpoints need --along-frames")
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    from umi_aug.data import ReplayBuffer
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.env import SquareEnv

    torch.set_num_threads(1)
    report = Path(args.dataset).with_name("report.json")
    seeds = json.loads(report.read_text())["seeds"] if report.is_file() else None
    pol = CheckpointEvalPolicy.from_checkpoint(args.checkpoint[0])
    n_exec = pol.n_exec
    env = SquareEnv(image_size=None)
    cam = WristFisheyeCamera(env.model, pol.image_size)
    t1 = Table(title="eval observation at the demo's start vs the training row")
    for c in ("episode", "seed", "image |Δ| mean", "image |Δ| max", "pos err mm", "rotvec err", "width err mm"):
        t1.add_column(c, justify="right")
    t2 = Table(title=f"open-loop chunk from the dataset's first observation: position error per target (mm), "
                     f"targets 0…{n_exec}")
    t2.add_column("episode", justify="right")
    t2.add_column("noise seed", justify="right")
    t2.add_column("error per target (mm)")
    t2.add_column("demo moves (mm)", justify="right")
    try:
        with ReplayBuffer.open(args.dataset) as buf:
            for ep in args.episodes:
                seed = seeds[ep] if seeds else ep
                sl = buf.get_episode_slice(ep)
                obs = env.reset(seed=seed)
                img = cam.render(env.data, env.wrist_pose()).astype(np.int16)
                row = {k: np.asarray(buf[k][sl.start], np.float64) for k in
                       ("robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width")}
                d_img = buf["camera0_rgb"][sl.start]
                diff = np.abs(img - d_img.astype(np.int16))
                t1.add_row(str(ep), str(seed), f"{diff.mean():.2f}", str(int(diff.max())),
                           f"{1000 * np.linalg.norm(obs['robot0_eef_pos'] - row['robot0_eef_pos']):.3f}",
                           f"{np.linalg.norm(obs['robot0_eef_rot_axis_angle'] - row['robot0_eef_rot_axis_angle']):.4f}",
                           f"{1000 * abs(np.ravel(obs['robot0_gripper_width'])[0] - row['robot0_gripper_width'][0]):.3f}")
                o = {k: np.stack([v, v]) for k, v in row.items()} | {"camera0_rgb": np.stack([d_img, d_img])}
                key = pol.policy.task.action_key  # the labels: commanded targets (square) or the poses (UMI)
                lab = buf[key][sl.start:sl.start + n_exec + 1, :3] if key else \
                    buf["robot0_eef_pos"][sl.start:sl.start + n_exec + 1]
                demo = np.asarray(lab, np.float64)
                for s in range(args.samples):
                    chunk = pol.policy.predict_action(o, n_steps=n_exec + 1,
                                                      generator=torch.Generator().manual_seed(s))["action"]
                    err = 1000 * np.linalg.norm(chunk[: len(demo), :3] - demo, axis=1)
                    t2.add_row(str(ep), str(s), " ".join(f"{e:.0f}" for e in err),
                               f"{1000 * np.linalg.norm(demo[-1] - demo[0]):.0f}")
    finally:
        cam.close()
        env.close()
    console = Console(width=160)
    console.print(t1)
    console.print(t2)


def along_the_demos(checkpoints: list[str], dataset: str, episodes: list[int], frames: list[int]) -> None:
    """Print, per checkpoint and frame, the open-loop chunk error against the demos' labels (module docstring)."""
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    from umi_aug.data import ReplayBuffer
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.geometry import pos_rotvec_to_pose, so3_log

    torch.set_num_threads(1)
    table = Table(title=f"open-loop chunk error along demos {episodes} (targets 1…n; mean over the episodes that "
                        "are long enough): position mm / rotation °")
    table.add_column("frame", justify="right")
    cols = []
    with ReplayBuffer.open(dataset) as buf:
        for ckpt in checkpoints:
            pol = CheckpointEvalPolicy.from_checkpoint(ckpt)
            P, n = pol.policy, pol.n_exec
            key = P.task.action_key
            err: dict[int, list[tuple[float, float]]] = {f: [] for f in frames}
            for ep in episodes:
                sl = buf.get_episode_slice(ep)
                pos = np.asarray(buf["robot0_eef_pos"][sl], np.float64)
                rot = np.asarray(buf["robot0_eef_rot_axis_angle"][sl], np.float64)
                width = np.asarray(buf["robot0_gripper_width"][sl], np.float64)
                lab = np.asarray(buf[key][sl], np.float64) if key else np.concatenate([pos, rot, width], 1)
                fs = [f for f in frames if f + n < len(pos)]
                if not fs:
                    continue
                rows = np.array([[max(f - 1, 0), f] for f in fs])
                obs = {"robot0_eef_pos": pos[rows], "robot0_eef_rot_axis_angle": rot[rows],
                       "robot0_gripper_width": width[rows],
                       "camera0_rgb": np.asarray(buf["camera0_rgb"][sl])[np.array(fs)][:, None]}
                P.reset(np.concatenate([pos[0], rot[0]]))
                chunk = P.predict_action(obs, n_steps=n + 1, generator=torch.Generator().manual_seed(0))["action"]
                for j, f in enumerate(fs):
                    c, want = chunk[j, 1:n + 1], lab[f + 1:f + n + 1]
                    dp = 1000.0 * np.linalg.norm(c[:, :3] - want[:, :3], axis=1).mean()
                    Rc, Rw = pos_rotvec_to_pose(c[:, :6])[:, :3, :3], pos_rotvec_to_pose(want[:, :6])[:, :3, :3]
                    dr = np.degrees(np.mean([np.linalg.norm(so3_log(a.T @ b)) for a, b in zip(Rc, Rw)]))
                    err[f].append((dp, dr))
            cols.append(err)
            names = [Path(c).parent.parent.name for c in checkpoints]  # <run>/checkpoints/<file>
            mine = names[len(cols) - 1]
            label = mine if names.count(mine) == 1 else "/".join(Path(ckpt).parts[-5:-2])
            table.add_column(label or ckpt, justify="right")
    for f in frames:
        table.add_row(str(f), *(f"{np.mean([e[0] for e in c[f]]):.1f} / {np.mean([e[1] for e in c[f]]):.1f}"
                                if c[f] else "-" for c in cols))
    Console(width=160).print(table)


if __name__ == "__main__":
    main()
