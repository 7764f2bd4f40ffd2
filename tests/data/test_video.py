"""raw_video.mp4 I/O: the selective one-pass decoder against the decode-everything reference, frame alignment,
the crop + resize geometry against FisheyeIntrinsics.scaled, bad files."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.errors import DatasetError

pytest.importorskip("imageio_ffmpeg")

W, H, N = 128, 96, 23


def _frame(i: int, w: int = W, h: int = H) -> np.ndarray:
    """Smooth texture that moves with ``i`` plus a flat central block whose grey level encodes the frame index."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.stack([128 + 100 * np.sin(xx / 7.0 + i / 3.0), 128 + 100 * np.cos(yy / 5.0 - i / 4.0),
                    128 + 90 * np.sin((xx + yy) / 11.0)], -1)
    img[h // 3 : 2 * h // 3, w // 3 : 2 * w // 3] = 10 * i + 5
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    from umi_aug.data.video import VideoWriter

    p = tmp_path_factory.mktemp("video") / "raw_video.mp4"
    with VideoWriter(p, W, H, 59.94) as w:
        for i in range(N):
            w.write(_frame(i))
    return p


def _index_of(img: np.ndarray) -> int:
    h, w = img.shape[:2]
    v = float(img[h // 2 - 2 : h // 2 + 2, w // 2 - 2 : w // 2 + 2].mean())
    return int(round((v - 5) / 10))


def test_probe(video):
    from umi_aug.data.video import probe_video

    info = probe_video(video)
    assert (info.width, info.height, info.n_frames, info.codec) == (W, H, N, "h264")
    assert abs(info.fps - 59.94) < 0.01


INDEX_SETS = [[], [0], [N - 1], [0, N - 1], list(range(N)), list(range(1, N, 3)), [2, 3, 4, 9, 17, 18, 22],
              [5, 7, 8, 13, 21]]


@pytest.mark.parametrize("idx", INDEX_SETS)
def test_selective_decode_equals_reference_native(video, idx):
    from umi_aug.data._ref import _read_video_frames_reference
    from umi_aug.data.video import read_video_frames

    fast = read_video_frames(video, idx)
    ref = _read_video_frames_reference(video, idx)
    assert fast.shape == ref.shape == (len(idx), H, W, 3)
    np.testing.assert_array_equal(fast, ref)  # same decoder, same colour conversion: bit-exact
    assert [_index_of(f) for f in fast] == idx  # frame k of the file is frame index k
    if idx:
        assert np.abs(fast[0].astype(int) - _frame(idx[0])).mean() < 6.0  # lossy (yuv420p chroma), but close


@pytest.mark.parametrize("size", [(64, 48), (32, 24), (48, 48), (50, 40), (100, 75)])
def test_selective_decode_resized_close_to_reference(video, size):
    from umi_aug.data._ref import _read_video_frames_reference
    from umi_aug.data.video import read_video_frames

    idx = [0, 4, 5, 6, 19, 22]
    fast = read_video_frames(video, idx, size)
    ref = _read_video_frames_reference(video, idx, size)  # full-size decode, crop, cv2.INTER_AREA
    assert fast.shape == ref.shape == (len(idx), size[1], size[0], 3)
    d = np.abs(fast.astype(int) - ref.astype(int))
    assert d.max() <= 4 and d.mean() < 0.25, (d.max(), d.mean())  # swscale area vs cv2.INTER_AREA rounding
    assert [_index_of(f) for f in fast] == idx


def test_huge_index_set_falls_back_to_superset(video, monkeypatch):
    import umi_aug.data.video as V

    idx = [1, 2, 6, 7, 11, 20]
    want = V.read_video_frames(video, idx)
    monkeypatch.setattr(V, "MAX_SELECT_EXPR", 10)
    got = V.read_video_frames(video, idx)
    np.testing.assert_array_equal(got, want)


def test_select_expression_runs():
    from umi_aug.data.video import select_expression

    assert select_expression(np.arange(0, 100, 2)) == "between(n\\,0\\,98)*not(mod(n-0\\,2))"
    assert select_expression(np.array([3])) == "eq(n\\,3)"
    assert select_expression(np.array([1, 2, 3, 10])) == "between(n\\,1\\,3)+eq(n\\,10)"
    assert select_expression(np.array([], dtype=int)) == "0"


def test_resize_geometry_matches_scaled_intrinsics(tmp_path):
    """A blob at the projection of a 3-D point stays at that point's projection through the scaled intrinsics."""
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
    from umi_aug.camera.kb import project
    from umi_aug.data.video import VideoWriter, read_video_frames

    w0, h0 = 320, 240
    intr = gopro_intrinsics_2_7k().scaled(w0, h0)
    pts = np.array([[0.3, -0.2, 1.0], [-0.5, 0.1, 0.8], [0.05, 0.3, 1.0]])
    uv0 = project(pts, intr)[0]
    yy, xx = np.mgrid[0:h0, 0:w0].astype(np.float64)
    img = np.zeros((h0, w0), np.float64)
    for u, v in uv0:
        img += 230 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 3.0 ** 2))
    rgb = np.repeat(np.clip(img, 0, 255).astype(np.uint8)[..., None], 3, -1)
    p = tmp_path / "blob.mp4"
    with VideoWriter(p, w0, h0, 30.0, crf=0) as wr:
        wr.write(rgb)
    for size in [(160, 120), (224, 224), (100, 75)]:
        small = read_video_frames(p, [0], size)[0, ..., 0].astype(np.float64)
        si = intr.scaled(*size)
        uv = project(pts, si)[0]
        ys, xs = np.mgrid[0 : size[1], 0 : size[0]]
        for u, v in uv:
            win = (np.abs(xs - u) < 6) & (np.abs(ys - v) < 6)
            wgt = small * win
            cu, cv = (wgt * xs).sum() / wgt.sum(), (wgt * ys).sum() / wgt.sum()
            assert abs(cu - u) < 0.2 and abs(cv - v) < 0.2, (size, (cu, cv), (u, v))


def test_bad_videos(tmp_path, video):
    from umi_aug.data.video import probe_video, read_video_frames

    with pytest.raises(DatasetError, match="not found"):
        probe_video(tmp_path / "nope.mp4")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(DatasetError, match="junk.mp4.*not a readable video"):
        probe_video(junk)
    with pytest.raises(DatasetError, match=f"frame {N} requested but the video has {N} frames"):
        read_video_frames(video, [0, N])
    with pytest.raises(DatasetError, match="strictly increasing"):
        read_video_frames(video, [3, 3])
    with pytest.raises(DatasetError, match="wider aspect"):
        read_video_frames(video, [0], (200, 50))
    # truncated file: the moov atom (index) is lost or frames are missing → one error naming the file
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(video.read_bytes()[: video.stat().st_size // 2])
    with pytest.raises(DatasetError, match="cut.mp4"):
        read_video_frames(cut, list(range(N)))
