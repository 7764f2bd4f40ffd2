"""Expert demo generation: N successful scripted demos → robomimic hdf5 + UMI zarr; parallel and resumable.

Each seed's rollout is stored as a shard in ``<out>/shards/`` (``seed_<seed>.npz`` when successful,
``seed_<seed>.failed.json`` otherwise) as soon as it finishes, so an interrupted run resumes where it stopped.
Seeds are tried in increasing order from ``start_seed`` in waves; the dataset is made of the first ``n``
successful seeds, so the result depends only on (``n``, ``start_seed``, ``image_size``, expert), not on the
number of workers. Worker processes are spawned (never forked: GL contexts do not survive a fork).
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator

from umi_aug.errors import SimError
from umi_aug.io_utils import atomic_write_text

__all__ = ["DemoConfig", "generate_demos", "run_seed", "shard_paths"]

log = logging.getLogger(__name__)

_ENV = None  # per-process SquareEnv (worker initializer)


@dataclass(frozen=True)
class DemoConfig:
    """Settings of :func:`generate_demos`.

    Attributes:
        n: number of successful demos wanted.
        image_size: fisheye image size (224 or 84).
        start_seed: first reset seed.
        workers: processes (1 = in this process).
        horizon: steps per episode at most.
        max_seeds: give up after this many seeds (default 2·n + 20).
        write_hdf5, write_zarr: which datasets to write at the end.
    """

    n: int
    image_size: int = 224
    start_seed: int = 0
    workers: int = 2
    horizon: int = 400
    max_seeds: int | None = None
    write_hdf5: bool = True
    write_zarr: bool = True


def shard_paths(out_dir: str | os.PathLike, seed: int) -> tuple[Path, Path]:
    """``(success shard .npz, failure marker .json)`` of ``seed`` in ``out_dir/shards``."""
    d = Path(out_dir) / "shards"
    return d / f"seed_{seed:07d}.npz", d / f"seed_{seed:07d}.failed.json"


def _init_worker(image_size: int) -> None:
    global _ENV
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from umi_aug.square.env import SquareEnv  # lazy, start-up: cv2

    _ENV = SquareEnv(image_size=image_size)


def run_seed(out_dir: str, seed: int, horizon: int, image_size: int) -> dict[str, Any]:
    """Roll out the expert for ``seed`` and store its shard (in the worker's env). Returns a summary."""
    # lazy, start-up: cv2, zarr
    from umi_aug.square.episode import rollout_expert
    from umi_aug.square.writers import save_episode

    if _ENV is None:
        _init_worker(image_size)
    ep = rollout_expert(_ENV, seed, horizon=horizon, render=True)
    ok_path, fail_path = shard_paths(out_dir, seed)
    summary = {"seed": seed, "success": ep.success, "steps": len(ep), "seconds": ep.seconds}
    if ep.success:
        save_episode(ok_path, ep)
    else:
        atomic_write_text(fail_path, json.dumps(summary | {"final_phase": ep.info.get("final_phase")}))
    return summary


def _existing(out_dir: Path, seed: int) -> dict[str, Any] | None:
    ok, fail = shard_paths(out_dir, seed)
    if ok.exists():
        return {"seed": seed, "success": True, "steps": None, "seconds": None, "resumed": True}
    if fail.exists():
        return json.loads(fail.read_text()) | {"resumed": True}
    return None


def _tick(bar, success: bool) -> None:
    if success and bar.n < bar.total:
        bar.update(1)


def _run_wave(seeds: list[int], cfg: DemoConfig, out_dir: Path, pool, bar) -> list[dict[str, Any]]:
    results = []
    if pool is None:
        for s in seeds:
            results.append(run_seed(str(out_dir), s, cfg.horizon, cfg.image_size))
            _tick(bar, results[-1]["success"])
        return results
    futures = [pool.submit(run_seed, str(out_dir), s, cfg.horizon, cfg.image_size) for s in seeds]
    for fut in as_completed(futures):
        results.append(fut.result())
        _tick(bar, results[-1]["success"])
    return results


def generate_demos(out_dir: str | os.PathLike, cfg: DemoConfig) -> dict[str, Any]:
    """Generate ``cfg.n`` successful expert demos into ``out_dir`` (resumable) and write the datasets.

    Returns:
        report dict: ``successes``, ``tried``, ``success_rate``, ``seconds_per_demo`` (new rollouts only),
        ``seeds`` (the dataset's seeds), ``paths`` (hdf5 / zarr / report). Also written to ``report.json``.
    Raises:
        SimError: fewer than ``n`` successes within ``max_seeds`` seeds.
    """
    from tqdm import tqdm  # lazy, start-up: tqdm

    out_dir = Path(out_dir)
    (out_dir / "shards").mkdir(parents=True, exist_ok=True)
    if cfg.n < 1:
        raise SimError(f"generate_demos: n must be >= 1, got {cfg.n}")
    max_seeds = cfg.max_seeds or 2 * cfg.n + 20
    results: dict[int, dict[str, Any]] = {}
    next_seed = cfg.start_seed
    pool = None
    if cfg.workers > 1:
        pool = ProcessPoolExecutor(cfg.workers, mp_context=mp.get_context("spawn"),
                                   initializer=_init_worker, initargs=(cfg.image_size,))
    try:
        with tqdm(total=cfg.n, desc="square demos", unit="demo") as bar:
            while True:
                ok = sum(r["success"] for r in results.values())
                if ok >= cfg.n:
                    break
                if next_seed - cfg.start_seed >= max_seeds:
                    raise SimError(f"generate_demos({out_dir}): only {ok}/{cfg.n} successful demos after "
                                   f"{max_seeds} seeds from {cfg.start_seed}; raise max_seeds")
                want = cfg.n - ok
                wave = list(range(next_seed, next_seed + max(want + math.ceil(0.1 * want), 1)))
                next_seed = wave[-1] + 1
                todo = []
                for s in wave:
                    prev = _existing(out_dir, s)
                    if prev is None:
                        todo.append(s)
                    else:
                        results[s] = prev
                        _tick(bar, prev["success"])
                for r in _run_wave(todo, cfg, out_dir, pool, bar):
                    results[r["seed"]] = r
    finally:
        if pool is not None:
            pool.shutdown()
    seeds = sorted(s for s, r in results.items() if r["success"])[: cfg.n]
    tried = sorted(results)[: sorted(results).index(seeds[-1]) + 1]
    new = [r for r in results.values() if not r.get("resumed")]
    report = {
        "config": asdict(cfg), "successes": len(seeds), "tried": len(tried),
        "success_rate": len(seeds) / len(tried), "seeds": seeds,
        "seconds_per_demo": (sum(r["seconds"] for r in new) / len(new)) if new else None,
        "paths": _write_datasets(out_dir, seeds, cfg),
    }
    report["paths"]["report"] = str(atomic_write_text(out_dir / "report.json", json.dumps(report, indent=2)))
    return report


def _episodes(out_dir: Path, seeds: list[int]) -> Iterator:
    from umi_aug.square.writers import load_episode  # lazy, start-up: cv2, zarr

    for s in seeds:
        yield load_episode(shard_paths(out_dir, s)[0])


def _write_datasets(out_dir: Path, seeds: list[int], cfg: DemoConfig) -> dict[str, str]:
    # lazy, start-up: cv2, zarr
    from umi_aug.square.camera import T_CAM_TCP, wrist_intrinsics
    from umi_aug.square.env import square_env_meta
    from umi_aug.square.writers import write_robomimic_hdf5, write_umi_zarr

    paths = {}
    stem = f"square_expert_fisheye{cfg.image_size}"
    if cfg.write_hdf5:
        paths["hdf5"] = str(write_robomimic_hdf5(out_dir / f"{stem}.hdf5", _episodes(out_dir, seeds),
                                                 square_env_meta()))
    if cfg.write_zarr:
        paths["zarr"] = str(write_umi_zarr(out_dir / f"{stem}.zarr.zip", _episodes(out_dir, seeds), T_CAM_TCP,
                                           wrist_intrinsics(cfg.image_size).to_dict()))
    return paths
