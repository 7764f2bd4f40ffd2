"""Video files of UMI sessions (``raw_video.mp4``): probe, selective decoding at a reduced size, an H.264 writer.

UMI keeps only the GoPro's videos (2.7K, 59.94 fps; umi_stack.md §1); the stages need a subset of the frames at a
fraction of that size. :func:`iter_video_frames` runs ONE sequential ffmpeg pass (the ``imageio-ffmpeg`` binary)
that keeps only the requested frame indices (``select`` before any other filter, so only those frames are cropped,
resized and converted) and stops after the last one: the full-size frames never leave ffmpeg.
:func:`umi_aug.data._ref._read_video_frames_reference` is the slow obviously-correct path (every frame decoded at
full size with the plain reader, crop + ``cv2.INTER_AREA`` in numpy/OpenCV) the tests compare against.

Frame indices are 0-based decode (presentation) order, the same ``frame_idx`` UMI's SLAM writes into
``camera_trajectory.csv``. Resizing is the full-height centre crop of ``crop_geometry`` followed by an area resize,
so the intrinsics of the result are ``FisheyeIntrinsics.scaled(w, h)``. Every problem raises
:class:`umi_aug.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import os
import pickle
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from tqdm import tqdm

from umi_aug.errors import DatasetError

__all__ = ["VideoInfo", "probe_video", "iter_video_frames", "read_video_frames", "select_expression", "VideoWriter",
           "centre_crop", "DEFAULT_CRF", "inpaint_tag", "read_tag_detections", "TAG_SCALE"]

#: libx264 constant rate factor of :class:`VideoWriter` (lower = better). 8 keeps the synthetic session's frames
#: at least as close to the renders as the JPEG-95 frames it used to write: PSNR against 40 rendered 320x240 scan
#: frames: JPEG-95 35.99 dB; with ``-tune psnr`` crf 12 36.07, 10 36.24, 8 36.37 dB (default tune: crf 16 34.86,
#: 12 35.72, 10 36.00, 8 36.20 dB).
DEFAULT_CRF: int = 8
#: Longest ``select`` expression passed on the command line; longer index sets decode a superset (gcd stride).
MAX_SELECT_EXPR: int = 60_000


def _ffmpeg() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as exc:  # pragma: no cover - part of the sim/recon extras
        raise DatasetError("reading/writing raw_video.mp4 needs imageio-ffmpeg (pip install 'umi-aug[recon]' or "
                           "'umi-aug[sim]')") from exc
    return imageio_ffmpeg.get_ffmpeg_exe()


@dataclass(frozen=True)
class VideoInfo:
    """First video stream of a file: ``width x height`` pixels, ``fps`` (average rate), ``n_frames`` (packets)."""

    path: Path
    width: int
    height: int
    fps: float
    n_frames: int
    codec: str


_STREAM = re.compile(r"Stream #\d+:\d+.*?: Video: (\w+).*?, (\d{2,5})x(\d{2,5})")
_FPS = re.compile(r"([\d.]+) fps")
_FRAME = re.compile(r"frame=\s*(\d+)")


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Size, frame rate and frame count of ``path``'s first video stream (packets counted without decoding).

    Raises:
        DatasetError: missing file, not a video / no video stream, ffmpeg failure.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: video file not found")
    cmd = [_ffmpeg(), "-hide_banner", "-nostdin", "-i", str(path), "-map", "0:v:0", "-c", "copy", "-f", "null", "-"]
    res = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = res.stderr.decode(errors="replace")
    m = _STREAM.search(err)
    frames = _FRAME.findall(err)
    if res.returncode != 0 or m is None or not frames:
        tail = " | ".join(err.strip().splitlines()[-3:])
        raise DatasetError(f"{path}: not a readable video (ffmpeg: {tail or 'no video stream'}); re-copy the "
                           f"GoPro file or re-create the session")
    line = err[m.start():].splitlines()[0]
    f = _FPS.search(line)
    return VideoInfo(path, int(m.group(2)), int(m.group(3)), float(f.group(1)) if f else float("nan"),
                     int(frames[-1]), m.group(1))


def centre_crop(width: int, height: int, out_width: int, out_height: int) -> tuple[int, int, int, int]:
    """Full-height, horizontally centred crop with the output's aspect ratio (``FisheyeIntrinsics.crop_geometry``):
    ``(x0, y0, crop_w, crop_h)``."""
    crop_h = int(height)
    crop_w = int(round(height * out_width / out_height))
    return (int(width) - crop_w) // 2, 0, crop_w, crop_h


def _check_indices(path: Path, indices: Sequence[int] | np.ndarray) -> np.ndarray:
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    if len(idx) and (idx[0] < 0 or np.any(np.diff(idx) <= 0)):
        raise DatasetError(f"{path}: frame indices must be non-negative and strictly increasing, got "
                           f"{idx[:8].tolist()}{'...' if len(idx) > 8 else ''}")
    return idx


def select_expression(indices: np.ndarray) -> str:
    """ffmpeg ``select`` expression true exactly on the (sorted, unique) frame numbers ``n`` in ``indices``:
    one ``between(n,a,b)*not(mod(n-a,s))`` term per maximal arithmetic run."""
    idx = [int(i) for i in indices]
    terms, k = [], 0
    while k < len(idx):
        if k + 1 == len(idx):
            terms.append(f"eq(n\\,{idx[k]})")
            break
        step = idx[k + 1] - idx[k]
        j = k + 1
        while j + 1 < len(idx) and idx[j + 1] - idx[j] == step:
            j += 1
        if j == k + 1 and step != 1:
            terms.append(f"eq(n\\,{idx[k]})")
            k += 1
            continue
        a, b = idx[k], idx[j]
        terms.append(f"between(n\\,{a}\\,{b})" + (f"*not(mod(n-{a}\\,{step}))" if step > 1 else ""))
        k = j + 1
    return "+".join(terms) if terms else "0"


def _resize_args(info: VideoInfo, size: tuple[int, int] | None) -> tuple[list[str], int, int]:
    if size is None or tuple(size) == (info.width, info.height):
        return [], info.width, info.height
    w, h = int(size[0]), int(size[1])
    x0, y0, cw, ch = centre_crop(info.width, info.height, w, h)
    if x0 < 0 or w < 1 or h < 1:
        raise DatasetError(f"{info.path}: cannot crop+resize the {info.width}x{info.height} frames to {w}x{h} "
                           f"(wider aspect than the video)")
    crop = [] if (cw, ch) == (info.width, info.height) else [f"crop={cw}:{ch}:{x0}:{y0}"]
    return crop + ["format=rgb24", f"scale={w}:{h}:flags=area"], w, h


def iter_video_frames(path: str | os.PathLike, indices: Sequence[int] | np.ndarray,
                      size: tuple[int, int] | None = None, *, info: VideoInfo | None = None,
                      threads: int = 2) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(frame_index, rgb [h, w, 3] uint8)`` for the requested frames of ``path``, in order, from one
    sequential decode that stops after the last requested frame.

    Args:
        path: the video.
        indices: strictly increasing 0-based frame indices.
        size: ``(w, h)`` output size (full-height centre crop to its aspect, area resize); None = native.
        info: :func:`probe_video` result if already known.
        threads: ffmpeg decoder threads.
    Raises:
        DatasetError: unreadable video, an index past the last frame, a decode that ends early (corrupt file).
    """
    path = Path(path)
    idx = _check_indices(path, indices)
    info = info or probe_video(path)
    if len(idx) == 0:
        return
    if idx[-1] >= info.n_frames:
        raise DatasetError(f"{path}: frame {int(idx[-1])} requested but the video has {info.n_frames} frames")
    expr = select_expression(idx)
    stride_filter = None
    if len(expr) > MAX_SELECT_EXPR:  # irregular and huge: decode a gcd-strided superset, keep the rest in Python
        g = int(np.gcd.reduce(np.diff(idx))) if len(idx) > 1 else 1
        expr = select_expression(np.arange(idx[0], idx[-1] + 1, g))
        stride_filter = set(idx.tolist())
    filters, w, h = _resize_args(info, size)
    vf = ",".join([f"select='{expr}'", *filters, "format=rgb24"])
    n_out = len(idx) if stride_filter is None else len(range(idx[0], idx[-1] + 1, max(1, g)))
    cmd = [_ffmpeg(), "-hide_banner", "-nostdin", "-loglevel", "error", "-threads", str(int(threads)),
           "-i", str(path), "-map", "0:v:0", "-vf", vf, "-fps_mode", "passthrough", "-frames:v", str(n_out),
           "-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=w * h * 3)
    nbytes = w * h * 3
    got = 0
    candidates = idx.tolist() if stride_filter is None else list(range(idx[0], idx[-1] + 1, max(1, g)))
    try:
        for k in candidates:
            buf = proc.stdout.read(nbytes)
            if len(buf) < nbytes:
                break
            got += 1
            if stride_filter is not None and k not in stride_filter:
                continue
            yield k, np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 3)
    finally:
        proc.stdout.close()
        if got < n_out:
            proc.kill()
        proc.wait()
        err = proc.stderr.read().decode(errors="replace").strip()
        proc.stderr.close()
    if got < n_out:
        raise DatasetError(f"{path}: decoding stopped after {got} of {n_out} requested frames (first missing: "
                           f"frame {candidates[got]}); the video is truncated or corrupt"
                           + (f" (ffmpeg: {err.splitlines()[-1]})" if err else ""))


def read_video_frames(path: str | os.PathLike, indices: Sequence[int] | np.ndarray,
                      size: tuple[int, int] | None = None, *, progress: bool = False, threads: int = 2) -> np.ndarray:
    """The frames of :func:`iter_video_frames` stacked: ``[K, h, w, 3]`` uint8 RGB."""
    idx = _check_indices(Path(path), indices)
    info = probe_video(path)
    _, w, h = _resize_args(info, size)
    out = np.empty((len(idx), h, w, 3), dtype=np.uint8)
    it = iter_video_frames(path, idx, size, info=info, threads=threads)
    if progress:
        it = tqdm(it, total=len(idx), desc=f"decode {Path(path).parent.name}/{Path(path).name}", unit="frame")
    for j, (_, img) in enumerate(it):
        out[j] = img
    return out


class VideoWriter:
    """Streaming H.264 (libx264, yuv420p like the GoPro's files) mp4 writer; single-threaded bit-exact flags, so the
    same frames give the same bytes. ``crf``: constant rate factor (0 = lossless luma, 8 default).

    ``-tune psnr`` turns off x264's psycho-visual optimisations, which add detail that is not in the source: with
    them, full SfM on the 40-frame synthetic scan mis-registered one frame at COLMAP seeds 0, 2 and 3 (Sim(3)
    residual 190-280 mm) where the JPEG-95 frames never did; with ``-tune psnr`` seeds 0 and 2 register correctly
    (1.2 / 1.7 mm) and the frames are closer to the renders (40.4 vs 39.6 dB)."""

    def __init__(self, path: str | os.PathLike, width: int, height: int, fps: float, crf: int = DEFAULT_CRF) -> None:
        try:
            import imageio_ffmpeg
        except ImportError as exc:  # pragma: no cover - part of the sim extra
            raise DatasetError("writing raw_video.mp4 needs imageio-ffmpeg (pip install 'umi-aug[sim]')") from exc
        self.path = Path(path)
        self._gen = imageio_ffmpeg.write_frames(
            str(self.path), (int(width), int(height)), fps=fps, codec="libx264", pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p", quality=None, macro_block_size=1, ffmpeg_log_level="error",
            output_params=["-crf", str(int(crf)), "-preset", "veryfast", "-tune", "psnr", "-threads", "1",
                           "-map_metadata", "-1",
                           "-fflags", "+bitexact", "-flags:v", "+bitexact"],
        )
        self._gen.send(None)

    def write(self, rgb: np.ndarray) -> None:
        """Append one ``[H, W, 3]`` uint8 RGB frame."""
        self._gen.send(np.ascontiguousarray(rgb))

    def close(self) -> None:
        """Finish the file."""
        self._gen.close()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------------ ArUco tags
#: UMI's ``inpaint_tag``: the tag quad is grown this many times about its centre before filling.
TAG_SCALE = 1.4
#: Points sampled along the grown quad's border for the fill colour.
TAG_BORDER_SAMPLES = 16


def inpaint_tag(img: np.ndarray,  # [H, W, 3] uint8, modified in place
                corners: np.ndarray,  # [4, 2] tag corners, pixels (x, y) of img
                scale: float = TAG_SCALE, n_samples: int = TAG_BORDER_SAMPLES) -> np.ndarray:
    """Cover one ArUco tag the way UMI's 07_generate_replay_buffer does (``inpaint_tag``): grow the quad ``scale``
    times about its centre, take the median colour of ``n_samples`` points along the grown quad's border
    (clipped to the image) and fill the grown quad with it. Returns ``img``."""
    import cv2  # lazy: start-up time (OpenCV loads in a fraction of a second; most callers only decode)

    c = np.asarray(corners, np.float64).reshape(4, 2)
    grown = scale * (c - c.mean(axis=0)) + c.mean(axis=0)
    closed = np.concatenate([grown, grown[:1]])
    t = np.linspace(0.0, 4.0, int(n_samples))
    seg = np.minimum(t.astype(int), 3)
    pts = closed[seg] + (t - seg)[:, None] * (closed[seg + 1] - closed[seg])
    pts = pts.astype(np.int32)
    h, w = img.shape[:2]
    colour = np.median(img[np.clip(pts[:, 1], 0, h - 1), np.clip(pts[:, 0], 0, w - 1)], axis=0).astype(img.dtype)
    cv2.fillPoly(img, [grown.astype(np.int32)], color=[int(v) for v in colour])
    return img


def read_tag_detections(path: str | os.PathLike) -> dict[int, list[np.ndarray]]:
    """UMI's ``tag_detection.pkl`` (04_detect_aruco: one entry per video frame, ``{frame_idx, time,
    tag_dict: {id: {rvec, tvec, corners}}}``) → ``{frame_idx: [corners [4, 2] (x, y) pixels of the video, ...]}``
    (frames without a tag left out).

    Raises:
        DatasetError: unreadable file or entries without ``frame_idx`` / ``tag_dict`` / ``corners``.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            rows = pickle.load(f)  # the session's own pipeline output (UMI writes it with pickle)
        out: dict[int, list[np.ndarray]] = {}
        for i, r in enumerate(rows):
            tags = [np.asarray(t["corners"], np.float64).reshape(4, 2) for t in dict(r["tag_dict"]).values()]
            if tags:
                out[int(r.get("frame_idx", i))] = tags
    except Exception as exc:  # noqa: BLE001 - any unpickling/shape failure is the same bad-input error
        raise DatasetError(f"{p}: unreadable tag detections ({type(exc).__name__}: {exc}); expected UMI's "
                           f"04_detect_aruco output (a list of {{frame_idx, time, tag_dict: {{id: {{corners}}}}}})"
                           ) from exc
    return out
