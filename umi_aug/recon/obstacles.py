"""Obstacle assets without downloads and their placement (paper §3.2 obstacle augmentation).

Assets (object frame: origin at the bottom centre, z up, metres): procedural trimesh primitives (``box``,
``cylinder``, ``bottle`` (revolved profile), ``mug`` (cylinder + torus handle)) and meshes shipped inside installed
packages (robosuite's object meshes, when robosuite is installed; :func:`packaged_mesh_assets`). An obstacle enters
the trajectory stage as its inflated convex hull (:class:`umi_aug.geometry.sdf.ConvexPolytopeSDF`, planes pushed
out by ``inflation``; exact inside/facet regions, a lower bound near edges).

:func:`sample_obstacle_placement` puts an asset on the support plane where it BLOCKS the demo's straight approach
(the gripper spheres along the straight-line interpolation from the demo's first pose to its pre-contact pose hit
the inflated hull) while the pre-contact approach tail, the pre-contact pose and the replayed post-contact motion
keep ``clearance`` from it, and the obstacle does not intersect the reconstructed scene.
Obstacle Gaussians (3DGS of the asset) are built downstream, by the splat stage:
:func:`umi_aug.splat.obstacle_gaussians.obstacle_gaussians` (surface-sampled, fitted to orbit renders, cached).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from umi_aug.errors import ReconError
from umi_aug.geometry.gripper import umi_gripper_spheres
from umi_aug.geometry.interp import interpolate_pose
from umi_aug.geometry.sdf import ConvexPolytopeSDF, SignedDistanceField
from umi_aug.recon import constants as C

__all__ = ["ObstacleAsset", "procedural_asset", "PROCEDURAL_ASSETS", "packaged_mesh_assets", "load_mesh_asset",
           "obstacle_hull_sdf", "ObstaclePlacement", "sample_obstacle_placement"]

PROCEDURAL_ASSETS = ("box", "cylinder", "bottle", "mug")


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - recon extra
        raise ReconError("obstacle assets need trimesh: pip install 'umi-aug[recon]' (trimesh==5.2.0)") from exc
    return trimesh


@dataclass
class ObstacleAsset:
    """A rigid obstacle mesh.

    Attributes:
        name: asset name.
        mesh: trimesh.Trimesh in the object frame (origin at the bottom centre, z up, metres).
    """

    name: str
    mesh: object

    def surface_points(self, n: int = C.OBSTACLE_SURFACE_POINTS, seed: int = 0) -> np.ndarray:
        """``[n, 3]`` points sampled uniformly by area on the surface (object frame)."""
        pts, _ = _trimesh().sample.sample_surface(self.mesh, int(n), seed=int(seed))
        return np.asarray(pts, dtype=np.float64)

    @property
    def hull_vertices(self) -> np.ndarray:
        """``[V, 3]`` vertices of the convex hull (object frame)."""
        return np.asarray(self.mesh.convex_hull.vertices, dtype=np.float64)

    @property
    def height(self) -> float:
        return float(self.mesh.bounds[1, 2] - self.mesh.bounds[0, 2])


def _on_ground(mesh):
    mesh.apply_translation([0.0, 0.0, -float(mesh.bounds[0, 2])])
    return mesh


def procedural_asset(name: str, scale: float = 1.0) -> ObstacleAsset:
    """A procedural primitive: ``box`` (8×8×20 cm), ``cylinder`` (r 4 cm, 22 cm), ``bottle`` (r 3.5 cm, 24 cm,
    revolved body–shoulder–neck profile), ``mug`` (r 4.5 cm, 10 cm + torus handle). ``scale`` multiplies all sizes."""
    tm = _trimesh()
    if name == "box":
        mesh = tm.creation.box(extents=(0.08, 0.08, 0.20))
    elif name == "cylinder":
        mesh = tm.creation.cylinder(radius=0.04, height=0.22, sections=32)
    elif name == "bottle":
        prof = np.array([[0.0, 0.0], [0.035, 0.0], [0.035, 0.15], [0.025, 0.18], [0.013, 0.195], [0.013, 0.24],
                         [0.0, 0.24]])
        mesh = tm.creation.revolve(prof, sections=32)
    elif name == "mug":
        body = tm.creation.cylinder(radius=0.045, height=0.10, sections=32)
        body.apply_translation([0.0, 0.0, 0.05])
        handle = tm.creation.torus(major_radius=0.028, minor_radius=0.007, major_sections=24, minor_sections=12)
        handle.apply_transform(tm.transformations.rotation_matrix(math.pi / 2, [1, 0, 0]))
        handle.apply_translation([0.045, 0.0, 0.05])
        mesh = tm.util.concatenate([body, handle])
    else:
        raise ReconError(f"procedural_asset: unknown asset {name!r}; choose one of {PROCEDURAL_ASSETS}")
    if not (np.isfinite(scale) and scale > 0):
        raise ReconError(f"procedural_asset: scale {scale!r} must be > 0")
    mesh.apply_scale(float(scale))
    return ObstacleAsset(name, _on_ground(mesh))


def packaged_mesh_assets() -> dict[str, Path]:
    """Meshes shipped inside installed packages (no downloads): robosuite's ``models/assets/objects/meshes/*.stl``
    when robosuite is installed. Returns ``{name: path}`` (empty when none is installed)."""
    out: dict[str, Path] = {}
    spec = importlib.util.find_spec("robosuite")
    if spec is not None and spec.submodule_search_locations:
        root = Path(list(spec.submodule_search_locations)[0]) / "models" / "assets" / "objects" / "meshes"
        if root.is_dir():
            for p in sorted(root.glob("*.stl")):
                out[f"robosuite/{p.stem}"] = p
    return out


def load_mesh_asset(path: str | Path, name: str | None = None, scale: float = 1.0) -> ObstacleAsset:
    """A mesh file (STL/OBJ/PLY) as an asset, recentred: bottom centre at the origin, z up as stored."""
    tm = _trimesh()
    try:
        mesh = tm.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types
        raise ReconError(f"{path}: cannot load the mesh ({exc})") from exc
    if len(getattr(mesh, "vertices", [])) < 4:
        raise ReconError(f"{path}: the mesh has fewer than 4 vertices")
    c = mesh.bounds.mean(axis=0)
    mesh.apply_translation([-c[0], -c[1], 0.0])
    mesh.apply_scale(float(scale))
    return ObstacleAsset(name or Path(path).stem, _on_ground(mesh))


def obstacle_hull_sdf(asset: ObstacleAsset, T_world_obj: np.ndarray, inflation: float = C.OBSTACLE_INFLATION_M
                      ) -> tuple[ConvexPolytopeSDF, np.ndarray]:
    """Inflated convex hull of the asset placed at ``T_world_obj`` ([4, 4]).

    Returns:
        (ConvexPolytopeSDF with every facet plane pushed out by ``inflation``, hull vertices [V, 3] world)
    """
    T = np.asarray(T_world_obj, np.float64)
    v = asset.hull_vertices @ T[:3, :3].T + T[:3, 3]
    base = ConvexPolytopeSDF.from_points(v)
    return ConvexPolytopeSDF(base.normals, base.offsets - float(inflation)), v


@dataclass
class ObstaclePlacement:
    """A placed obstacle.

    Attributes:
        asset: the asset; T_world_obj: [4, 4] pose (world, metres); sdf: inflated hull field;
        hull_world: [V, 3] hull vertices; inflation: metres;
        blocked_min_clearance: min sphere clearance to the inflated hull along the straight approach (< 0: blocked);
        precontact_min_clearance: min clearance over the protected frames (tail, pre-contact pose, post-contact);
        tries: candidates drawn.
    """

    asset: ObstacleAsset
    T_world_obj: np.ndarray
    sdf: ConvexPolytopeSDF
    hull_world: np.ndarray
    inflation: float
    blocked_min_clearance: float
    precontact_min_clearance: float
    tries: int


def _sphere_world(T: np.ndarray, widths: np.ndarray, spheres_fn) -> tuple[np.ndarray, np.ndarray]:
    sets = [spheres_fn(float(w)) for w in widths]
    cen = np.stack([s.centers_cam for s in sets])
    rad = np.stack([s.radii for s in sets])
    return np.einsum("tij,tsj->tsi", T[:, :3, :3], cen) + T[:, None, :3, 3], rad


def sample_obstacle_placement(asset: ObstacleAsset, T_world_cam: np.ndarray, gripper_width: np.ndarray,
                              contact_index: int, rng: np.random.Generator | int,
                              scene_sdf: SignedDistanceField | None = None,
                              inflation: float = C.OBSTACLE_INFLATION_M, clearance: float = C.OBSTACLE_CLEARANCE_M,
                              support_z: float = 0.0, tail_fraction: float = 0.15,
                              path_range: tuple[float, float] = (0.1, 0.9), lateral_jitter_m: float = 0.08,
                              max_tries: int = C.OBSTACLE_MAX_TRIES,
                              spheres_fn: Callable[[float], object] | None = None) -> ObstaclePlacement:
    """Place ``asset`` so that it blocks the demo's straight approach but not its pre-contact pose.

    Args:
        asset: obstacle.
        T_world_cam: np.ndarray,  # [T, 4, 4] the demo's camera poses (world, metres)
        gripper_width: np.ndarray,  # [T] metres
        contact_index: the demo's pre-contact / contact frame.
        rng: Generator or seed.
        scene_sdf: when given, the obstacle's surface (above ``support_z`` + 5 mm) must be in its free space.
        inflation: hull inflation, metres; clearance: required clearance of the protected frames, metres.
        support_z: height of the support plane (table top = 0 in the table-tag frame).
        tail_fraction: the last fraction (by path length) of the demo approach that is protected.
        path_range: where along the straight approach (fraction) candidate positions are drawn.
    Raises:
        ReconError: no valid placement within ``max_tries`` (the approach is too short / too high for this
            asset, or the tail is too long): try a taller/larger asset or another demo.
    """
    if spheres_fn is None:
        spheres_fn = umi_gripper_spheres
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(int(rng))
    T = np.asarray(T_world_cam, np.float64)
    w = np.asarray(gripper_width, np.float64).reshape(-1)
    c = int(contact_index)
    if T.ndim != 3 or len(T) != len(w) or not 0 < c < len(T):
        raise ReconError(f"sample_obstacle_placement: poses {T.shape}, widths {w.shape}, contact {contact_index}")
    # straight approach: start pose → pre-contact pose, fingers at the start width
    s = np.linspace(0.0, 1.0, 48)
    straight = interpolate_pose(T[0], T[c], s)
    sp_str, r_str = _sphere_world(straight, np.full(len(s), w[0]), spheres_fn)
    # protected frames: the approach tail (by path length), the pre-contact pose, and everything after contact
    pos = T[: c + 1, :3, 3]
    lam = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    tail0 = int(np.searchsorted(lam, (1.0 - tail_fraction) * lam[-1])) if lam[-1] > 0 else c
    prot = np.arange(min(tail0, c), len(T))
    sp_pr, r_pr = _sphere_world(T[prot], w[prot], spheres_fn)
    ref = sp_str.mean(axis=1)  # [48, 3] centre of the gripper along the straight approach
    pts_obj = asset.surface_points(C.OBSTACLE_SURFACE_POINTS, seed=int(gen.integers(1 << 31)))
    lo_s, hi_s = path_range
    best = None
    why = {"not_blocking": 0, "hits_precontact": 0, "hits_scene": 0}
    for k in range(1, max_tries + 1):
        t = gen.uniform(lo_s, hi_s)
        p = np.array([np.interp(t, s, ref[:, i]) for i in range(3)])
        p[:2] += gen.uniform(-lateral_jitter_m, lateral_jitter_m, 2)
        yaw = gen.uniform(0.0, 2 * math.pi)
        Tobj = np.eye(4)
        Tobj[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0, 0, 1]]
        Tobj[:3, 3] = [p[0], p[1], support_z]
        sdf, hull = obstacle_hull_sdf(asset, Tobj, inflation)
        d_str = sdf.distance_and_gradient(sp_str)[0] - r_str
        if d_str.min() >= 0.0:
            why["not_blocking"] += 1
            continue  # does not block the straight approach
        d_pr = sdf.distance_and_gradient(sp_pr)[0] - r_pr
        if d_pr.min() < clearance:
            why["hits_precontact"] += 1
            continue  # touches the pre-contact approach / pose / post-contact motion
        if scene_sdf is not None:
            pw = pts_obj @ Tobj[:3, :3].T + Tobj[:3, 3]
            pw = pw[pw[:, 2] > support_z + 0.005]
            if len(pw) and np.asarray(scene_sdf.distance_and_gradient(pw)[0]).min() < 0.0:
                why["hits_scene"] += 1
                continue  # intersects the reconstructed scene
        best = ObstaclePlacement(asset, Tobj, sdf, hull, float(inflation), float(d_str.min()), float(d_pr.min()), k)
        break
    if best is None:
        raise ReconError(f"sample_obstacle_placement: no placement of {asset.name!r} (height "
                         f"{asset.height * 100:.0f} cm) blocks the straight approach while keeping "
                         f"{clearance * 1000:.0f} mm from the pre-contact tail after {max_tries} tries (rejections: {why}); "
                         f"use a "
                         f"taller or larger asset (scale), widen path_range, or a demo with a longer approach")
    return best
