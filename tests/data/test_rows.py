"""``data.rows.read_rows`` equals zarr's own ``get_orthogonal_selection`` on fresh random arrays and rows: UMI's JPEG XL
image chunks (one frame each), Blosc chunks of several rows with a partial last chunk, chunks never written (fill
value), arrays chunked along another axis (zarr's path), rows in any order with repeats, one thread and several, in
a zip store; a bad row or a corrupt chunk is one clear error naming the array."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from numcodecs import Blosc

from umi_aug.data import ReplayBuffer, umi_image_compressor
from umi_aug.data.rows import DecodedChunks, read_rows, shared_decoded_chunks
from umi_aug.errors import DatasetError


def _rows(rng, n: int) -> np.ndarray:
    return rng.integers(0, n, size=int(rng.integers(1, 2 * n)))


def test_read_rows_equals_zarr(rng, tmp_path):
    ReplayBuffer.create()  # registers UMI's codec
    root = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    n = int(rng.integers(5, 14))
    img = root.create_dataset("img", shape=(n, 24, 32, 3), chunks=(1, 24, 32, 3), dtype=np.uint8,
                              compressor=umi_image_compressor())
    img[:] = rng.integers(0, 256, size=img.shape, dtype=np.uint8)
    low = root.create_dataset("low", shape=(n, 7), chunks=(3, 7), dtype=np.float32, compressor=Blosc("zstd"))
    low[: n - 2] = rng.normal(size=(n - 2, 7)).astype(np.float32)  # the last rows' chunk may never be written
    other = root.create_dataset("other", shape=(n, 6), chunks=(n, 2), dtype=np.int32, compressor=Blosc())
    other[:] = rng.integers(-9, 9, size=other.shape)
    empty = root.create_dataset("empty", shape=(n, 4), chunks=(2, 4), dtype=np.float64, fill_value=np.nan)
    for arr in (img, low, other, empty):
        for threads in (1, 2, 5):
            rows = _rows(rng, n)
            uniq, inv = np.unique(rows, return_inverse=True)
            want = arr.get_orthogonal_selection((uniq,))[inv]
            got = read_rows(arr, rows, threads=threads)
            assert got.dtype == arr.dtype and got.shape == want.shape, arr.name
            np.testing.assert_array_equal(got, want)
        assert read_rows(arr, []).shape == (0,) + arr.shape[1:]
    with pytest.raises(DatasetError, match=r"/img: row -1 outside"):
        read_rows(img, [0, -1])
    with pytest.raises(DatasetError, match=rf"/low: row {n} outside"):
        read_rows(low, [n])


def test_read_rows_from_a_zip_and_a_corrupt_chunk(rng, tmp_path):
    buf = ReplayBuffer.create()
    frames = rng.integers(0, 256, size=(6, 16, 16, 3), dtype=np.uint8)
    buf.add_episode({"camera0_rgb": frames, "robot0_gripper_width": np.zeros((6, 1), np.float32)},
                    compressors={"camera0_rgb": umi_image_compressor()})
    path = buf.save(tmp_path / "d.zarr.zip")
    with ReplayBuffer.open(path) as rb:
        rows = np.array([5, 0, 3, 3, 1])
        a = rb["camera0_rgb"]
        want = np.stack([a[int(r)] for r in rows])  # (lossy: what the codec gives back, not ``frames``)
        np.testing.assert_array_equal(read_rows(a, rows, threads=2), want)
    store = zarr.DirectoryStore(str(tmp_path / "c.zarr"))
    root = zarr.open_group(store, mode="w")
    arr = root.create_dataset("img", shape=(3, 16, 16, 3), chunks=(1, 16, 16, 3), dtype=np.uint8,
                              compressor=umi_image_compressor())
    arr[:] = frames[:3]
    store[arr._chunk_key((1, 0, 0, 0))] = b"not a JPEG XL stream"
    with pytest.raises(DatasetError, match=r"/img: chunk '.*1\.0\.0\.0' does not decode"):
        read_rows(arr, [0, 1, 2], threads=2)


def test_read_rows_through_a_cache_equals_without(rng, tmp_path):
    """Reads through a :class:`DecodedChunks` give zarr's own rows, decode each stored chunk once (hits counted),
    see a chunk rewritten in place as new bytes, keep to their byte budget (least recently used dropped), and
    return arrays of the caller's own (writing to them leaves the cache as it was)."""
    ReplayBuffer.create()
    root = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    n = 12
    img = root.create_dataset("img", shape=(n, 24, 32, 3), chunks=(1, 24, 32, 3), dtype=np.uint8,
                              compressor=umi_image_compressor())
    img[:] = rng.integers(0, 256, size=img.shape, dtype=np.uint8)
    low = root.create_dataset("low", shape=(n, 5), chunks=(4, 5), dtype=np.float32, compressor=Blosc("zstd"))
    low[: n - 4] = rng.normal(size=(n - 4, 5)).astype(np.float32)  # the last chunk is never written
    for arr in (img, low):
        cache = DecodedChunks()
        for threads in (1, 2):
            for _ in range(3):
                rows = _rows(rng, n)
                uniq, inv = np.unique(rows, return_inverse=True)
                want = arr.get_orthogonal_selection((uniq,))[inv]
                np.testing.assert_array_equal(read_rows(arr, rows, threads=threads, cache=cache), want)
    cache = DecodedChunks()
    first = read_rows(img, np.arange(n), cache=cache)
    assert (cache.misses, cache.hits, len(cache)) == (n, 0, n)
    again = read_rows(img, [3, 3, 7], cache=cache)
    assert (cache.misses, cache.hits) == (n, 2)
    np.testing.assert_array_equal(again, first[[3, 3, 7]])
    again[:] = 0  # the caller's copy
    np.testing.assert_array_equal(read_rows(img, [3], cache=cache), first[[3]])
    new = rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8)
    img[3] = new  # rewritten in place: other bytes, a miss
    misses = cache.misses
    np.testing.assert_array_equal(read_rows(img, [3], cache=cache)[0], img[3])
    assert cache.misses == misses + 1
    one = first[0].nbytes
    small = DecodedChunks(max_bytes=3 * one)
    read_rows(img, [0, 1, 2, 4], cache=small, threads=1)
    assert len(small) == 3 and small.nbytes <= 3 * one
    read_rows(img, [0], cache=small)  # the oldest (row 0) was dropped
    assert small.hits == 0
    kept = next(iter(small._items.values()))
    assert not kept.flags.writeable
    assert shared_decoded_chunks() is shared_decoded_chunks()
    with pytest.raises(ValueError, match="max_bytes"):
        DecodedChunks(-1)


def test_a_cache_never_hides_a_corrupt_chunk(rng, tmp_path):
    ReplayBuffer.create()
    store = zarr.DirectoryStore(str(tmp_path / "c.zarr"))
    root = zarr.open_group(store, mode="w")
    arr = root.create_dataset("img", shape=(3, 16, 16, 3), chunks=(1, 16, 16, 3), dtype=np.uint8,
                              compressor=umi_image_compressor())
    arr[:] = rng.integers(0, 256, size=arr.shape, dtype=np.uint8)
    cache = DecodedChunks()
    read_rows(arr, [0, 1, 2], cache=cache)
    store[arr._chunk_key((1, 0, 0, 0))] = b"not a JPEG XL stream"
    with pytest.raises(DatasetError, match=r"/img: chunk '.*1\.0\.0\.0' does not decode"):
        read_rows(arr, [0, 1, 2], threads=2, cache=cache)
