"""The replay oracle of the train/eval contract (issue #29; eval/README.md): each seed's scripted-expert demo, its
own action chunks cut and re-anchored exactly as the network outputs them, replayed through eval_sim's policy
interface from the demo's start state — with the commanded-target labels the square task trains on, and, for the
contrast, the reached-pose labels used before.

    python eval/square_oracle.py                       # seeds 0..19, both label kinds
    python eval/square_oracle.py --seeds 0:100 --labels commanded --out oracle.json

With ``--export``, the episodes of an augmented square export (the study's ``data/ours_n50.zarr.zip``, ...) instead:
each one's own chunks from its own start (the source demo's objects, the arm placed by IK at the episode's first
pose), once per action representation (``task.action_pose_repr``: relative to the current pose, or absolute):

    python eval/square_oracle.py --export square_study/cpu_regression/data/ours_n50.zarr.zip \
        --episodes 50:1050:59 --action-pose-repr relative,abs
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0:20", help="reset seeds 'a:b' (default 0:20)")
    ap.add_argument("--labels", default="commanded,reached", help="comma-separated: commanded, reached")
    ap.add_argument("--out", default=None, help="write the per-seed records as JSON here")
    ap.add_argument("--export", default=None, help="an augmented square export: replay its episodes instead")
    ap.add_argument("--demos-hdf5", default="square_demos/square_expert_fisheye84.hdf5",
                    help="the export's source demos (robomimic hdf5 of umi-aug square-demos)")
    ap.add_argument("--episodes", default=None, help="export episodes 'a:b' or 'a:b:step' (default: all)")
    ap.add_argument("--action-pose-repr", default="relative,abs", help="comma-separated: relative, abs")
    args = ap.parse_args(argv)
    if args.export:
        return _export_main(args)
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.runtime import configure_threads
    from umi_aug.square.oracle import LABELS, run_oracle

    try:
        a, b = (int(x) for x in args.seeds.split(":"))
        seeds = list(range(a, b))
    except ValueError:
        print(f"error: --seeds {args.seeds!r}: expected 'a:b' with integers a < b", file=sys.stderr)
        return 2
    kinds = [k.strip() for k in args.labels.split(",") if k.strip()]
    bad = [k for k in kinds if k not in LABELS]
    if bad or not seeds or not kinds:
        print(f"error: --labels {args.labels!r} / --seeds {args.seeds!r}: labels must be among {list(LABELS)} and "
              "the seed range non-empty", file=sys.stderr)
        return 2
    configure_threads(1)
    out = {k: run_oracle(seeds, k, progress=True) for k in kinds}
    print(f"\nreplay oracle over {len(seeds)} seeds ({seeds[0]}..{seeds[-1]}): the demo's own chunks through "
          f"eval_sim's policy interface")
    head = f"{'labels':<11}{'success':>10}{'pre-grasp':>11}{'steps to success / demo steps (median)':>40}"
    print(head + "\n" + "-" * len(head))
    for k, recs in out.items():
        ok = [r for r in recs if r["success"]]
        ratio = sorted(r["steps_to_success"] / r["demo_steps"] for r in ok)
        med = f"{ratio[len(ratio) // 2]:.2f}" if ratio else "-"
        print(f"{k:<11}{len(ok):>6}/{len(recs):<3}{sum(r['pregrasp_reached'] for r in recs):>7}/{len(recs):<3}"
              f"{med:>40}")
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(out, indent=1))
    return 0


def _export_main(args: argparse.Namespace) -> int:
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.runtime import configure_threads
    from umi_aug.square.oracle import oracle_config, run_export_oracle

    reprs = [r.strip() for r in args.action_pose_repr.split(",") if r.strip()]
    if not reprs or any(r not in ("relative", "abs") for r in reprs):
        print(f"error: --action-pose-repr {args.action_pose_repr!r}: expected 'relative', 'abs' or both",
              file=sys.stderr)
        return 2
    episodes = None
    if args.episodes:
        try:
            episodes = list(range(*(int(x) for x in args.episodes.split(":"))))
        except (ValueError, TypeError):
            episodes = []
        if not episodes:
            print(f"error: --episodes {args.episodes!r}: expected a non-empty range 'a:b' or 'a:b:step'",
                  file=sys.stderr)
            return 2
    from umi_aug.errors import UmiAugError

    configure_threads(1)
    try:
        out = {r: run_export_oracle(args.export, args.demos_hdf5, episodes,
                                    oracle_config("commanded", action_pose_repr=r), progress=True) for r in reprs}
    except (UmiAugError, OSError) as exc:  # a missing / foreign file, an episode out of range or reach
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"\nexport oracle: {args.export}, each episode's own chunks from its own start (time-indexed)")
    head = f"{'action_pose_repr':<18}{'episodes':<10}{'success':>10}{'pre-grasp':>11}{'lifted':>9}"
    print(head + "\n" + "-" * len(head))
    for r, recs in out.items():
        for kind, rows in (("originals", [x for x in recs if x["aug_id"] < 0]),
                           ("augmented", [x for x in recs if x["aug_id"] >= 0])):
            if rows:
                n = len(rows)
                print(f"{r:<18}{kind:<10}{sum(x['success'] for x in rows):>6}/{n:<3}"
                      f"{sum(x['pregrasp_reached'] for x in rows):>7}/{n:<3}{sum(x['lifted'] for x in rows):>5}/{n:<3}")
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
