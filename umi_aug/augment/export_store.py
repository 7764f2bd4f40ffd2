"""The export's output store: a UMI replay buffer plus per-episode records, created, resumed and appended to.

Per-episode records are extra ``meta/`` arrays of length E (:data:`RECORD_KEYS`; UMI copies ``meta/`` whole and
never indexes it): the originals' records are written when the store is created, each augmented episode's before
its data (:func:`add_records`, then :func:`append_episode`, whose ``meta/episode_ends`` commit comes last).
Root attribute :data:`ATTR` holds the run key, the job list size, failures and progress (:func:`export_progress`).
"""

from __future__ import annotations

import json
import logging
import os
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from zarr.util import json_dumps

from umi_aug.augment.encode import write_encoded
from umi_aug.augment.plan import MODE_CODES
from umi_aug.augment.session_assets import SessionAssets
from umi_aug.data import ReplayBuffer, schema
from umi_aug.data.codecs import JPEGXL_CODEC_ID, umi_image_codec_from
from umi_aug.data.store import close_store, open_store
from umi_aug.errors import AugmentError, UmiAugError

__all__ = ["ATTR", "ExportProgress", "IMAGE_KEY", "RECORD_CHUNK", "RECORD_KEYS", "add_records", "append_episode",
           "count_episodes", "create_store", "export_progress", "interrupted_export_message", "not_this_runs_output",
           "open_export_store", "raw_copy_ok", "read_episode_records", "stored_key", "working_path"]

log = logging.getLogger(__name__)

#: Per-episode record arrays in ``meta/`` (name → dtype).
RECORD_KEYS: dict[str, str] = {"aug_source_episode": "int64", "aug_mode": "int8", "aug_id": "int64",
                               "aug_seed": "int64", "aug_attempts": "int16", "aug_splice_index": "int64",
                               "aug_job": "int64"}
#: Root attribute of the run's key, job count, failures and progress.
ATTR = "umi_aug_export"
#: Chunk length (episodes) of the record arrays.
RECORD_CHUNK = 1024
#: The image key an export writes (UMI's single-camera layout).
IMAGE_KEY = "camera0_rgb"
#: JPEG-XL codec parameters that only steer the encoder: chunks written with any value decode alike.
ENCODER_ONLY_JPEGXL_KEYS: frozenset[str] = frozenset({"effort"})
#: Frames read at once when an image array of another codec is re-encoded with UMI's JPEG-XL (~38 MB at 224²).
REENCODE_BLOCK = 256


def working_path(out: Path) -> Path:
    """The zarr directory an export to ``out`` writes into: ``out`` itself, or ``<out>.partial`` for a ``.zip``
    output (written whole at the end)."""
    return out.with_name(out.name + ".partial") if out.name.endswith(".zip") else out


def add_records(buf: ReplayBuffer, rows: dict[str, int]) -> None:
    """Grow every record array of ``buf`` by one row (``rows``: record name → value), before the episode's data."""
    meta = buf.meta
    for k, dt in RECORD_KEYS.items():
        a = meta[k]
        a.resize(a.shape[0] + 1)
        a[-1] = np.asarray(rows[k], dtype=dt)


def create_store(path: Path, assets: SessionAssets, key: str, n_jobs: int) -> None:
    """A new working store: the originals copied as stored + their records, in one atomic directory write."""
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


def _set_umi_image_codec(buf, effort: int | None) -> None:
    """Make every ``camera*_rgb`` array of ``buf`` store UMI's exact 12-key JPEG-XL codec config (``id`` + the 11
    parameters of UMI's ``JpegXl``; :func:`umi_aug.data.codecs.umi_image_codec_from`), whatever the source wrote:

    * a JPEG-XL config with other keys (newer imagecodecs' ``bitspersample``, ``squeeze``, ...) is rewritten in the
      array's ``.zarray`` (the stored chunks decode alike: those keys do not change the bitstream), with ``effort``
      (the encoder setting of every frame written from now on) when given;
    * an array of another codec (Blosc, uncompressed, ...) is re-encoded with UMI's ``JpegXl(level=99)``, in blocks
      of :data:`REENCODE_BLOCK` frames, one frame per chunk (lossy, as UMI's own images).

    UMI's reader rebuilds the codec as ``JpegXl(**config)``, so any key beyond its 11 parameters fails there."""
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


def open_export_store(path: Path, key: str):
    buf = ReplayBuffer.open(path, mode="a", repair=True)
    attrs = dict(buf.root.attrs.get(ATTR, {}))
    if attrs.get("key") != key:
        buf.close()
        raise AugmentError(not_this_runs_output(path, attrs.get("key"), key))
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


def not_this_runs_output(path: Path, stored: str | None, key: str) -> str:
    """The message for an existing ``--out`` (or its working store) that this run cannot resume: umi-aug's own
    export of another configuration (``--restart`` replaces it), or no umi-aug export at all (never touched)."""
    if stored is None:
        return (f"{path}: exists and is not an umi-aug export (no attribute '{ATTR}'; a dataset of yours?); "
                f"umi-aug never writes into it, and --restart deletes only umi-aug's own outputs: choose another "
                f"--out")
    return (f"{path}: an export of another configuration/session (attribute '{ATTR}.key' = {stored!r}, this run "
            f"{key!r}); rerun with --restart to replace it (it is umi-aug's own output), or choose another --out")


def stored_key(path: Path) -> str | None:
    """The run key stored in an export (directory store read raw: it may hold an interrupted append)."""
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


def raw_copy_ok(dst_arr, src_arr) -> bool:
    """Chunks of ``src_arr`` can be copied byte for byte into ``dst_arr`` (one frame per chunk, the same codec up
    to encoder-only settings)."""
    return (dst_arr.chunks == src_arr.chunks and dst_arr.chunks[0] == 1 and dst_arr.dtype == src_arr.dtype
            and dst_arr.shape[1:] == src_arr.shape[1:] and dst_arr.filters == src_arr.filters
            and dst_arr.compressor is not None and src_arr.compressor is not None
            and _decoder_config(dst_arr.compressor) == _decoder_config(src_arr.compressor))


def _decoder_config(codec) -> dict:
    """A codec's config without the encoder-only keys (JPEG-XL ``effort``)."""
    cfg = dict(codec.get_config())
    if cfg.get("id") == JPEGXL_CODEC_ID:
        for k in ENCODER_ONLY_JPEGXL_KEYS:
            cfg.pop(k, None)
    return cfg


def append_episode(buf, lowdim: dict[str, np.ndarray], new_frames: np.ndarray | None, src_arr, src_rows: np.ndarray,
                   encoded: list | None = None) -> float:
    """Append one episode like :meth:`ReplayBuffer.add_episode` (data first, ``meta/episode_ends`` LAST): the
    ``new_frames`` [n, S, S, 3] are encoded, the tail frames are the source array's rows ``src_rows`` copied as
    stored (compressed chunks, no decode/re-encode; a chunk missing in the source is the fill value there and is
    left missing here). ``encoded``: the new frames' chunks already encoded (futures of
    :meth:`umi_aug.augment.encode.FrameEncoder.submit`, or ``(bytes, seconds)`` pairs made by an episode task;
    the same bytes; ``new_frames`` may then be None) — otherwise zarr encodes them here (the reference path).
    Returns the seconds spent encoding on the encoder's threads or in the task (0 on the reference path)."""
    keys = sorted([*lowdim, IMAGE_KEY])
    if keys != buf.keys():
        raise AugmentError(f"{buf.name}: episode keys {keys} differ from the dataset's {buf.keys()}")
    n, m = len(encoded) if encoded is not None else len(new_frames), len(src_rows)
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


def count_episodes(path: Path) -> int:
    """Episodes of a UMI dataset (``meta/episode_ends``, read raw)."""
    store, root = open_store(path, mode="r")
    try:
        return int(root["meta/episode_ends"].shape[0])
    except (KeyError, ValueError) as exc:
        raise AugmentError(f"{path}: no readable key 'meta/episode_ends' ({exc})") from exc
    finally:
        close_store(store)


def read_episode_records(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The per-episode records (``meta/aug_*``, each ``[E]``) of an exported dataset."""
    with ReplayBuffer.open(path) as buf:
        missing = [k for k in RECORD_KEYS if k not in set(buf.meta.array_keys())]
        if missing:
            raise AugmentError(f"{path}: no per-episode records {missing} in meta/ (not an umi-aug export)")
        return {k: np.asarray(buf.meta[k][:]) for k in RECORD_KEYS}


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
