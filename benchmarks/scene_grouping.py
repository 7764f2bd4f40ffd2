"""Grouping a plain dataset's episodes by place (``--scene-group auto``) on synthetic places with ground truth.

Run: ``python benchmarks/scene_grouping.py [--sessions DIR DIR ...] [--work DIR]``

Each synthetic session (``umi-aug make-session --seed K --demos 2``; made in ``<work>`` when ``--sessions`` is not
given) is one place: its own layout and textures, its poses in its own tag frame, which looks like every other
session's (the tag lies on the table beside the objects). The sessions' episodes are merged into one plain dataset,
once session by session (as UMI stores them) and once interleaved, and grouped by
:func:`umi_aug.augment.scene_grouping.group_by_place` as ``umi-aug augment <dataset> --scene-group auto`` does.
Printed: every comparison's matches and epipolar inliers, the groups against the truth, and seconds per episode.
(The synthetic demos hold the camera exactly still for their first frames, which the dataset check rejects as lost
tracking: the TCP positions get 20 µm of noise, ``far_views.jittered_dataset``.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", nargs="+", default=None, help="synthetic session folders, one per place")
    ap.add_argument("--work", default="/tmp/umi_aug_scene_grouping")
    args = ap.parse_args()

    from far_views import jittered_dataset

    from umi_aug.augment.dataset_source import DatasetInput, _policy_intrinsics, check_dataset
    from umi_aug.augment.scene_grouping import group_by_place
    from umi_aug.data import ReplayBuffer
    from umi_aug.geometry.umi import camera_poses_from_tcp_poses
    from umi_aug.recon.pipeline import first_close_index
    from umi_aug.recon.sfm import feature_mask
    from umi_aug.sim.session import make_session

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    sessions = [Path(s) for s in args.sessions] if args.sessions else [work / f"session_seed{k}" for k in (0, 1)]
    for k, s in enumerate(sessions):
        if not (s / "dataset.zarr.zip").exists():
            print(f"# making the synthetic session {s}")
            make_session(s, seed=k, n_demos=2, scan_frames=2)
    places = [jittered_dataset(s, work / f"place{k}.zarr.zip") for k, s in enumerate(sessions)]
    n_per = [ReplayBuffer.open(p).n_episodes for p in places]
    orders = {"session by session": [(k, e) for k in range(len(places)) for e in range(n_per[k])],
              "interleaved": [(k, e) for e in range(max(n_per)) for k in range(len(places)) if e < n_per[k]]}
    inp = DatasetInput()
    intr = _policy_intrinsics(224)
    for name, order in orders.items():
        path = work / f"merged_{name.split()[0]}.zarr.zip"
        if not path.exists():
            dst = ReplayBuffer.create()
            for k, e in order:
                with ReplayBuffer.open(places[k]) as src:
                    dst.add_episode(src.get_episode(e))
            dst.save(path)
        chk = check_dataset(path, 224, inp)
        T = {}
        for e, Ttcp in chk.T_world_tcp.items():
            c = first_close_index(chk.gripper_width[e])
            T[e] = camera_poses_from_tcp_poses(Ttcp, inp.T_cam_tcp)[: None if c is None else c]
        with ReplayBuffer.open(path) as buf:
            start = {e: buf.get_episode_slice(e).start for e in T}
            frames = buf["camera0_rgb"]
            t0 = time.perf_counter()
            groups, evidence = group_by_place(sorted(T), T, lambda e, f: np.asarray(frames[start[e] + int(f)]), intr,
                                              feature_mask(intr))
            secs = time.perf_counter() - t0
        truth = {}
        for i, (k, _) in enumerate(order):
            truth.setdefault(k, []).append(i)
        ok = sorted(groups.values()) == sorted(truth.values())
        print(f"\n## {name}: episodes' places {[k for k, _ in order]}")
        print("| episodes | same place (truth) | decided | SIFT matches per frame pair | epipolar inliers | median "
              "inlier fraction |\n|---|---|---|---|---|---|")
        for ev in evidence:
            same = order[ev.episode_a][0] == order[ev.episode_b][0]
            print(f"| {ev.episode_a}–{ev.episode_b} | {same} | {ev.same_place} | {list(ev.matches)} | "
                  f"{list(ev.inliers)} | {ev.median_inlier_fraction:.2f} |")
        print(f"groups {groups} — {'right' if ok else 'WRONG'}; {secs:.2f} s for {len(T)} episodes "
              f"({secs / len(T):.2f} s per episode, frames decoded and SIFT included)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
