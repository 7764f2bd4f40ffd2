"""Rows of a zarr array with their chunks decoded on several threads.

zarr (v2) decodes the chunks of a selection one after the other. A UMI image array keeps one frame per JPEG XL
chunk (``camera0_rgb``, chunks ``(1, S, S, 3)``; 5-10 ms to decode at 224², lossless longer), and the
libjxl decoder releases the GIL, so reading the frames a stage needs on the machine's cores takes about
1/threads of the time. :func:`read_rows` returns exactly ``arr.get_orthogonal_selection((rows,))`` (its reference
in ``tests/data/test_rows.py``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import zarr
from numcodecs.compat import ensure_ndarray

from umi_aug.errors import DatasetError

__all__ = ["read_rows"]


def _default_threads() -> int:
    try:
        return int(os.environ.get("OMP_NUM_THREADS") or len(os.sched_getaffinity(0)))
    except (ValueError, AttributeError):  # pragma: no cover - non-Linux / a malformed variable
        return os.cpu_count() or 1


def _fast_path(arr: zarr.Array) -> bool:
    """Chunks split only axis 0, one compressor and no filter, C order: a chunk's bytes decode to a C array."""
    return (arr.ndim >= 1 and tuple(arr.chunks[1:]) == tuple(arr.shape[1:]) and arr.compressor is not None
            and not arr.filters and arr.order == "C" and arr.dtype != object)


def read_rows(arr: zarr.Array, rows: np.ndarray | list[int], threads: int | None = None) -> np.ndarray:
    """``arr[rows]`` for integer rows along axis 0 (any order, repeats allowed): each chunk holding a wanted row is
    read once and decoded on ``threads`` threads (default: ``OMP_NUM_THREADS``, else the cores this process may
    use). Arrays chunked along other axes, filtered or uncompressed are read by zarr itself.

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

    k = max(1, min(int(threads or _default_threads()), len(keys)))
    if k == 1:
        chunks = [decode(i) for i in range(len(keys))]
    else:
        with ThreadPoolExecutor(k) as ex:
            chunks = list(ex.map(decode, range(len(keys))))
    within = rows - chunk_ids[inv] * c0
    out = np.empty((len(rows),) + tuple(arr.shape[1:]), dtype=arr.dtype)
    for j in range(len(rows)):
        out[j] = chunks[inv[j]][within[j]]
    return out
