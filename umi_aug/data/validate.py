"""Validate a UMI replay buffer (zarr root with ``data/`` and ``meta/episode_ends``).

Each malformed case raises one :class:`~umi_aug.errors.DatasetError` naming the file and the key;
harmless deviations from UMI's layout (chunks, dtypes) become warnings in the report.

Chunks: the listing of every ``data/*`` array is checked to be complete (a missing chunk silently reads as the
fill value: black frames); ``deep=True`` also decodes every chunk (a garbage chunk raises there, naming the
chunk and its rows, instead of an anonymous codec traceback in training).
"""

from __future__ import annotations

import itertools
import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr
from tqdm import tqdm

from umi_aug.data import schema
from umi_aug.data.codecs import register_codecs
from umi_aug.data.store import close_store, open_store
from umi_aug.errors import DatasetError

#: Gripper width range (m) a UMI dataset may hold: UMI's gripper opens about 0.09 m, a WSG-50 0.11 m; a width
#: below 0 or above this maximum is a unit or calibration error (mm instead of m, a wrong tag offset).
GRIPPER_WIDTH_MIN_M, GRIPPER_WIDTH_MAX_M = 0.0, 0.2
#: Consecutive steps whose TCP moves at most ``FROZEN_STEP_M`` and turns at most ``FROZEN_ANGLE_RAD`` are "the
#: same pose" (exact equality missed poses whose round-off turns them by 1e-8 rad); ``FROZEN_MIN_STEPS`` of them in
#: a row is a held pose of lost tracking. A hand-held camera at 60 fps moves far more than this per frame.
FROZEN_STEP_M, FROZEN_ANGLE_RAD, FROZEN_MIN_STEPS = 1e-6, 1e-5, 8
#: Keys of every arm a UMI policy reads (``UmiDataset``'s low-dim obs); one camera key at least.
UMI_ROBOT_KEYS = ("eef_pos", "eef_rot_axis_angle", "gripper_width")

_REPAIR_HINT = ("extra trailing data beyond episode_ends[-1] (an interrupted append?); `umi-aug repair {name} --out "
                "<new path>` writes a copy cut back to the last complete episode (this one is not changed)")


@dataclass(frozen=True)
class ArrayInfo:
    """Layout of one ``data/*`` array: shape, dtype string, chunks and compressor codec id (None = raw)."""

    shape: tuple[int, ...]
    dtype: str
    chunks: tuple[int, ...]
    compressor: str | None


@dataclass
class ValidationReport:
    """Result of :func:`validate_replay_buffer`: episode/step counts, per-key layout, warnings."""

    n_episodes: int
    n_steps: int
    keys: dict[str, ArrayInfo] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def _codec_ids(group: zarr.Group, key: str) -> str:
    """Codec ids named in ``<group>/<key>/.zarray`` (compressor and filters), read without numcodecs."""
    prefix = f"{group.path}/" if group.path else ""
    try:
        meta = json.loads(group.store[f"{prefix}{key}/.zarray"])
    except Exception:  # noqa: BLE001 - best effort, only for the message
        return "?"
    ids = [c.get("id") for c in [meta.get("compressor")] + list(meta.get("filters") or []) if c]
    return ", ".join(repr(i) for i in ids) or "none"


def _bad_metadata(group: zarr.Group, key: str) -> str | None:
    """Why ``<group>/<key>/.zarray`` is unusable (missing, not JSON, not an object), or None."""
    prefix = f"{group.path}/" if group.path else ""
    try:
        raw = group.store[f"{prefix}{key}/.zarray"]
    except KeyError:
        return "is missing"
    try:
        meta = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        return f"is not valid JSON ({exc})"
    return None if isinstance(meta, dict) else f"holds a {type(meta).__name__}, not a JSON object"


def open_array(group: zarr.Group, key: str, name: str) -> zarr.Array:
    """``group[key]``, turning numcodecs' unknown-codec error into a DatasetError naming key and codec."""
    where = f"{group.path}/{key}" if group.path else key
    try:
        return group[key]
    except Exception as exc:  # numcodecs UnknownCodecError (a ValueError), bad metadata, ...
        bad_meta = _bad_metadata(group, key)
        if bad_meta:
            raise DatasetError(f"{name}: key '{where}': its metadata file '{where}/.zarray' {bad_meta}; the "
                               "dataset is damaged: re-copy or re-create it") from exc
        ids = _codec_ids(group, key)
        raise DatasetError(
            f"{name}: key '{where}' cannot be opened: codec {ids} is not available ({type(exc).__name__}: "
            f"{exc}). Install and register it with numcodecs (for 'imagecodecs_jpegxl' call "
            "umi_aug.data.register_codecs(); other imagecodecs_* ids need the imagecodecs package and "
            "imagecodecs.numcodecs.register_codecs())"
        ) from exc


def check_episode_ends(ends: np.ndarray, name: str) -> None:
    """Raise unless ``ends`` (E,) is 1-D integer, strictly increasing with a positive first entry."""
    where = f"{name}: key 'meta/{schema.EPISODE_ENDS}'"
    if ends.ndim != 1 or not np.issubdtype(ends.dtype, np.integer):
        raise DatasetError(f"{where} must be a 1-D integer array (UMI: int64, shape (E,)), got "
                           f"shape {ends.shape} dtype {ends.dtype}")
    if ends.size and ends[0] <= 0:
        raise DatasetError(f"{where}: first episode end must be > 0, got {int(ends[0])}")
    bad = np.flatnonzero(np.diff(ends) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        last = (f"; a half-written last entry (an interrupted append?): `umi-aug repair {name} --out <new path>` "
                "writes a copy without it (this one is not changed)") if i == ends.size - 1 else ""
        raise DatasetError(f"{where} must be strictly increasing: episode_ends[{i}] = {int(ends[i])} <= "
                           f"episode_ends[{i - 1}] = {int(ends[i - 1])}{last}")


def first_nonfinite_row(values: np.ndarray) -> int | None:
    """Index of the first row (along axis 0) holding NaN/Inf, or None (non-float arrays: None)."""
    if not np.issubdtype(values.dtype, np.floating) or values.shape[0] == 0:
        return None
    ok = np.isfinite(values.reshape(values.shape[0], -1)).all(axis=1)
    return None if ok.all() else int(np.argmin(ok))


def _check_data_array(key: str, arr: zarr.Array, n_steps: int, name: str, check_values: bool,
                      warnings: list[str]) -> None:
    where = f"{name}: key 'data/{key}'"
    if arr.ndim == 0 or arr.shape[0] != n_steps:
        length = arr.shape[0] if arr.ndim else "scalar"
        longer = arr.ndim and arr.shape[0] > n_steps
        hint = _REPAIR_HINT.format(name=name) if longer else "missing rows: the buffer is truncated or corrupt"
        raise DatasetError(f"{where} has length {length} but episode_ends[-1] = {n_steps}: {hint}")
    if schema.is_image_key(key):
        if arr.ndim != 4 or arr.shape[-1] != 3:
            raise DatasetError(f"{where} must have shape (N, H, W, 3) (RGB images), got {arr.shape}")
        if arr.dtype != np.uint8:
            raise DatasetError(f"{where} must have dtype uint8, got {arr.dtype}")
        if tuple(arr.chunks) != (1,) + tuple(arr.shape[1:]):
            warnings.append(f"{where}: chunks {arr.chunks} differ from UMI's one-frame chunks "
                            f"{(1,) + tuple(arr.shape[1:])}")
        return
    step_shape = schema.pose_key_shape(key)
    if key == schema.ACTION_KEY:
        if arr.ndim != 2 or arr.shape[1] < 7 or arr.shape[1] % 7:
            raise DatasetError(f"{where} (commanded targets) must have shape (N, 7·R): per arm pos(3), rotvec(3), "
                               f"gripper width; got {arr.shape}")
        step_shape = tuple(arr.shape[1:])
    if step_shape is None:
        return
    if tuple(arr.shape[1:]) != step_shape:
        raise DatasetError(f"{where} must have shape (N, {', '.join(map(str, step_shape))}), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        warnings.append(f"{where}: dtype {arr.dtype} is not floating point (UMI writes float32/float64)")
    if check_values:
        row = first_nonfinite_row(arr[:])
        if row is not None:
            raise DatasetError(f"{where} holds NaN/Inf, first at row {row}: {arr[row].tolist()}")


def expected_chunk_keys(arr: zarr.Array) -> list[str]:
    """Store keys (relative to the array) of every chunk of ``arr``, in row order."""
    grid = [range(-(-s // c)) for s, c in zip(arr.shape, arr.chunks)]
    sep = getattr(arr, "_dimension_separator", None) or "."
    return [sep.join(map(str, idx)) for idx in itertools.product(*grid)]


def _stored_chunk_keys(arr: zarr.Array) -> set[str]:
    prefix = f"{arr.path}/" if arr.path else ""
    store = arr.chunk_store if arr.chunk_store is not None else arr.store
    listdir = getattr(store, "listdir", None)
    if callable(listdir) and "/" not in (getattr(arr, "_dimension_separator", None) or "."):
        try:
            return set(listdir(arr.path))
        except Exception:  # noqa: BLE001 - fall back to the full key listing
            pass
    return {k[len(prefix):] for k in store.keys() if k.startswith(prefix)}


def _plain(v) -> str:
    return repr(v.item() if isinstance(v, np.generic) else v)


def check_chunk_listing(key: str, arr: zarr.Array, name: str) -> None:
    """Raise when a chunk of ``data/<key>`` is missing from the store (the listing only; nothing is decoded)."""
    if arr.ndim == 0 or arr.shape[0] == 0:
        return
    stored = _stored_chunk_keys(arr)
    expected = expected_chunk_keys(arr)
    missing = [k for k in expected if k not in stored]
    if missing:
        row = int(missing[0].replace("/", ".").split(".")[0]) * arr.chunks[0]
        raise DatasetError(f"{name}: key 'data/{key}': {len(missing)} of {len(expected)} chunks missing, first "
                           f"'{missing[0]}' (rows {row}..{min(row + arr.chunks[0], arr.shape[0]) - 1}); they would "
                           f"read as fill value {_plain(arr.fill_value)} (black frames / zeros). The dataset is "
                           f"truncated or was copied incompletely: re-copy or re-create it")


def decode_all_chunks(key: str, arr: zarr.Array, name: str, progress: bool = False) -> int:
    """Decode every chunk of ``data/<key>`` (one row block at a time); raise naming the first bad chunk.

    Returns the number of chunks decoded.
    """
    c0 = arr.chunks[0]
    n = -(-arr.shape[0] // c0) if arr.ndim else 0
    for i in tqdm(range(n), desc=f"decode data/{key}", unit="chunk", disable=not progress, leave=False,
                  dynamic_ncols=True):
        try:
            arr[i * c0:(i + 1) * c0]
        except Exception as exc:  # codec errors are of many types (imagecodecs, numcodecs, zlib, ValueError)
            last = min((i + 1) * c0, arr.shape[0]) - 1
            raise DatasetError(f"{name}: key 'data/{key}': chunk {i} (rows {i * c0}..{last}) "
                               f"cannot be decoded ({type(exc).__name__}: {exc}); the chunk is corrupt: re-copy "
                               f"or re-create the dataset") from exc
    return n


def relative_turn_rad(rotvec: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between consecutive rotation vectors ``rotvec`` [T, 3] → [T-1], accurate near 0
    (``atan2(|sin|, cos)`` of the relative rotation, not ``arccos`` of its trace)."""
    from scipy.spatial.transform import Rotation  # lazy, start-up: scipy

    R = Rotation.from_rotvec(np.asarray(rotvec, np.float64)).as_matrix()
    R_rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    skew = np.stack([R_rel[:, 2, 1] - R_rel[:, 1, 2], R_rel[:, 0, 2] - R_rel[:, 2, 0],
                     R_rel[:, 1, 0] - R_rel[:, 0, 1]], axis=1)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=1), 0.5 * (np.trace(R_rel, axis1=1, axis2=2) - 1.0))


def first_frozen_step(pos: np.ndarray, rotvec: np.ndarray, min_steps: int = FROZEN_MIN_STEPS) -> int | None:
    """First step of ``min_steps`` consecutive steps between identical poses (within :data:`FROZEN_STEP_M` /
    :data:`FROZEN_ANGLE_RAD`) in one episode's ``pos`` [T, 3] (m) and ``rotvec`` [T, 3] (rad), or None."""
    pos = np.asarray(pos, np.float64)
    if len(pos) < min_steps + 1:
        return None
    same = (np.linalg.norm(np.diff(pos, axis=0), axis=1) <= FROZEN_STEP_M) & \
        (relative_turn_rad(rotvec) <= FROZEN_ANGLE_RAD)
    run = np.convolve(same.astype(int), np.ones(min_steps, int), mode="valid")
    hit = np.flatnonzero(run == min_steps)
    return int(hit[0]) if hit.size else None


def gripper_width_problem(widths: np.ndarray, ends: np.ndarray) -> str | None:
    """``"= -0.03 m at row 12 (episode 1) is outside the gripper's range …"`` when a width of ``widths``
    [N] or [N, 1] (m) lies outside [:data:`GRIPPER_WIDTH_MIN_M`, :data:`GRIPPER_WIDTH_MAX_M`], else None."""
    w = np.asarray(widths, np.float64).reshape(len(widths), -1)[:, 0]
    bad = np.flatnonzero((w < GRIPPER_WIDTH_MIN_M) | (w > GRIPPER_WIDTH_MAX_M))
    if not bad.size:
        return None
    i = int(bad[0])
    e = int(np.searchsorted(np.asarray(ends), i, side="right"))
    return (f"= {w[i]:.6g} m at row {i} (episode {e}) is outside the gripper's range [{GRIPPER_WIDTH_MIN_M}, "
            f"{GRIPPER_WIDTH_MAX_M}] m ({bad.size} of {len(w)} rows, range {np.nanmin(w):.6g}..{np.nanmax(w):.6g} m); "
            "widths are metres between the fingers: a unit (mm?) or gripper-calibration error — re-create the "
            "dataset")


def check_umi_values(data: zarr.Group, ends: np.ndarray, name: str, warnings: list[str]) -> None:
    """UMI's physical rules, beyond the layout: every arm's required keys present, gripper widths within
    [:data:`GRIPPER_WIDTH_MIN_M`, :data:`GRIPPER_WIDTH_MAX_M`] (errors), no episode whose pose is frozen
    (a warning: lost tracking held the last pose)."""
    keys = set(data.array_keys())
    robots = sorted({k.split("_", 1)[0] for k in keys if k.startswith("robot") and schema.pose_key_shape(k)}) \
        or ["robot0"]
    missing = [f"{r}_{k}" for r in robots for k in UMI_ROBOT_KEYS if f"{r}_{k}" not in keys]
    if not any(schema.is_image_key(k) for k in keys):
        missing.append("camera0_rgb")
    if missing:
        raise DatasetError(f"{name}: required key(s) {', '.join(repr('data/' + m) for m in missing)} missing; a UMI "
                           f"dataset holds {', '.join(f'robot<i>_{k}' for k in UMI_ROBOT_KEYS)} for every arm and "
                           "camera<j>_rgb frames (UMI's 07_generate_replay_buffer.py writes them all)")
    starts = np.concatenate([[0], ends[:-1]]).astype(int)
    for r in robots:
        key = f"{r}_gripper_width"
        problem = gripper_width_problem(data[key][:], ends)
        if problem:
            raise DatasetError(f"{name}: key 'data/{key}' {problem}")
        pos = np.asarray(data[f"{r}_eef_pos"][:], np.float64)
        rot = np.asarray(data[f"{r}_eef_rot_axis_angle"][:], np.float64)
        for e, (a, b) in enumerate(zip(starts, ends)):
            i = first_frozen_step(pos[a:b], rot[a:b])
            if i is not None:
                warnings.append(f"{name}: episode {e}: keys 'data/{r}_eef_pos'/'{r}_eef_rot_axis_angle' are "
                                f"frozen (the same pose within {FROZEN_STEP_M} m / {FROZEN_ANGLE_RAD} rad) from "
                                f"step {i} for >= {FROZEN_MIN_STEPS} steps (row {a + i}): tracking lost and the "
                                "last pose held? augment refuses such an episode")
                break


def _validate_root(root: zarr.Group, name: str, check_values: bool, deep: bool = False,
                   progress: bool = False, umi: bool = False) -> ValidationReport:
    groups = set(root.group_keys())
    for g in (schema.DATA_GROUP, schema.META_GROUP):
        if g not in groups:
            raise DatasetError(f"{name}: missing group '{g}/' (a UMI replay buffer has data/ and meta/ groups)")
    meta, data = root[schema.META_GROUP], root[schema.DATA_GROUP]
    if schema.EPISODE_ENDS not in set(meta.array_keys()):
        raise DatasetError(f"{name}: missing key 'meta/{schema.EPISODE_ENDS}' (int64 (E,) episode end indices)")
    ends = open_array(meta, schema.EPISODE_ENDS, name)[:]
    check_episode_ends(ends, name)
    warnings: list[str] = []
    if ends.dtype != np.int64:
        warnings.append(f"{name}: key 'meta/{schema.EPISODE_ENDS}' has dtype {ends.dtype}, UMI writes int64")
    n_steps = int(ends[-1]) if ends.size else 0
    if not ends.size:
        warnings.append(f"{name}: no episodes (meta/{schema.EPISODE_ENDS} is empty)")
    for sub in sorted(data.group_keys()):
        warnings.append(f"{name}: 'data/{sub}' is a group; UMI expects only arrays in data/")
    report = ValidationReport(n_episodes=int(ends.size), n_steps=n_steps, warnings=warnings)
    for key in sorted(data.array_keys()):
        arr = open_array(data, key, name)
        _check_data_array(key, arr, n_steps, name, check_values, warnings)
        try:
            check_chunk_listing(key, arr, name)
        except DatasetError as exc:
            if schema.is_image_key(key):
                raise
            warnings.append(f"{exc} (a zarr written with write_empty_chunks=False leaves all-fill chunks out)")
        if deep:
            decode_all_chunks(key, arr, name, progress)
        report.keys[key] = ArrayInfo(tuple(arr.shape), str(arr.dtype), tuple(arr.chunks),
                                     arr.compressor.codec_id if arr.compressor is not None else None)
    if umi and ends.size:
        check_umi_values(data, ends, name, warnings)
    return report


def validate_replay_buffer(root_or_path: zarr.Group | str | os.PathLike | Any,
                           name_for_messages: str | None = None,
                           check_values: bool = True, deep: bool = False,
                           progress: bool = False, umi: bool = False) -> ValidationReport:
    """Check a UMI replay buffer and describe it.

    Args:
        root_or_path: a zarr root group, a :class:`ReplayBuffer` (its ``root``), or the path of a zarr
            directory / ``.zarr.zip`` (opened read-only, lazily, and closed again).
        name_for_messages: what error messages call the buffer (default: the path, or ``<in-memory>``).
        check_values: also read the pose/gripper arrays and reject NaN/Inf.
        deep: decode every chunk of every ``data/*`` array (images included; slow on big datasets).
        progress: a progress bar per array while decoding (``deep``).
        umi: also apply UMI's physical rules (:func:`check_umi_values`: required keys, gripper width range;
            frozen poses warn) — ``umi-aug validate``.

    Returns:
        ValidationReport with ``n_episodes``, ``n_steps`` (= ``episode_ends[-1]``), per-key layout and
        warnings for harmless deviations from UMI's layout.

    Raises:
        DatasetError: one per malformed case (missing groups/keys, bad episode_ends, length mismatch,
            bad image/pose shapes or dtypes, NaN/Inf in pose arrays, unknown codec, unreadable path, missing
            chunks; with ``deep`` an undecodable chunk).
    """
    register_codecs()
    if isinstance(root_or_path, (str, os.PathLike)):
        name = name_for_messages or str(root_or_path)
        store, root = open_store(root_or_path, mode="r")
        try:
            return _validate_root(root, name, check_values, deep, progress, umi)
        finally:
            close_store(store)
    root = getattr(root_or_path, "root", root_or_path)
    if not isinstance(root, zarr.Group):
        raise DatasetError(f"validate_replay_buffer: expected a zarr.Group, ReplayBuffer or path, got "
                           f"{type(root_or_path).__name__}")
    return _validate_root(root, name_for_messages or "<in-memory replay buffer>", check_values, deep, progress, umi)
