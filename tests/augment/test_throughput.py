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
    aug_assets.memo.pop("overlay_originals", None)
    few = np.array([c // 2])  # an on-the-fly sample's few frames: decoded directly, nothing cached
    assert np.array_equal(overlay_originals(aug_assets, d, few), aug_assets.original_frames(d, few))
    assert "overlay_originals" not in aug_assets.memo
    for _ in range(3):
        src = rng.integers(0, c + 1, size=int(rng.integers(c // 2 + 1, 2 * c + 2)))
        src[:2] = (0, c)  # an export episode's sources span the pre-contact range
        assert np.array_equal(overlay_originals(aug_assets, d, src), aug_assets.original_frames(d, src))
    assert "overlay_originals" in aug_assets.memo


def _stored_chunks(path):
    """Every stored key of a zarr directory store → its bytes (chunks, metadata, attributes)."""
    out = {}
    for p in sorted(path.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(path))] = p.read_bytes()
    return out


@pytest.mark.parametrize("mode", ["freespace", "obstacle"])
def test_export_with_fast_paths_is_byte_identical_to_the_reference(aug_session, aug_work, tmp_path, mode):
    """Obstacle mode also exercises ``obstacle_tiles`` (the replayed frames' scene depth rendered only where the
    obstacle shows)."""
    from umi_aug.augment import export
    from umi_aug.augment.exporter import FAST_PATHS

    cfg = small_config(mode=mode, n_per_demo=3 if mode == "freespace" else 2)
    ref = export(aug_session, tmp_path / "ref.zarr", cfg, work_dir=aug_work, progress=False, pictures=False,
                 fast_paths=())
    fast = export(aug_session, tmp_path / "fast.zarr", cfg, work_dir=aug_work, progress=False, pictures=False,
                  fast_paths=FAST_PATHS, encode_threads=2)
    # (an obstacle job may fail to plan — the same in both runs; its episodes' tails are the obstacle path)
    assert ref.n_augmented == fast.n_augmented >= (3 if mode == "freespace" else 1)
    assert ref.timings_s["encode_s"] == 0 and fast.timings_s["encode_s"] > 0  # the paths did differ
    a, b = _stored_chunks(tmp_path / "ref.zarr"), _stored_chunks(tmp_path / "fast.zarr")
    assert a.keys() == b.keys()
    differing = [k for k in a if a[k] != b[k]]
    assert differing == []


def test_export_jpegxl_effort_changes_only_the_new_frames_bytes(aug_session, aug_work, tmp_path):
    """``AugmentConfig.jpegxl_effort`` sets the image array's codec effort (UMI's schema, decoder unaffected): the
    originals and replayed frames are still the source's chunks, the new frames decode to the same shape and
    nearly the same pixels as at libjxl's default effort, and the export's run key follows the setting."""
    import json

    from umi_aug.augment import export, read_episode_records
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.codecs import UMI_JPEGXL_PARAMS
    from umi_aug.errors import AugmentError

    base = small_config(mode="freespace", n_per_demo=1)
    assert base.jpegxl_effort == 4
    source = aug_session / "dataset.zarr.zip"
    source_bytes = source.read_bytes()
    outs = {}
    for effort in (None, 4):
        cfg = small_config(mode="freespace", n_per_demo=1, jpegxl_effort=effort)
        outs[effort] = tmp_path / f"effort_{effort}.zarr"
        s = export(aug_session, outs[effort], cfg, work_dir=aug_work, progress=False, pictures=False)
        assert s.n_augmented == 1
    comp = {e: json.loads((p / "data" / "camera0_rgb" / ".zarray").read_text())["compressor"] for e, p in outs.items()}
    assert comp[4]["effort"] == 4 and comp[None]["effort"] is None
    assert {k: v for k, v in comp[4].items() if k != "effort"} == {k: v for k, v in comp[None].items() if k != "effort"}
    assert set(comp[4]) == {"id", *UMI_JPEGXL_PARAMS}  # UMI's reader rebuilds its JpegXl from exactly these keys

    rec = read_episode_records(outs[4])
    new_rows = set()
    with ReplayBuffer.open(outs[4]) as buf:
        for e in np.flatnonzero(rec["aug_mode"] > 0):
            sl = buf.get_episode_slice(int(e))
            new_rows.update(range(sl.start, sl.start + int(rec["aug_splice_index"][e])))
        n_rows = buf.n_steps
    assert 0 < len(new_rows) < n_rows
    img = {e: p / "data" / "camera0_rgb" for e, p in outs.items()}
    n_differ = 0
    for row in range(n_rows):
        a, b = (img[e] / f"{row}.0.0.0" for e in (None, 4))
        if row in new_rows:
            n_differ += a.read_bytes() != b.read_bytes()
        else:  # originals and the replayed tail: the source's stored chunks, copied
            assert a.read_bytes() == b.read_bytes(), f"row {row} is not a raw copy"
    assert n_differ > 0  # the setting reached the encoder
    assert source.read_bytes() == source_bytes  # the codec change is made on the export's copy only
    with ReplayBuffer.open(outs[None]) as x, ReplayBuffer.open(outs[4]) as y:
        for k in x.keys():
            if k != "camera0_rgb":
                assert np.array_equal(x[k][:], y[k][:]), k
        fa, fb = x["camera0_rgb"][:].astype(np.float64), y["camera0_rgb"][:].astype(np.float64)
    assert fa.shape == fb.shape
    psnr = 10 * np.log10(255.0 ** 2 / max(1e-12, float(np.mean((fa - fb) ** 2))))
    assert psnr > 40.0, psnr
    with pytest.raises(AugmentError, match="another configuration"):  # the effort is part of the run key
        export(aug_session, outs[None], base, work_dir=aug_work, progress=False, pictures=False)


def test_jpegxl_effort_is_checked():
    from umi_aug.augment.cli import _effort_arg
    from umi_aug.errors import AugmentError

    for bad in (0, 10, 4.0, True):
        with pytest.raises(AugmentError, match="jpegxl_effort"):
            small_config(jpegxl_effort=bad)
    assert _effort_arg("default") is None and _effort_arg("7") == 7
    with pytest.raises(AugmentError, match="--jpegxl-effort"):
        _effort_arg("fast")


def _spec_chunks(spec, frames):
    """``encode_with_spec`` in a fresh process (what an episode task on another worker does)."""
    from umi_aug.augment.encode import encode_with_spec

    return [c for c, _ in encode_with_spec(spec, frames)]


@pytest.mark.parametrize("write_empty_chunks", [True, False])
def test_chunks_encoded_from_a_spec_in_another_process_are_the_bytes_zarr_writes(write_empty_chunks):
    """``encode_in_task``: a spawned process with only the array's :class:`ChunkSpec` (pickled) makes the chunk
    bytes zarr itself stores — JPEG-XL effort 4 included (the export's setting), and a fill-value frame left out
    where zarr leaves it out."""
    import multiprocessing as mp
    import pickle

    import zarr

    from umi_aug.augment.encode import chunk_spec
    from umi_aug.data.codecs import register_codecs, umi_image_codec_from

    rng = _fresh_rng()
    n, size = 5, 40
    frames = _smooth_frames(rng, n, size)
    frames[2] = 0
    register_codecs()
    comp = umi_image_codec_from(None, effort=4)
    ref = zarr.zeros((n, size, size, 3), chunks=(1, size, size, 3), dtype=np.uint8, compressor=comp,
                     write_empty_chunks=write_empty_chunks)
    ref[:] = frames
    spec = chunk_spec(ref)
    assert pickle.loads(pickle.dumps(spec)) == spec and "effort" in spec.compressor_json
    with mp.get_context("spawn").Pool(1) as pool:
        chunks = pool.apply(_spec_chunks, (spec, frames))
    for i, c in enumerate(chunks):
        k = ref._chunk_key((i, 0, 0, 0))
        want = bytes(ref.store[k]) if k in ref.store else None
        assert (None if c is None else bytes(c)) == want, i
    assert (chunks[2] is None) == (not write_empty_chunks)


def test_export_with_tasks_encoding_is_byte_identical_to_the_reference(aug_session, aug_work, tmp_path):
    """Two worker processes that encode their episodes' frames (``encode_in_task``) write the same dataset, byte
    for byte, as one process on the reference paths."""
    import dataclasses

    from umi_aug.augment import export
    from umi_aug.augment.exporter import FAST_PATHS

    assert "encode_in_task" in FAST_PATHS
    cfg = small_config(mode="freespace", n_per_demo=3)
    ref = export(aug_session, tmp_path / "ref.zarr", cfg, work_dir=aug_work, progress=False, pictures=False,
                 fast_paths=())
    fast = export(aug_session, tmp_path / "tasks.zarr", dataclasses.replace(cfg, workers=2), work_dir=aug_work,
                  progress=False, pictures=False, fast_paths=("encode_in_task",))
    assert ref.n_augmented == fast.n_augmented == 3
    assert ref.timings_s["encode_s"] == 0 and fast.timings_s["encode_s"] > 0  # the tasks encoded
    a, b = _stored_chunks(tmp_path / "ref.zarr"), _stored_chunks(tmp_path / "tasks.zarr")
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []


def test_new_frames_skip_what_the_overlay_covers_and_equal_the_reference(aug_assets):
    """``overlay_pixels``: the pixels the gripper overlay covers completely are not rendered; the frames are the
    reference's, byte for byte (free-space episode: every frame before the splice is new)."""
    from umi_aug.augment.plan import plan_episode
    from umi_aug.augment.render import render_episode_frames

    keep = aug_assets.rendered_pixels
    assert keep.dtype == bool and np.array_equal(keep, aug_assets.overlay_alpha < 1.0)
    assert 0 < keep.mean() < 1  # the overlay covers part of the frame, the render shows the rest
    planned = plan_episode(aug_assets, aug_assets.augmentable[0], 1, "freespace")
    idx = np.arange(min(planned.splice_index, 6))
    fast = render_episode_frames(aug_assets, planned, idx)
    ref = render_episode_frames(aug_assets, planned, idx, overlay_pixels=False)
    assert fast.shape == ref.shape and np.array_equal(fast, ref)
