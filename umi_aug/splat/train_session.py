"""Training views from a UMI session folder (:func:`umi_aug.recon.session_io.load_session`) and
:func:`train_splat_from_session`.

Views: every ``scan_stride``-th tracked frame of the mapping scan, plus every ``demo_stride``-th tracked frame of
each demo up to its contact frame (the scene is static only until the gripper touches the object; contact frames
come from ``contact`` or the reconstruction's ``recon_report.json``; a demo without a known contact frame is
skipped). Poses in the world (table-tag) frame. Loss mask = NOT (UMI gripper/mirror[/finger] polygons) AND inside
the valid KB image circle. Optional training at a reduced width (intrinsics via
:meth:`FisheyeIntrinsics.scaled`, frames cropped the same way and resized with ``cv2.INTER_AREA``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Mapping

import cv2
import numpy as np

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.kb import unproject
from umi_aug.camera.masks import predefined_mask
from umi_aug.errors import SplatError, UmiAugError
from umi_aug.recon.session_io import load_session
from umi_aug.splat.ply import _parse_header
from umi_aug.splat.train import SplatTrainConfig, SplatTrainResult, TrainView, scene_scale, train_splat

__all__ = ["session_views", "loss_mask", "read_point_cloud", "random_init_points", "train_splat_from_session",
           "resize_frame", "top_up_init_points", "DEFAULT_INIT_EXTENT", "DEFAULT_RANDOM_POINTS",
           "DEFAULT_MIN_INIT_FRACTION"]

log = logging.getLogger(__name__)

#: Random initialisation: points uniform in a cube of half-side ``DEFAULT_INIT_EXTENT x scene scale`` around the
#: mean camera centre (gsplat ``init_extent``), ``DEFAULT_RANDOM_POINTS`` of them.
DEFAULT_INIT_EXTENT: float = 3.0
DEFAULT_RANDOM_POINTS: int = 30_000
#: A point cloud below this fraction of the Gaussian budget is topped up with random points.
DEFAULT_MIN_INIT_FRACTION: float = 0.5


def loss_mask(intr: FisheyeIntrinsics, finger: bool = True) -> np.ndarray:
    """``[H, W]`` bool: pixel inside the valid KB image circle and not covered by UMI's gripper / mirror (and,
    with ``finger``, finger) polygons."""
    H, W = intr.height, intr.width
    vv, uu = np.mgrid[0:H, 0:W]
    _, valid = unproject(np.stack([uu, vv], axis=-1).astype(np.float64), intr)
    return valid & ~predefined_mask(H, W, mirror=True, gripper=True, finger=finger)


def resize_frame(img: np.ndarray, intr: FisheyeIntrinsics, width: int, height: int) -> np.ndarray:
    """The image operation matching ``intr.scaled(width, height)``: full-height centre crop to the aspect ratio,
    then ``cv2.resize`` with INTER_AREA. ``img [H, W, 3]`` uint8 at ``intr``'s size."""
    intr.check_image_shape(img.shape)
    x0, y0, cw, ch = intr.crop_geometry(width, height)
    if x0 < 0:
        raise SplatError(f"resize_frame: {width}x{height} is wider than the {intr.width}x{intr.height} frame's aspect")
    crop = img[y0 : y0 + ch, x0 : x0 + cw]
    return cv2.resize(crop, (width, height), interpolation=cv2.INTER_AREA)


def _contacts_from_report(path: Path) -> dict[str, int]:
    try:
        rep = json.loads(Path(path).read_text())
        return {c["episode"]: int(c["contact_index"]) for c in rep["contacts"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SplatError(f"{path}: cannot read contacts[].episode / contact_index ({exc})") from exc


def session_views(
    session_dir: str | Path,
    *,
    image_size: int | None = None,
    contact: Mapping[str, int] | None = None,
    recon_report: str | Path | None = None,
    scan_stride: int = 1,
    demo_stride: int = 4,
    mask_finger: bool = True,
) -> tuple[list[TrainView], FisheyeIntrinsics]:
    """Posed, masked training views of a session (see the module docstring).

    Args:
        session_dir: UMI session folder.
        image_size: train at this width (height keeps the aspect ratio); None = the frames' size.
        contact: demo name -> contact frame index (overrides ``recon_report``).
        recon_report: ``recon_report.json`` of :func:`umi_aug.recon.reconstruct_session` (contact indices);
            default ``<session>/recon/recon_report.json`` when present.
        scan_stride, demo_stride: use every n-th frame.
        mask_finger: also exclude UMI's finger trapezoid (the fingers move during demos).

    Returns:
        ``(views, intrinsics)`` at the training resolution.
    """
    root = Path(session_dir)
    try:
        sess = load_session(root)
    except UmiAugError as exc:
        raise SplatError(f"{root}: {exc}") from exc
    intr0 = sess.intrinsics
    if image_size is None or int(image_size) == intr0.width:
        intr, size = intr0, None
    else:
        w = int(image_size)
        h = int(round(w * intr0.height / intr0.width))
        intr, size = intr0.scaled(w, h), (w, h)
    contacts: dict[str, int] = {}
    rp = Path(recon_report) if recon_report is not None else root / "recon" / "recon_report.json"
    if recon_report is not None or rp.is_file():
        contacts.update(_contacts_from_report(rp))
    contacts.update({k: int(v) for k, v in (contact or {}).items()})
    mask = loss_mask(intr, finger=mask_finger)

    seqs = [(sess.mapping, len(sess.mapping), max(1, int(scan_stride)))]
    for d in sess.demos:
        if d.name not in contacts:
            log.info("%s: no contact frame known; its frames are not used for training", d.name)
            continue
        seqs.append((d, min(len(d), contacts[d.name] + 1), max(1, int(demo_stride))))
    views = []
    for seq, n, stride in seqs:
        if seq.T_world_cam is None:
            log.warning("%s: no camera trajectory; skipped", seq.name)
            continue
        ks = [k for k in range(0, n, stride) if seq.valid[k]]  # SLAM-lost frames have no pose: skipped
        try:  # one sequential decode per video, only these frames, at the training size
            for k, img in seq.iter_frames(ks, size):
                views.append(TrainView(f"{seq.name}/{seq.frame_name(k)}", np.array(img),
                                       np.asarray(seq.T_world_cam[k], dtype=np.float64), mask.copy()))
        except UmiAugError as exc:
            raise SplatError(f"{root}: {exc}") from exc
    if not views:
        raise SplatError(f"{root}: no tracked frames with poses to train on")
    return views, intr


def read_point_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``xyz [N, 3]`` float64 and ``rgb [N, 3]`` in [0, 1] (None without ``red/green/blue``) of a PLY point cloud
    (any binary/ASCII PLY with x, y, z; e.g. recon's ``scene_cloud.ply``, the simulator's ``scene_points.ply``)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SplatError(f"{path}: cannot read point cloud ({exc})") from exc
    fmt, elements, offset = _parse_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise SplatError(f"{path}: PLY has no 'vertex' element")
    vi = names.index("vertex")
    _, n, props = elements[vi]
    if any(t == "list" for _, t in props) or fmt == "ascii" and vi != 0:
        raise SplatError(f"{path}: unsupported point-cloud PLY layout (list properties / ASCII with extra elements)")
    if fmt == "ascii":
        rows = [r.split() for r in raw[offset:].decode("ascii").splitlines() if r.strip()][:n]
        table = np.asarray(rows, dtype=np.float64).reshape(-1, len(props))
        cols = {p: table[:, j] for j, (p, _) in enumerate(props)}
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        for _, cnt, ep in elements[:vi]:
            offset += cnt * sum(np.dtype(t).itemsize for _, t in ep)
        dt = np.dtype([(p, end + t) for p, t in props])
        if len(raw) < offset + n * dt.itemsize:
            raise SplatError(f"{path}: truncated PLY ({n} vertices)")
        arr = np.frombuffer(raw, dtype=dt, count=n, offset=offset)
        cols = {p: arr[p] for p, _ in props}
    if not all(k in cols for k in "xyz"):
        raise SplatError(f"{path}: vertices lack x/y/z")
    xyz = np.stack([cols[k] for k in "xyz"], axis=1).astype(np.float64)
    rgb = None
    if all(k in cols for k in ("red", "green", "blue")):
        rgb = np.stack([cols[k] for k in ("red", "green", "blue")], axis=1).astype(np.float64) / 255.0
    ok = np.isfinite(xyz).all(axis=1)
    if not ok.all():
        log.warning("%s: %d non-finite points dropped", path, int((~ok).sum()))
        xyz, rgb = xyz[ok], (None if rgb is None else rgb[ok])
    if len(xyz) == 0:
        raise SplatError(f"{path}: point cloud has no finite points")
    return xyz, rgb


def random_init_points(T_world_cam: np.ndarray, n: int, rng: np.random.Generator,
                       extent: float = DEFAULT_INIT_EXTENT) -> np.ndarray:
    """``n`` points uniform in the cube of half-side ``extent x scene_scale`` around the mean camera centre
    (``T_world_cam [V, 4, 4]``), world frame, metres."""
    c = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    half = extent * scene_scale(T_world_cam)
    return c.mean(0) + rng.uniform(-half, half, size=(int(n), 3))


def top_up_init_points(xyz: np.ndarray, rgb: np.ndarray | None, n: int, T_world_cam: np.ndarray,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``xyz [N, 3]`` (+ ``rgb [N, 3]`` in [0, 1] or None) plus ``max(0, n - N)`` random points around the cameras
    (:func:`random_init_points`, random colours) → ``(xyz [max(N, n), 3], rgb [max(N, n), 3])``.

    A sparse SfM cloud (a few thousand points) alone starves the budgeted MCMC growth (N x growth_factor per
    refinement) and its Gaussians start huge (scale from the nearest-neighbour distance), which makes every step
    slow; random points fill the rest of the scene as random initialisation would.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = rng.uniform(0.0, 1.0, (len(xyz), 3)) if rgb is None else np.asarray(rgb, np.float64).reshape(-1, 3)
    extra = max(0, int(n) - len(xyz))
    if extra == 0:
        return xyz, rgb
    return (np.concatenate([xyz, random_init_points(T_world_cam, extra, rng)]),
            np.concatenate([rgb, rng.uniform(0.0, 1.0, (extra, 3))]))


def train_splat_from_session(
    session_dir: str | Path,
    out_dir: str | Path,
    cfg: SplatTrainConfig = SplatTrainConfig(),
    *,
    init_cloud: str | Path | None = None,
    image_size: int | None = None,
    contact: Mapping[str, int] | None = None,
    recon_report: str | Path | None = None,
    scan_stride: int = 1,
    demo_stride: int = 4,
    mask_finger: bool = True,
    max_init_points: int | None = None,
    min_init_fraction: float = DEFAULT_MIN_INIT_FRACTION,
    n_random_points: int = DEFAULT_RANDOM_POINTS,
    resume: bool = True,
    progress: bool = True,
    stop_at: int | None = None,
) -> SplatTrainResult:
    """Train a fisheye 3DGS scene on a UMI session (views from :func:`session_views`).

    Args:
        session_dir, out_dir: the session folder and the output folder (see :func:`train_splat`).
        cfg: trainer settings.
        init_cloud: PLY point cloud (with colours) for the initial Gaussians, e.g. recon's ``scene_cloud.ply``;
            None = ``n_random_points`` random points around the cameras (:func:`random_init_points`).
        max_init_points: random subset of the cloud of at most this many points (default ``cfg.max_gaussians``).
        min_init_fraction: a cloud with fewer than this fraction of ``cfg.max_gaussians`` points is topped up with
            random points around the cameras (a sparse cloud alone starves the budgeted growth).
        image_size, contact, recon_report, scan_stride, demo_stride, mask_finger: see :func:`session_views`.
        resume, progress, stop_at: see :func:`train_splat`.
    """
    views, intr = session_views(session_dir, image_size=image_size, contact=contact, recon_report=recon_report,
                                scan_stride=scan_stride, demo_stride=demo_stride, mask_finger=mask_finger)
    rng = np.random.default_rng([cfg.seed, 0x1A17])
    if init_cloud is not None:
        xyz, rgb = read_point_cloud(init_cloud)
        cap = cfg.max_gaussians if max_init_points is None else int(max_init_points)
        if len(xyz) > cap:
            keep = np.sort(rng.choice(len(xyz), cap, replace=False))
            xyz, rgb = xyz[keep], (None if rgb is None else rgb[keep])
        floor = min(cap, int(min_init_fraction * cfg.max_gaussians))
        if len(xyz) < floor:
            log.info("%s: %d cloud points < %d: topping up with random points", init_cloud, len(xyz), floor)
            xyz, rgb = top_up_init_points(xyz, rgb, floor, np.stack([v.T_world_cam for v in views]), rng)
    else:
        xyz = random_init_points(np.stack([v.T_world_cam for v in views]), min(n_random_points, cfg.max_gaussians),
                                 rng)
        rgb = None
    log.info("%s: %d views at %dx%d, %d initial points", session_dir, len(views), intr.width, intr.height, len(xyz))
    return train_splat(views, intr, xyz, rgb, cfg, out_dir, resume=resume, progress=progress, stop_at=stop_at)
