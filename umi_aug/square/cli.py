"""``umi-aug square-demos | square-convert | square-init-configs`` (wired into umi_aug/cli.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_square_parsers", "cmd_square_demos", "cmd_square_convert", "cmd_square_init_configs"]


def add_square_parsers(sub: "argparse._SubParsersAction") -> None:
    """Add the three square sub-commands (imports neither robosuite nor robomimic)."""
    p = sub.add_parser("square-demos", help="scripted-expert square demos -> robomimic hdf5 + UMI zarr (fisheye)")
    p.add_argument("--n", type=int, required=True, help="number of successful demos")
    p.add_argument("--out", required=True, help="output folder (resumable: rerun to continue)")
    p.add_argument("--image-size", type=int, default=224, choices=(224, 84))
    p.add_argument("--start-seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--horizon", type=int, default=400)
    p.set_defaults(func=cmd_square_demos)

    p = sub.add_parser("square-convert", help="robomimic square hdf5 -> fisheye hdf5 + UMI zarr (re-rendered)")
    p.add_argument("hdf5", help="robomimic square dataset (ph/mh, robosuite 1.4 states)")
    p.add_argument("--out", required=True, help="output folder (resumable)")
    p.add_argument("--image-size", type=int, default=224, choices=(224, 84))
    p.add_argument("--max-demos", type=int, default=None)
    p.set_defaults(func=cmd_square_convert)

    p = sub.add_parser("square-init-configs", help="seeded evaluation start configurations (cone + IK)")
    p.add_argument("--n", type=int, default=1000)
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--hdf5", default=None, help="dataset whose demos' initial states are the sources "
                                                "(default: seeded resets 0..--n-sources-1)")
    p.add_argument("--n-sources", type=int, default=200)
    p.add_argument("--first-seed", type=int, default=0, help="seeded resets --first-seed.. are the sources")
    p.add_argument("--no-cone", action="store_true",
                   help="write the seeded resets themselves (the demos' own start distribution; --n of them, "
                        "seeds --first-seed..; use seeds no demo used) instead of cone samples around them")
    p.add_argument("--theta-deg", type=float, default=50.0)
    p.add_argument("--radius", type=float, default=0.15, help="metres")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_square_init_configs)


def cmd_square_demos(args: argparse.Namespace) -> int:
    from umi_aug.square.generate import DemoConfig, generate_demos

    rep = generate_demos(args.out, DemoConfig(n=args.n, image_size=args.image_size, start_seed=args.start_seed,
                                              workers=args.workers, horizon=args.horizon))
    print(f"{rep['successes']} demos from {rep['tried']} seeds (expert success {100 * rep['success_rate']:.1f} %)")
    print(json.dumps(rep["paths"]))
    return 0


def cmd_square_convert(args: argparse.Namespace) -> int:
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.square.convert import convert_robomimic_hdf5

    paths = convert_robomimic_hdf5(args.hdf5, args.out, args.image_size, args.max_demos)
    # the same report.json as square-demos, so `umi-aug augment <out>` takes the folder as square demos
    atomic_write_text(Path(args.out) / "report.json", json.dumps({"source": str(args.hdf5), "paths": paths,
                                                                  "image_size": args.image_size}, indent=2) + "\n")
    print(json.dumps(paths))
    return 0


def cmd_square_init_configs(args: argparse.Namespace) -> int:
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.init_configs import (InitConfigSpec, reset_init_configs, sample_init_configs,
                                                 source_states_from_hdf5, source_states_from_seeds,
                                                 write_init_configs)

    if args.no_cone:
        if args.hdf5:
            from umi_aug.errors import SimError

            raise SimError("--no-cone takes seeded resets (seeds --first-seed..); drop --hdf5")
        env = SquareEnv(image_size=None)
        seeds = list(range(args.first_seed, args.first_seed + args.n))
        configs = reset_init_configs(env, source_states_from_seeds(env, seeds), seeds)
        path = write_init_configs(args.out, configs, env.env_meta)
        print(json.dumps(configs["report"]))
        print(path)
        return 0
    if args.hdf5:
        sources, env_args = source_states_from_hdf5(args.hdf5)
        env = SquareEnv(env_meta=json.loads(env_args), image_size=None)
    else:
        env = SquareEnv(image_size=None)
        sources = source_states_from_seeds(env, list(range(args.first_seed, args.first_seed + args.n_sources)))
    spec = InitConfigSpec(n=args.n, theta_deg=args.theta_deg, radius=args.radius, seed=args.seed)
    configs = sample_init_configs(env, sources, spec)
    path = write_init_configs(args.out, configs, env.env_meta)
    print(json.dumps(configs["report"]))
    print(path)
    return 0
