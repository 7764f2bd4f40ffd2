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

Encoding inside the episode tasks (issue #34; fast path ``encode_in_task``, used with more than one worker): a task
on another process or machine has no handle on the output array, so :func:`chunk_spec` describes what its chunks
are made with (dtype, chunk shape, order, fill value, empty-chunk rule, filters and compressor configs; small and
picklable) and :func:`encode_with_spec` makes the same chunk bytes there, from an in-memory array of that
description — zarr's own ``_encode_chunk`` again, so the stored bytes do not depend on where a frame was encoded.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

__all__ = ["FrameEncoder", "can_encode_ahead", "write_encoded", "encode_frame_chunks", "ChunkSpec", "chunk_spec",
           "encode_with_spec"]


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


@dataclass(frozen=True)
class ChunkSpec:
    """What the chunks of a frame array are made with (JSON of zarr's ``.zarray`` fields that encoding reads):
    ``dtype`` (numpy str), ``chunks``, ``order``, ``fill_value`` (JSON), ``write_empty_chunks``, ``filters`` and
    ``compressor`` (numcodecs configs as JSON text, None for none). Picklable and hashable."""

    dtype: str
    chunks: tuple[int, ...]
    order: str
    fill_value_json: str
    write_empty_chunks: bool
    filters_json: str
    compressor_json: str


def chunk_spec(arr) -> ChunkSpec:
    """The :class:`ChunkSpec` of a zarr array of frames (one frame per chunk: :func:`can_encode_ahead`)."""
    if not can_encode_ahead(arr):
        raise ValueError(f"chunk_spec: array chunks {arr.chunks} for shape {arr.shape} are not one frame each")
    fill = arr.fill_value
    fill = fill.item() if isinstance(fill, np.generic) else fill
    return ChunkSpec(dtype=np.dtype(arr.dtype).str, chunks=tuple(int(c) for c in arr.chunks), order=str(arr.order),
                     fill_value_json=json.dumps(fill), write_empty_chunks=bool(arr.write_empty_chunks),
                     filters_json=json.dumps([f.get_config() for f in (arr.filters or [])]),
                     compressor_json=json.dumps(None if arr.compressor is None else arr.compressor.get_config()))


#: In-memory arrays of the specs this process has encoded with (one per spec: an export has one image array).
_SPEC_ARRAYS: dict[ChunkSpec, object] = {}


def _array_of(spec: ChunkSpec):
    arr = _SPEC_ARRAYS.get(spec)
    if arr is None:
        import numcodecs  # lazy, start-up: zarr
        import zarr

        from umi_aug.data.codecs import register_codecs  # the export's JPEG-XL codec, in this process too

        register_codecs()
        comp = json.loads(spec.compressor_json)
        arr = zarr.create(shape=spec.chunks, chunks=spec.chunks, dtype=np.dtype(spec.dtype), order=spec.order,
                          fill_value=json.loads(spec.fill_value_json), store=zarr.storage.MemoryStore(),
                          write_empty_chunks=spec.write_empty_chunks,
                          compressor=None if comp is None else numcodecs.get_codec(comp),
                          filters=[numcodecs.get_codec(f) for f in json.loads(spec.filters_json)] or None)
        _SPEC_ARRAYS[spec] = arr
    return arr


def encode_with_spec(spec: ChunkSpec, frames: np.ndarray) -> list[tuple[bytes | None, float]]:
    """``(chunk bytes, seconds)`` of each of ``frames [n, H, W, C]`` as the array ``spec`` describes would store
    it (None: no chunk stored), made in this process: the bytes of :func:`encode_frame_chunks` on that array."""
    arr = _array_of(spec)
    frames = np.asarray(frames)
    return [_encode_one(arr, frames[i:i + 1]) for i in range(len(frames))]


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
