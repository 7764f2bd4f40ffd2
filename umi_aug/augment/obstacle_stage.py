"""The per-asset obstacle stages: ``obstacles/<asset>`` holds the Gaussians of one obstacle asset, fitted on first
use (:meth:`umi_aug.augment.SessionAssets.obstacle_gaussians`) or ahead of it by a background process
(:func:`start_obstacle_prefit`) while the scene's 3DGS trains and leaves part of a core idle.

Run as ``python -m umi_aug.augment.obstacle_stage WORK ASSET...`` (the pickled config on stdin) it is that
background process.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import pickle
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from umi_aug.augment.cache import StageResult, build_lock, read_manifest, run_stage
from umi_aug.augment.config import OBSTACLE_FIT_ITERATIONS, AugmentConfig
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.recon.obstacles import PROCEDURAL_ASSETS, load_mesh_asset, procedural_asset
from umi_aug.runtime import start_background_helper

if TYPE_CHECKING:
    import subprocess

__all__ = ["check_obstacle_assets", "load_obstacle_asset", "obstacle_lock", "obstacle_stage", "obstacle_stage_folder",
           "scaled_obstacle_asset", "start_obstacle_prefit"]

log = logging.getLogger(__name__)


def scaled_obstacle_asset(name: str, scale: float):
    """Asset ``name`` (procedural or mesh path) scaled by ``scale`` about its object origin."""
    if name in PROCEDURAL_ASSETS:
        return procedural_asset(name, scale)
    if Path(name).is_file():
        return load_mesh_asset(name, scale=scale)
    raise AugmentError(f"obstacle asset {name!r}: neither a procedural asset {PROCEDURAL_ASSETS} nor a mesh file")


def load_obstacle_asset(asset: str):
    """Procedural asset name or mesh file path → :class:`umi_aug.recon.ObstacleAsset` (unscaled)."""
    return scaled_obstacle_asset(asset, 1.0)


def check_obstacle_assets(cfg: AugmentConfig) -> None:
    """Load every obstacle asset of an obstacle-mode run once, up front (their Gaussians are fitted lazily, so
    a bad name or mesh file must fail here, before any work, not in an episode). Raises :class:`AugmentError`."""
    if "obstacle" not in cfg.modes:
        return
    for name in cfg.obstacle.assets:
        try:
            load_obstacle_asset(name)
        except AugmentError:
            raise
        except (UmiAugError, OSError, ValueError) as exc:
            raise AugmentError(f"obstacle asset {name!r}: {exc}") from exc


def obstacle_stage_folder(name: str) -> str:
    """``obstacles/<slug>-<hash8>``: the stage folder of obstacle asset ``name`` (relative to the work folder)."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(name).name)[:40]
    return f"obstacles/{slug}-{hashlib.sha256(name.encode()).hexdigest()[:8]}"


def obstacle_stage(work: Path, cfg: AugmentConfig, name: str) -> StageResult:
    """The ``obstacles/<asset>`` stage: the Gaussians of obstacle asset ``name`` (a procedural name or a mesh
    path) in its object frame, ``scene.ply``. Keyed by the asset and the Gaussian settings only (not the session,
    not the other assets). Callers that may run concurrently hold the asset's :func:`build_lock` (as
    :meth:`SessionAssets.obstacle_gaussians` does)."""
    def fn(out: Path):
        # lazy, start-up: torch
        from umi_aug.splat import write_ply
        from umi_aug.splat.obstacle_gaussians import ObstacleGaussianConfig, obstacle_gaussians

        g = obstacle_gaussians(load_obstacle_asset(name), cache_dir=out / "cache", fit=cfg.obstacle.fit_gaussians,
                               n_gaussians=cfg.obstacle.n_gaussians, seed=cfg.seed,
                               config=ObstacleGaussianConfig(fit_iterations=cfg.obstacle.fit_iterations))
        write_ply(out / "scene.ply", g)
        return {"ply": "scene.ply"}, ["scene.ply"], {"asset": name, "gaussians": int(g.n)}

    folder = obstacle_stage_folder(name)
    conf = {"asset": name, "fit": cfg.obstacle.fit_gaussians, "n_gaussians": cfg.obstacle.n_gaussians,
            "seed": cfg.seed}
    if cfg.obstacle.fit_gaussians and cfg.obstacle.fit_iterations != OBSTACLE_FIT_ITERATIONS:
        conf["fit_iterations"] = cfg.obstacle.fit_iterations  # the default keeps earlier work folders' keys
    return run_stage(folder, work, conf, {}, fn)


def obstacle_lock(work: Path, name: str) -> contextlib.AbstractContextManager:
    """The build lock of asset ``name``'s stage (one per asset: two processes fit two assets at once, and a
    process that needs an asset being fitted elsewhere waits for it, then reads it from the cache)."""
    return build_lock(Path(work) / "obstacles", f".{obstacle_stage_folder(name)[10:]}.lock")


def start_obstacle_prefit(work: Path, cfg: AugmentConfig, names: Sequence[str]) -> subprocess.Popen | None:
    """Fit the obstacle assets ``names`` in a background process (``nice`` 10, one thread, killed with its
    parent), each under its :func:`obstacle_lock`, so that the episodes find them cached. Meant to run beside the
    scene's 3DGS training, which leaves ~0.4 of the second core idle on 2 cores. Returns the child, or None when
    there is nothing to fit (no names, fitting off, or every asset's stage folder already there). Nothing depends
    on the child: an episode that needs an asset first fits it itself (or waits for the child's lock); its failures
    are only logged to ``obstacles/prefit.log`` (the episode's fit raises them where they count).
    ``UMI_AUG_NO_OBSTACLE_PREFIT=1`` turns it off."""
    if os.environ.get("UMI_AUG_NO_OBSTACLE_PREFIT", "") not in ("", "0") or not cfg.obstacle.fit_gaussians:
        return None
    todo = [n for n in dict.fromkeys(names) if read_manifest(Path(work) / obstacle_stage_folder(n)) is None]
    if not todo:
        return None
    folder = Path(work) / "obstacles"
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "prefit.log", "ab") as logf:  # the config goes over stdin: no file to leave behind
        child = start_background_helper("umi_aug.augment.obstacle_stage", [str(work), *todo],
                                        stdin_bytes=pickle.dumps(cfg), output=logf)
    if child is None:  # pragma: no cover - no process could be started: the episodes fit on first use
        log.info("obstacle prefit not started")
    return child


def _prefit_main(work: str, names: Sequence[str]) -> int:
    """The child of :func:`start_obstacle_prefit` (its :class:`AugmentConfig` pickled on stdin): fit each asset
    (cached ones are skipped), under its lock."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    cfg = pickle.loads(sys.stdin.buffer.read())
    status = 0
    for name in names:
        try:
            with obstacle_lock(Path(work), name):
                st = obstacle_stage(Path(work), cfg, name)
            log.info("prefit obstacles/%s: %s", name, "cached" if st.skipped else f"fitted in {st.seconds:.1f} s")
        except (UmiAugError, OSError, ValueError) as exc:
            log.warning("prefit obstacles/%s failed: %s", name, exc)
            status = 1
    return status


if __name__ == "__main__":  # pragma: no cover - the child of start_obstacle_prefit (its test runs it)
    sys.exit(_prefit_main(sys.argv[1], sys.argv[2:]))
