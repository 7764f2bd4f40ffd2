"""Structure from motion with pycolmap on fisheye video frames (paper §3.1).

Camera model ``OPENCV_FISHEYE`` (= our Kannala–Brandt, :mod:`umi_aug.camera.kb`) with the session's intrinsics held
FIXED (never refined: UMI's calibration is better than what a few dozen frames can estimate). Gripper pixels and the
black border outside the fisheye image circle are masked out of feature extraction. Matching suits video:
each frame against its next ``overlap`` frames of the same sequence, plus a sparse all-pairs grid of every
``loop_stride``-th frame over all sequences (loop closure without COLMAP's vocabulary tree, whose file would
have to be downloaded), plus, when poses are known, pairs of cameras that are close and look the same way.

Two modes:
* ``full``: incremental mapping; poses come out in COLMAP's arbitrary similarity frame (align them with
  :func:`umi_aug.recon.align.align_sfm_to_poses`).
* ``known_poses``: the cameras are fixed at given ``T_world_cam`` (UMI SLAM / ARKit poses) and points are only
  triangulated: the result is directly in the metric world frame.

COLMAP's pixel convention differs from ours by half a pixel (:func:`colmap_camera_params`).
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Sequence

import cv2
import numpy as np

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.masks import predefined_mask
from umi_aug.errors import ReconError
from umi_aug.geometry import hat
from umi_aug.recon import constants as C
from umi_aug.recon.colmap_blocks import extract_in_blocks
from umi_aug.recon.session_io import check_image_sizes
from umi_aug.runtime import restore_python_signal_handlers

__all__ = ["SfmConfig", "SfmResult", "run_sfm", "colmap_camera_params", "feature_mask", "video_pairs",
           "pose_pairs"]

log = logging.getLogger(__name__)

SfmMode = Literal["full", "known_poses"]


def _pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - recon extra
        raise ReconError("structure from motion needs pycolmap: pip install 'umi-aug[recon]' "
                         "(pycolmap==4.2.1)") from exc

    restore_python_signal_handlers()  # glog's SIGTERM handler printed 21 native frames instead of our one line
    # COLMAP's glog INFO/WARNING lines stay out of the user's console unless they ask for them (DEBUG logging of
    # this module, e.g. `umi-aug -v`); errors still print.
    pycolmap.logging.minloglevel = 0 if log.isEnabledFor(logging.DEBUG) else 2
    return pycolmap


@dataclass(frozen=True)
class SfmConfig:
    """Settings of :func:`run_sfm`.

    Attributes:
        mode: ``"full"`` SfM or ``"known_poses"`` triangulation.
        max_num_features: SIFT features per frame.
        max_image_size: longest side features are extracted at (-1 = full size; keypoints are rescaled).
        peak_threshold: SIFT peak threshold.
        overlap: sequential neighbours matched per frame.
        loop_stride: every this-many-th frame enters the all-pairs loop grid (0 = off).
        pose_pair_max_dist_m / pose_pair_max_angle_deg: extra pairs from known poses (``known_poses`` or when
            poses are given; 0 = off).
        min_registered_fraction / min_registered: refuse reconstructions registering fewer frames.
        num_threads: cores for feature extraction (blocks of frames, one COLMAP thread each, joined into the
            bytes of one thread: :mod:`umi_aug.recon.colmap_blocks`; on the real episode 9.7 -> 5.2 s with 2)
            and for ``full`` mode's matching threads and mapping. ``known_poses`` mode matches and triangulates
            with one COLMAP thread, so a known-pose cloud is the same bytes run after run and for every
            ``num_threads`` (COLMAP's own extraction pool stored keypoints in the order its threads finished,
            and with 2 matching threads on a loaded machine the verification kept other inliers: 459 vs 460
            points, tests/recon/test_sfm_determinism.py beside 3 busy processes; the triangulation took the same
            time on 1 thread, and the FAISS matcher keeps two cores busy from one COLMAP thread). ``full``
            mode's matching and mapping are multi-threaded and not bit-reproducible.
        seed: COLMAP random seed (reproducible RANSAC).
        known_pose_verification: ``known_poses`` mode only: keep each matched pair's matches that agree with the
            essential matrix of the two known poses (Sampson error within COLMAP's 4 px, on the normalised image
            plane as COLMAP measures it) instead of COLMAP's two-view RANSAC, which estimates that matrix again
            from the matches (about a third of the matching stage's time). Pairs with a baseline under 1 mm or
            fewer than COLMAP's 15 inliers keep no geometry. False: COLMAP's verification.
    """

    mode: SfmMode = "full"
    max_num_features: int = C.SIFT_MAX_FEATURES
    max_image_size: int = -1
    peak_threshold: float = C.SIFT_PEAK_THRESHOLD
    overlap: int = C.SEQUENTIAL_OVERLAP
    loop_stride: int = C.LOOP_STRIDE
    pose_pair_max_dist_m: float = 0.25
    pose_pair_max_angle_deg: float = 45.0
    min_registered_fraction: float = C.MIN_REGISTERED_FRACTION
    min_registered: int = C.MIN_REGISTERED_IMAGES
    num_threads: int = 2
    seed: int = 0
    known_pose_verification: bool = False


@dataclass
class SfmResult:
    """Output of :func:`run_sfm`.

    Attributes:
        names: list of N image names (``<sequence>/<file>``), input order.
        registered: np.ndarray,  # [N] bool
        T_world_cam: np.ndarray,  # [N, 4, 4] camera poses in the reconstruction frame (identity if unregistered)
        points: np.ndarray,  # [P, 3] float64 3-D points, reconstruction frame
        colors: np.ndarray,  # [P, 3] uint8 RGB
        errors_px: np.ndarray,  # [P] mean reprojection error of each point, pixels
        track_length: np.ndarray,  # [P] number of observing images
        view_dirs: np.ndarray,  # [P, 3] unit vector from the point towards the mean of its observing cameras
        mean_reproj_error_px: float
        obs_point: np.ndarray,  # [O] int index into points of each observation (point seen by a camera)
        obs_image: np.ndarray,  # [O] int index into names of the observing image
        mode: "full" or "known_poses" ("known_poses": the frame is the metric world frame)
        timings_s: dict of stage → seconds (extract, match, map)
        n_models: number of disconnected models COLMAP found (the largest is kept)
    """

    names: list[str]
    registered: np.ndarray
    T_world_cam: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    errors_px: np.ndarray
    track_length: np.ndarray
    view_dirs: np.ndarray
    mean_reproj_error_px: float
    obs_point: np.ndarray
    obs_image: np.ndarray
    mode: str
    timings_s: dict[str, float] = field(default_factory=dict)
    n_models: int = 1

    @property
    def registered_fraction(self) -> float:
        return float(np.mean(self.registered)) if len(self.registered) else 0.0

    def transformed(self, s: float, R: np.ndarray, t: np.ndarray) -> "SfmResult":
        """The result mapped by the similarity ``x ↦ s R x + t`` (poses keep unit-scale rotations)."""
        T = self.T_world_cam.copy()
        T[:, :3, :3] = R @ T[:, :3, :3]
        T[:, :3, 3] = s * self.T_world_cam[:, :3, 3] @ R.T + t
        return SfmResult(list(self.names), self.registered.copy(), T, s * self.points @ R.T + t, self.colors,
                         self.errors_px, self.track_length, self.view_dirs @ R.T, self.mean_reproj_error_px,
                         self.obs_point, self.obs_image, self.mode, dict(self.timings_s), self.n_models)


def colmap_camera_params(intr: FisheyeIntrinsics) -> list[float]:
    """``OPENCV_FISHEYE`` parameters ``[fx, fy, cx, cy, k1, k2, k3, k4]`` in COLMAP's pixel convention.

    COLMAP places the top-left pixel's centre at (0.5, 0.5), we (OpenCV) at (0, 0): ``c_colmap = c + 0.5``. This is
    the only place the conversion happens (tested in tests/recon/test_sfm.py)."""
    o = C.COLMAP_PIXEL_OFFSET
    return [intr.fx, intr.fy, intr.cx + o, intr.cy + o, *intr.k]


def feature_mask(intr: FisheyeIntrinsics, gripper_mask: np.ndarray | None = None,
                 dilate_px: int = C.MASK_DILATE_PX) -> np.ndarray:
    """Where features may be extracted: ``[H, W]`` uint8, 255 = keep, 0 = masked (COLMAP's mask format).

    Masks UMI's predefined gripper + finger + mirror polygons (:func:`umi_aug.camera.predefined_mask`, as UMI's SLAM
    mask) or ``gripper_mask`` (``[H, W]`` bool, True = gripper, e.g. a session's own mask), grown by ``dilate_px``,
    and everything outside ``IMAGE_CIRCLE_MARGIN`` of the valid fisheye image circle."""
    h, w = intr.height, intr.width
    if gripper_mask is None:
        gm = predefined_mask(h, w, mirror=True, gripper=True, finger=True)
    else:
        gm = np.asarray(gripper_mask, dtype=bool)
        if gm.shape != (h, w):
            raise ReconError(f"feature_mask: gripper mask of shape {gm.shape} does not match the intrinsics "
                             f"{w}x{h}")
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        gm = cv2.dilate(gm.astype(np.uint8), k) > 0
    rx, ry = intr.image_circle_radius_px
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    inside = ((u - intr.cx) / rx) ** 2 + ((v - intr.cy) / ry) ** 2 <= C.IMAGE_CIRCLE_MARGIN ** 2
    return np.where(inside & ~gm, 255, 0).astype(np.uint8)


def video_pairs(lengths: Sequence[int], overlap: int, loop_stride: int) -> np.ndarray:
    """Image pairs for video: sequential within each sequence + a sparse all-pairs loop grid.

    Args:
        lengths: frames per sequence; images are numbered consecutively over the sequences.
        overlap: each frame is paired with the next ``overlap`` frames of its sequence.
        loop_stride: frames whose index within their sequence is a multiple of this are paired with each other
            across the whole set (0 = off).
    Returns:
        np.ndarray,  # [M, 2] int, i < j, unique
    """
    pairs = []
    start = 0
    grid = []
    for n in lengths:
        idx = np.arange(start, start + n)
        for k in range(1, max(0, overlap) + 1):
            if k < n:
                pairs.append(np.stack([idx[:-k], idx[k:]], 1))
        if loop_stride > 0:
            grid.append(idx[::loop_stride])
        start += n
    if grid:
        g = np.concatenate(grid)
        i, j = np.triu_indices(len(g), 1)
        pairs.append(np.stack([g[i], g[j]], 1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    return np.unique(np.concatenate(pairs).astype(np.int64), axis=0)


def pose_pairs(T_world_cam: np.ndarray, valid: np.ndarray, max_dist_m: float, max_angle_deg: float) -> np.ndarray:
    """Pairs of cameras closer than ``max_dist_m`` whose optical axes differ by less than ``max_angle_deg``.

    Args:
        T_world_cam: np.ndarray,  # [N, 4, 4]
        valid: np.ndarray,  # [N] bool (invalid poses never pair)
    Returns:
        np.ndarray,  # [M, 2] int, i < j
    """
    if max_dist_m <= 0 or max_angle_deg <= 0:
        return np.zeros((0, 2), dtype=np.int64)
    from scipy.spatial import cKDTree  # lazy, start-up: scipy

    idx = np.flatnonzero(valid)
    if len(idx) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    c = T_world_cam[idx, :3, 3]
    z = T_world_cam[idx, :3, 2]
    pr = cKDTree(c).query_pairs(max_dist_m, output_type="ndarray")
    if len(pr) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    ok = np.sum(z[pr[:, 0]] * z[pr[:, 1]], axis=1) >= np.cos(np.radians(max_angle_deg))
    out = idx[pr[ok]]
    return np.sort(out, axis=1).astype(np.int64)


def _stage_images(work: Path, paths: Sequence[Path], names: Sequence[str], masks: Sequence[np.ndarray]) -> None:
    img_dir, mask_dir = work / "images", work / "masks"
    for p, n, m in zip(paths, names, masks):
        dst = img_dir / n
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.symlink(Path(p).resolve(), dst)
        except OSError:
            shutil.copyfile(p, dst)
        md = mask_dir / f"{n}.png"
        md.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(md), m):
            raise ReconError(f"could not write the feature mask {md}")


def _extract_and_match(pc, work: Path, names: list[str], intr: FisheyeIntrinsics, cfg: SfmConfig,
                       pairs: np.ndarray, timings: dict[str, float],
                       T_world_cam: np.ndarray | None = None, pose_valid: np.ndarray | None = None) -> Path:
    db = work / "database.db"
    reader = pc.ImageReaderOptions()
    reader.camera_model = "OPENCV_FISHEYE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in colmap_camera_params(intr))
    reader.mask_path = str(work / "masks")
    ext = pc.FeatureExtractionOptions()
    # one COLMAP thread per block (COLMAP's own pool stores keypoints in the order its threads finish, so the cloud
    # changed run to run); the blocks join into one thread's bytes: recon.colmap_blocks
    ext.num_threads = 1
    ext.max_image_size = cfg.max_image_size
    ext.sift.max_num_features = cfg.max_num_features
    ext.sift.peak_threshold = cfg.peak_threshold
    t = time.perf_counter()
    extract_in_blocks(pc, db, work / "images", names, reader, ext, cfg.num_threads)
    timings["extract"] = time.perf_counter() - t
    pair_file = work / "pairs.txt"
    pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    mopt = pc.FeatureMatchingOptions()
    # known poses: one matching thread, see SfmConfig.num_threads (which thread verifies which pair changed the
    # two-view inliers under load); COLMAP's FAISS matcher still keeps two cores busy
    mopt.num_threads = cfg.num_threads if cfg.mode == "full" else 1
    by_poses = cfg.known_pose_verification and cfg.mode == "known_poses" and T_world_cam is not None
    mopt.skip_geometric_verification = bool(by_poses)
    popt = pc.ImportedPairingOptions()
    popt.match_list_path = str(pair_file)
    vopt = pc.TwoViewGeometryOptions()
    vopt.ransac.random_seed = cfg.seed
    t = time.perf_counter()
    pc.match_image_pairs(db, matching_options=mopt, pairing_options=popt, verification_options=vopt,
                         device=pc.Device.cpu)
    if by_poses:
        verify_with_known_poses(pc, db, names, T_world_cam, vopt.ransac.max_error, vopt.min_num_inliers,
                                pose_valid=pose_valid)
    timings["match"] = time.perf_counter() - t
    return db


def _open_database(pc, db_path: Path):
    """The COLMAP database at ``db_path``, opened (``Database.open`` where pycolmap has it)."""
    return pc.Database.open(str(db_path)) if hasattr(pc.Database, "open") else pc.Database(str(db_path))


def epipolar_sampson_sq(x1: np.ndarray, x2: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Squared Sampson distances ``[M]`` of correspondences ``x1 -> x2`` (``[M, 2]`` normalised image coordinates,
    ``x = X / Z`` in each camera) to the essential matrix ``E`` (``x2h^T E x1h = 0``), as COLMAP's
    ``EssentialMatrixEstimator::Residuals`` computes them."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Ex1 = h1 @ E.T  # [M, 3] = E x1
    Etx2 = h2 @ E  # [M, 3] = E^T x2
    num = np.einsum("ij,ij->i", h2, Ex1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return num / np.maximum(den, 1e-300)


def verify_with_known_poses(pc, db_path: Path, names: list[str], T_world_cam: np.ndarray, max_error_px: float,
                            min_inliers: int, min_baseline_m: float = 1e-3,
                            pose_valid: np.ndarray | None = None) -> int:
    """Geometric verification of a database's raw matches by the known poses (``SfmConfig.known_pose_verification``):
    each pair's two-view geometry becomes the essential matrix of its two poses (``cam2_from_cam1``, CALIBRATED) and
    the matches within ``max_error_px`` of it (Sampson, on the normalised plane: ``max_error_px`` / the camera's
    mean focal length, COLMAP's threshold). A pair with a frame whose pose is not trusted (``pose_valid`` False:
    the triangulation leaves that frame out) keeps no geometry. Returns the number of pairs written."""
    db = _open_database(pc, db_path)
    try:
        images = {im.image_id: im for im in db.read_all_images()}
        index = {nm: i for i, nm in enumerate(names)}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        normalised: dict[int, np.ndarray] = {}

        def xy(image_id: int) -> np.ndarray:
            if image_id not in normalised:
                kp = db.read_keypoints(image_id)[:, :2].astype(np.float64)
                normalised[image_id] = np.asarray(cams[images[image_id].camera_id].cam_from_img(kp), np.float64)
            return normalised[image_id]

        pair_ids, matches = db.read_all_matches()
        written = 0
        for pid, m in zip(pair_ids, matches):
            id1, id2 = pc.pair_id_to_image_pair(pid)
            m = np.asarray(m, dtype=np.uint32).reshape(-1, 2)
            if len(m) < min_inliers:
                continue
            i1, i2 = index[images[id1].name], index[images[id2].name]
            if pose_valid is not None and not (pose_valid[i1] and pose_valid[i2]):
                continue
            T1, T2 = T_world_cam[i1], T_world_cam[i2]
            T21 = np.linalg.inv(T2) @ T1  # cam2_from_cam1
            R, t = T21[:3, :3], T21[:3, 3]
            if np.linalg.norm(t) < min_baseline_m:
                continue
            tn = t / np.linalg.norm(t)
            E = hat(tn) @ R
            thr = max_error_px / cams[images[id1].camera_id].mean_focal_length()
            keep = epipolar_sampson_sq(xy(id1)[m[:, 0]], xy(id2)[m[:, 1]], E) <= thr * thr
            if int(keep.sum()) < min_inliers:
                continue
            g = pc.TwoViewGeometry()
            g.config = pc.TwoViewGeometryConfiguration.CALIBRATED
            g.E = E
            g.cam2_from_cam1 = pc.Rigid3d(T21[:3, :4])
            g.inlier_matches = m[keep]
            db.write_two_view_geometry(id1, id2, g)
            written += 1
    finally:
        db.close()
    return written


def _mapping_options(pc, cfg: SfmConfig):
    opt = pc.IncrementalPipelineOptions()
    opt.num_threads = cfg.num_threads if cfg.mode == "full" else 1  # see SfmConfig.num_threads
    opt.random_seed = cfg.seed
    opt.ba_refine_focal_length = False
    opt.ba_refine_principal_point = False
    opt.ba_refine_extra_params = False
    opt.mapper.abs_pose_refine_focal_length = False
    opt.mapper.abs_pose_refine_extra_params = False
    opt.mapper.random_seed = cfg.seed
    opt.triangulation.random_seed = cfg.seed
    opt.multiple_models = True
    return opt


def _known_pose_reconstruction(pc, db_path: Path, intr: FisheyeIntrinsics, names: list[str],
                               T_world_cam: np.ndarray):
    db = _open_database(pc, db_path)
    try:
        db_images = {im.name: im for im in db.read_all_images()}
        cams = db.read_all_cameras()
    finally:
        db.close()
    # one camera row per extraction block, all with the same fixed parameters (recon.colmap_blocks)
    if not cams or any(list(c.params) != list(cams[0].params) or c.model != cams[0].model for c in cams):
        raise ReconError(f"{db_path}: expected cameras that share one model and parameters, found "
                         f"{[(str(c.model), list(c.params)) for c in cams]}")
    rec = pc.Reconstruction()
    for cam in cams:
        rec.add_camera_with_trivial_rig(cam)
    for n, T in zip(names, T_world_cam):
        dbi = db_images.get(n)
        if dbi is None:
            continue
        T_cam_world = np.linalg.inv(T)
        im = pc.Image(name=n, camera_id=dbi.camera_id, image_id=dbi.image_id)
        rec.add_image_with_trivial_frame(im, pc.Rigid3d(T_cam_world[:3, :4]))
    return rec


def _result(pc, rec, names: list[str], mode: str, timings: dict[str, float], n_models: int) -> SfmResult:
    n = len(names)
    reg = np.zeros(n, dtype=bool)
    T = np.tile(np.eye(4), (n, 1, 1))
    index = {nm: i for i, nm in enumerate(names)}
    centres = {}
    img_index = {}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        i = index.get(im.name)
        if i is None:
            continue
        M = np.eye(4)
        M[:3, :4] = im.cam_from_world().matrix() if callable(im.cam_from_world) else im.cam_from_world.matrix()
        T[i] = np.linalg.inv(M)
        reg[i] = True
        centres[iid] = T[i, :3, 3]
        img_index[iid] = i
    pids = list(rec.point3D_ids())
    P = len(pids)
    pts = np.zeros((P, 3))
    cols = np.zeros((P, 3), dtype=np.uint8)
    err = np.zeros(P)
    tl = np.zeros(P, dtype=np.int64)
    vd = np.zeros((P, 3))
    op, oi = [], []
    for k, pid in enumerate(pids):
        p = rec.point3D(pid)
        pts[k] = p.xyz
        cols[k] = p.color
        err[k] = p.error
        els = p.track.elements
        tl[k] = len(els)
        cc = [centres[e.image_id] for e in els if e.image_id in centres]
        for e in els:
            if e.image_id in img_index:
                op.append(k)
                oi.append(img_index[e.image_id])
        if cc:
            d = np.mean(cc, axis=0) - pts[k]
            vd[k] = d / max(np.linalg.norm(d), 1e-12)
    mean_err = float(err.mean()) if P else float("inf")
    return SfmResult(list(names), reg, T, pts, cols, err, tl, vd, mean_err, np.asarray(op, np.int64),
                     np.asarray(oi, np.int64), mode, timings, n_models)


def run_sfm(image_paths: Sequence[str | os.PathLike], names: Sequence[str], intr: FisheyeIntrinsics,
            work_dir: str | os.PathLike, config: SfmConfig | None = None,
            sequence_lengths: Sequence[int] | None = None, T_world_cam: np.ndarray | None = None,
            pose_valid: np.ndarray | None = None, masks: np.ndarray | Sequence[np.ndarray] | None = None,
            before_mapping: Callable[[], object] | None = None) -> SfmResult:
    """Run SfM (or known-pose triangulation) on frames.

    Args:
        image_paths: N frame files (all of the intrinsics' size; checked).
        names: N unique names, ``<sequence>/<file>`` (become COLMAP image names).
        intr: fisheye intrinsics at the frames' size (held fixed).
        work_dir: scratch folder (database, staged images, masks, pair list); created, replaced if present.
        config: :class:`SfmConfig`.
        sequence_lengths: frames per video in input order (sequential matching stays within a video); default
            one video.
        T_world_cam: np.ndarray | None,  # [N, 4, 4] known poses (required by ``known_poses``; else only pairs)
        pose_valid: np.ndarray | None,  # [N] bool, which known poses to trust (default all)
        masks: one ``[H, W]`` uint8 feature mask (255 keep) for all frames, or N of them; default
            :func:`feature_mask` (UMI's predefined gripper mask + image circle).
        before_mapping: called once the features are matched, right before the mapping / triangulation (e.g. to
            start work for the idle cores: known-pose triangulation runs on one thread).
    Returns:
        :class:`SfmResult` (in COLMAP's frame for ``full``, in the world frame for ``known_poses``).
    Raises:
        ReconError: a frame's size differs from the intrinsics; known poses missing; COLMAP registers fewer than
            ``min_registered_fraction`` of the frames (or no model at all); too few 3-D points.
    """
    pc = _pycolmap()
    cfg = config or SfmConfig()
    paths = [Path(p) for p in image_paths]
    names = list(names)
    n = len(paths)
    if n != len(names) or len(set(names)) != n:
        raise ReconError(f"run_sfm: need one unique name per image, got {n} images and {len(set(names))} names")
    if n < 2:
        raise ReconError(f"run_sfm: {n} frame(s); structure from motion needs at least {cfg.min_registered}")
    check_image_sizes(paths, intr)
    lengths = list(sequence_lengths) if sequence_lengths is not None else [n]
    if sum(lengths) != n:
        raise ReconError(f"run_sfm: sequence_lengths sum to {sum(lengths)}, not the {n} frames")
    if T_world_cam is not None:
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if T_world_cam.shape != (n, 4, 4) or not np.isfinite(T_world_cam).all():
            raise ReconError(f"run_sfm: T_world_cam must be finite [{n}, 4, 4], got {T_world_cam.shape}")
    pose_valid = np.ones(n, dtype=bool) if pose_valid is None else np.asarray(pose_valid, dtype=bool)
    if cfg.mode == "known_poses" and T_world_cam is None:
        raise ReconError("run_sfm: mode 'known_poses' needs T_world_cam (the session's SLAM poses); use mode "
                         "'full' for a scan without poses")
    if masks is None:
        mask_list = [feature_mask(intr)] * n
    else:
        m = np.asarray(masks) if not isinstance(masks, (list, tuple)) else None
        mask_list = [m] * n if (m is not None and m.ndim == 2) else list(masks)
        if len(mask_list) != n:
            raise ReconError(f"run_sfm: {len(mask_list)} masks for {n} frames")
        for mk in mask_list[:1]:
            if np.asarray(mk).shape != (intr.height, intr.width):
                raise ReconError(f"run_sfm: mask shape {np.asarray(mk).shape} does not match the intrinsics "
                                 f"{intr.width}x{intr.height}")
        mask_list = [np.asarray(mk, dtype=np.uint8) for mk in mask_list]

    work = Path(work_dir)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    _stage_images(work, paths, names, mask_list)
    pairs = video_pairs(lengths, cfg.overlap, cfg.loop_stride)
    if T_world_cam is not None:
        pairs = np.unique(np.concatenate([pairs, pose_pairs(T_world_cam, pose_valid, cfg.pose_pair_max_dist_m,
                                                            cfg.pose_pair_max_angle_deg)]), axis=0)
    timings: dict[str, float] = {}
    db = _extract_and_match(pc, work, names, intr, cfg, pairs, timings,
                            T_world_cam if cfg.mode == "known_poses" else None, pose_valid)
    opt = _mapping_options(pc, cfg)
    if before_mapping is not None:
        before_mapping()
    t = time.perf_counter()
    if cfg.mode == "full":
        models = pc.incremental_mapping(db, work / "images", work / "sparse", options=opt)
        if not models:
            raise ReconError(f"SfM on {n} frames built no model (too few matches: {len(pairs)} pairs tried). Scan "
                             f"more slowly with more texture in view, raise max_num_features, or use mode "
                             f"'known_poses' with the SLAM poses")
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        n_models = len(models)
    elif cfg.mode == "known_poses":
        rec0 = _known_pose_reconstruction(pc, db, intr, [nm for nm, v in zip(names, pose_valid) if v],
                                          T_world_cam[pose_valid])
        out = work / "triangulated"
        out.mkdir()
        rec = pc.triangulate_points(rec0, db, work / "images", out, clear_points=True, options=opt,
                                    refine_intrinsics=False)
        n_models = 1
    else:
        raise ReconError(f"SfmConfig.mode must be 'full' or 'known_poses', got {cfg.mode!r}")
    timings["map"] = time.perf_counter() - t
    res = _result(pc, rec, names, cfg.mode, timings, n_models)
    n_reg = int(res.registered.sum())
    need = max(cfg.min_registered, int(np.ceil(cfg.min_registered_fraction * n)))
    if n_reg < need:
        raise ReconError(f"SfM registered {n_reg}/{n} frames (< {need} required: min_registered_fraction="
                         f"{cfg.min_registered_fraction}); COLMAP split the video into {n_models} model(s). Scan "
                         f"more slowly / with more overlap, increase `overlap`/`max_num_features`, check that the "
                         f"intrinsics match the camera, or use mode 'known_poses' with the SLAM poses")
    if len(res.points) < C.MIN_POINTS3D:
        raise ReconError(f"SfM triangulated only {len(res.points)} points (< {C.MIN_POINTS3D}); the scan sees too "
                         f"little texture or too little parallax: move the camera around the scene more")
    log.info("SfM %s: %d/%d frames, %d points, %.2f px", cfg.mode, n_reg, n, len(res.points),
             res.mean_reproj_error_px)
    return res
