"""Fast paths of :class:`~umi_aug.policy.augmented_dataset.AugmentedUmiDataset` (issue #17 part 2), each with its
reference kept (the dataset's ``fast_paths=()``) and compared in ``tests/policy/test_augmented_dataset_fast.py``:

* ``"plan_disk_cache"`` — :class:`PlanDiskCache`: planned episodes pickled under
  ``<work_dir>/plans/<key>/<mode>_d<demo>_a<aug_id>.pkl`` (the exporter's layout), shared by every epoch, DataLoader
  worker and later run; failed plans are cached too. The key is a content key of everything a plan reads: the
  scene SDF file's bytes, the demo (poses, timestamps, widths, splice frame), the render views, the planning
  settings, and the source of the planning code (so a code change never serves a stale plan).
* ``"frames"`` — :func:`sample_frames`: the same pixels as :func:`umi_aug.augment.render_episode_frames` for the
  1–2 frames of a sample, but each original frame it needs (replayed frames and overlay sources) is decoded once,
  alone (the reference decodes every frame between the lowest and the highest index asked for, or the demo's whole
  pre-contact range for the overlay cache); the overlay is :func:`umi_aug.augment.overlay.composite_overlay`, which
  blends only inside the mask's feathered band.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import time
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import AugmentError
from umi_aug.io_utils import atomic_path

__all__ = ["FAST_PATHS", "PlanDiskCache", "plan_code_fingerprint", "plan_cache_key", "read_rows",
           "sample_frames"]

log = logging.getLogger(__name__)

#: Every fast path of the dataset (its default); ``()`` is the reference.
FAST_PATHS: tuple[str, ...] = ("plan_disk_cache", "frames")
#: Bump when the pickled layout of a cached plan changes.
PLAN_CACHE_VERSION = 1
#: Source (relative to the ``umi_aug`` package) whose code decides a plan; hashed into the plan key.
PLAN_CODE = ("augment/plan.py", "augment/session_assets.py", "augment/config.py", "traj", "geometry",
             "recon/sdf_grid.py", "recon/obstacles.py")


@lru_cache(maxsize=1)
def plan_code_fingerprint() -> str:
    """sha256 (16 hex) of the planning code's source files (:data:`PLAN_CODE`), once per process (~50 files)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for rel in PLAN_CODE:
        p = root / rel
        files = sorted(p.rglob("*.py")) if p.is_dir() else [p]
        for f in files:
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


@lru_cache(maxsize=16)
def _file_sha(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _array_sha(*arrays: Any) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def plan_cache_key(handle: Any, demo_index: int) -> str:
    """Content key of the plans of demo ``demo_index`` on ``handle`` (a :class:`SessionAssets` serving the demo:
    ``assets.for_demo(d)``): SDF bytes, demo arrays + splice frame, render views, planning config, code."""
    from umi_aug.augment.config import config_hash  # lazy, start-up: cv2, scipy

    cfg = handle.cfg
    d = handle.demos[int(demo_index)]
    sdf = str(handle.paths["sdf"])
    st = os.stat(sdf)
    return config_hash("umi-aug on-the-fly plans", PLAN_CACHE_VERSION, plan_code_fingerprint(),
                       _file_sha(sdf, st.st_size, st.st_mtime_ns),
                       _array_sha(d.T_world_cam, d.timestamps, d.gripper_width), d.contact_index, d.name,
                       _array_sha(handle.render_views), cfg.seed, cfg.cone_half_angle_deg, cfg.cone_radius_m,
                       cfg.max_extra_rotation_deg, cfg.max_attempts, cfg.traj, cfg.obstacle)


class PlanDiskCache:
    """Planned episodes on disk, ``<root>/<plan_cache_key>/<mode>_d<demo:03d>_a<aug_id:05d>.pkl`` (atomic writes;
    any process may read what another wrote). A file that cannot be read or names another episode is ignored.

    Args:
        root: the plans folder (default of the dataset: ``<assets.work_dir>/plans``).
    """

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self._keys: dict[tuple[str, int], str] = {}

    def __getstate__(self) -> dict:
        return {"root": self.root, "_keys": {}}

    def path(self, handle: Any, demo_index: int, aug_id: int, mode: str) -> Path:
        ck = (handle.cache_id, int(demo_index))
        if ck not in self._keys:  # once per process and demo (hashes the SDF file)
            self._keys[ck] = plan_cache_key(handle, demo_index)
        return self.root / self._keys[ck] / f"{mode}_d{int(demo_index):03d}_a{int(aug_id):05d}.pkl"

    @staticmethod
    def _ident(handle: Any, demo_index: int, aug_id: int, mode: str) -> tuple:
        from umi_aug.augment.plan import episode_seed  # lazy, start-up: cv2, scipy

        return (int(demo_index), int(aug_id), str(mode), episode_seed(handle.cfg.seed, demo_index, aug_id, mode))

    def load(self, handle: Any, demo_index: int, aug_id: int, mode: str) -> tuple[bool, Any]:
        """``(found, planned or None)``; ``found`` is False when there is no usable file."""
        p = self.path(handle, demo_index, aug_id, mode)
        try:
            with open(p, "rb") as fh:
                rec = pickle.load(fh)
        except FileNotFoundError:
            return False, None
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError, ValueError) as exc:
            log.warning("plan cache %s unreadable (%s): planning again", p, exc)
            return False, None
        if not isinstance(rec, dict) or rec.get("ident") != self._ident(handle, demo_index, aug_id, mode):
            log.warning("plan cache %s holds another episode: planning again", p)
            return False, None
        return True, rec["planned"]

    def save(self, handle: Any, demo_index: int, aug_id: int, mode: str, planned: Any) -> None:
        p = self.path(handle, demo_index, aug_id, mode)
        rec = {"ident": self._ident(handle, demo_index, aug_id, mode), "planned": planned}
        try:
            with atomic_path(p) as tmp:
                with open(tmp, "wb") as fh:
                    pickle.dump(rec, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except OSError as exc:  # a read-only work dir: the plan stays in memory only
            log.warning("plan cache %s not written (%s)", p, exc)


def read_rows(handle: Any, demo_index: int, rows: np.ndarray) -> np.ndarray:
    """Original policy frames ``[K, S, S, 3]`` uint8 at demo frame indices ``rows`` (any order, repeats allowed);
    each distinct frame decoded once and alone. Same pixels as ``handle.original_frames(demo_index, rows)``."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    if rows.size == 0:
        return handle.original_frames(demo_index, rows)
    uniq, inv = np.unique(rows, return_inverse=True)
    buf = handle.original
    sl = buf.get_episode_slice(int(demo_index))
    n = sl.stop - sl.start
    if uniq[0] < 0 or uniq[-1] >= n:  # let the reference path name the error
        return handle.original_frames(demo_index, rows)
    arr = buf["camera0_rgb"]
    frames = np.stack([arr[sl.start + int(r)] for r in uniq])
    return frames[inv.reshape(-1)]


def sample_frames(handle: Any, planned: Any, frame_indices: np.ndarray, timings: dict | None = None) -> np.ndarray:
    """:func:`umi_aug.augment.render_episode_frames` ``(handle, planned, frame_indices)`` (same pixels) for a
    sample's few frames: originals decoded alone (:func:`read_rows`).
    Obstacle episodes go to the reference. ``timings`` (seconds) accumulates ``decode``, ``render``, ``overlay``."""
    from umi_aug.augment.overlay import composite_overlay  # lazy, start-up: cv2
    from umi_aug.augment.render import overlay_sources, render_episode_frames, render_view  # lazy, start-up: cv2

    t = timings if timings is not None else {}
    idx = np.asarray(frame_indices, dtype=np.int64).reshape(-1)
    if planned.obstacle is not None:
        t0 = time.perf_counter()
        out = render_episode_frames(handle, planned, idx)
        t["render"] = t.get("render", 0.0) + time.perf_counter() - t0
        return out
    ep = planned.episode
    S = handle.cfg.image_size
    N, n = len(ep.timestamps), int(ep.splice_index)
    if idx.size and (idx.min() < 0 or idx.max() >= N):
        raise AugmentError(f"render_episode_frames: frame indices {idx.min()}..{idx.max()} outside [0, {N})")
    out = np.zeros((idx.size, S, S, 3), np.uint8)
    if idx.size == 0:
        return out
    new = idx < n
    src_new = overlay_sources(handle, planned, idx[new]) if new.any() else np.zeros(0, np.int64)
    src_old = int(ep.source_contact_index) + (idx[~new] - n)
    t0 = time.perf_counter()
    originals = read_rows(handle, planned.demo_index, np.concatenate([src_new, src_old]))
    t1 = time.perf_counter()
    t["decode"] = t.get("decode", 0.0) + t1 - t0
    if new.any():
        rendered = np.stack([render_view(handle, ep.T_world_cam[k]) for k in idx[new]])
        t2 = time.perf_counter()
        alpha = handle.overlay_alpha
        out[new] = composite_overlay(rendered, originals[: len(src_new)], alpha)
        t["render"] = t.get("render", 0.0) + t2 - t1
        t["overlay"] = t.get("overlay", 0.0) + time.perf_counter() - t2
    out[~new] = originals[len(src_new):]
    return out
