"""The on-the-fly Dataset on a bigger machine (issue #17 part 2: "samples/s that grows with workers"): the
steady-state scaling curve of ``AugmentedUmiDataset`` with spawn workers, then the plain ``UmiPolicyDataset`` with
FORKED workers after CUDA is initialised in the main process (as ``train/train.py device=cuda`` does; the 10x stall
of ``docs/gpu_training_check.md``).

A lent GPU machine has 16 cores but no ffmpeg, which reading a session's videos needs; so the scene's
``SessionAssets`` are prepared here and pickled, and the run there loads them:

    python benchmarks/dataset_bigmachine.py prepare --demo /tmp/umi_aug_bench_dataset --to .dd
    # .dd now holds demo/ (the session's zarr, the cached stages; no videos) and assets.pkl: carry it over, then
    python benchmarks/dataset_bigmachine.py run --from .dd --workers 0,2,4,8,15 --samples 1440

Same setting as ``benchmarks/dataset.py`` (224², obs horizon 2, batch 8, ``aug=freespace``, ratio 0.9).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
import dataset as B  # noqa: E402  (benchmarks/dataset.py)

#: what the run needs of an ``umi-aug demo`` folder (no videos, no COLMAP database, no 3DGS checkpoint)
_KEEP = ["session/dataset.zarr.zip", "session/session.json", "session/calibration", "work/contact",
         "work/gripper_mask", "work/splat/scene.ply", "work/splat/manifest.json", "work/splat/metrics.json",
         "work/reconstruct/scene_cloud.ply", "work/reconstruct/scene_sdf.npz", "work/reconstruct/manifest.json",
         "work/reconstruct/recon_report.json"]


def prepare(demo: Path, to: Path) -> None:
    """Copy the parts of ``demo`` the run reads to ``to/demo`` and pickle its prepared SessionAssets (relative
    paths: run from the repository root)."""
    B._demo(demo)
    dst = to / "demo"
    for rel in _KEEP:
        src, out = demo / rel, dst / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, out)
    for v in (demo / "session" / "demos").glob("*/*"):  # load_session probes the videos: here, with ffmpeg
        (dst / v.relative_to(demo)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(v, dst / v.relative_to(demo))
    assets = B._assets(dst)
    shutil.rmtree(dst / "session" / "demos")
    (to / "assets.pkl").write_bytes(pickle.dumps(assets))
    print(f"prepared {to}: {sum(f.stat().st_size for f in to.rglob('*') if f.is_file()) / 2**20:.0f} MiB")


def plain_fork(demo: Path, workers: list[int], epochs: int) -> dict:
    """Epoch rates of the plain dataset with forked workers, new loader per epoch and persistent, after CUDA init."""
    import torch

    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.workspace import make_loader

    if torch.cuda.is_available():  # a CUDA context and a backward pass in the parent before any fork
        net = torch.nn.Linear(4096, 4096).cuda()
        net(torch.randn(64, 4096, device="cuda")).sum().backward()
        torch.cuda.synchronize()
    plain = UmiPolicyDataset(demo / "session" / "dataset.zarr.zip", TaskConfig(image_size=224, val_ratio=0.0),
                             "train")
    print(f"plain dataset: {len(plain)} samples; CUDA initialised: {torch.cuda.is_available()}", flush=True)
    out = {}
    for w in workers:
        for persistent in ([False, True] if w else [False]):
            rows, loader = [], None
            for e in range(epochs):
                t0 = time.perf_counter()
                if loader is None or not persistent:
                    loader = make_loader(plain, 64, True, seed=0, epoch=e, num_workers=w, persistent=persistent,
                                         context="fork" if w else None)
                else:
                    loader.sampler.set_epoch(e)
                first, n = None, 0
                for b in loader:
                    first = first or time.perf_counter() - t0
                    n += len(b["action"])
                rows.append({"wall_s": time.perf_counter() - t0, "first_batch_s": first, "samples": n})
            del loader
            name = f"{w}w_{'persistent' if persistent else 'per_epoch'}"
            out[name] = rows
            print(f"plain, {w} fork workers, {'persistent' if persistent else 'new loader per epoch'}: " + "; ".join(
                f"{r['samples'] / r['wall_s']:.0f}/s (first batch {r['first_batch_s']:.2f} s)" for r in rows),
                flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--demo", default="/tmp/umi_aug_bench_dataset", help="an `umi-aug demo` out folder")
    p.add_argument("--to", default=".dd")
    r = sub.add_parser("run")
    r.add_argument("--from", dest="src", default=".dd")
    r.add_argument("--workers", default="0,2,4,8,15")
    r.add_argument("--samples", type=int, default=1440)
    r.add_argument("--plain-workers", default="0,8,15")
    r.add_argument("--plain-epochs", type=int, default=4)
    r.add_argument("--out", default=os.environ.get("OUT", "."), help="folder for dataset_bigmachine.json")
    args = ap.parse_args()
    if args.cmd == "prepare":
        prepare(Path(args.demo), Path(args.to))
        return
    import numba
    import torch

    torch.set_num_threads(1)
    t_all = time.perf_counter()
    print(f"{os.cpu_count()} cores; torch {torch.__version__}; numba {numba.__version__}; cuda "
          f"{torch.cuda.is_available()}; load {open('/proc/loadavg').read().split()[:3]}", flush=True)
    src = Path(args.src)
    assets = pickle.loads((src / "assets.pkl").read_bytes())
    workers = [int(w) for w in args.workers.split(",")]
    res: dict = {"cores": os.cpu_count(), "args": vars(args)}
    sc = B.scaling(src / "demo", assets, workers, args.samples, 8, "spawn", 1)
    res["scaling_spawn"] = sc
    B._print_scaling(sc, workers, argparse.Namespace(scaling_samples=args.samples, context="spawn"))
    res["plain_fork"] = plain_fork(src / "demo", [int(w) for w in args.plain_workers.split(",")], args.plain_epochs)
    Path(args.out, "dataset_bigmachine.json").write_text(json.dumps(res, indent=1))
    print(f"total {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
