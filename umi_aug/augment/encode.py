"""Image frames of an export encoded on a thread pool (issue #17): the same chunk bytes zarr writes, made while the
next episode renders.

Reference path: ``img[old:old + n] = frames`` — zarr encodes the ``n`` one-frame chunks one after another in the
calling thread (JPEG-XL level 99: ~10–15 ms a 224² frame on a free core, ~1.5 s an episode of ~139 new frames).
Fast path: :class:`FrameEncoder` hands each frame to a thread pool (``imagecodecs`` releases the GIL while it
encodes) as soon as the episode's frames exist, and :func:`write_encoded` later stores the finished chunks under
the keys zarr would use. Each chunk is made by the array's own :meth:`zarr.Array._encode_chunk` (filters, then
compressor) from the array zarr itself would encode, so the stored bytes are identical to the reference's —
``tests/augment/test_throughput.py`` checks that, and that whole exports are byte-identical.

Only arrays with one frame per chunk (UMI's ``camera*_rgb`` layout: chunks ``(1, H, W, C)``) take the fast path;
:func:`can_encode_ahead` says whether an array qualifies, anything else uses the reference path.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

__all__ = ["FrameEncoder", "can_encode_ahead", "write_encoded", "encode_frame_chunks"]


def can_encode_ahead(arr) -> bool:
    """``arr`` (a zarr array of frames ``[T, H, W, C]``) stores one whole frame per chunk."""
    return (arr.ndim >= 2 and arr.chunks[0] == 1 and tuple(arr.chunks[1:]) == tuple(arr.shape[1:])
            and arr.dtype != object)


def _encode_one(arr, frame: np.ndarray) -> tuple[bytes | None, float]:
    """``(chunk bytes, seconds)`` of one frame ``[1, H, W, C]``; ``None`` when zarr would store no chunk (an
    all-fill-value frame of an array with ``write_empty_chunks=False``)."""
    from zarr.util import all_equal  # lazy, start-up: zarr

    t0 = time.perf_counter()
    chunk = frame.astype(arr.dtype, order=arr.order, copy=False)  # what zarr's _process_for_setitem passes on
    if not arr.write_empty_chunks and all_equal(arr.fill_value, chunk):
        return None, time.perf_counter() - t0
    return arr._encode_chunk(chunk), time.perf_counter() - t0


def encode_frame_chunks(arr, frames: np.ndarray) -> list[bytes | None]:
    """The chunk bytes zarr would store for ``frames [n, H, W, C]`` written to ``arr`` (this thread)."""
    frames = np.asarray(frames)
    return [_encode_one(arr, frames[i:i + 1])[0] for i in range(len(frames))]


class FrameEncoder:
    """A thread pool that encodes episodes' frames for an array while the caller does other work.

    ``submit(frames)`` returns the futures of the ``n`` chunks (each ``(bytes | None, seconds)``); pass them to
    :func:`write_encoded`. ``threads`` encode at once (each with the codec's own ``numthreads``, 1 for UMI's).
    Use as a context manager (the pool is shut down on exit; pending encodes of an abandoned episode are
    cancelled).
    """

    def __init__(self, arr, threads: int) -> None:
        if not can_encode_ahead(arr):
            raise ValueError(f"FrameEncoder: array chunks {arr.chunks} for shape {arr.shape} are not one frame each")
        self.arr = arr
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="umi-aug-encode")

    def submit(self, frames: np.ndarray) -> list[Future]:
        frames = np.ascontiguousarray(frames)
        return [self._pool.submit(_encode_one, self.arr, frames[i:i + 1]) for i in range(len(frames))]

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "FrameEncoder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_encoded(arr, start: int, chunks: list) -> float:
    """Store encoded frame chunks at rows ``start, start + 1, ...`` of ``arr`` (already resized to hold them), as
    zarr's own write would (a ``None`` chunk: the key is removed). ``chunks`` are bytes, ``(bytes, seconds)`` pairs
    or futures of them. Returns the summed encode seconds."""
    store = arr.chunk_store
    zeros = (0,) * (arr.ndim - 1)
    enc_s = 0.0
    for i, c in enumerate(chunks):
        if isinstance(c, Future):
            c = c.result()
        if isinstance(c, tuple):
            c, s = c
            enc_s += s
        key = arr._chunk_key((start + i,) + zeros)
        if c is None:
            try:
                del store[key]
            except KeyError:
                pass
        else:
            store[key] = c
    return enc_s
