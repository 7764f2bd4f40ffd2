"""UMI-compatible zarr replay buffer (own implementation of the layout of UMI's ``ReplayBuffer``).

Layout: root group with ``data/<key>`` arrays concatenated over episodes along axis 0 and
``meta/episode_ends`` (int64 (E,), exclusive cumulative ends), so episode ``i`` is rows
``episode_ends[i-1]:episode_ends[i]``.

Appends are ordered so an interruption is detectable: every ``data/*`` array is grown and written
first and ``meta/episode_ends`` is updated LAST. A crash mid-append therefore leaves data arrays longer
than ``episode_ends[-1]``; :meth:`ReplayBuffer.open` rejects such a buffer with a DatasetError, and
``ReplayBuffer.open(path, mode="a", repair=True)`` truncates it back to the last complete episode.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import zarr

from umi_aug.data import schema
from umi_aug.data.codecs import register_codecs, resolve_compressor, umi_image_compressor
from umi_aug.data.store import close_store, open_store
from umi_aug.data.validate import (
    ValidationReport, check_episode_ends, first_nonfinite_row, open_array, validate_replay_buffer,
)
from umi_aug.errors import DatasetError
from umi_aug.io_utils import atomic_path

log = logging.getLogger(__name__)

#: Chunk length of ``meta/episode_ends`` (never rechunked, so appends never rewrite old ends).
EPISODE_ENDS_CHUNK = 1024


class ReplayBuffer:
    """A UMI replay buffer backed by a zarr-2 group (memory, directory or read-only ``.zarr.zip``).

    Build with :meth:`create` (in memory) or :meth:`open` (from disk); do not call the constructor.
    Arrays are read lazily: indexing decodes only the requested frames. ``report`` holds the
    :class:`ValidationReport` made by :meth:`open` (None after :meth:`create`); ``name`` is what error
    messages call the buffer (its path).
    """

    def __init__(self, root: zarr.Group, store: Any, name: str, writable: bool,
                 report: ValidationReport | None = None) -> None:
        self.root = root
        self._store = store
        self.name = name
        self.writable = writable
        self.report = report
        self._arrays: dict[str, zarr.Array] = {}  # opened data arrays (metadata read once)
        self._keys: list[str] | None = None
        self._ends: np.ndarray | None = None
        self._data: zarr.Group | None = None
        self._meta: zarr.Group | None = None

    def _invalidate(self) -> None:
        self._arrays, self._keys, self._ends = {}, None, None

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(cls) -> "ReplayBuffer":
        """An empty, writable buffer in a ``zarr.MemoryStore`` (``data/``, ``meta/episode_ends`` int64 (0,))."""
        register_codecs()
        store = zarr.MemoryStore()
        root = zarr.group(store=store)
        root.require_group(schema.DATA_GROUP)
        root.require_group(schema.META_GROUP).zeros(
            schema.EPISODE_ENDS, shape=(0,), chunks=(EPISODE_ENDS_CHUNK,), dtype=np.int64, compressor=None)
        return cls(root, store, "<in-memory replay buffer>", writable=True)

    @classmethod
    def open(cls, path: str | os.PathLike, mode: str = "r", load_to_memory: bool = False,
             repair: bool = False, check_values: bool = True) -> "ReplayBuffer":
        """Open a UMI replay buffer (zarr directory or ``.zarr.zip``) and validate it.

        Args:
            path: zarr directory store or ``*.zarr.zip`` file.
            mode: ``"r"`` read-only; ``"a"`` appends in place (directory stores only, or any store with
                ``load_to_memory=True``, where the in-memory copy becomes writable).
            load_to_memory: copy the whole store (still compressed) into a ``zarr.MemoryStore`` first, like
                UMI's ``copy_from_path``; the file is closed afterwards. Default: lazy access to the file.
            repair: with ``mode="a"``, truncate data left beyond ``episode_ends[-1]`` by an interrupted
                append (and drop a half-written last episode end) instead of raising.
            check_values: reject NaN/Inf in pose/gripper arrays (reads those arrays, never the images).

        Raises:
            DatasetError: unreadable path, malformed buffer (see :func:`validate_replay_buffer`).
        """
        register_codecs()
        name = str(path)
        if repair and mode != "a":
            raise DatasetError(f"{name}: repair=True needs mode='a' (got mode={mode!r})")
        if load_to_memory:
            src, _ = open_store(path, mode="r")
            store = zarr.MemoryStore()
            try:
                zarr.copy_store(src, store)
            finally:
                close_store(src)
            root = zarr.open_group(store, mode="a" if mode == "a" else "r")
        else:
            store, root = open_store(path, mode=mode)
        buf = cls(root, store, name, writable=(mode == "a"))
        try:
            repaired = buf._repair() if repair else []
            buf.report = validate_replay_buffer(root, name_for_messages=name, check_values=check_values)
        except BaseException:
            buf.close()
            raise
        buf.report.warnings.extend(repaired)
        return buf

    def close(self) -> None:
        """Close the underlying store (needed for a ``.zarr.zip``; harmless otherwise)."""
        close_store(self._store)

    def __enter__(self) -> "ReplayBuffer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ read API
    @property
    def data(self) -> zarr.Group:
        """The ``data/`` group."""
        if self._data is None:
            self._data = self.root[schema.DATA_GROUP]
        return self._data

    @property
    def meta(self) -> zarr.Group:
        """The ``meta/`` group."""
        if self._meta is None:
            self._meta = self.root[schema.META_GROUP]
        return self._meta

    def _cached_ends(self) -> np.ndarray:
        if self._ends is None:
            self._ends = np.asarray(self.meta[schema.EPISODE_ENDS][:], dtype=np.int64)
        return self._ends

    @property
    def episode_ends(self) -> np.ndarray:
        """int64 (E,) exclusive cumulative episode ends (a copy)."""
        return self._cached_ends().copy()

    @property
    def n_episodes(self) -> int:
        """Number of episodes E."""
        return int(self._cached_ends().shape[0])

    @property
    def n_steps(self) -> int:
        """Total number of steps N = ``episode_ends[-1]`` (0 when empty)."""
        ends = self._cached_ends()
        return int(ends[-1]) if ends.size else 0

    @property
    def episode_lengths(self) -> np.ndarray:
        """int64 (E,) number of steps per episode."""
        return np.diff(self.episode_ends, prepend=0)

    def keys(self) -> list[str]:
        """Sorted names of the ``data/*`` arrays."""
        if self._keys is None:
            self._keys = sorted(self.data.array_keys())
        return list(self._keys)

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and key in self.keys()

    def __getitem__(self, key: str) -> zarr.Array:
        """The zarr array ``data/<key>`` (lazy; index it to read)."""
        if key not in self._arrays:
            if key not in self:
                raise DatasetError(f"{self.name}: no key 'data/{key}'; available: {self.keys()}")
            self._arrays[key] = open_array(self.data, key, self.name)
        return self._arrays[key]

    def __repr__(self) -> str:
        return f"ReplayBuffer({self.name!r}, n_episodes={self.n_episodes}, n_steps={self.n_steps}, keys={self.keys()})"

    def get_episode_slice(self, i: int) -> slice:
        """Row slice ``start:stop`` of episode ``i`` (negative ``i`` counts from the end)."""
        ends = self.episode_ends
        n = ends.shape[0]
        if not -n <= i < n:
            raise DatasetError(f"{self.name}: episode index {i} out of range for n_episodes={n}")
        i = i % n
        return slice(int(ends[i - 1]) if i > 0 else 0, int(ends[i]))

    def get_episode(self, i: int, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Episode ``i`` as ``{key: array (T_i, ...)}`` for ``keys`` (default: all); decodes only its frames."""
        sl = self.get_episode_slice(i)
        return {k: self[k][sl] for k in (self.keys() if keys is None else keys)}

    def get_steps(self, key: str, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` of ``data/<key>`` across episodes (0 <= start <= stop <= n_steps)."""
        n = self.n_steps
        if not 0 <= start <= stop <= n:
            raise DatasetError(f"{self.name}: key 'data/{key}': step range {start}:{stop} outside 0:{n}")
        return self[key][start:stop]

    # ------------------------------------------------------------------ write API
    def _check_episode(self, data: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
        if not data:
            raise DatasetError(f"{self.name}: add_episode got no arrays")
        arrays = {k: np.asarray(v) for k, v in data.items()}
        lengths = {k: (v.shape[0] if v.ndim else None) for k, v in arrays.items()}
        length = next(iter(lengths.values()))
        if any(n is None or n != length for n in lengths.values()) or not length:
            raise DatasetError(f"{self.name}: add_episode arrays must share one length >= 1 along axis 0, "
                               f"got {lengths}")
        for k, v in arrays.items():
            where = f"{self.name}: add_episode key '{k}'"
            if schema.is_image_key(k) and (v.ndim != 4 or v.shape[-1] != 3 or v.dtype != np.uint8):
                raise DatasetError(f"{where} must be uint8 (T, H, W, 3), got {v.dtype} {v.shape}")
            step = schema.pose_key_shape(k)
            if step is not None and v.shape[1:] != step:
                raise DatasetError(f"{where} must have shape (T, {', '.join(map(str, step))}), got {v.shape}")
            row = first_nonfinite_row(v)
            if row is not None:
                raise DatasetError(f"{where} holds NaN/Inf, first at index {row}: {v[row].tolist()}")
        existing = self.keys()
        if existing:
            if sorted(arrays) != existing:
                raise DatasetError(f"{self.name}: add_episode keys must match the buffer's keys exactly: "
                                   f"missing {sorted(set(existing) - set(arrays))}, "
                                   f"unexpected {sorted(set(arrays) - set(existing))}")
            for k, v in arrays.items():
                arr = self[k]
                if v.shape[1:] != arr.shape[1:] or v.dtype != arr.dtype:
                    raise DatasetError(f"{self.name}: add_episode key '{k}': expected (T, {arr.shape[1:]}) "
                                       f"{arr.dtype}, got {v.shape[1:]} {v.dtype}")
        return arrays, int(length)

    def add_episode(self, data: Mapping[str, np.ndarray], chunks: Mapping[str, tuple[int, ...]] | None = None,
                    compressors: Mapping[str, Any] | None = None) -> None:
        """Append one episode.

        Args:
            data: ``{key: array (T, ...)}``, all with the same T >= 1. ``camera{j}_rgb`` must be uint8
                (T, H, W, 3) RGB; pose keys need UMI's shapes (see :mod:`umi_aug.data.schema`); float
                arrays must be finite. After the first episode the keys, trailing shapes and dtypes must
                match the existing arrays exactly.
            chunks: per-key chunk override, used only when the first episode creates the array. Default:
                images (1, H, W, 3); other keys chunked along time only, length from this episode
                (``min(T, ceil(2 MB / row bytes))``), as UMI does.
            compressors: per-key compressor override (codec, ``None``, or UMI's names ``'default'`` =
                Blosc lz4 / ``'disk'`` = Blosc zstd / ``'jpegxl'``), used when creating arrays. Default:
                images ``JpegXl(level=99, numthreads=1)``, other keys uncompressed.

        Raises:
            DatasetError: read-only buffer or any mismatch above (nothing is written in that case).
        """
        if not self.writable:
            raise DatasetError(f"{self.name}: opened read-only; open with mode='a' (directory store) or "
                               "mode='a', load_to_memory=True (any store) to add episodes")
        arrays, length = self._check_episode(data)
        chunks, compressors = dict(chunks or {}), dict(compressors or {})
        new_layout = {}  # resolved before anything is written, so a bad name writes nothing
        for key, value in arrays.items():
            if key not in self:
                is_img = schema.is_image_key(key)
                default_chunks = (1,) + value.shape[1:] if is_img else schema.time_chunks(value.shape, value.dtype)
                cpr = resolve_compressor(compressors[key]) if key in compressors else (
                    umi_image_compressor() if is_img else None)
                new_layout[key] = (tuple(chunks.get(key, default_chunks)), cpr)
        old = self.n_steps
        for key, value in arrays.items():
            if key in new_layout:
                cks, cpr = new_layout[key]
                self.data.zeros(key, shape=(0,) + value.shape[1:], chunks=cks, dtype=value.dtype, compressor=cpr)
                self._keys = None
            arr = self[key]
            arr.resize((old + length,) + value.shape[1:])
            arr[old:old + length] = value
        self._commit_episode_end(old + length)

    def _commit_episode_end(self, new_end: int) -> None:
        """Append ``new_end`` to ``meta/episode_ends`` — the last step of an append."""
        self._ends = None
        ends = self.meta[schema.EPISODE_ENDS]
        ends.resize(ends.shape[0] + 1)
        ends[-1] = new_end

    def _repair(self) -> list[str]:
        """Roll an interrupted append back to the last complete episode; returns notes on what changed."""
        notes: list[str] = []
        self._invalidate()
        meta, data = self.meta, self.data
        if schema.EPISODE_ENDS not in set(meta.array_keys()) or not self.writable:
            return notes
        ends_arr = meta[schema.EPISODE_ENDS]
        ends = ends_arr[:]
        if ends.ndim == 1 and ends.size and ends[-1] <= (ends[-2] if ends.size > 1 else 0):
            ends_arr[-1] = 0  # clear the half-written slot so a later resize cannot resurrect it
            ends_arr.resize(ends.size - 1)
            notes.append(f"{self.name}: repair dropped a half-written last entry of meta/episode_ends "
                         f"({int(ends[-1])})")
            ends = ends[:-1]
        check_episode_ends(ends, self.name)
        n = int(ends[-1]) if ends.size else 0
        for key in sorted(data.array_keys()):
            arr = open_array(data, key, self.name)
            if arr.ndim and arr.shape[0] > n:
                notes.append(f"{self.name}: repair truncated key 'data/{key}' from {arr.shape[0]} to {n} rows "
                             "(data of an interrupted append)")
                arr.resize((n,) + arr.shape[1:])
        self._invalidate()
        for note in notes:
            log.warning(note)
        return notes

    def save(self, path: str | os.PathLike) -> Path:
        """Write the whole buffer to ``path``: a ``*.zip`` name gives a ``zarr.ZipStore`` (UMI's
        ``dataset.zarr.zip``), anything else a zarr directory. Chunks are copied as stored (no
        re-encoding). Atomic: written to ``<path>.tmp-<random>`` and renamed; on error nothing is left."""
        path = Path(path)
        with atomic_path(path) as tmp:
            if path.name.endswith(".zip"):
                dest = zarr.ZipStore(str(tmp), mode="w")
                try:
                    zarr.copy_store(self.root.store, dest)
                finally:
                    dest.close()
            else:
                zarr.copy_store(self.root.store, zarr.DirectoryStore(str(tmp)))
        return path
