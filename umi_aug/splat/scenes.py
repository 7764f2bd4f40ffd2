"""Procedural Gaussian scenes for tests and benchmarks (no files; same seed -> same scene).

* :func:`random_gaussians`: Gaussians scattered inside the fisheye field of view of a camera, with footprints of
  a chosen size in pixels (fwd-vs-reference and gradient tests).
* :func:`room_gaussians` + :func:`room_camera_pose`: a tabletop room covered by flat surface Gaussians the way
  a trained scene is (textured table, striped walls, a few objects), for render benchmarks.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.geometry import look_at_rotation, make_pose, matrix_to_quat_wxyz
from umi_aug.splat._constants import SH_COEFFS
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.sh import rgb_to_sh

__all__ = ["random_gaussians", "room_gaussians", "room_camera_pose", "random_quats_wxyz", "look_at_pose"]


def random_quats_wxyz(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform random unit quaternions ``[n, 4]`` (w, x, y, z)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def look_at_pose(cam_pos, target, up_hint=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam [4, 4]`` (OpenCV camera frame) at ``cam_pos`` looking at ``target``."""
    R = look_at_rotation(np.asarray(cam_pos, float), np.asarray(target, float), np.asarray(up_hint, float))
    return make_pose(R, np.asarray(cam_pos, float))


def _dirs_from_angles(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def random_gaussians(
    n: int,
    rng: np.random.Generator,
    intr: FisheyeIntrinsics,
    T_world_cam: np.ndarray | None = None,
    *,
    theta_max: float | None = None,
    depth_range: tuple[float, float] = (0.5, 3.0),
    sigma_px_range: tuple[float, float] = (0.6, 5.0),
    anisotropy: float = 4.0,
    opacity_range: tuple[float, float] = (0.05, 0.97),
    sh_degree: int = 3,
    sh_rest_scale: float = 0.15,
    dtype: torch.dtype = torch.float64,
) -> Gaussians:
    """Gaussians inside the camera's field of view with footprints of roughly ``sigma_px_range`` pixels.

    Args:
        n: number of Gaussians.
        rng: numpy generator.
        intr: camera; sizes are chosen from its focal length.
        T_world_cam: camera pose (default identity).
        theta_max: largest ray angle of the means (default ``intr.theta_max``; larger puts some beyond the
            fold-over, where they are culled).
        depth_range: ray distances of the means, metres.
        sigma_px_range: log-uniform standard deviation of the footprint (largest axis) in pixels (at the image
            centre; off-axis the KB model shrinks/stretches it).
        anisotropy: log-uniform ratio between the largest and the other axes (1 = isotropic).
        opacity_range: uniform opacity range.
        sh_degree: degree of the returned SH.
        sh_rest_scale: standard deviation of the higher SH coefficients.
        dtype: torch dtype.
    """
    T = np.eye(4) if T_world_cam is None else np.asarray(T_world_cam, dtype=np.float64)
    th_max = intr.theta_max if theta_max is None else float(theta_max)
    # uniform on the spherical cap theta <= th_max
    cos_t = rng.uniform(math.cos(th_max), 1.0, n)
    theta = np.arccos(cos_t)
    phi = rng.uniform(-math.pi, math.pi, n)
    dist = rng.uniform(*depth_range, n)
    p_cam = _dirs_from_angles(theta, phi) * dist[:, None]
    means = p_cam @ T[:3, :3].T + T[:3, 3]
    f = 0.5 * (intr.fx + intr.fy)
    sigma_px = np.exp(rng.uniform(np.log(sigma_px_range[0]), np.log(sigma_px_range[1]), n))
    big = sigma_px * dist / f
    ratio = np.exp(rng.uniform(0.0, np.log(max(anisotropy, 1.0)), (n, 3)))
    ratio[:, 0] = 1.0
    scales = big[:, None] / ratio
    rng.permuted(scales, axis=1, out=scales)
    op = rng.uniform(*opacity_range, n)
    k = SH_COEFFS[sh_degree]
    arrays = {
        "means": means,
        "log_scales": np.log(scales),
        "quats_wxyz": random_quats_wxyz(n, rng) * rng.uniform(0.5, 2.0, (n, 1)),
        "logit_opacities": np.log(op / (1.0 - op)),
        "sh0": rgb_to_sh(torch.as_tensor(rng.uniform(0.05, 0.95, (n, 3)))).numpy(),
        "sh_rest": rng.normal(0.0, sh_rest_scale, (n, k - 1, 3)),
    }
    return Gaussians.from_numpy(arrays, dtype=dtype)


# ------------------------------------------------------------------------------------------------------------
# Tabletop room
# ------------------------------------------------------------------------------------------------------------
_ROOM_HALF = (1.0, 0.8)
_ROOM_HEIGHT = 1.3


def room_camera_pose(which: int = 0) -> np.ndarray:
    """UMI-like wrist-camera poses in the room (``T_world_cam``): 0 = looking down at the table from 35 cm,
    1 = closer and tilted, 2 = looking across the room."""
    poses = [
        ((0.05, -0.32, 0.33), (0.0, 0.02, 0.0)),
        ((0.20, -0.15, 0.18), (0.05, 0.10, 0.0)),
        ((-0.5, -0.4, 0.45), (0.6, 0.5, 0.2)),
    ]
    pos, tgt = poses[which % len(poses)]
    return look_at_pose(pos, tgt)


def _frame_from_normal(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotations ``[n, 3, 3]`` whose third column is the normal, random in-plane angle."""
    n = normals.shape[0]
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    ang = rng.uniform(0, 2 * math.pi, n)[:, None]
    a = np.cos(ang) * t1 + np.sin(ang) * t2
    b = np.cross(normals, a)
    return np.stack([a, b, normals], axis=-1)


def _room_colour(points: np.ndarray, face: np.ndarray) -> np.ndarray:
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rgb = np.empty_like(points)
    checker = ((np.floor(x / 0.05) + np.floor(y / 0.05)) % 2)[:, None]
    table = checker * np.array([0.85, 0.8, 0.7]) + (1 - checker) * np.array([0.35, 0.25, 0.18])
    stripes = (0.5 + 0.5 * np.sin(2 * math.pi * (x + y + z) / 0.16))[:, None]
    hues = np.array([[0.8, 0.3, 0.3], [0.3, 0.7, 0.35], [0.3, 0.4, 0.85], [0.85, 0.75, 0.3], [0.7, 0.7, 0.7]])
    wall = hues[np.clip(face, 0, 4)] * (0.55 + 0.45 * stripes)
    rgb[:] = wall
    rgb[face == 0] = table[face == 0]
    return rgb


def room_gaussians(
    n: int, rng: np.random.Generator, sh_degree: int = 3, dtype: torch.dtype = torch.float32
) -> Gaussians:
    """``n`` flat Gaussians covering a tabletop room (table z = 0 fills the floor, 4 walls, ceiling, three
    objects on the table), sized so that neighbouring splats overlap as in a trained scene.

    About 45% of the Gaussians are on the table and objects (where the wrist camera looks), the rest on walls
    and ceiling. Opacities: 75% in [0.6, 0.99], 25% in [0.05, 0.6]; small random view-dependent SH.
    """
    hx, hy = _ROOM_HALF
    h = _ROOM_HEIGHT
    n_obj = int(0.15 * n)
    n_table = int(0.30 * n)
    n_wall = n - n_obj - n_table
    pts, nrm, face, area_per = [], [], [], []
    # table
    p = np.stack([rng.uniform(-hx, hx, n_table), rng.uniform(-hy, hy, n_table), np.zeros(n_table)], -1)
    pts.append(p)
    nrm.append(np.tile([0.0, 0.0, 1.0], (n_table, 1)))
    face.append(np.zeros(n_table, int))
    area_per.append(np.full(n_table, 4 * hx * hy / max(n_table, 1)))
    # walls + ceiling, area weighted
    walls = [  # (axis, value, normal, face id, area)
        (0, -hx, (1.0, 0, 0), 1, 2 * hy * h), (0, hx, (-1.0, 0, 0), 2, 2 * hy * h),
        (1, -hy, (0, 1.0, 0), 3, 2 * hx * h), (1, hy, (0, -1.0, 0), 4, 2 * hx * h),
        (2, h, (0, 0, -1.0), 5, 4 * hx * hy),
    ]
    areas = np.array([w[4] for w in walls])
    which = rng.choice(len(walls), size=n_wall, p=areas / areas.sum())
    p = np.stack([rng.uniform(-hx, hx, n_wall), rng.uniform(-hy, hy, n_wall), rng.uniform(0, h, n_wall)], -1)
    nw = np.zeros((n_wall, 3))
    for i, (axis, val, normal, fid, _) in enumerate(walls):
        sel = which == i
        p[sel, axis] = val
        nw[sel] = normal
    pts.append(p)
    nrm.append(nw)
    face.append(np.clip(which + 1, 1, 4))
    area_per.append(np.full(n_wall, areas.sum() / max(n_wall, 1)))
    # objects: spheres on the table
    centres = np.array([[0.15, 0.10, 0.06], [-0.12, 0.05, 0.04], [0.02, 0.25, 0.08]])
    radii = np.array([0.06, 0.04, 0.08])
    sel = rng.integers(0, 3, n_obj)
    d = rng.normal(size=(n_obj, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2]) * 0.9 + 0.1 * d[:, 2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts.append(centres[sel] + radii[sel, None] * d)
    nrm.append(d)
    face.append(np.full(n_obj, 4))
    obj_area = 4 * math.pi * radii**2
    area_per.append(obj_area[sel] / np.maximum(np.bincount(sel, minlength=3)[sel], 1))
    pts, nrm, face, area_per = map(np.concatenate, (pts, nrm, face, area_per))
    rgb = _room_colour(pts, face)
    obj_rgb = np.array([[0.85, 0.2, 0.15], [0.15, 0.45, 0.85], [0.9, 0.85, 0.3]])
    rgb[n_table + n_wall :] = obj_rgb[sel] * rng.uniform(0.8, 1.0, (n_obj, 1))
    rgb = np.clip(rgb + rng.normal(0, 0.03, rgb.shape), 0.0, 1.0)
    R = _frame_from_normal(nrm, rng)
    tangential = 0.6 * np.sqrt(area_per)[:, None] * np.exp(rng.normal(0, 0.35, (pts.shape[0], 2)))
    scales = np.concatenate([tangential, 0.08 * tangential[:, :1]], axis=1)
    n_all = pts.shape[0]
    hi = rng.uniform(size=n_all) < 0.75
    op = np.where(hi, rng.uniform(0.6, 0.99, n_all), rng.uniform(0.05, 0.6, n_all))
    k = SH_COEFFS[sh_degree]
    arrays = {
        "means": pts + nrm * rng.normal(0, 0.002, (n_all, 1)),
        "log_scales": np.log(scales),
        "quats_wxyz": matrix_to_quat_wxyz(R),
        "logit_opacities": np.log(op / (1 - op)),
        "sh0": rgb_to_sh(torch.as_tensor(rgb)).numpy(),
        "sh_rest": rng.normal(0, 0.05, (n_all, k - 1, 3)),
    }
    return Gaussians.from_numpy(arrays, dtype=dtype)
