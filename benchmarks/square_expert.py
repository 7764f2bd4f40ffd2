"""Success rate and speed of the scripted square expert (umi_aug.square.expert).

Run: ``python benchmarks/square_expert.py [--seeds 200] [--start-seed 0] [--workers 2] [--render-demos 3]``

Table 1: success over ``--seeds`` reset seeds (no rendering: the expert reads privileged state only, so images do
not change its actions), failures by final phase, episode length, and time per rollout without images.
Table 2: time per demo with the 224² (and 84²) fisheye wrist view rendered each step, for ``--render-demos``
seeds, in this process, and the ratio to the image-free rollout of the same seeds measured in the same process.
Timings are wall clock on whatever cores this process gets (project machines: 2 shared cores).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

_ENV = None


def _init() -> None:
    global _ENV
    from umi_aug.square.env import SquareEnv

    _ENV = SquareEnv(image_size=None)


def _run(seed: int) -> tuple[int, bool, int, float, str]:
    from umi_aug.square.episode import rollout_expert

    if _ENV is None:
        _init()
    ep = rollout_expert(_ENV, seed, render=False)
    return seed, ep.success, len(ep), ep.seconds, ep.info.get("final_phase", "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--start-seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--render-demos", type=int, default=3)
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seeds = list(range(args.start_seed, args.start_seed + args.seeds))
    t0 = time.perf_counter()
    if args.workers > 1:
        import multiprocessing as mp

        with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn"), initializer=_init) as pool:
            res = list(pool.map(_run, seeds, chunksize=4))
    else:
        res = [_run(s) for s in seeds]
    wall = time.perf_counter() - t0
    ok = [r for r in res if r[1]]
    fails = Counter(r[4] for r in res if not r[1])
    lens = [r[2] for r in ok]
    print(f"\n## Square expert over {len(seeds)} seeds ({args.start_seed}..{seeds[-1]}), {args.workers} workers")
    print("| metric | value |\n|---|---|")
    print(f"| success | {len(ok)}/{len(res)} = {100.0 * len(ok) / len(res):.1f} % |")
    print(f"| failures by final phase | {dict(fails) or '-'} |")
    print(f"| failed seeds | {[r[0] for r in res if not r[1]] or '-'} |")
    print(f"| steps (successful) median / min / max | {statistics.median(lens):.0f} / {min(lens)} / {max(lens)} |")
    print(f"| s per rollout, no images (mean, per process) | {statistics.mean(r[3] for r in res):.2f} |")
    print(f"| wall for all seeds | {wall:.0f} s |")

    if args.render_demos > 0:
        from umi_aug.square.env import SquareEnv
        from umi_aug.square.episode import rollout_expert

        print(f"\n## Time per demo with the fisheye wrist view (this process, {args.render_demos} seeds)")
        print("| image | s/demo | steps | ms/step | ratio to no-image rollout (same seeds) |\n|---|---|---|---|---|")
        rs = seeds[: args.render_demos]
        env0 = SquareEnv(image_size=None)
        base = [rollout_expert(env0, s, render=False) for s in rs]
        env0.close()
        t_base = sum(e.seconds for e in base)
        print(f"| none | {t_base / len(rs):.2f} | {sum(map(len, base)) / len(rs):.0f} | "
              f"{1000 * t_base / sum(map(len, base)):.1f} | 1.00 |")
        for size in (224, 84):
            env = SquareEnv(image_size=size)
            eps = [rollout_expert(env, s, render=True) for s in rs]
            env.close()
            t = sum(e.seconds for e in eps)
            print(f"| fisheye {size}² | {t / len(rs):.2f} | {sum(map(len, eps)) / len(rs):.0f} | "
                  f"{1000 * t / sum(map(len, eps)):.1f} | {t / t_base:.1f} |")


if __name__ == "__main__":
    main()
