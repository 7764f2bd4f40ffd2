"""The lossless bundle of a replay buffer (umi_aug.data.carry): every array comes back equal to the source's
decoded array, on fresh random data, wrap-around differences included; a packed single file (a checkpoint) comes
back byte for byte, and a damaged one is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from umi_aug.data import ReplayBuffer
from umi_aug.data.carry import (
    episode_frames_decode, episode_frames_encode, main, pack_bundle, pack_file, shuffle4, unpack_bundle, unpack_file,
    unshuffle4,
)
from umi_aug.errors import DatasetError
from tests.data.helpers import random_episode


def _buffer(tmp_path, rng, lengths, zip_=True):
    buf = ReplayBuffer.create()
    for n in lengths:
        ep = random_episode(rng, n, size=16)
        ep["camera0_rgb"][n // 2] = rng.integers(0, 256, ep["camera0_rgb"][n // 2].shape, dtype=np.uint8)  # noise
        buf.add_episode(ep)
    path = tmp_path / ("src.zarr.zip" if zip_ else "src.zarr")
    buf.save(path)
    return path


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frame_encoding_round_trip(seed):
    rng = np.random.default_rng()  # fresh each run
    t = int(rng.integers(1, 6))
    frames = rng.integers(0, 256, (t, 5, 7, 3), dtype=np.uint8)
    frames[0] = 255  # a wrap-around difference on the next frame
    np.testing.assert_array_equal(episode_frames_decode(episode_frames_encode(frames), frames.shape), frames)
    with pytest.raises(DatasetError, match="bytes decoded"):
        episode_frames_decode(episode_frames_encode(frames), (t + 1, 5, 7, 3))


@pytest.mark.parametrize("zip_", [True, False])
def test_pack_unpack_equals_the_decoded_source(tmp_path, zip_):
    rng = np.random.default_rng()
    src = _buffer(tmp_path, rng, [int(n) for n in rng.integers(1, 9, 3)], zip_)
    pack_bundle(src, tmp_path / "bundle", progress=False)
    out = unpack_bundle(tmp_path / "bundle", tmp_path / "out.zarr", progress=False)
    a, b = ReplayBuffer.open(src).root, ReplayBuffer.open(out).root  # opening validates the unpacked buffer
    assert sorted(a["data"].array_keys()) == sorted(b["data"].array_keys())
    for key in a["data"].array_keys():
        x, y = a[f"data/{key}"], b[f"data/{key}"]
        assert x.dtype == y.dtype and x.chunks == y.chunks, key
        np.testing.assert_array_equal(x[:], y[:], err_msg=key)
    np.testing.assert_array_equal(a["meta/episode_ends"][:], b["meta/episode_ends"][:])
    assert dict(a.attrs) == dict(b.attrs)
    # the first k episodes only
    first = unpack_bundle(tmp_path / "bundle", tmp_path / "first.zarr", episodes=2, progress=False)
    c = ReplayBuffer.open(first).root
    n2 = int(a["meta/episode_ends"][1])
    np.testing.assert_array_equal(c["meta/episode_ends"][:], a["meta/episode_ends"][:2])
    for key in a["data"].array_keys():
        np.testing.assert_array_equal(c[f"data/{key}"][:], a[f"data/{key}"][:n2], err_msg=key)


def test_bad_bundles_name_the_problem(tmp_path, capsys):
    with pytest.raises(DatasetError, match="manifest.json"):
        unpack_bundle(tmp_path, tmp_path / "x.zarr")
    ReplayBuffer.create().save(tmp_path / "empty.zarr.zip")
    with pytest.raises(DatasetError, match="no episode"):
        pack_bundle(tmp_path / "empty.zarr.zip", tmp_path / "e")
    assert not (tmp_path / "e").exists()
    src = _buffer(tmp_path, np.random.default_rng(), [3, 4])
    pack_bundle(src, tmp_path / "bundle", progress=False)
    (tmp_path / "kept.zarr").mkdir()
    (tmp_path / "kept.zarr" / "mine").write_text("user data")
    with pytest.raises(DatasetError, match="kept.zarr exists"):
        unpack_bundle(tmp_path / "bundle", tmp_path / "kept.zarr")
    with pytest.raises(DatasetError, match="bundle exists"):
        pack_bundle(src, tmp_path / "bundle")
    assert (tmp_path / "kept.zarr" / "mine").read_text() == "user data"
    with pytest.raises(DatasetError, match="episodes=3: the bundle holds 2"):
        unpack_bundle(tmp_path / "bundle", tmp_path / "x.zarr", episodes=3)
    assert not (tmp_path / "x.zarr").exists()
    m = tmp_path / "bundle" / "manifest.json"
    m.write_text(json.dumps({**json.loads(m.read_text()), "format": "other/9"}))
    assert main(["unpack", str(tmp_path / "bundle"), str(tmp_path / "y.zarr")]) == 2
    assert "format 'other/9'" in capsys.readouterr().err
    assert not (tmp_path / "y.zarr").exists()


def _shuffle4_reference(data: bytes) -> bytes:
    """Byte j of word i goes to position j * words + i (loops; zero padding to whole words)."""
    padded = data + b"\0" * ((-len(data)) % 4)
    words = len(padded) // 4
    out = bytearray(len(padded))
    for i in range(words):
        for j in range(4):
            out[j * words + i] = padded[4 * i + j]
    return bytes(out)


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 5, 7, 64, 1001])
def test_shuffle4_matches_the_loop_and_inverts(n):
    data = np.random.default_rng().integers(0, 256, n, dtype=np.uint8).tobytes()  # fresh each run
    shuffled = shuffle4(data)
    assert shuffled == _shuffle4_reference(data)
    assert unshuffle4(shuffled, n) == data
    with pytest.raises(DatasetError, match="cannot hold"):
        unshuffle4(shuffled, n + 4)


@pytest.mark.parametrize("tail", [0, 1, 2, 3])
def test_packed_file_round_trip_byte_for_byte(tmp_path, tail):
    rng = np.random.default_rng()  # fresh each run
    weights = rng.normal(0, 0.05, 20_000).astype(np.float32)
    adam_v = (rng.random(20_000) * 1e-6).astype(np.float32)
    data = b"PK header" + weights.tobytes() + adam_v.tobytes() + bytes(rng.integers(0, 256, tail, dtype=np.uint8))
    src = tmp_path / "latest.ckpt"
    src.write_bytes(data)
    info = pack_file(src, tmp_path / "x.s4xz")
    assert info["bytes"] == len(data) and info["packed_bytes"] < len(data)
    assert unpack_file(tmp_path / "x.s4xz", tmp_path / "back.ckpt") == tmp_path / "back.ckpt"
    assert (tmp_path / "back.ckpt").read_bytes() == data
    with pytest.raises(DatasetError, match="exists"):
        unpack_file(tmp_path / "x.s4xz", tmp_path / "back.ckpt")
    with pytest.raises(DatasetError, match="exists"):
        pack_file(src, tmp_path / "x.s4xz")


def test_damaged_packed_files_are_refused_and_nothing_is_written(tmp_path, capsys):
    src = tmp_path / "a.ckpt"
    src.write_bytes(np.random.default_rng().normal(size=5000).astype(np.float32).tobytes())
    pack_file(src, tmp_path / "a.s4xz")
    blob = (tmp_path / "a.s4xz").read_bytes()
    (tmp_path / "cut.s4xz").write_bytes(blob[:-100])
    (tmp_path / "other.s4xz").write_bytes(b"not packed" + blob)
    wrong_sha = bytearray(blob)
    wrong_sha[len(b"umi_aug.carry.s4xz/1\n") + 8] ^= 0xFF  # first byte of the stored SHA-256
    (tmp_path / "sha.s4xz").write_bytes(bytes(wrong_sha))
    for name, match in (("cut", "corrupt or cut short"), ("other", "not a file written by"),
                        ("sha", "do not match the SHA-256")):
        with pytest.raises(DatasetError, match=match):
            unpack_file(tmp_path / f"{name}.s4xz", tmp_path / f"{name}.out")
        assert not (tmp_path / f"{name}.out").exists()
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(DatasetError, match="empty"):
        pack_file(tmp_path / "empty.ckpt", tmp_path / "e.s4xz")
    assert main(["unpack-file", str(tmp_path / "cut.s4xz"), str(tmp_path / "c.out")]) == 2
    assert "corrupt or cut short" in capsys.readouterr().err
    assert main(["pack-file", str(src), str(tmp_path / "b.s4xz")]) == 0 and (tmp_path / "b.s4xz").is_file()
