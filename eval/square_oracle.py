"""The replay oracle of the train/eval contract (issue #29; eval/README.md): each seed's scripted-expert demo, its
own action chunks cut and re-anchored exactly as the network outputs them, replayed through eval_sim's policy
interface from the demo's start state — with the commanded-target labels the square task trains on, and, for the
contrast, the reached-pose labels used before.

    python eval/square_oracle.py                       # seeds 0..19, both label kinds
    python eval/square_oracle.py --seeds 0:100 --labels commanded --out oracle.json
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
    args = ap.parse_args(argv)
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


if __name__ == "__main__":
    sys.exit(main())
