"""Issue #17 speed-ups of the export equal their reference paths: frames encoded ahead on threads give the bytes
zarr writes itself, the once-per-demo overlay frames are the frames decoded per call, and an export with every
fast path is byte-identical (stored chunks, not only decoded arrays) to one with none."""

from __future__ import annotations

import numpy as np
import pytest

from tests.augment.conftest import small_config


def _fresh_rng():
    seed = int(np.random.SeedSequence().entropy % (2**32))
    print(f"seed {seed}")  # shown when a test fails
    return np.random.default_rng(seed)


def _frames_array(n: int, size: int, write_empty_chunks: bool = True):
    import zarr

    from umi_aug.data.codecs import register_codecs, umi_image_compressor

    register_codecs()  # the zarr array re-reads its compressor by codec id
    return zarr.zeros((n, size, size, 3), chunks=(1, size, size, 3), dtype=np.uint8,
                      compressor=umi_image_compressor(), write_empty_chunks=write_empty_chunks)


def _smooth_frames(rng, n: int, size: int) -> np.ndarray:
    """Random images with structure (a lossy codec on pure noise is not a realistic input)."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    out = np.empty((n, size, size, 3), np.uint8)
    for i in range(n):
        f = rng.uniform(1, 6, size=(3, 2))
        ph = rng.uniform(0, 2 * np.pi, size=3)
        base = np.stack([np.sin(f[c, 0] * 2 * np.pi * xx + f[c, 1] * 2 * np.pi * yy + ph[c]) for c in range(3)], -1)
        out[i] = np.clip(127.5 * (base + 1) + rng.normal(0, 8, size=base.shape), 0, 255).astype(np.uint8)
    return out


@pytest.mark.parametrize("write_empty_chunks", [True, False])
def test_encoded_ahead_chunks_are_the_bytes_zarr_writes(write_empty_chunks):
    from umi_aug.augment.encode import FrameEncoder, can_encode_ahead, encode_frame_chunks, write_encoded

    rng = _fresh_rng()
    n, size = 7, 48
    frames = _smooth_frames(rng, n, size)
    frames[3] = 0  # a fill-value frame: stored or left out exactly as zarr does
    ref = _frames_array(n + 2, size, write_empty_chunks)
    ref[1:1 + n] = frames  # the reference path: zarr encodes in this thread
    fast = _frames_array(n + 2, size, write_empty_chunks)
    assert can_encode_ahead(fast)
    with FrameEncoder(fast, threads=2) as enc:
        futures = enc.submit(frames)
        enc_s = write_encoded(fast, 1, futures)
    assert enc_s > 0
    ref_keys = {k for k in ref.store if not k.startswith(".")}
    fast_keys = {k for k in fast.store if not k.startswith(".")}
    assert ref_keys == fast_keys and len(ref_keys) == (n if write_empty_chunks else n - 1)
    for k in ref_keys:
        assert bytes(ref.store[k]) == bytes(fast.store[k]), k
    assert np.array_equal(ref[:], fast[:])
    # the single-thread helper makes the same chunks
    assert [bytes(c) if c is not None else None for c in encode_frame_chunks(fast, frames)] == \
        [bytes(ref.store[ref._chunk_key((1 + i, 0, 0, 0))]) if ref._chunk_key((1 + i, 0, 0, 0)) in ref.store
         else None for i in range(n)]


def test_encoder_refuses_arrays_with_several_frames_per_chunk():
    import zarr

    from umi_aug.augment.encode import FrameEncoder, can_encode_ahead

    arr = zarr.zeros((4, 8, 8, 3), chunks=(2, 8, 8, 3), dtype=np.uint8)
    assert not can_encode_ahead(arr)
    with pytest.raises(ValueError, match="one frame each"):
        FrameEncoder(arr, 1)


def test_overlay_originals_equal_the_frames_decoded_per_call(aug_assets):
    from umi_aug.augment.render import overlay_originals

    rng = _fresh_rng()
    d = aug_assets.augmentable[0]
    c = int(aug_assets.demos[d].contact_index)
    aug_assets._lazy.pop("overlay_originals", None)
    few = np.array([c // 2])  # an on-the-fly sample's few frames: decoded directly, nothing cached
    assert np.array_equal(overlay_originals(aug_assets, d, few), aug_assets.original_frames(d, few))
    assert "overlay_originals" not in aug_assets._lazy
    for _ in range(3):
        src = rng.integers(0, c + 1, size=int(rng.integers(c // 2 + 1, 2 * c + 2)))
        src[:2] = (0, c)  # an export episode's sources span the pre-contact range
        assert np.array_equal(overlay_originals(aug_assets, d, src), aug_assets.original_frames(d, src))
    assert "overlay_originals" in aug_assets._lazy


def _stored_chunks(path):
    """Every stored key of a zarr directory store → its bytes (chunks, metadata, attributes)."""
    out = {}
    for p in sorted(path.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(path))] = p.read_bytes()
    return out


def test_export_with_fast_paths_is_byte_identical_to_the_reference(aug_session, aug_work, tmp_path):
    from umi_aug.augment import export
    from umi_aug.augment.exporter import FAST_PATHS

    cfg = small_config(mode="freespace", n_per_demo=3)
    ref = export(aug_session, tmp_path / "ref.zarr", cfg, work_dir=aug_work, progress=False, pictures=False,
                 fast_paths=())
    fast = export(aug_session, tmp_path / "fast.zarr", cfg, work_dir=aug_work, progress=False, pictures=False,
                  fast_paths=FAST_PATHS, encode_threads=2)
    assert ref.n_augmented == fast.n_augmented == 3
    assert ref.timings_s["encode_s"] == 0 and fast.timings_s["encode_s"] > 0  # the paths did differ
    a, b = _stored_chunks(tmp_path / "ref.zarr"), _stored_chunks(tmp_path / "fast.zarr")
    assert a.keys() == b.keys()
    differing = [k for k in a if a[k] != b[k]]
    assert differing == []
