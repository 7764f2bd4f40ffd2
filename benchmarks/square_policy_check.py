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
position error (mm), rotation error (degrees) and its yaw part (the turn of the gripper's x axis about the world's
vertical, degrees) of targets 1…n against the labels, averaged over the episodes — where along the demo each policy
has learned its data (issue #29: ``ours_n50`` is 58 mm / 26° off at the demos' first frame, where ``none_n50`` is
16 mm / 4°; the rotation error is the yaw the expert turns to meet the nut, which ``ours_n50`` leaves out):

    python benchmarks/square_policy_check.py --checkpoint A.ckpt B.ckpt --episodes 0 5 10 15 20 \
        --along-frames 0 8 16 24 32 48 64 96

With ``--swap-inputs FRAME ...`` (``--augmented`` for augmented episodes of an export): each checkpoint's error at
those frames of 40 random episodes, and how far its chunk moves with another sample's image or pose in place of
its own — whether it reads the image (issue #29: ``ours_n50`` fits its approach frames, 8 mm, and reads the image
there, 53 mm, but not its first frames, 37 mm):

    python benchmarks/square_policy_check.py --checkpoint A.ckpt B.ckpt --dataset .../ours_n50.zarr.zip \
        --augmented --swap-inputs -1 0 3
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
    ap.add_argument("--swap-inputs", type=int, nargs="+", default=None, metavar="FRAME",
                    help="how much each checkpoint's chunk follows its image and its pose at these frames of 40 "
                         "random episodes (-1: a random frame 0-29) of --dataset (--augmented: augmented ones)")
    ap.add_argument("--augmented", action="store_true", help="--swap-inputs on augmented episodes (meta aug_id>=0)")
    args = ap.parse_args()
    if args.along_frames:
        along_the_demos(args.checkpoint, args.dataset, args.episodes, args.along_frames)
        return
    if args.swap_inputs:
        swap_inputs(args.checkpoint, args.dataset, args.swap_inputs, args.augmented)
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


def swap_inputs(checkpoints: list[str], dataset: str, frames: list[int], augmented: bool, n_episodes: int = 40
                ) -> None:
    """Print, per checkpoint and frame, the open-loop error of its chunk (targets 1…n, mean position mm) against the
    labels at that frame of ``n_episodes`` random episodes, and how far its chunk moves when the image — or the pose
    (the chunk taken relative to the pose it was given) — is another of those samples' (a cyclic shift): a policy
    that ignores an input does not move. The labels' own pose-relative difference between the pairs is the scale."""
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    from umi_aug.data import ReplayBuffer
    from umi_aug.eval.policies import CheckpointEvalPolicy

    torch.set_num_threads(1)
    table = Table(title=f"chunk vs inputs on {n_episodes} {'augmented' if augmented else 'original'} episodes of "
                        f"{dataset}: mean position mm over targets 1…n")
    for col in ("checkpoint", "frame", "error vs labels", "image swapped: moves", "pose swapped: moves",
                "labels differ"):
        table.add_column(col, justify="right")
    with ReplayBuffer.open(dataset) as buf:
        ends = np.asarray(buf.episode_ends)
        starts = np.concatenate([[0], ends[:-1]])
        aug_id = np.asarray(buf.meta["aug_id"][:]) if "aug_id" in buf.meta else np.full(len(ends), -1)
        pos = np.asarray(buf["robot0_eef_pos"][:], np.float64)
        rot = np.asarray(buf["robot0_eef_rot_axis_angle"][:], np.float64)
        width = np.asarray(buf["robot0_gripper_width"][:], np.float64)
        for ckpt in checkpoints:
            pol = CheckpointEvalPolicy.from_checkpoint(ckpt)
            P, n = pol.policy, pol.n_exec
            key = P.task.action_key
            lab_all = np.asarray(buf[key][:], np.float64) if key else np.concatenate([pos, rot, width], 1)
            for frame in frames:
                rng = np.random.default_rng(0)
                pool = np.flatnonzero(aug_id >= 0) if augmented else np.flatnonzero(aug_id < 0)
                eps = rng.choice(pool, size=min(n_episodes, len(pool)), replace=False)
                rows = [(int(starts[e]), frame if frame >= 0 else int(rng.integers(0, min(30, ends[e] - starts[e]
                                                                                         - n - 1)))) for e in eps]
                img = np.stack([np.asarray(buf["camera0_rgb"][s + f]) for s, f in rows])
                cur = np.array([pos[s + f] for s, f in rows])
                lab = np.array([lab_all[s + f + 1:s + f + n + 1, :3] for s, f in rows])

                def run(image_of: np.ndarray, pose_of: np.ndarray) -> np.ndarray:
                    out = []
                    for j in range(len(rows)):
                        s2, f2 = rows[pose_of[j]]
                        idx = np.array([s2 + max(f2 - 1, 0), s2 + f2])
                        obs = {"robot0_eef_pos": pos[idx][None], "robot0_eef_rot_axis_angle": rot[idx][None],
                               "robot0_gripper_width": width[idx][None], "camera0_rgb": img[image_of[j]][None, None]}
                        P.reset(np.concatenate([pos[s2], rot[s2]]))
                        out.append(P.predict_action(obs, n_steps=n + 1, generator=torch.Generator().manual_seed(0)
                                                    )["action"][0, 1:n + 1, :3])
                    return np.array(out)

                same, shift = np.arange(len(rows)), np.roll(np.arange(len(rows)), 1)
                base = run(same, same)
                mm = (lambda a, b: 1000.0 * np.linalg.norm(a - b, axis=2).mean())  # noqa: E731
                table.add_row(Path(ckpt).parent.parent.name, str(frame) if frame >= 0 else "0-29",
                              f"{mm(base, lab):.1f}", f"{mm(run(shift, same), base):.1f}",
                              f"{mm(run(same, shift) - cur[shift][:, None], base - cur[:, None]):.1f}",
                              f"{mm(lab[shift] - cur[shift][:, None], lab - cur[:, None]):.1f}")
    Console(width=160).print(table)


def _yaw_between(Ra, Rb):
    """[N] signed angle (rad) from the gripper x axis of ``Ra`` [N, 3, 3] to that of ``Rb``, both projected on the
    world's horizontal plane (the yaw the square expert turns to meet the nut)."""
    import numpy as np

    xa, xb = Ra[:, :2, 0], Rb[:, :2, 0]
    return np.arctan2(xa[:, 0] * xb[:, 1] - xa[:, 1] * xb[:, 0], (xa * xb).sum(axis=1))


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
                        "are long enough): position mm / rotation ° (of which yaw about the vertical °)")
    table.add_column("frame", justify="right")
    cols = []
    with ReplayBuffer.open(dataset) as buf:
        for ckpt in checkpoints:
            pol = CheckpointEvalPolicy.from_checkpoint(ckpt)
            P, n = pol.policy, pol.n_exec
            key = P.task.action_key
            err: dict[int, list[tuple[float, float, float]]] = {f: [] for f in frames}
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
                    err[f].append((dp, dr, np.degrees(np.abs(_yaw_between(Rc, Rw)).mean())))
            cols.append(err)
            names = [Path(c).parent.parent.name for c in checkpoints]  # <run>/checkpoints/<file>
            mine = names[len(cols) - 1]
            label = mine if names.count(mine) == 1 else "/".join(Path(ckpt).parts[-5:-2])
            table.add_column(label or ckpt, justify="right")
    for f in frames:
        table.add_row(str(f), *(f"{np.mean([e[0] for e in c[f]]):.1f} / {np.mean([e[1] for e in c[f]]):.1f} "
                                f"({np.mean([e[2] for e in c[f]]):.1f})" if c[f] else "-" for c in cols))
    Console(width=160).print(table)


if __name__ == "__main__":
    main()
