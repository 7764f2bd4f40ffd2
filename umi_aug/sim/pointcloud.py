"""Ground-truth scene point clouds sampled from MuJoCo geom surfaces, and a minimal binary PLY writer.

Points are sampled uniformly by area on every selected geom (plane, box, sphere, ellipsoid, capsule, cylinder,
mesh) at its current pose in ``data``; colours are the geom's material/RGBA colour times the mean colour of its
texture (textures are not sampled per point). World frame, metres.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable

import numpy as np

from umi_aug.errors import SimError
from umi_aug.io_utils import atomic_path
from umi_aug.sim.gl import import_mujoco

__all__ = ["ScenePoints", "sample_geom_points", "write_ply"]


class ScenePoints(dict):
    """``{"points": [N,3] float32 m, "normals": [N,3] float32, "colors": [N,3] uint8, "geom_id": [N] int32}``."""


def _geom_colors(model) -> np.ndarray:
    """[ngeom, 3] float RGB in 0..1: material (or geom) rgba × mean texture colour."""
    cols = np.array(model.geom_rgba[:, :3], dtype=np.float64)
    tex_mean: dict[int, np.ndarray] = {}
    for g in range(model.ngeom):
        m = int(model.geom_matid[g])
        if m < 0:
            continue
        cols[g] = model.mat_rgba[m, :3]
        tid = -1
        texid = np.asarray(model.mat_texid[m]).reshape(-1)
        for t in texid:
            if t >= 0:
                tid = int(t)
                break
        if tid < 0:
            continue
        if tid not in tex_mean:
            adr, w, h, c = (int(model.tex_adr[tid]), int(model.tex_width[tid]), int(model.tex_height[tid]),
                            int(model.tex_nchannel[tid]))
            data = np.asarray(model.tex_data[adr:adr + w * h * c]).reshape(-1, c)[:, :3]
            tex_mean[tid] = data.mean(axis=0) / 255.0
        cols[g] = cols[g] * tex_mean[tid]
    return cols


def _unit_sphere(n: int, rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _sample_local(gtype: int, size: np.ndarray, n: int, rng: np.random.Generator, model, g: int, mj):
    """Points and normals in the geom frame."""
    T = mj.mjtGeom
    if gtype == T.mjGEOM_PLANE:
        hx, hy = float(size[0]), float(size[1])
        p = np.stack([rng.uniform(-hx, hx, n), rng.uniform(-hy, hy, n), np.zeros(n)], 1)
        return p, np.tile([0.0, 0.0, 1.0], (n, 1))
    if gtype == T.mjGEOM_BOX:
        h = np.asarray(size[:3], dtype=np.float64)
        areas = np.array([h[1] * h[2], h[1] * h[2], h[0] * h[2], h[0] * h[2], h[0] * h[1], h[0] * h[1]])
        face = rng.choice(6, n, p=areas / areas.sum())
        p = rng.uniform(-1.0, 1.0, (n, 3)) * h
        nrm = np.zeros((n, 3))
        ax = face // 2
        sgn = np.where(face % 2 == 0, 1.0, -1.0)
        p[np.arange(n), ax] = sgn * h[ax]
        nrm[np.arange(n), ax] = sgn
        return p, nrm
    if gtype == T.mjGEOM_SPHERE:
        d = _unit_sphere(n, rng)
        return d * float(size[0]), d
    if gtype == T.mjGEOM_ELLIPSOID:
        a = np.asarray(size[:3], dtype=np.float64)
        d = _unit_sphere(n, rng)
        p = d * a
        nrm = p / (a * a)
        return p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    if gtype in (T.mjGEOM_CYLINDER, T.mjGEOM_CAPSULE):
        r, hh = float(size[0]), float(size[1])
        side = 2 * math.pi * r * 2 * hh
        cap = math.pi * r * r * 2 if gtype == T.mjGEOM_CYLINDER else 4 * math.pi * r * r
        on_side = rng.random(n) < side / (side + cap)
        phi = rng.uniform(0, 2 * math.pi, n)
        p = np.stack([r * np.cos(phi), r * np.sin(phi), rng.uniform(-hh, hh, n)], 1)
        nrm = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], 1)
        k = int((~on_side).sum())
        if k:
            if gtype == T.mjGEOM_CYLINDER:
                rad = r * np.sqrt(rng.random(k))
                ph = rng.uniform(0, 2 * math.pi, k)
                top = rng.random(k) < 0.5
                z = np.where(top, hh, -hh)
                p[~on_side] = np.stack([rad * np.cos(ph), rad * np.sin(ph), z], 1)
                nrm[~on_side] = np.stack([np.zeros(k), np.zeros(k), np.where(top, 1.0, -1.0)], 1)
            else:
                d = _unit_sphere(k, rng)
                p[~on_side] = d * r + np.stack([np.zeros(k), np.zeros(k), np.sign(d[:, 2]) * hh], 1)
                nrm[~on_side] = d
        return p, nrm
    if gtype == T.mjGEOM_MESH:
        mid = int(model.geom_dataid[g])
        va, vn = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
        fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
        V = np.asarray(model.mesh_vert[va:va + vn], dtype=np.float64)
        F = np.asarray(model.mesh_face[fa:fa + fn], dtype=np.int64)
        A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        cr = np.cross(B - A, C - A)
        area = 0.5 * np.linalg.norm(cr, axis=1)
        if area.sum() <= 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        tri = rng.choice(len(F), n, p=area / area.sum())
        u, v = rng.random(n), rng.random(n)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        p = A[tri] + u[:, None] * (B[tri] - A[tri]) + v[:, None] * (C[tri] - A[tri])
        nrm = cr[tri] / np.maximum(np.linalg.norm(cr[tri], axis=1, keepdims=True), 1e-12)
        return p, nrm
    return np.zeros((0, 3)), np.zeros((0, 3))


def _area(gtype: int, size: np.ndarray, model, g: int, mj) -> float:
    T = mj.mjtGeom
    if gtype == T.mjGEOM_PLANE:
        return 4.0 * float(size[0]) * float(size[1])
    if gtype == T.mjGEOM_BOX:
        a, b, c = (float(x) for x in size[:3])
        return 8.0 * (a * b + b * c + a * c)
    if gtype == T.mjGEOM_SPHERE:
        return 4 * math.pi * float(size[0]) ** 2
    if gtype == T.mjGEOM_ELLIPSOID:  # Knud Thomsen's approximation
        a, b, c = (float(x) ** 1.6075 for x in size[:3])
        return 4 * math.pi * ((a * b + a * c + b * c) / 3.0) ** (1 / 1.6075)
    if gtype == T.mjGEOM_CYLINDER:
        r, h = float(size[0]), float(size[1])
        return 2 * math.pi * r * 2 * h + 2 * math.pi * r * r
    if gtype == T.mjGEOM_CAPSULE:
        r, h = float(size[0]), float(size[1])
        return 2 * math.pi * r * 2 * h + 4 * math.pi * r * r
    if gtype == T.mjGEOM_MESH:
        mid = int(model.geom_dataid[g])
        fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
        va = int(model.mesh_vertadr[mid])
        V = np.asarray(model.mesh_vert[va:va + int(model.mesh_vertnum[mid])], dtype=np.float64)
        F = np.asarray(model.mesh_face[fa:fa + fn], dtype=np.int64)
        return float(0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum())
    return 0.0


def sample_geom_points(
    model,
    data,
    geom_ids: Iterable[int],
    rng: np.random.Generator,
    density_per_m2: float | dict[int, float] = 20000.0,
    max_points_per_geom: int = 200000,
) -> ScenePoints:
    """Sample points uniformly by area on the surfaces of the given geoms at their poses in ``data``.

    Args:
        model, data: ``MjModel`` / ``MjData`` (kinematics up to date).
        geom_ids: geoms to sample.
        rng: random generator.
        density_per_m2: points per square metre, scalar or ``{geom_id: density}`` (missing ids: 20000).
        max_points_per_geom: cap per geom.

    Returns:
        :class:`ScenePoints` (world frame, metres; normals unit, outward).
    """
    mj = import_mujoco()
    cols = _geom_colors(model)
    P, N, C, G = [], [], [], []
    for g in geom_ids:
        g = int(g)
        if not 0 <= g < model.ngeom:
            raise SimError(f"sample_geom_points: geom id {g} out of range [0, {model.ngeom})")
        gtype = int(model.geom_type[g])
        size = np.asarray(model.geom_size[g], dtype=np.float64)
        dens = density_per_m2.get(g, 20000.0) if isinstance(density_per_m2, dict) else float(density_per_m2)
        n = int(min(max_points_per_geom, round(_area(gtype, size, model, g, mj) * dens)))
        if n <= 0:
            continue
        p, nrm = _sample_local(gtype, size, n, rng, model, g, mj)
        if not len(p):
            continue
        R = np.asarray(data.geom_xmat[g], dtype=np.float64).reshape(3, 3)
        t = np.asarray(data.geom_xpos[g], dtype=np.float64)
        P.append(p @ R.T + t)
        N.append(nrm @ R.T)
        C.append(np.tile(np.clip(np.round(cols[g] * 255.0), 0, 255), (len(p), 1)))
        G.append(np.full(len(p), g, dtype=np.int32))
    if not P:
        return ScenePoints(points=np.zeros((0, 3), np.float32), normals=np.zeros((0, 3), np.float32),
                           colors=np.zeros((0, 3), np.uint8), geom_id=np.zeros(0, np.int32))
    return ScenePoints(
        points=np.concatenate(P).astype(np.float32),
        normals=np.concatenate(N).astype(np.float32),
        colors=np.concatenate(C).astype(np.uint8),
        geom_id=np.concatenate(G),
    )


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None,
              normals: np.ndarray | None = None, labels: np.ndarray | None = None) -> Path:
    """Write a binary little-endian PLY point cloud (atomic).

    Args:
        path: output ``.ply``.
        points: np.ndarray,  # [N, 3] float, metres → float32 ``x y z``
        colors: np.ndarray | None,  # [N, 3] uint8 → ``red green blue``
        normals: np.ndarray | None,  # [N, 3] float → float32 ``nx ny nz``
        labels: np.ndarray | None,  # [N] int → int32 ``label`` (here: MuJoCo geom id)
    """
    pts = np.asarray(points, dtype=np.float32)
    n = len(pts)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if labels is not None:
        fields += [("label", "<i4")]
    arr = np.empty(n, dtype=fields)
    arr["x"], arr["y"], arr["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if normals is not None:
        nn = np.asarray(normals, dtype=np.float32)
        arr["nx"], arr["ny"], arr["nz"] = nn[:, 0], nn[:, 1], nn[:, 2]
    if colors is not None:
        cc = np.asarray(colors, dtype=np.uint8)
        arr["red"], arr["green"], arr["blue"] = cc[:, 0], cc[:, 1], cc[:, 2]
    if labels is not None:
        arr["label"] = np.asarray(labels, dtype=np.int32)
    ply_types = {"<f4": "float", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {ply_types[t]} {name}" for name, t in fields]
    header += ["end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(arr.tobytes())
    return Path(path)
