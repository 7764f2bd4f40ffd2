"""Offline export (paper §3.4 data compilation): original + augmented episodes in one UMI replay buffer.

Layout: the UMI keys (``robot0_*``, ``camera0_rgb`` at ``S x S``) that UMI's and our trainer read unchanged, plus
per-episode records as extra ``meta/`` arrays of length E (UMI copies ``meta/`` whole and never indexes them;
``data/`` stays UMI's): ``aug_source_episode`` (original demo index), ``aug_mode`` (0 original, 1 freespace,
2 obstacle — :data:`umi_aug.augment.plan.MODE_CODES`), ``aug_id`` (−1 for originals), ``aug_seed`` (derived
seed), ``aug_attempts`` (1 = no resampling), ``aug_splice_index`` (first replayed frame), ``aug_job`` (job number).
Root attribute ``umi_aug_export`` holds the run key, the job list size, failures and progress.

Resumability: jobs run in a fixed order (demo, mode, aug_id) and every one is deterministic on its own. The
working store is a zarr directory (``<out>`` itself, or ``<out>.partial`` for a ``.zip`` output that is written at
the end). Per episode the meta records are grown first, then :meth:`ReplayBuffer.add_episode` writes the data
and commits ``meta/episode_ends`` last; after a kill, :meth:`ReplayBuffer.open` with ``repair=True`` truncates a
half-written append, the records are cut to the committed episodes, and the run continues after the last job
that finished (an episode committed or a failure recorded) — nothing duplicated, nothing lost.

Original episodes are copied as stored (compressed chunks, no re-encoding); new frames are JPEG-XL encoded by the
replay buffer's UMI codec.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import pickle
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from umi_aug.augment.config import AugmentConfig, config_hash, obstacle_key
from umi_aug.augment.encode import FrameEncoder, can_encode_ahead, write_encoded
from umi_aug.augment.executor import map_ordered, usable_cores
from umi_aug.augment.plan import (MODE_CODES, PlannedEpisode, episode_seed, first_attempt_obstacle_assets,
                                  try_plan_episode)
from umi_aug.augment.render import render_episode_frames
from umi_aug.augment.session_assets import SessionAssets
from umi_aug.augment.sources import InputSource, open_source
from umi_aug.augment.stages import OVERLAY_MASK_RULE
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.io_utils import (PathLock, atomic_path, atomic_write_text, check_free_space, is_inside,
                               remove_tree_atomically, tree_size)

__all__ = ["ExportSummary", "ExportProgress", "FAST_PATHS", "append_episode", "export", "export_jobs",
           "export_progress", "interrupted_export_message", "RECORD_KEYS", "read_episode_records", "summary_table"]

log = logging.getLogger(__name__)

#: Per-episode record arrays in ``meta/`` (name → dtype).
RECORD_KEYS: dict[str, str] = {"aug_source_episode": "int64", "aug_mode": "int8", "aug_id": "int64",
                               "aug_seed": "int64", "aug_attempts": "int16", "aug_splice_index": "int64",
                               "aug_job": "int64"}
ATTR = "umi_aug_export"
RECORD_CHUNK = 1024
#: Speed-ups of :func:`export` (issue #17), each with its reference path kept (``fast_paths=()``).
FAST_PATHS: tuple[str, ...] = ("overlay_cache", "encode_ahead", "obstacle_tiles")


@dataclass
class ExportSummary:
    """What :func:`export` did (also written as ``<out>.summary.json``).

    Attributes:
        out_path / work_dir: paths; n_original / n_augmented: episodes in the dataset; n_failed: jobs that
        failed after the retry budget; n_resampled: extra attempts over all emitted episodes;
        n_jobs: augmented jobs; resumed_jobs: jobs already done when this run started;
        status_counts: reasons of failed attempts by status; stages: per stage seconds / skipped;
        timings_s: scene (plain dataset: groups built lazily) / plan / render / write / pictures / total;
        frames_rendered: new frames rendered in this run;
        episodes_per_s: jobs finished per second in this run; pictures: contact sheet + trajectory plots.
    """

    out_path: str
    work_dir: str
    n_original: int
    n_augmented: int
    n_failed: int
    n_resampled: int
    n_jobs: int
    resumed_jobs: int
    status_counts: dict = field(default_factory=dict)
    stages: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    frames_rendered: int = 0
    episodes_per_s: float = 0.0
    pictures: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)


def export_jobs(assets: SessionAssets) -> list[tuple[int, str, int]]:
    """The run's augmented jobs ``(demo_index, mode, aug_id)`` in export order."""
    cfg = assets.cfg
    return [(d, m, a) for d in assets.augmentable for m in cfg.modes for a in range(cfg.n_per_demo)]


def _run_key(cfg: AugmentConfig, fingerprint: str) -> str:
    # Everything that changes the episodes' content (not: workers, executor); the overlay-mask rule is code, not
    # config, so its version is part of the key too.
    return config_hash("export", 1, OVERLAY_MASK_RULE, fingerprint, cfg.seed, cfg.mode, cfg.n_per_demo, cfg.cone_half_angle_deg,
                       cfg.cone_radius_m, cfg.max_extra_rotation_deg, cfg.image_size, cfg.max_attempts, cfg.splat,
                       cfg.recon, obstacle_key(cfg.obstacle), cfg.overlay, cfg.traj, cfg.render_near_m, cfg.render_far_m,
                       cfg.include_original,
                       # the codec's effort changes the stored bytes; None (the library default) keeps the key of
                       # exports made before the setting existed
                       *(() if cfg.jpegxl_effort is None else (("jpegxl_effort", cfg.jpegxl_effort),)))


def _working_path(out: Path) -> Path:
    return out.with_name(out.name + ".partial") if out.name.endswith(".zip") else out


def _add_records(buf, rows: dict[str, int]) -> None:
    meta = buf.meta
    for k, dt in RECORD_KEYS.items():
        a = meta[k]
        a.resize(a.shape[0] + 1)
        a[-1] = np.asarray(rows[k], dtype=dt)


def _create_store(path: Path, assets: SessionAssets, key: str, n_jobs: int) -> None:
    """A new working store: the originals copied as stored + their records, in one atomic directory write."""
    from umi_aug.data import ReplayBuffer

    cfg = assets.cfg
    if cfg.include_original:
        buf = ReplayBuffer.open(assets.paths["dataset"], mode="a", load_to_memory=True)
    else:  # empty arrays with the session dataset's layout (chunks, codecs), so chunks can be copied raw
        buf = ReplayBuffer.create()
        src = assets.original
        for k in src.keys():
            a = src[k]
            buf.data.zeros(k, shape=(0,) + a.shape[1:], chunks=a.chunks, dtype=a.dtype, compressor=a.compressor,
                           filters=a.filters)
    E = buf.n_episodes
    if cfg.include_original and "camera0_rgb" in buf and tuple(buf["camera0_rgb"].shape[1:3]) != (cfg.image_size,) * 2:
        raise AugmentError(f"{assets.paths['dataset']}: key 'data/camera0_rgb' frames are "
                           f"{tuple(buf['camera0_rgb'].shape[1:3])}, image_size = {cfg.image_size}")
    contact = {d.index: d.contact_index for d in assets.demos}
    init = {"aug_source_episode": np.arange(E), "aug_mode": np.zeros(E), "aug_id": np.full(E, -1),
            "aug_seed": np.zeros(E), "aug_attempts": np.ones(E),
            "aug_splice_index": np.array([-1 if contact.get(i) is None else contact[i] for i in range(E)]),
            "aug_job": np.full(E, -1)}
    for k, dt in RECORD_KEYS.items():
        buf.meta.array(k, np.asarray(init[k], dtype=dt), chunks=(RECORD_CHUNK,), compressor=None)
    _set_umi_image_codec(buf, cfg.jpegxl_effort)
    buf.root.attrs[ATTR] = {"key": key, "n_jobs": n_jobs, "n_original": E, "last_job_done": -1, "failures": [],
                            "modes": MODE_CODES, "format": "umi_aug export v1: meta/aug_* per episode"}
    buf.save(path)


#: JPEG-XL codec parameters that only steer the encoder: chunks written with any value decode alike.
ENCODER_ONLY_JPEGXL_KEYS: frozenset[str] = frozenset({"effort"})
#: Frames read at once when an image array of another codec is re-encoded with UMI's JPEG-XL (~38 MB at 224²).
REENCODE_BLOCK = 256


def _set_umi_image_codec(buf, effort: int | None) -> None:
    """Make every ``camera*_rgb`` array of ``buf`` store UMI's exact 12-key JPEG-XL codec config (``id`` + the 11
    parameters of UMI's ``JpegXl``; :func:`umi_aug.data.codecs.umi_image_codec_from`), whatever the source wrote:

    * a JPEG-XL config with other keys (newer imagecodecs' ``bitspersample``, ``squeeze``, ...) is rewritten in the
      array's ``.zarray`` (the stored chunks decode alike: those keys do not change the bitstream), with ``effort``
      (the encoder setting of every frame written from now on) when given;
    * an array of another codec (Blosc, uncompressed, ...) is re-encoded with UMI's ``JpegXl(level=99)``, in blocks
      of :data:`REENCODE_BLOCK` frames, one frame per chunk (lossy, as UMI's own images).

    UMI's reader rebuilds the codec as ``JpegXl(**config)``, so any key beyond its 11 parameters fails there."""
    from zarr.util import json_dumps

    from umi_aug.data import schema
    from umi_aug.data.codecs import JPEGXL_CODEC_ID, umi_image_codec_from

    changed = False
    for key in [k for k in buf.keys() if schema.is_image_key(k)]:
        arr = buf[key]
        zkey = f"{arr.path}/.zarray"
        meta = json.loads(arr.store[zkey])
        stored = meta.get("compressor")
        codec = umi_image_codec_from(stored, effort)
        if stored is not None and stored.get("id") == JPEGXL_CODEC_ID and not meta.get("filters"):
            if stored != codec.get_config():
                meta["compressor"] = codec.get_config()
                arr.store[zkey] = json_dumps(meta)
                changed = True
            continue
        log.info("export: %s frames stored with codec %s are re-encoded with UMI's JPEG-XL", key,
                 None if stored is None else stored.get("id"))
        tmp = f"{key}.umi_aug_reencode"
        dst = buf.data.zeros(tmp, shape=arr.shape, chunks=(1,) + arr.shape[1:], dtype=arr.dtype, compressor=codec)
        for s in range(0, arr.shape[0], REENCODE_BLOCK):
            dst[s:s + REENCODE_BLOCK] = arr[s:s + REENCODE_BLOCK]
        del buf.data[key]
        buf.data.move(tmp, key)
        changed = True
    if changed:
        buf._invalidate()


def _open_store(path: Path, key: str):
    from umi_aug.data import ReplayBuffer

    buf = ReplayBuffer.open(path, mode="a", repair=True)
    attrs = dict(buf.root.attrs.get(ATTR, {}))
    if attrs.get("key") != key:
        buf.close()
        raise AugmentError(_not_this_runs_output(path, attrs.get("key"), key))
    E = buf.n_episodes
    for k in RECORD_KEYS:
        a = buf.meta[k]
        if a.shape[0] < E:
            raise AugmentError(f"{path}: key 'meta/{k}' has {a.shape[0]} rows for {E} episodes (records are "
                               f"written before the episode; the store was modified by something else)")
        if a.shape[0] > E:
            log.warning("%s: dropping %d record(s) of an interrupted append from meta/%s", path, a.shape[0] - E, k)
            a.resize(E)
    return buf, attrs


def _not_this_runs_output(path: Path, stored: str | None, key: str) -> str:
    """The message for an existing ``--out`` (or its working store) that this run cannot resume: umi-aug's own
    export of another configuration (``--restart`` replaces it), or no umi-aug export at all (never touched)."""
    if stored is None:
        return (f"{path}: exists and is not an umi-aug export (no attribute '{ATTR}'; a dataset of yours?); "
                f"umi-aug never writes into it, and --restart deletes only umi-aug's own outputs: choose another "
                f"--out")
    return (f"{path}: an export of another configuration/session (attribute '{ATTR}.key' = {stored!r}, this run "
            f"{key!r}); rerun with --restart to replace it (it is umi-aug's own output), or choose another --out")


def _stored_key(path: Path) -> str | None:
    """The run key stored in an export (directory store read raw: it may hold an interrupted append)."""
    from umi_aug.data.store import close_store, open_store

    try:
        store, root = open_store(path, mode="r")
    except UmiAugError as exc:
        raise AugmentError(f"{path}: exists but is not a readable zarr store ({exc}); delete it or choose another "
                           f"--out") from exc
    try:
        return dict(root.attrs.get(ATTR, {})).get("key")
    except (KeyError, ValueError, TypeError):
        return None
    finally:
        close_store(store)


@dataclass(frozen=True)
class ExportProgress:
    """How far an umi-aug export got, from its own records (:func:`export_progress`).

    Attributes:
        n_episodes: committed episodes (``meta/episode_ends``); n_original: the originals among the planned;
        n_jobs: augmentation jobs planned (one episode each when it does not fail); jobs_done: jobs finished (an
        episode committed or a failure recorded); n_failed: failed jobs; command / cwd: the command line that wrote
        it and its working folder (None: an export made before they were recorded, or through the Python API).
    """

    n_episodes: int
    n_original: int
    n_jobs: int
    jobs_done: int
    n_failed: int
    command: tuple[str, ...] | None = None
    cwd: str | None = None

    @property
    def planned(self) -> int:
        """Episodes the export holds when every job succeeds."""
        return self.n_original + self.n_jobs

    @property
    def complete(self) -> bool:
        return self.jobs_done >= self.n_jobs


def export_progress(path: str | os.PathLike) -> ExportProgress | None:
    """The :class:`ExportProgress` of an umi-aug export (a zarr directory or ``.zarr.zip``, read raw and read-only:
    it may hold an interrupted append), or None when ``path`` is not one (no attribute ``umi_aug_export``, or not
    a readable store)."""
    from umi_aug.data.store import close_store, open_store

    try:
        store, root = open_store(Path(path), mode="r")
    except UmiAugError:
        return None
    try:
        attrs = dict(root.attrs.get(ATTR, {}))
        if "n_jobs" not in attrs:
            return None
        E = int(root["meta/episode_ends"].shape[0])
        recs = root["meta/aug_job"][:E] if "aug_job" in root["meta"] else np.zeros(0, np.int64)
        done = max(int(attrs.get("last_job_done", -1)), int(recs.max()) if len(recs) else -1) + 1
        cmd = attrs.get("command") or {}
        return ExportProgress(n_episodes=E, n_original=int(attrs.get("n_original", 0)), n_jobs=int(attrs["n_jobs"]),
                              jobs_done=done, n_failed=len(attrs.get("failures", [])),
                              command=tuple(cmd["argv"]) if cmd.get("argv") else None, cwd=cmd.get("cwd"))
    except (KeyError, ValueError, TypeError):
        return None
    finally:
        close_store(store)


def interrupted_export_message(path: str | os.PathLike, shown: str | os.PathLike | None = None) -> str | None:
    """The one line ``umi-aug validate`` gives for an interrupted umi-aug export at ``path`` (episodes written vs
    planned, from the export's own records, and the command that resumes it), or None (complete, or not an
    export). ``shown``: the path the user passed, when that is not ``path`` (a ``.zarr.zip`` not yet written,
    whose working store ``<out>.partial`` is ``path``)."""
    import shlex

    st = export_progress(path)
    if st is None or st.complete:
        return None
    head = (f"{shown}: not written yet — the export was interrupted; its working store {path} holds"
            if shown is not None else f"{path}: an interrupted umi-aug export, not complete: it holds")
    failed = f", {st.n_failed} failed" if st.n_failed else ""
    if st.command:
        where = f" (run in {st.cwd})" if st.cwd and Path(st.cwd) != Path.cwd() else ""
        how = f"resume it with `{shlex.join(st.command)}`{where}"
    else:
        how = ("resume it by rerunning the `umi-aug augment` command that wrote it (the same input, --out and flags, "
               "without --restart)")
    return (f"{head} {st.n_episodes} of the {st.planned} planned episodes ({st.n_original} original + "
            f"{st.n_episodes - st.n_original} augmented; {st.jobs_done} of {st.n_jobs} augmentation jobs "
            f"finished{failed}); {how}: it continues after the last finished job")


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


def _job_task(args) -> _JobResult:
    """One export job (top-level, picklable: runs in this process or on an executor's worker): plan (or load the
    cached plan), then render the new frames — and the replayed ones too when they cannot be copied raw."""
    assets, j, job, key, raw_ok, overlay_cache, obstacle_tiles = args
    d, m, a = job
    t_scene = time.perf_counter()
    assets = assets.for_demo(d)  # the demo's scene (a source may build it here, on first use)
    scene_s = time.perf_counter() - t_scene
    if assets.demos[d].contact_index is None:  # known only once a lazily built group has run its contact stage
        return _JobResult(j, None, 0, [f"scene: {assets.demos[d].name} has no splice frame (no contact frame, or "
                                       f"none with the pre-grasp clearance); not augmented"], None, False,
                          0.0, 0.0, scene_s)
    t0 = time.perf_counter()
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
                                       obstacle_tiles=obstacle_tiles)
    return _JobResult(j, planned, attempts, reasons, frames, copy_tail, t1 - t0, time.perf_counter() - t1, scene_s)


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


IMAGE_KEY = "camera0_rgb"


def _raw_copy_ok(dst_arr, src_arr) -> bool:
    """Chunks of ``src_arr`` can be copied byte for byte into ``dst_arr`` (one frame per chunk, the same codec up
    to encoder-only settings)."""
    return (dst_arr.chunks == src_arr.chunks and dst_arr.chunks[0] == 1 and dst_arr.dtype == src_arr.dtype
            and dst_arr.shape[1:] == src_arr.shape[1:] and dst_arr.filters == src_arr.filters
            and dst_arr.compressor is not None and src_arr.compressor is not None
            and _decoder_config(dst_arr.compressor) == _decoder_config(src_arr.compressor))


def _decoder_config(codec) -> dict:
    """A codec's config without the encoder-only keys (JPEG-XL ``effort``)."""
    from umi_aug.data.codecs import JPEGXL_CODEC_ID

    cfg = dict(codec.get_config())
    if cfg.get("id") == JPEGXL_CODEC_ID:
        for k in ENCODER_ONLY_JPEGXL_KEYS:
            cfg.pop(k, None)
    return cfg


def append_episode(buf, lowdim: dict[str, np.ndarray], new_frames: np.ndarray, src_arr, src_rows: np.ndarray,
                   encoded: list | None = None) -> float:
    """Append one episode like :meth:`ReplayBuffer.add_episode` (data first, ``meta/episode_ends`` LAST): the
    ``new_frames`` [n, S, S, 3] are encoded, the tail frames are the source array's rows ``src_rows`` copied as
    stored (compressed chunks, no decode/re-encode; a chunk missing in the source is the fill value there and is
    left missing here). ``encoded``: the new frames' chunks already encoded (futures of
    :meth:`umi_aug.augment.encode.FrameEncoder.submit`; the same bytes) — otherwise zarr encodes them here
    (the reference path). Returns the seconds spent encoding on the encoder's threads (0 on the reference path)."""
    keys = sorted([*lowdim, IMAGE_KEY])
    if keys != buf.keys():
        raise AugmentError(f"{buf.name}: episode keys {keys} differ from the dataset's {buf.keys()}")
    n, m = len(new_frames), len(src_rows)
    L = n + m
    for k, v in lowdim.items():
        arr = buf[k]
        v = np.asarray(v)
        if len(v) != L or v.shape[1:] != arr.shape[1:] or v.dtype != arr.dtype:
            raise AugmentError(f"{buf.name}: key 'data/{k}': expected ({L}, {arr.shape[1:]}) {arr.dtype}, got "
                               f"{v.shape} {v.dtype}")
        if v.dtype.kind == "f" and not np.isfinite(v).all():
            raise AugmentError(f"{buf.name}: key 'data/{k}' of the new episode holds NaN/Inf")
    old = buf.n_steps
    for k, v in lowdim.items():
        arr = buf[k]
        arr.resize((old + L,) + arr.shape[1:])
        arr[old:old + L] = v
    img = buf[IMAGE_KEY]
    img.resize((old + L,) + img.shape[1:])
    enc_s = 0.0
    if n and encoded is not None:
        enc_s = write_encoded(img, old, encoded)
    elif n:
        img[old:old + n] = new_frames
    dst_store, src_store = img.store, src_arr.store
    for i, r in enumerate(np.asarray(src_rows, dtype=np.int64)):
        skey = src_arr._chunk_key((int(r),) + (0,) * (src_arr.ndim - 1))
        dkey = img._chunk_key((old + n + i,) + (0,) * (img.ndim - 1))
        try:
            dst_store[dkey] = src_store[skey]
        except KeyError:
            if dkey in dst_store:
                del dst_store[dkey]
    buf._commit_episode_end(old + L)
    return enc_s


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
            tiles where the obstacle shows.
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
        raise AugmentError(_disk_full_message(exc, writing, _working_path(out))) from exc
    finally:
        if not work_existed:  # the lock made it: a run stopped by an up-front check leaves no empty <out>.work/
            with contextlib.suppress(OSError):
                work.rmdir()  # only when empty (a stage wrote nothing); never anything else


#: errno of a full disk / an exhausted quota.
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def _disk_full_message(exc: OSError, writing: dict, wpath: Path) -> str:
    """One line for a full disk: the path being written (the file when the error names one), the free space left on
    its file system, and what is kept — the export's episodes written so far, from its own records."""
    import shutil

    path = Path(exc.filename) if exc.filename else Path(writing["path"])
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = f"{_human_bytes(shutil.disk_usage(probe).free)} free on it"
    except OSError:
        free = "free space unknown"
    st = export_progress(wpath)
    kept = (f"{st.n_episodes} of the {st.planned} planned episodes are written and kept in {wpath}" if st is not None
            else "nothing half-written is kept")
    return (f"{path}: disk full while writing {writing['what']} ({exc.strerror or 'No space left on device'}; "
            f"{free}); {kept}: free some space (or choose --out/--work on another disk) and rerun the same command "
            f"to resume")


def _human_bytes(n: float) -> str:
    from umi_aug.io_utils import _human

    return _human(n)


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
    for what, p in (("--out", out), ("--out", _working_path(out)), ("--work", work)):
        if is_inside(src, p) or (src.is_dir() and is_inside(p, src) and any(is_inside(p, r) for r in reads)):
            raise AugmentError(f"{what} {p}: is, contains or lies inside the input {src}; umi-aug never writes "
                               f"into or deletes its inputs: choose another {what}")


def _is_own_export(p: Path, wpath: Path) -> bool:
    """True when ``p`` is an umi-aug export (its root attribute ``umi_aug_export``), or umi-aug's working store
    ``<out>.partial`` holding nothing but zarr groups (a half-deleted one)."""
    from umi_aug.data.store import close_store, open_store

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
    import glob
    import re

    pat = re.compile(re.escape(out.name) + r"(\.partial)?\.tmp-[0-9a-f]{8}")
    for p in out.parent.glob(glob.escape(out.name) + "*.tmp-*") if out.parent.is_dir() else []:
        if pat.fullmatch(p.name):
            log.info("export: removing %s (left by an interrupted run)", p)
            remove_tree_atomically(p)


def _expected_bytes(src: Path, n_jobs_max: int, n_src_eps: int, include_original: bool) -> int:
    """About the bytes of the output: the input dataset's bytes per episode x the episodes written."""
    per_ep = tree_size(src) / max(1, n_src_eps)
    return int(per_ep * (n_jobs_max + (n_src_eps if include_original else 0)))


def _export(src: InputSource, out: Path, work: Path, cfg: AugmentConfig, *, resume: bool, progress: bool,
            pictures: bool, fast: frozenset = frozenset(), encode_threads: int | None = None,
            command: list[str] | None = None, writing: dict | None = None) -> ExportSummary:
    from tqdm import tqdm

    t_start = time.perf_counter()
    src.check(cfg.image_size)  # every input, before anything is removed or computed: one error naming the key
    key = _run_key(cfg, src.fingerprint())
    src_ds = Path(src.dataset)
    n_src = _n_episodes(src_ds)
    n_aug = src.n_augment(n_src)
    wpath = _working_path(out)
    _remove_leftover_temporaries(out)
    if not resume:
        _discard_previous(out, wpath)
    finished = False
    if out.name.endswith(".zip") and out.exists():  # checked before any stage runs: a mismatch costs nothing
        stored = _stored_key(out)
        if stored != key:
            raise AugmentError(_not_this_runs_output(out, stored, key))
        finished = True
        if wpath.exists():  # killed during the final clean-up: the output is complete, the working copy is left
            log.warning("export: %s is complete; removing the leftover working store %s", out, wpath)
            remove_tree_atomically(wpath)
    elif wpath.exists() and _stored_key(wpath) != key:
        raise AugmentError(_not_this_runs_output(wpath, _stored_key(wpath), key))
    if not finished:  # before minutes of compute: the output (and a .zip's working copy) must fit
        need = _expected_bytes(src_ds, n_aug * len(cfg.modes) * cfg.n_per_demo, n_src, cfg.include_original)
        need = need * (2 if out.name.endswith(".zip") else 1) - tree_size(wpath)
        check_free_space(out, need, f"writing {out.name} (about {n_aug * len(cfg.modes) * cfg.n_per_demo} new "
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
        _create_store(wpath, assets, key, len(jobs))
    buf, attrs = _open_store(wpath, key)
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
        raw_ok = IMAGE_KEY in buf and _raw_copy_ok(buf[IMAGE_KEY], src_img)
        if not raw_ok:
            log.info("export: replayed frames are re-encoded (the output's image codec/chunks differ from the "
                     "session dataset's)")
        t_loop = time.perf_counter()
        bar = tqdm(total=len(jobs), initial=start, desc="augment", unit="episode", disable=not progress,
                   dynamic_ncols=True)
        overlay_cache, obstacle_tiles = "overlay_cache" in fast, "obstacle_tiles" in fast
        tasks = ((assets, j, jobs[j], key, raw_ok, overlay_cache, obstacle_tiles) for j in range(start, len(jobs)))
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
                _add_records(buf, {"aug_source_episode": d, "aug_mode": MODE_CODES[m], "aug_id": a,
                                   "aug_seed": planned.seed, "aug_attempts": planned.attempts,
                                   "aug_splice_index": planned.splice_index, "aug_job": j})
                ep = planned.episode
                rows = np.zeros(0, np.int64)
                if res.copy_tail:  # replayed frames: the original compressed chunks
                    r0 = assets.original.get_episode_slice(d).start + int(ep.source_contact_index)
                    rows = np.arange(r0, r0 + planned.n_frames - planned.splice_index)
                timings["encode_s"] += append_episode(buf, assets.umi_episode(ep, d), res.frames, src_img, rows,
                                                      encoded)
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
                for res in map_ordered(_job_task, tasks, executor=cfg.executor, workers=cfg.workers,
                                       address=cfg.ray_address):
                    timings["scene_s"] += res.scene_s
                    timings["plan_s"] += res.plan_s
                    timings["render_s"] += res.render_s
                    while pending:
                        commit(*pending.pop(0))
                    if encoder is not None and res.planned is not None and res.frames is not None:
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
        from umi_aug.data import ReplayBuffer

        t0 = time.perf_counter()
        writing.update(path=out, what="the .zarr.zip")
        with ReplayBuffer.open(wpath) as final:
            final.save(out)
        remove_tree_atomically(wpath)  # a kill here leaves <out>.partial.tmp-*, never a half-deleted .partial
        timings["write_s"] += time.perf_counter() - t0
    writing.update(path=out.parent, what=f"the summary and pictures of {out.name}")
    return _finish(out, work, assets, key, jobs, resumed, t_start, timings, frames_rendered, pictures, read_from=out,
                   loop_s=time.perf_counter() - t_start)


def _n_episodes(path: Path) -> int:
    """Episodes of a UMI dataset (``meta/episode_ends``, read raw)."""
    from umi_aug.data.store import close_store, open_store

    store, root = open_store(path, mode="r")
    try:
        return int(root["meta/episode_ends"].shape[0])
    except (KeyError, ValueError) as exc:
        raise AugmentError(f"{path}: no readable key 'meta/episode_ends' ({exc})") from exc
    finally:
        close_store(store)


def _status_of(reason: str) -> str:
    """``"attempt 3: collision: ..."`` → ``"collision"``."""
    parts = reason.split(":")
    return parts[1].strip() if len(parts) > 1 else reason


def read_episode_records(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The per-episode records (``meta/aug_*``, each ``[E]``) of an exported dataset."""
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(path) as buf:
        missing = [k for k in RECORD_KEYS if k not in set(buf.meta.array_keys())]
        if missing:
            raise AugmentError(f"{path}: no per-episode records {missing} in meta/ (not an umi-aug export)")
        return {k: np.asarray(buf.meta[k][:]) for k in RECORD_KEYS}


def _finish(out: Path, work: Path, assets: SessionAssets, key: str, jobs, resumed: int, t_start: float,
            timings: dict, frames_rendered: int, pictures: bool, read_from: Path, loop_s: float = 0.0
            ) -> ExportSummary:
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(read_from) as buf:
        attrs = dict(buf.root.attrs.get(ATTR, {}))
        rec = {k: np.asarray(buf.meta[k][:]) for k in RECORD_KEYS}
        n_orig = int((rec["aug_mode"] == 0).sum())
        aug = rec["aug_mode"] > 0
        failures = list(attrs.get("failures", []))
        counts = dict(attrs.get("attempt_failures", {}))
        pics = {}
        t0 = time.perf_counter()
        if pictures:
            pics = _pictures(out, assets, buf, rec, key, jobs)
        timings["pictures_s"] = time.perf_counter() - t0
    done_now = len(jobs) - resumed
    total = time.perf_counter() - t_start
    timings["total_s"] = total
    summary = ExportSummary(
        out_path=str(out), work_dir=str(work), n_original=n_orig, n_augmented=int(aug.sum()),
        n_failed=len(failures), n_resampled=int((rec["aug_attempts"][aug] - 1).sum()), n_jobs=len(jobs),
        resumed_jobs=resumed, status_counts=dict(counts),
        stages={k: {"seconds": round(v.seconds, 3), "skipped": v.skipped} for k, v in assets.stages.items()},
        timings_s={k: round(v, 3) for k, v in timings.items()}, frames_rendered=frames_rendered,
        episodes_per_s=round(done_now / loop_s, 4) if loop_s > 0 else 0.0, pictures=pics, failures=failures)
    atomic_write_text(out.with_name(out.name + ".summary.json"), json.dumps(asdict(summary), indent=2) + "\n")
    return summary


class _EpisodeFrames:
    """One episode's frames of a zarr image array, decoded on access: a contact sheet shows 7 of an episode's
    hundreds of frames (decoding them all took most of a real episode's picture time)."""

    def __init__(self, arr, sl: slice) -> None:
        self.arr, self.start, self.n = arr, int(sl.start), int(sl.stop - sl.start)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k: int) -> np.ndarray:
        if not -self.n <= int(k) < self.n:
            raise IndexError(f"frame {k} of an episode of {self.n}")
        return self.arr[self.start + int(k) % self.n]


def _pictures(out: Path, assets: SessionAssets, buf, rec: dict, key: str, jobs) -> dict:
    from umi_aug.augment.pictures import contact_sheet
    from umi_aug.traj import plot_trajectories

    pics = {}
    E = buf.n_episodes
    orig = [i for i in range(E) if rec["aug_mode"][i] == 0][:2]
    augm = [i for i in range(E) if rec["aug_mode"][i] > 0][:6]
    rows = orig + augm
    if rows:
        frames = [_EpisodeFrames(buf["camera0_rgb"], buf.get_episode_slice(i)) for i in rows]
        splice = [int(rec["aug_splice_index"][i]) if rec["aug_splice_index"][i] >= 0 else len(f) - 1
                  for i, f in zip(rows, frames)]
        inv = {v: k for k, v in MODE_CODES.items()}
        names = [f"{inv[int(rec['aug_mode'][i])]} d{int(rec['aug_source_episode'][i])}"
                 + (f" a{int(rec['aug_id'][i])}" if rec["aug_id"][i] >= 0 else "") for i in rows]
        pics["contact_sheet"] = str(contact_sheet(frames, out.with_name(out.name + ".contact_sheet.png"),
                                                  splice_indices=splice, row_names=names))
    for d in assets.augmentable:
        eps = []
        for job in jobs:
            if job[0] == d:
                p = _plan_cache_path(assets, job, key)
                pl = _load_planned(p) if p.exists() else None
                if pl is not None:
                    eps.append(pl.episode)
        if eps:
            name = assets.demos[d].name
            path = out.with_name(f"{out.name}.trajectories_{name}.png")
            pics[f"trajectories/{name}"] = str(plot_trajectories(
                path, assets.for_demo(d).traj_problem(d), eps,
                title=f"{name}: {len(eps)} augmented trajectories ({assets.cfg.mode}; obstacles not drawn)"))
    return pics


def summary_table(summary: ExportSummary):
    """A ``rich.table.Table`` of the summary (episodes, failures, resampling, per-stage timings)."""
    from rich.table import Table

    t = Table(title=f"umi-aug augment → {summary.out_path}")
    t.add_column("item")
    t.add_column("value", justify="right")
    for k, v in [("original episodes", summary.n_original), ("augmented episodes", summary.n_augmented),
                 ("failed jobs", summary.n_failed), ("resampled attempts", summary.n_resampled),
                 ("jobs resumed", summary.resumed_jobs), ("new frames rendered", summary.frames_rendered),
                 ("episodes/s (this run)", summary.episodes_per_s)]:
        t.add_row(k, str(v))
    for k, v in summary.stages.items():
        t.add_row(f"stage {k}", "cached" if v["skipped"] else f"{v['seconds']:.1f} s")
    for k, v in summary.timings_s.items():
        t.add_row(k, f"{v:.2f}")
    for k, v in summary.status_counts.items():
        t.add_row(f"failed attempts: {k}", str(v))
    return t
