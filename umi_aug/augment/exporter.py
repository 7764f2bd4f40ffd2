"""Offline export (paper §3.4 data compilation): original + augmented episodes in one UMI replay buffer.

Layout: the UMI keys (``robot0_*``, ``camera0_rgb`` at ``S x S``) that UMI's and our trainer read unchanged, plus
per-episode records as extra ``meta/`` arrays of length E (UMI copies ``meta/`` whole and never indexes them;
``data/`` stays UMI's): ``aug_source_episode`` (original demo index), ``aug_mode`` (0 original, 1 freespace,
2 obstacle, 3 a demo re-rendered — :data:`umi_aug.augment.plan.MODE_CODES`), ``aug_id`` (−1 for originals),
``aug_seed`` (derived seed), ``aug_attempts`` (1 = no resampling), ``aug_splice_index`` (first replayed frame),
``aug_job`` (job number).
Root attribute ``umi_aug_export`` holds the run key, the job list size, failures and progress.

Resumability: jobs run in a fixed order (demo, mode, aug_id) and every one is deterministic on its own. The
working store is a zarr directory (``<out>`` itself, or ``<out>.partial`` for a ``.zip`` output that is written at
the end). Per episode the meta records are grown first, then :meth:`ReplayBuffer.add_episode` writes the data
and commits ``meta/episode_ends`` last; after a kill, :meth:`ReplayBuffer.open` with ``repair=True`` truncates a
half-written append, the records are cut to the committed episodes, and the run continues after the last job
that finished (an episode committed or a failure recorded) — nothing duplicated, nothing lost.

Original episodes are copied as stored (compressed chunks, no re-encoding); new frames are JPEG-XL encoded by the
replay buffer's UMI codec. With ``rerender_originals`` each augmentable demo is written once more ahead of its
augmented episodes (job ``(demo, "rerender", 0)``): its low-dim rows exactly as stored, its frames before the
splice rendered at its own poses (:func:`umi_aug.augment.plan.rerender_episode`), the rest copied as stored.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import glob
import json
import logging
import os
import pickle
import re
import shutil
import socket
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from umi_aug.augment.config import (DEFAULT_RENDER_MIN_TRANSMITTANCE, AugmentConfig, config_hash, obstacle_key,
                                    splat_key)
from umi_aug.augment.encode import FrameEncoder, can_encode_ahead, chunk_spec, encode_with_spec
from umi_aug.augment.executor import map_ordered, usable_cores
from umi_aug.augment.export_report import ExportSummary, export_pictures
from umi_aug.augment.export_store import (ATTR, IMAGE_KEY, RECORD_KEYS, add_records, append_episode,
                                          count_episodes, create_store, export_progress, not_this_runs_output,
                                          open_export_store, raw_copy_ok, stored_key, working_path)
from umi_aug.augment.plan import (MODE_CODES, RERENDER_MODE, PlannedEpisode, episode_seed,
                                  first_attempt_obstacle_assets, rerender_episode, try_plan_episode)
from umi_aug.augment.render import render_episode_frames
from umi_aug.augment.session_assets import SessionAssets
from umi_aug.augment.sources import InputSource, open_source
from umi_aug.augment.stages import OVERLAY_MASK_RULE
from umi_aug.data import ReplayBuffer
from umi_aug.data.store import close_store, open_store
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.io_utils import (PathLock, atomic_path, atomic_write_text, check_free_space, human_bytes, is_inside,
                               remove_tree_atomically, tree_size)

__all__ = ["FAST_PATHS", "export", "export_jobs"]

log = logging.getLogger(__name__)

#: Speed-ups of :func:`export` (issue #17), each with its reference path kept (``fast_paths=()``).
FAST_PATHS: tuple[str, ...] = ("overlay_cache", "encode_ahead", "obstacle_tiles", "encode_in_task", "overlay_pixels")


def export_jobs(assets: SessionAssets) -> list[tuple[int, str, int]]:
    """The run's augmented jobs ``(demo_index, mode, aug_id)`` in export order: per augmentable demo, its
    re-rendered copy ``(d, "rerender", 0)`` first when ``cfg.rerender_originals``, then its episodes per mode."""
    cfg = assets.cfg
    first = [(RERENDER_MODE, 0)] if cfg.rerender_originals else []
    return [(d, m, a) for d in assets.augmentable
            for m, a in first + [(m, a) for m in cfg.modes for a in range(cfg.n_per_demo)]]


def _run_key(cfg: AugmentConfig, fingerprint: str) -> str:
    # Everything that changes the episodes' content (not: workers, executor); the overlay-mask rule is code, not
    # config, so its version is part of the key too.
    return config_hash("export", 1, OVERLAY_MASK_RULE, fingerprint, cfg.seed, cfg.mode, cfg.n_per_demo, cfg.cone_half_angle_deg,
                       cfg.cone_radius_m, cfg.max_extra_rotation_deg, cfg.image_size, cfg.max_attempts,
                       splat_key(cfg.splat),
                       cfg.recon, obstacle_key(cfg.obstacle), cfg.overlay, cfg.traj, cfg.render_near_m, cfg.render_far_m,
                       cfg.include_original,
                       # the codec's effort changes the stored bytes; None (the library default) keeps the key of
                       # exports made before the setting existed
                       *(() if cfg.jpegxl_effort is None else (("jpegxl_effort", cfg.jpegxl_effort),)),
                       # early termination changes the new frames; the default keeps earlier exports' keys
                       *(() if cfg.render_min_transmittance == DEFAULT_RENDER_MIN_TRANSMITTANCE
                         else (("render_min_transmittance", cfg.render_min_transmittance),)),
                       # the re-rendered demos add episodes; off keeps earlier exports' keys
                       *((("rerender_originals", True),) if cfg.rerender_originals else ()))


@dataclass
class _JobResult:
    job: int
    planned: PlannedEpisode | None
    attempts: int
    reasons: list
    frames: np.ndarray | None
    copy_tail: bool
    plan_s: float
    render_s: float
    scene_s: float = 0.0  # the demo's scene built (or read from its cache) for this job by a lazy source
    encoded: list | None = None  # encode_in_task: the new frames' chunks, (bytes | None, seconds) each; frames None


def _job_task(args) -> _JobResult:
    """One export job (top-level, picklable: runs in this process or on an executor's worker): plan (or load the
    cached plan), then render the new frames — and the replayed ones too when they cannot be copied raw."""
    assets, j, job, key, raw_ok, overlay_cache, obstacle_tiles, overlay_pixels, spec = args
    d, m, a = job
    t_scene = time.perf_counter()
    assets = assets.for_demo(d)  # the demo's scene (built by its scene task before this job, else here)
    scene_s = time.perf_counter() - t_scene
    if assets.demos[d].contact_index is None:  # known only once a lazily built group has run its contact stage
        return _JobResult(j, None, 0, [f"scene: {assets.demos[d].name} has no splice frame (no contact frame, or "
                                       f"none with the pre-grasp clearance); not augmented"], None, False,
                          0.0, 0.0, scene_s)
    t0 = time.perf_counter()
    if m == RERENDER_MODE:  # the demo itself: nothing to plan (or cache)
        planned, attempts, reasons = rerender_episode(assets, d), 1, []
    else:
        cache = _plan_cache_path(assets, job, key)
        planned = _load_planned(cache) if cache.exists() else None
        if planned is None:
            outcome = try_plan_episode(assets, d, a, m)
            planned, attempts, reasons = outcome.planned, outcome.attempts, list(outcome.failures)
            if planned is not None:
                _save_planned(cache, planned)
        else:
            attempts, reasons = planned.attempts, list(planned.failures)
    t1 = time.perf_counter()
    frames, copy_tail = None, False
    if planned is not None:
        copy_tail = planned.obstacle is None and raw_ok
        n = planned.splice_index if copy_tail else planned.n_frames
        frames = render_episode_frames(assets, planned, range(n), cache_originals=overlay_cache,
                                       obstacle_tiles=obstacle_tiles, overlay_pixels=overlay_pixels)
    t2 = time.perf_counter()
    if spec is not None and frames is not None:  # encode_in_task: the chunks travel back, not the frames
        return _JobResult(j, planned, attempts, reasons, None, copy_tail, t1 - t0, t2 - t1, scene_s,
                          encoded=encode_with_spec(spec, frames))
    return _JobResult(j, planned, attempts, reasons, frames, copy_tail, t1 - t0, t2 - t1, scene_s)


def _scene_task(assets: SessionAssets, scene: str) -> dict:
    """One scene build (top-level, picklable: a task of its own ahead of the scene's episodes): build or load the
    scene's stages; returns its seconds, the machine and the folder it wrote (which the export then checks it
    can see: the stage cache must be shared by every machine of a cluster)."""
    t0 = time.perf_counter()
    folder = assets.build_scene(scene)
    return {"seconds": time.perf_counter() - t0, "host": socket.gethostname(), "folder": str(folder)}


def _check_scene_visible(scene: str, built: dict) -> None:
    """A scene built on another machine must be in this machine's stage cache too (a shared ``--work``)."""
    if not Path(built["folder"]).is_dir():
        raise AugmentError(f"scene {scene} was built on {built['host']} into {built['folder']}, which this "
                           f"machine ({socket.gethostname()}) cannot see: with a Ray cluster, put the export's "
                           f"work folder (--work) on a filesystem every node mounts at the same path")


def _plan_cache_path(assets: SessionAssets, job: tuple[int, str, int], key: str) -> Path:
    d, m, a = job
    return assets.work_dir / "plans" / key / f"{m}_d{d:03d}_a{a:05d}.pkl"


def _load_planned(path: Path) -> PlannedEpisode | None:
    try:
        with open(path, "rb") as fh:
            return pickle.load(fh)
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError):
        return None


def _save_planned(path: Path, planned: PlannedEpisode) -> None:
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                pickle.dump(planned, fh, protocol=pickle.HIGHEST_PROTOCOL)
    except OSError as exc:
        if exc.errno in DISK_FULL_ERRNOS and not exc.filename:  # a write() names no file: name the cache file
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def export(session_dir: str | os.PathLike, out_path: str | os.PathLike, cfg: AugmentConfig, *,
           resume: bool = True, work_dir: str | os.PathLike | None = None, progress: bool = True,
           pictures: bool = True, dataset_input=None, fast_paths=None, encode_threads: int | None = None,
           source=None, command: list[str] | None = None) -> ExportSummary:
    """Write the original and the augmented episodes of an input to a UMI zarr (``.zarr.zip`` or directory).

    Args:
        session_dir: the input: a UMI session folder, a plain UMI dataset (``*.zarr.zip`` / zarr directory; scenes
            built from its own frames), or any kind registered with
            :func:`umi_aug.augment.sources.register_source` (a square demo folder once ``umi_aug.square.source``
            is imported; :func:`~umi_aug.augment.sources.open_source` picks its
            :class:`~umi_aug.augment.sources.InputSource`).
        dataset_input: the input settings :func:`~umi_aug.augment.sources.open_source` passes on: a plain
            dataset's :class:`~umi_aug.augment.dataset_source.DatasetInput`, a registered kind's own (a square
            folder's ``SquareInput``; None: the defaults; a session has none).
        out_path: ``*.zip`` → a ``.zarr.zip`` written at the end (working directory ``<out>.partial``); anything
            else → a zarr directory written in place.
        cfg: :class:`AugmentConfig`.
        resume: continue an interrupted export of the same configuration (False: start over).
        work_dir: stage cache (default ``<out>.work``).
        progress: tqdm bar (episodes/s).
        pictures: contact sheet + trajectory plots next to the output.
        fast_paths: the speed-ups to use (default: all of :data:`FAST_PATHS`; ``()``: the reference paths). The
            dataset is byte-identical either way (``tests/augment/test_throughput.py``): ``"overlay_cache"`` —
            the demo's pre-contact frames the gripper overlay draws from are decoded once per demo, not once per
            episode; ``"encode_ahead"`` — new frames are JPEG-XL encoded on ``encode_threads`` threads (default:
            the usable cores) while the next episode renders; ``"obstacle_tiles"`` — on the replayed frames of
            an obstacle episode the scene's depth (for the obstacle's depth test) is rasterised only in the
            tiles where the obstacle shows; ``"encode_in_task"`` — with more than one worker, each episode task
            encodes its own new frames (:func:`umi_aug.augment.encode.encode_with_spec`) and sends back the chunks,
            so the driver only stores them (it no longer encodes every worker's frames); ``"overlay_pixels"`` —
            the new frames' pixels the gripper overlay covers completely (gripper, fingers, and the mirrors when
            they come from the source frame) are not rasterised.
        source: the :class:`~umi_aug.augment.sources.InputSource` of ``session_dir``, opened by the caller
            (e.g. the square benchmark's ``SquareSource`` with its settings); default:
            ``open_source(session_dir, dataset_input)``.
        command: the command line that runs this export (``["umi-aug", "augment", ...]``, without ``--restart``),
            kept in the export's records with the working folder: ``umi-aug validate`` names it as the command that
            resumes an interrupted export.
    Returns:
        :class:`ExportSummary` (also ``<out>.summary.json``).
    Raises:
        AugmentError: stage failures, an existing export of another configuration, mismatched dataset keys, an
            input problem (checked before any compute), an output/work dir that is the input, another run holding
            the output's or work dir's lock (its PID), too little free disk space, ``resume=False`` on a path
            umi-aug did not write; a full disk during the run (naming the path being written, the free space and the
            episodes kept: a rerun resumes).
    """
    out = Path(out_path)
    work = Path(work_dir) if work_dir is not None else out.with_name(out.name + ".work")
    src = source if source is not None else open_source(session_dir, dataset_input)
    _check_paths(Path(session_dir), src.reads(), out, work)
    # one run per output and per work dir: a second run fails at once naming the holder's PID
    work_existed = work.exists()
    writing = {"path": work, "what": "the stage cache (--work)"}  # what a full disk interrupts (updated by _export)
    try:
        with PathLock(out, "output", AugmentError), PathLock(work, "work dir", AugmentError, inside=True):
            return _export(src, out, work, cfg, resume=resume, progress=progress, pictures=pictures,
                           fast=_fast_paths(fast_paths), encode_threads=encode_threads, command=command,
                           writing=writing)
    except OSError as exc:
        if exc.errno not in DISK_FULL_ERRNOS:
            raise
        raise AugmentError(_disk_full_message(exc, writing, working_path(out))) from exc
    finally:
        if not work_existed:  # the lock made it: a run stopped by an up-front check leaves no empty <out>.work/
            with contextlib.suppress(OSError):
                work.rmdir()  # only when empty (a stage wrote nothing); never anything else


#: errno of a full disk / an exhausted quota.
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def _disk_full_message(exc: OSError, writing: dict, wpath: Path) -> str:
    """One line for a full disk: the path being written (the file when the error names one), the free space left on
    its file system, and what is kept — the export's episodes written so far, from its own records."""
    path = Path(exc.filename) if exc.filename else Path(writing["path"])
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = f"{human_bytes(shutil.disk_usage(probe).free)} free on it"
    except OSError:
        free = "free space unknown"
    st = export_progress(wpath)
    kept = (f"{st.n_episodes} of the {st.planned} planned episodes are written and kept in {wpath}" if st is not None
            else "nothing half-written is kept")
    return (f"{path}: disk full while writing {writing['what']} ({exc.strerror or 'No space left on device'}; "
            f"{free}); {kept}: free some space (or choose --out/--work on another disk) and rerun the same command "
            f"to resume")


def _fast_paths(fast_paths) -> frozenset:
    fast = frozenset(FAST_PATHS if fast_paths is None else fast_paths)
    unknown = sorted(fast - set(FAST_PATHS))
    if unknown:
        raise AugmentError(f"fast_paths: unknown {unknown}; choose from {list(FAST_PATHS)}")
    return fast


def _check_paths(src: Path, reads: tuple[Path, ...], out: Path, work: Path) -> None:
    """Refuse an output / work dir that is, contains or lies inside the input ``src`` — inside a folder input, in
    what the source ``reads`` (:meth:`InputSource.reads`: a session's inputs, all of a zarr directory) — nothing
    is touched."""
    for what, p in (("--out", out), ("--out", working_path(out)), ("--work", work)):
        if is_inside(src, p) or (src.is_dir() and is_inside(p, src) and any(is_inside(p, r) for r in reads)):
            raise AugmentError(f"{what} {p}: is, contains or lies inside the input {src}; umi-aug never writes "
                               f"into or deletes its inputs: choose another {what}")


def _is_own_export(p: Path, wpath: Path) -> bool:
    """True when ``p`` is an umi-aug export (its root attribute ``umi_aug_export``), or umi-aug's working store
    ``<out>.partial`` holding nothing but zarr groups (a half-deleted one)."""
    try:
        store, root = open_store(p, mode="r")
    except UmiAugError:
        store = root = None
    if root is not None:
        try:
            if ATTR in root.attrs:
                return True
        except (KeyError, ValueError, TypeError):
            pass
        finally:
            close_store(store)
    return p == wpath and p.is_dir() and {q.name for q in p.iterdir()} <= {".zgroup", ".zattrs", "data", "meta"}


def _discard_previous(out: Path, wpath: Path) -> None:
    """``--restart``: delete the previous export / working store — only when umi-aug wrote it."""
    for p in dict.fromkeys([wpath, out]):
        if not p.exists() and not p.is_symlink():
            continue
        if p.is_symlink() or not _is_own_export(p, wpath):
            raise AugmentError(f"{p}: exists and is not an umi-aug export (no attribute '{ATTR}'); --restart "
                               f"deletes only umi-aug's own outputs: move it away yourself or choose another "
                               f"--out")
        log.info("export: --restart removes the previous export %s", p)
        remove_tree_atomically(p)


def _remove_leftover_temporaries(out: Path) -> None:
    """Delete ``<out>.tmp-<8 hex>`` / ``<out>.partial.tmp-<8 hex>`` left by a killed atomic write or clean-up
    (:func:`umi_aug.io_utils.temp_sibling` names; this run holds the output's lock, so none is in use)."""
    pat = re.compile(re.escape(out.name) + r"(\.partial)?\.tmp-[0-9a-f]{8}")
    for p in out.parent.glob(glob.escape(out.name) + "*.tmp-*") if out.parent.is_dir() else []:
        if pat.fullmatch(p.name):
            log.info("export: removing %s (left by an interrupted run)", p)
            remove_tree_atomically(p)


def _n_jobs_max(cfg: AugmentConfig, n_aug: int) -> int:
    """Jobs of ``n_aug`` augmentable demos (:func:`export_jobs`' length when every demo has a splice frame)."""
    return n_aug * (len(cfg.modes) * cfg.n_per_demo + int(cfg.rerender_originals))


def _expected_bytes(src: Path, n_jobs_max: int, n_src_eps: int, include_original: bool) -> int:
    """About the bytes of the output: the input dataset's bytes per episode x the episodes written."""
    per_ep = tree_size(src) / max(1, n_src_eps)
    return int(per_ep * (n_jobs_max + (n_src_eps if include_original else 0)))


def _export(src: InputSource, out: Path, work: Path, cfg: AugmentConfig, *, resume: bool, progress: bool,
            pictures: bool, fast: frozenset = frozenset(), encode_threads: int | None = None,
            command: list[str] | None = None, writing: dict | None = None) -> ExportSummary:
    t_start = time.perf_counter()
    src.check(cfg.image_size)  # every input, before anything is removed or computed: one error naming the key
    key = _run_key(cfg, src.fingerprint())
    src_ds = Path(src.dataset)
    n_src = count_episodes(src_ds)
    n_aug = src.n_augment(n_src)
    wpath = working_path(out)
    _remove_leftover_temporaries(out)
    if not resume:
        _discard_previous(out, wpath)
    finished = False
    if out.name.endswith(".zip") and out.exists():  # checked before any stage runs: a mismatch costs nothing
        stored = stored_key(out)
        if stored != key:
            raise AugmentError(not_this_runs_output(out, stored, key))
        finished = True
        if wpath.exists():  # killed during the final clean-up: the output is complete, the working copy is left
            log.warning("export: %s is complete; removing the leftover working store %s", out, wpath)
            remove_tree_atomically(wpath)
    elif wpath.exists() and stored_key(wpath) != key:
        raise AugmentError(not_this_runs_output(wpath, stored_key(wpath), key))
    if not finished:  # before minutes of compute: the output (and a .zip's working copy) must fit
        need = _expected_bytes(src_ds, _n_jobs_max(cfg, n_aug), n_src, cfg.include_original)
        need = need * (2 if out.name.endswith(".zip") else 1) - tree_size(wpath)
        check_free_space(out, need, f"writing {out.name} (about {_n_jobs_max(cfg, n_aug)} new "
                         f"episodes{' + a .zarr.zip copy of the working store' if out.name.endswith('.zip') else ''})",
                         AugmentError)
    # the obstacle assets the jobs' first attempts draw: a source may fit them beside a long stage
    assets = src.prepare(work, cfg, progress=progress,
                         prefit_obstacles=() if finished else first_attempt_obstacle_assets(cfg, range(n_src)))
    jobs = export_jobs(assets)
    if finished:
        log.info("export: %s is complete for this configuration; nothing to do", out)
        return _finish(out, work, assets, key, jobs, len(jobs), t_start, {}, 0, pictures, read_from=out)
    writing = writing if writing is not None else {}
    writing.update(path=wpath, what="the export" if wpath == out else "the export's working store")
    if not wpath.exists():
        create_store(wpath, assets, key, len(jobs))
    buf, attrs = open_export_store(wpath, key)
    if command is not None and attrs.get("command", {}).get("argv") != list(command):
        # `umi-aug validate` names it as the command that resumes an interrupted export
        attrs["command"] = {"argv": list(command), "cwd": os.getcwd()}
        buf.root.attrs[ATTR] = attrs
    timings = {"scene_s": 0.0, "plan_s": 0.0, "render_s": 0.0, "write_s": 0.0, "encode_s": 0.0}
    frames_rendered = 0
    try:
        recs = buf.meta["aug_job"][:]
        done_job = max(int(attrs.get("last_job_done", -1)), int(recs.max()) if recs.size else -1)
        start = done_job + 1
        resumed = start
        if start > 0:
            log.info("export: resuming %s after job %d of %d (%d episodes present)", wpath, done_job, len(jobs),
                     buf.n_episodes)
        failures = list(attrs.get("failures", []))
        src_img = assets.original[IMAGE_KEY]
        raw_ok = IMAGE_KEY in buf and raw_copy_ok(buf[IMAGE_KEY], src_img)
        if not raw_ok:
            log.info("export: replayed frames are re-encoded (the output's image codec/chunks differ from the "
                     "session dataset's)")
        t_loop = time.perf_counter()
        bar = tqdm(total=len(jobs), initial=start, desc="augment", unit="episode", disable=not progress,
                   dynamic_ncols=True)
        overlay_cache, obstacle_tiles = "overlay_cache" in fast, "obstacle_tiles" in fast
        overlay_pixels = "overlay_pixels" in fast
        # encode_in_task: with several workers the tasks encode (one process renders and encodes alike: it keeps
        # encode_ahead's threads, which overlap the next render)
        spec = (chunk_spec(buf[IMAGE_KEY]) if "encode_in_task" in fast and cfg.workers > 1 and IMAGE_KEY in buf
                and can_encode_ahead(buf[IMAGE_KEY]) else None)
        tasks = ((assets, j, jobs[j], key, raw_ok, overlay_cache, obstacle_tiles, overlay_pixels, spec)
                 for j in range(start, len(jobs)))
        # encode_ahead: a finished episode's new frames are encoded on threads while the next one renders; it is
        # committed (records, data, meta/episode_ends, progress attribute — in the reference's order) when the next
        # result arrives or at the end, so a kill loses at most that one episode (resume redoes it).
        encoder = (FrameEncoder(buf[IMAGE_KEY], encode_threads or usable_cores())
                   if "encode_ahead" in fast and IMAGE_KEY in buf and can_encode_ahead(buf[IMAGE_KEY]) else None)
        pending: list = []

        def commit(res: _JobResult, encoded: list | None) -> None:
            nonlocal frames_rendered
            j, planned = res.job, res.planned
            d, m, a = jobs[j]
            if planned is None:
                failures.append({"job": j, "demo": d, "mode": m, "aug_id": a,
                                 "seed": episode_seed(cfg.seed, d, a, m), "attempts": res.attempts,
                                 "reasons": res.reasons[-3:]})
            else:
                frames_rendered += planned.splice_index
                if cfg.include_original and int(buf.meta["aug_splice_index"][d]) < 0:  # group built lazily
                    buf.meta["aug_splice_index"][d] = int(planned.episode.source_contact_index)
                t0 = time.perf_counter()
                add_records(buf, {"aug_source_episode": d, "aug_mode": MODE_CODES[m], "aug_id": a,
                                   "aug_seed": planned.seed, "aug_attempts": planned.attempts,
                                   "aug_splice_index": planned.splice_index, "aug_job": j})
                ep = planned.episode
                rows = np.zeros(0, np.int64)
                if res.copy_tail:  # replayed frames: the original compressed chunks
                    r0 = assets.original.get_episode_slice(d).start + int(ep.source_contact_index)
                    rows = np.arange(r0, r0 + planned.n_frames - planned.splice_index)
                # a re-rendered demo keeps its own rows exactly (every key its source stores)
                lowdim = assets.original_lowdim(d) if m == RERENDER_MODE else assets.umi_episode(ep, d)
                timings["encode_s"] += append_episode(buf, lowdim, res.frames, src_img, rows, encoded)
                timings["write_s"] += time.perf_counter() - t0
            tally = dict(attrs.get("attempt_failures", {}))
            for r in res.reasons:
                tally[_status_of(r)] = tally.get(_status_of(r), 0) + 1
            attrs.update({"last_job_done": j, "failures": failures, "attempt_failures": tally})
            buf.root.attrs[ATTR] = attrs
            bar.update(1)
            rate = (j + 1 - start) / max(1e-9, time.perf_counter() - t_loop)
            bar.set_postfix(eps=f"{rate:.2f}/s", failed=len(failures))

        with bar:
            try:
                def scene_built(scene: str, built: dict) -> None:
                    _check_scene_visible(scene, built)
                    timings["scene_s"] += built["seconds"]
                    assets.build_scene(scene)  # a worker built it: read its stages from the cache (the summary)

                # a plain dataset's scenes build as tasks of their own, several at once, ahead of their episodes
                for res in map_ordered(_job_task, tasks, executor=cfg.executor, workers=cfg.workers,
                                       address=cfg.ray_address, needs=lambda task: assets.scene_to_build(task[2][0]),
                                       build=functools.partial(_scene_task, assets), on_built=scene_built):
                    timings["scene_s"] += res.scene_s
                    timings["plan_s"] += res.plan_s
                    timings["render_s"] += res.render_s
                    while pending:
                        commit(*pending.pop(0))
                    if res.encoded is not None:
                        commit(res, res.encoded)
                    elif encoder is not None and res.planned is not None and res.frames is not None:
                        pending.append((res, encoder.submit(res.frames)))
                    else:
                        commit(res, None)
                while pending:
                    commit(*pending.pop(0))
            except Exception:  # a later job failed: the finished episode before it is still written (as reference)
                while pending:
                    commit(*pending.pop(0))
                raise
            finally:
                if encoder is not None:
                    encoder.close()
        timings["loop_s"] = time.perf_counter() - t_loop
    finally:
        buf.close()
    if out.name.endswith(".zip"):
        t0 = time.perf_counter()
        writing.update(path=out, what="the .zarr.zip")
        with ReplayBuffer.open(wpath) as final:
            final.save(out)
        remove_tree_atomically(wpath)  # a kill here leaves <out>.partial.tmp-*, never a half-deleted .partial
        timings["write_s"] += time.perf_counter() - t0
    writing.update(path=out.parent, what=f"the summary and pictures of {out.name}")
    return _finish(out, work, assets, key, jobs, resumed, t_start, timings, frames_rendered, pictures, read_from=out,
                   loop_s=time.perf_counter() - t_start)


def _status_of(reason: str) -> str:
    """``"attempt 3: collision: ..."`` → ``"collision"``."""
    parts = reason.split(":")
    return parts[1].strip() if len(parts) > 1 else reason


def _planned_episodes(assets: SessionAssets, key: str, jobs) -> dict[int, list]:
    """Demo index → the planned trajectories of its finished jobs (from the plan cache), for the pictures."""
    out: dict[int, list] = {}
    for job in jobs:
        if job[1] == RERENDER_MODE:  # the demo's own path, not a planned one
            continue
        p = _plan_cache_path(assets, job, key)
        pl = _load_planned(p) if p.exists() else None
        if pl is not None:
            out.setdefault(job[0], []).append(pl.episode)
    return out


def _finish(out: Path, work: Path, assets: SessionAssets, key: str, jobs, resumed: int, t_start: float,
            timings: dict, frames_rendered: int, pictures: bool, read_from: Path, loop_s: float = 0.0
            ) -> ExportSummary:
    with ReplayBuffer.open(read_from) as buf:
        attrs = dict(buf.root.attrs.get(ATTR, {}))
        rec = {k: np.asarray(buf.meta[k][:]) for k in RECORD_KEYS}
        n_orig = int((rec["aug_mode"] == 0).sum())
        rerendered = rec["aug_mode"] == MODE_CODES[RERENDER_MODE]
        aug = (rec["aug_mode"] > 0) & ~rerendered
        failures = list(attrs.get("failures", []))
        counts = dict(attrs.get("attempt_failures", {}))
        pics = {}
        t0 = time.perf_counter()
        if pictures:
            pics = export_pictures(out, assets, buf, rec, _planned_episodes(assets, key, jobs))
        timings["pictures_s"] = time.perf_counter() - t0
    done_now = len(jobs) - resumed
    total = time.perf_counter() - t_start
    timings["total_s"] = total
    summary = ExportSummary(
        out_path=str(out), work_dir=str(work), n_original=n_orig, n_augmented=int(aug.sum()),
        n_rerendered=int(rerendered.sum()),
        n_failed=len(failures), n_resampled=int((rec["aug_attempts"][aug] - 1).sum()), n_jobs=len(jobs),
        resumed_jobs=resumed, status_counts=dict(counts),
        stages={k: {"seconds": round(v.seconds, 3), "skipped": v.skipped} for k, v in assets.stages.items()},
        timings_s={k: round(v, 3) for k, v in timings.items()}, frames_rendered=frames_rendered,
        episodes_per_s=round(done_now / loop_s, 4) if loop_s > 0 else 0.0, pictures=pics, failures=failures)
    atomic_write_text(out.with_name(out.name + ".summary.json"), json.dumps(asdict(summary), indent=2) + "\n")
    return summary
