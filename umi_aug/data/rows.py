"""Rows of a zarr array with their chunks decoded on several threads.

zarr (v2) decodes the chunks of a selection one after the other. A UMI image array keeps one frame per JPEG XL
chunk (``camera0_rgb``, chunks ``(1, S, S, 3)``; 5-10 ms to decode at 224², lossless longer), and the
libjxl decoder releases the GIL, so reading the frames a stage needs on the machine's cores takes about
1/threads of the time. :func:`read_rows` returns exactly ``arr.get_orthogonal_selection((rows,))`` (its reference
in ``tests/data/test_rows.py``).

Stages that read the same frames one after the other (a dataset scene's triangulation, its 3DGS views, the gripper
mask, the export's overlay originals) can share a :class:`DecodedChunks`: decoded chunks kept by their stored bytes'
hash, so a frame is decoded once per process (:func:`shared_decoded_chunks`).
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import zarr
from numcodecs.compat import ensure_ndarray

from umi_aug.errors import DatasetError

__all__ = ["DecodedChunks", "read_rows", "shared_decoded_chunks"]

#: What :func:`shared_decoded_chunks` keeps at most: ~1,700 UMI policy frames at 224².
SHARED_DECODED_CHUNKS_BYTES: int = 256 << 20


class DecodedChunks:
    """Decoded chunks by content, least recently used dropped first beyond ``max_bytes``; thread-safe.

    A chunk's key is its array's dtype, chunk shape and codec configuration and a 128-bit BLAKE2b of its stored
    bytes, so a hit is the decode of the very same bytes (whatever the store, path or array it came from) and a
    chunk rewritten in place is a miss. The arrays kept are read-only."""

    def __init__(self, max_bytes: int = SHARED_DECODED_CHUNKS_BYTES):
        if int(max_bytes) < 0:
            raise ValueError(f"DecodedChunks: max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(arr: zarr.Array, raw: bytes) -> tuple:
        """The cache key of stored chunk bytes ``raw`` of ``arr``."""
        codec = repr(sorted(arr.compressor.get_config().items()))
        return (arr.dtype.str, tuple(int(c) for c in arr.chunks), codec,
                hashlib.blake2b(memoryview(raw), digest_size=16).digest())

    def get(self, key: tuple) -> np.ndarray | None:
        with self._lock:
            a = self._items.get(key)
            if a is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return a

    def put(self, key: tuple, chunk: np.ndarray) -> None:
        """Keep ``chunk`` (a freshly decoded array nothing else writes to: not copied; kept as a read-only view)."""
        a = chunk.view()
        a.flags.writeable = False
        if a.nbytes > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._items[key] = a
            self._bytes += a.nbytes
            while self._bytes > self.max_bytes:
                _, dropped = self._items.popitem(last=False)
                self._bytes -= dropped.nbytes

    def __len__(self) -> int:
        return len(self._items)

    @property
    def nbytes(self) -> int:
        """Bytes of the decoded chunks kept."""
        return self._bytes


_SHARED: DecodedChunks | None = None


def shared_decoded_chunks() -> DecodedChunks:
    """This process's :class:`DecodedChunks` (``SHARED_DECODED_CHUNKS_BYTES``), made on first use."""
    global _SHARED
    if _SHARED is None:
        _SHARED = DecodedChunks()
    return _SHARED


def _default_threads() -> int:
    try:
        return int(os.environ.get("OMP_NUM_THREADS") or len(os.sched_getaffinity(0)))
    except (ValueError, AttributeError):  # pragma: no cover - non-Linux / a malformed variable
        return os.cpu_count() or 1


def _fast_path(arr: zarr.Array) -> bool:
    """Chunks split only axis 0, one compressor and no filter, C order: a chunk's bytes decode to a C array."""
    return (arr.ndim >= 1 and tuple(arr.chunks[1:]) == tuple(arr.shape[1:]) and arr.compressor is not None
            and not arr.filters and arr.order == "C" and arr.dtype != object)


def read_rows(arr: zarr.Array, rows: np.ndarray | list[int], threads: int | None = None,
              cache: DecodedChunks | None = None) -> np.ndarray:
    """``arr[rows]`` for integer rows along axis 0 (any order, repeats allowed): each chunk holding a wanted row is
    read once and decoded on ``threads`` threads (default: ``OMP_NUM_THREADS``, else the cores this process may
    use). Arrays chunked along other axes, filtered or uncompressed are read by zarr itself. ``cache``: chunks
    decoded before (the same stored bytes) are taken from it and the ones decoded here are added to it.

    Raises:
        DatasetError: a row outside ``[0, len(arr))``, or a chunk that does not decode to the chunk's size.
    """
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    n = int(arr.shape[0]) if arr.ndim else 0
    if len(rows) and (rows.min() < 0 or rows.max() >= n):
        bad = int(rows[(rows < 0) | (rows >= n)][0])
        raise DatasetError(f"{arr.name}: row {bad} outside [0, {n})")
    if len(rows) == 0:
        return np.zeros((0,) + tuple(arr.shape[1:]), dtype=arr.dtype)
    if not _fast_path(arr):
        uniq, inv = np.unique(rows, return_inverse=True)
        return arr.get_orthogonal_selection((uniq,))[inv]
    c0 = int(arr.chunks[0])
    chunk_ids, inv = np.unique(rows // c0, return_inverse=True)
    store = arr.chunk_store if arr.chunk_store is not None else arr.store
    keys = [arr._chunk_key((int(c),) + (0,) * (arr.ndim - 1)) for c in chunk_ids]  # zarr 2's key of a chunk
    raw = [store.get(k) for k in keys]  # read serially (a zip store is not for concurrent readers)
    chunk_shape = tuple(int(s) for s in arr.chunks)

    def decode(i: int) -> np.ndarray:
        if raw[i] is None:  # a chunk never written holds the fill value
            return np.full(chunk_shape, arr.fill_value if arr.fill_value is not None else 0, dtype=arr.dtype)
        try:
            flat = ensure_ndarray(arr.compressor.decode(raw[i])).view(arr.dtype).reshape(-1)
        except Exception as exc:  # noqa: BLE001 - a codec's own error, named with the chunk
            raise DatasetError(f"{arr.name}: chunk {keys[i]!r} does not decode ({type(exc).__name__}: {exc})") from exc
        if flat.size != int(np.prod(chunk_shape)):
            raise DatasetError(f"{arr.name}: chunk {keys[i]!r} decodes to {flat.size} values, expected "
                               f"{int(np.prod(chunk_shape))} (chunk shape {chunk_shape})")
        return flat.reshape(chunk_shape)

    chunks: list[np.ndarray | None] = [None] * len(keys)
    ckeys: list[tuple | None] = [None] * len(keys)
    if cache is not None:
        for i, r in enumerate(raw):
            if r is not None:
                ckeys[i] = cache.key(arr, r)
                chunks[i] = cache.get(ckeys[i])
    todo = [i for i in range(len(keys)) if chunks[i] is None]
    k = max(1, min(int(threads or _default_threads()), len(todo)))
    if k == 1:
        decoded = [decode(i) for i in todo]
    else:
        with ThreadPoolExecutor(k) as ex:
            decoded = list(ex.map(decode, todo))
    for i, c in zip(todo, decoded):
        chunks[i] = c
        if ckeys[i] is not None:
            cache.put(ckeys[i], c)
    within = rows - chunk_ids[inv] * c0
    out = np.empty((len(rows),) + tuple(arr.shape[1:]), dtype=arr.dtype)
    for j in range(len(rows)):
        out[j] = chunks[inv[j]][within[j]]
    return out
