"""Scene point cloud: clean-up (open3d statistical outlier removal, voxel down-sampling), oriented normals,
binary PLY I/O (atomic writes). World frame (table tag, z up), metres.

Normals are estimated from the ``NORMAL_NEIGHBOURS`` nearest points (PCA) and oriented towards the cameras that
saw each point (``view_dirs`` from SfM): a surface is seen from its free side. The oriented normals give the sign of
the scene SDF (:mod:`umi_aug.recon.sdf_grid`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from umi_aug.errors import ReconError
from umi_aug.geometry.gripper import CollisionSpheres, umi_camera_body_spheres
from umi_aug.io_utils import atomic_path
from umi_aug.recon import constants as C

__all__ = ["SceneCloud", "clean_cloud", "inside_camera_body", "write_ply", "read_ply"]


def _o3d():
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - recon extra / system lib
        raise ReconError("point-cloud clean-up needs open3d: pip install 'umi-aug[recon]' (open3d-cpu==0.20.0); "
                         f"on Debian also `apt-get install libusb-1.0-0` ({exc})") from exc
    return o3d


@dataclass
class SceneCloud:
    """A coloured point cloud with oriented normals.

    Attributes:
        points: np.ndarray,  # [N, 3] float64 world, metres
        colors: np.ndarray,  # [N, 3] uint8 RGB
        normals: np.ndarray,  # [N, 3] float64 unit, pointing to free space (zeros when unknown)
    """

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def check(self, who: str, min_points: int = C.MIN_CLOUD_POINTS) -> None:
        """Raise :class:`ReconError` for empty / tiny / non-finite clouds, naming ``who``."""
        n = len(self)
        if n < min_points:
            raise ReconError(f"{who}: the point cloud has {n} points (< {min_points}); reconstruction found too "
                             f"little of the scene: scan again with more texture and parallax, or lower the "
                             f"clean-up strength")
        if not (np.isfinite(self.points).all() and np.isfinite(self.normals).all()):
            raise ReconError(f"{who}: the point cloud contains non-finite coordinates or normals")


def clean_cloud(points: np.ndarray, colors: np.ndarray | None = None, view_dirs: np.ndarray | None = None,
                voxel_m: float = C.CLOUD_VOXEL_M, sor_neighbours: int = C.SOR_NEIGHBOURS,
                sor_std_ratio: float = C.SOR_STD_RATIO, radius_m: float = C.ROR_RADIUS_M,
                radius_min_points: int = C.ROR_MIN_POINTS, normal_neighbours: int = C.NORMAL_NEIGHBOURS,
                bounds: tuple[np.ndarray, np.ndarray] | None = None) -> SceneCloud:
    """Statistical outlier removal, voxel down-sampling and oriented normals.

    Args:
        points: np.ndarray,  # [N, 3] world, metres
        colors: np.ndarray | None,  # [N, 3] uint8
        view_dirs: np.ndarray | None,  # [N, 3] unit directions from each point towards its cameras (orients
            the normals; without it normals point towards the cloud's... +z hemisphere)
        voxel_m: voxel size of the down-sampling (0 = none).
        sor_neighbours, sor_std_ratio: open3d ``remove_statistical_outlier`` (0 neighbours = off).
        radius_m, radius_min_points: open3d ``remove_radius_outlier``: drop points with fewer than this many
            neighbours within ``radius_m`` (isolated SfM points floating in free space; 0 = off).
        normal_neighbours: points per normal estimate.
        bounds: (lo [3], hi [3]) crop box applied first, or None.
    Raises:
        ReconError: empty/tiny input or output.
    """
    o3d = _o3d()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    cols = np.zeros((n, 3), np.uint8) if colors is None else np.asarray(colors, np.uint8).reshape(-1, 3)
    vd = np.tile([0.0, 0.0, 1.0], (n, 1)) if view_dirs is None else np.asarray(view_dirs, np.float64).reshape(-1, 3)
    if len(cols) != n or len(vd) != n:
        raise ReconError(f"clean_cloud: {n} points but {len(cols)} colours / {len(vd)} view directions")
    keep = np.isfinite(pts).all(1)
    if bounds is not None:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
        keep &= np.all((pts >= lo) & (pts <= hi), axis=1)
    pts, cols, vd = pts[keep], cols[keep], vd[keep]
    SceneCloud(pts, cols, np.zeros_like(pts)).check("clean_cloud (input)")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.colors = o3d.utility.Vector3dVector(cols.astype(np.float64) / 255.0)
    pc.normals = o3d.utility.Vector3dVector(vd)  # carried through down-sampling (averaged), re-estimated below
    if sor_neighbours > 0 and len(pts) > sor_neighbours:
        pc, _ = pc.remove_statistical_outlier(nb_neighbors=int(sor_neighbours), std_ratio=float(sor_std_ratio))
    if radius_m > 0 and radius_min_points > 0:
        pc, _ = pc.remove_radius_outlier(nb_points=int(radius_min_points), radius=float(radius_m))
    if voxel_m > 0:
        pc = pc.voxel_down_sample(float(voxel_m))
    view = np.asarray(pc.normals).copy()
    if len(pc.points) >= 3:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(max(3, normal_neighbours))))
    nrm = np.asarray(pc.normals).copy()
    flip = np.sum(nrm * view, axis=1) < 0
    nrm[flip] *= -1.0
    nn = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(nn > 1e-12, nrm / np.maximum(nn, 1e-12), 0.0)
    out = SceneCloud(np.asarray(pc.points).copy(), np.round(np.asarray(pc.colors) * 255).astype(np.uint8), nrm)
    out.check("clean_cloud (after outlier removal / down-sampling)")
    return out


_PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def _body_inputs(points: np.ndarray, T_world_cam: np.ndarray, spheres: CollisionSpheres | None):
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    T = np.asarray(T_world_cam, np.float64).reshape(-1, 4, 4)
    if not (np.isfinite(pts).all() and np.isfinite(T).all()):
        raise ReconError(f"inside_camera_body: non-finite points ({len(pts)}) or poses ({len(T)})")
    return pts, T, spheres or umi_camera_body_spheres()


def inside_camera_body(points: np.ndarray, T_world_cam: np.ndarray,
                       spheres: CollisionSpheres | None = None) -> np.ndarray:
    """Which points lie inside the camera body at any of the given poses.

    Nothing of a static scene can be where the demonstrator's camera was, so such points are triangulation
    artefacts: features that move with the camera (lens dirt, the gripper's own parts, mirror content) or outliers
    of a sparse cloud. One of them, 29 mm in front of the lens at the first frame of the real episode's sparse cloud
    (no SIFT upscaling), put that demo's contact at frame 0. Pass only poses where the camera moved through free
    space (before the gripper first closes).

    Args:
        points: np.ndarray,  # [N, 3] world, metres
        T_world_cam: np.ndarray,  # [T, 4, 4] camera poses, world, metres
        spheres: the body model (camera frame); default :func:`umi_camera_body_spheres` (GoPro + mount).
    Returns:
        np.ndarray,  # [N] bool, True = strictly inside some sphere at some pose
    """
    from scipy.spatial import cKDTree  # lazy, start-up: scipy

    pts, T, sph = _body_inputs(points, T_world_cam, spheres)
    hit = np.zeros(len(pts), bool)
    if len(pts) == 0 or len(T) == 0:
        return hit
    tree = cKDTree(pts)
    centres = sph.world(T)  # [T, S, 3]
    for s, r in enumerate(sph.radii):
        idx = tree.query_ball_point(centres[:, s], float(r), return_sorted=False)
        pose = np.repeat(np.arange(len(T)), [len(i) for i in idx])
        if len(pose):  # the ball query keeps d <= r; a point on the surface is not inside
            pt = np.concatenate([np.asarray(i, np.int64) for i in idx])
            d = np.linalg.norm(pts[pt] - centres[pose, s], axis=1)
            hit[pt[d < r]] = True
    return hit


def _inside_camera_body_reference(points: np.ndarray, T_world_cam: np.ndarray,
                                  spheres: CollisionSpheres | None = None) -> np.ndarray:
    """Slow reference of :func:`inside_camera_body`: every point against every sphere at every pose."""
    pts, T, sph = _body_inputs(points, T_world_cam, spheres)
    hit = np.zeros(len(pts), bool)
    for Tt in T:
        for c_cam, r in zip(sph.centers_cam, sph.radii):
            c = Tt[:3, :3] @ c_cam + Tt[:3, 3]
            for i, p in enumerate(pts):
                if np.sqrt(np.sum((p - c) ** 2)) < r:
                    hit[i] = True
    return hit


def write_ply(path: str | os.PathLike, cloud: SceneCloud) -> Path:
    """Write a binary little-endian PLY (x y z nx ny nz float32, red green blue uchar) atomically."""
    n = len(cloud)
    arr = np.empty(n, _PLY_DTYPE)
    for k, key in enumerate("xyz"):
        arr[key] = cloud.points[:, k]
        arr["n" + key] = cloud.normals[:, k]
    for k, key in enumerate(("red", "green", "blue")):
        arr[key] = cloud.colors[:, k]
    header = ("ply\nformat binary_little_endian 1.0\ncomment umi-aug scene cloud, world = table-tag frame, metres\n"
              f"element vertex {n}\n" + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(arr.tobytes())
    return Path(path)


def read_ply(path: str | os.PathLike) -> SceneCloud:
    """Read a PLY written by :func:`write_ply` (or any binary little-endian PLY whose vertex element has x, y, z
    float32 and optionally nx ny nz float32 and red green blue uchar, in that layout)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ReconError(f"{path}: cannot read the point cloud ({exc})") from exc
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise ReconError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ReconError(f"{path}: only binary_little_endian PLY is supported")
    n, props = None, []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts and parts[0] == "element" and n is not None:
            break
        elif parts[:1] == ["property"] and n is not None:
            props.append((parts[2], {"float": "<f4", "uchar": "u1", "double": "<f8"}.get(parts[1], "?")))
    if n is None or any(t == "?" for _, t in props):
        raise ReconError(f"{path}: unsupported PLY header (vertex element with float/uchar/double properties)")
    dt = np.dtype([(k, t) for k, t in props])
    body = raw[end + len(b"end_header\n"):]
    if len(body) < n * dt.itemsize:
        raise ReconError(f"{path}: truncated PLY ({len(body)} bytes for {n} vertices of {dt.itemsize})")
    arr = np.frombuffer(body[: n * dt.itemsize], dt)
    names = dt.names or ()
    if not all(k in names for k in "xyz"):
        raise ReconError(f"{path}: PLY vertices lack x/y/z")
    pts = np.stack([arr[k] for k in "xyz"], 1).astype(np.float64)
    nrm = (np.stack([arr[k] for k in ("nx", "ny", "nz")], 1).astype(np.float64)
           if all(k in names for k in ("nx", "ny", "nz")) else np.zeros_like(pts))
    cols = (np.stack([arr[k] for k in ("red", "green", "blue")], 1).astype(np.uint8)
            if all(k in names for k in ("red", "green", "blue")) else np.zeros((n, 3), np.uint8))
    return SceneCloud(pts, cols, nrm)
