"""Simulated mapping scan of the square scene: wrist-camera scan poses and fisheye renders with parts hidden.

The simulator's analogue of UMI's mapping video: a short scan of the workspace rendered through the true fisheye
(:class:`umi_aug.sim.fisheye_renderer.FisheyeRenderer`, the same renderer as the policy images). The robot (arm,
gripper, mount: bodies named ``robot0_*``, ``gripper0_*``, ``mount0_*``, their geoms AND sites) is never in a scan:
the augmentation pastes the real gripper in later. What else is shown depends on the scan ``kind``:

- ``"scene"``: everything but the robot (a demo's full scene; the evaluation's ground truth);
- ``"static"``: also without the square nut (what every square demo shares: table, pegs, room);
- ``"nut"``: the square nut alone (for its asset; ``ScanFrames.mask`` marks its pixels).

Hiding works on a COPY of the model: the hidden geoms/sites move to geom/site group :data:`HIDDEN_GROUP`, which
MuJoCo's default visual options do not draw (neither colour nor segmentation); nothing else changes, so the
visible parts render exactly as in the policy images.

Frames: poses ``T_world_cam`` [4, 4], OpenCV camera axes, metres; ray depth in metres along each pixel's ray.
States are robomimic flat MuJoCo states ``[time, qpos (nq), qvel (nv)]`` (45 values for the square task).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from umi_aug.camera import FisheyeIntrinsics
from umi_aug.camera.kb import unproject
from umi_aug.errors import SimError
from umi_aug.geometry import look_at_rotation
from umi_aug.sim.fisheye_renderer import FisheyeRenderer
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.raster import RasterOptions
from umi_aug.square.camera import FAR_M, NEAR_M
from umi_aug.square.env import NUT_BODY

__all__ = ["ROBOT_BODY_PREFIXES", "HIDDEN_GROUP", "SCAN_KINDS", "robot_body_ids", "hidden_geom_ids", "scan_model",
           "data_at_state", "state_length", "scan_poses", "nut_orbit_poses", "nut_orbit_intrinsics", "ScanFrames",
           "ScanRenderer", "render_scan", "scan_points", "body_pose"]

#: MuJoCo body-name prefixes of the robot (arm, gripper, mount): never part of a scan.
ROBOT_BODY_PREFIXES: tuple[str, ...] = ("robot0_", "gripper0_", "mount0_")
#: Geom/site group of hidden parts (MuJoCo draws groups 0-2 by default).
HIDDEN_GROUP: int = 5
SCAN_KINDS: tuple[str, ...] = ("scene", "static", "nut")


# ------------------------------------------------------------------------------------------------ model / state
def _names(model, obj, n: int) -> list[str]:
    mujoco = import_mujoco()
    return [mujoco.mj_id2name(model, obj, i) or "" for i in range(n)]


def robot_body_ids(model) -> np.ndarray:
    """Ids ``[k]`` of the robot's bodies (names starting with :data:`ROBOT_BODY_PREFIXES`)."""
    mujoco = import_mujoco()
    names = _names(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody)
    ids = np.array([i for i, n in enumerate(names) if n.startswith(ROBOT_BODY_PREFIXES)], dtype=np.int64)
    if ids.size == 0:
        raise SimError(f"scan: the model has no robot body (none named {'/'.join(ROBOT_BODY_PREFIXES)}*)")
    return ids


def _nut_body_ids(model) -> np.ndarray:
    """The square nut's body and its descendants."""
    mujoco = import_mujoco()
    root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, NUT_BODY)
    if root < 0:
        raise SimError(f"scan: the model has no body named {NUT_BODY!r} (not a NutAssemblySquare model?)")
    ids = [root]
    for b in range(model.nbody):
        p = b
        while p > 0 and p != root:
            p = int(model.body_parentid[p])
        if p == root and b != root:
            ids.append(b)
    return np.array(ids, dtype=np.int64)


def _hidden_bodies(model, kind: str) -> np.ndarray:
    """Bool ``[nbody]``: bodies whose geoms and sites a scan of ``kind`` hides."""
    if kind not in SCAN_KINDS:
        raise SimError(f"scan: kind must be one of {SCAN_KINDS}, got {kind!r}")
    hide = np.zeros(model.nbody, dtype=bool)
    hide[robot_body_ids(model)] = True
    nut = _nut_body_ids(model)
    if kind == "static":
        hide[nut] = True
    elif kind == "nut":
        hide[:] = True
        hide[nut] = False
    return hide


def hidden_geom_ids(model, kind: str) -> np.ndarray:
    """Geom ids ``[k]`` that a scan of ``kind`` does not draw (see the module docstring)."""
    return np.flatnonzero(_hidden_bodies(model, kind)[np.asarray(model.geom_bodyid)])


def scan_model(model, kind: str):
    """A copy of ``model`` whose hidden geoms/sites (for ``kind``) sit in :data:`HIDDEN_GROUP` (not drawn)."""
    hide = _hidden_bodies(model, kind)
    m = copy.deepcopy(model)
    m.geom_group[hide[np.asarray(m.geom_bodyid)]] = HIDDEN_GROUP
    m.site_group[hide[np.asarray(m.site_bodyid)]] = HIDDEN_GROUP
    return m


def state_length(model) -> int:
    """Length of a robomimic flat state of ``model``: ``1 + nq + nv``."""
    return 1 + int(model.nq) + int(model.nv)


def data_at_state(model, state: np.ndarray):
    """``mujoco.MjData`` of ``model`` at a robomimic flat state ``[time, qpos, qvel]``, kinematics computed.

    Raises:
        SimError: the state has the wrong length or non-finite entries (one message naming both).
    """
    mujoco = import_mujoco()
    s = np.asarray(state, dtype=np.float64)
    n = state_length(model)
    if s.ndim != 1 or s.shape[0] != n:
        raise SimError(f"scan: state has shape {list(s.shape)}; this model needs a flat robomimic state of "
                       f"1 + nq ({model.nq}) + nv ({model.nv}) = {n} values [time, qpos, qvel]")
    if not np.all(np.isfinite(s)):
        raise SimError("scan: state has non-finite entries")
    d = mujoco.MjData(model)
    d.time = float(s[0])
    d.qpos[:] = s[1:1 + model.nq]
    d.qvel[:] = s[1 + model.nq:]
    mujoco.mj_forward(model, d)
    return d


def body_pose(model, data, body: str = NUT_BODY) -> np.ndarray:
    """World pose ``[4, 4]`` of a body (default: the square nut)."""
    mujoco = import_mujoco()
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if b < 0:
        raise SimError(f"scan: the model has no body named {body!r}")
    T = np.eye(4)
    T[:3, :3] = np.asarray(data.xmat[b]).reshape(3, 3)
    T[:3, 3] = data.xpos[b]
    return T


# ----------------------------------------------------------------------------------------------------- poses
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _look_at_rolled(pos: np.ndarray, target: np.ndarray, roll: np.ndarray) -> np.ndarray:
    R = look_at_rotation(pos, target, np.array([0.0, 0.0, 1.0]))
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.zeros((len(roll), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    T = np.tile(np.eye(4), (len(pos), 1, 1))
    T[:, :3, :3] = R @ Rz
    T[:, :3, 3] = pos
    return T


def scan_poses(center_world: np.ndarray, n: int, seed: int, radius: tuple[float, float] = (0.18, 0.40),
               max_polar_deg: float = 60.0, target_radius: float = 0.12) -> np.ndarray:
    """Scan poses on a cap above a workspace point, each looking at a point of the table near it.

    Positions ``center + r d``: directions ``d`` on the cap of half-angle ``max_polar_deg`` around +z (a Fibonacci
    spiral, uniform by area, rotated by a seeded azimuth), radii ``r`` stratified over ``radius`` (golden-ratio
    sequence, seeded offset); each camera looks at ``center`` plus a seeded horizontal offset within
    ``target_radius`` and is rolled by a seeded angle about its optical axis. Deterministic from ``seed``.

    Args:
        center_world: np.ndarray,  # [3] workspace point (on the table top), world, metres
        n: number of poses (>= 1).
        seed: randomness of the azimuth offset, radii offset, targets and rolls.
    Returns:
        T_world_cam: np.ndarray,  # [n, 4, 4] OpenCV axes
    """
    c = np.asarray(center_world, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise SimError(f"scan_poses: center_world must be a finite [3] point, got {c.tolist()}")
    n = int(n)
    r0, r1 = (float(v) for v in radius)
    if n < 1 or not 0.0 < r0 <= r1 or not 0.0 < max_polar_deg < 90.0 or target_radius < 0:
        raise SimError(f"scan_poses: need n >= 1, 0 < radius[0] <= radius[1], max_polar_deg in (0, 90), "
                       f"target_radius >= 0; got n={n}, radius={radius}, max_polar_deg={max_polar_deg}, "
                       f"target_radius={target_radius}")
    rng = np.random.default_rng([int(seed), 0x5CA7])
    i = np.arange(n) + 0.5
    w = i / n * (1.0 - math.cos(math.radians(max_polar_deg)))  # 1 - cos(polar), uniform by area
    polar = np.arccos(1.0 - w)
    az = 2.0 * math.pi * _GOLDEN * np.arange(n) + rng.uniform(0, 2 * math.pi)
    d = np.stack([np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)], axis=-1)
    frac = (rng.uniform() + _GOLDEN * np.arange(n)) % 1.0
    r = r0 + (r1 - r0) * frac
    pos = c + r[:, None] * d
    ang = rng.uniform(0, 2 * math.pi, n)
    rad = target_radius * np.sqrt(rng.uniform(0, 1, n))
    target = c + np.stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(n)], axis=-1)
    roll = rng.uniform(-math.pi, math.pi, n)
    return _look_at_rolled(pos, target, roll)


def nut_orbit_poses(T_world_nut: np.ndarray, n: int, seed: int, radius: tuple[float, float] = (0.16, 0.26),
                    elevation_deg: tuple[float, float] = (25.0, 85.0)) -> np.ndarray:
    """Orbit poses around the nut's centre (above the table only), looking at it, seeded roll.

    Elevations stratified over ``elevation_deg`` and azimuths on a golden-angle spiral, radii over ``radius``.

    Args:
        T_world_nut: np.ndarray,  # [4, 4] nut body pose
    Returns:
        T_world_cam: np.ndarray,  # [n, 4, 4] OpenCV axes, world frame
    """
    T = np.asarray(T_world_nut, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SimError("nut_orbit_poses: T_world_nut must be a finite [4, 4] pose")
    n = int(n)
    if n < 1:
        raise SimError(f"nut_orbit_poses: n must be >= 1, got {n}")
    rng = np.random.default_rng([int(seed), 0x0A07])
    e0, e1 = (math.radians(float(v)) for v in elevation_deg)
    i = np.arange(n) + 0.5
    s0, s1 = math.sin(e0), math.sin(e1)
    el = np.arcsin(s0 + (s1 - s0) * i / n)  # uniform by area within the elevation band
    az = 2.0 * math.pi * _GOLDEN * np.arange(n) + rng.uniform(0, 2 * math.pi)
    frac = (rng.uniform() + _GOLDEN * np.arange(n)) % 1.0
    r = float(radius[0]) + (float(radius[1]) - float(radius[0])) * frac
    centre = T[:3, 3]
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    return _look_at_rolled(centre + r[:, None] * d, np.tile(centre, (n, 1)), rng.uniform(-math.pi, math.pi, n))


def nut_orbit_intrinsics(size: int, fov_deg: float = 70.0) -> FisheyeIntrinsics:
    """Equidistant fisheye of the nut's orbit views: ``size`` square, ``fov_deg`` across the image circle."""
    s = int(size)
    if s < 16 or not 10.0 <= fov_deg <= 170.0:
        raise SimError(f"nut_orbit_intrinsics: need size >= 16 and fov_deg in [10, 170], got {size}, {fov_deg}")
    half = math.radians(fov_deg / 2.0)
    return FisheyeIntrinsics.equidistant(s, s, (s / 2.0) / half, theta_limit=half)


# ---------------------------------------------------------------------------------------------------- render
@dataclass
class ScanFrames:
    """Renders of one scan.

    Attributes:
        rgb: np.ndarray,  # [V, H, W, 3] uint8, black outside the image circle
        ray_depth: np.ndarray,  # [V, H, W] float32 metres along the ray; 0 where nothing visible was hit
        mask: np.ndarray,  # [V, H, W] bool: inside the image circle and a visible geom is seen
        geom_id: np.ndarray,  # [V, H, W] int32 MuJoCo geom id seen (−1: none / outside)
        valid: np.ndarray,  # [H, W] bool: the lens's image circle
        T_world_cam: np.ndarray,  # [V, 4, 4]
        intr: FisheyeIntrinsics of the images
        kind: the scan kind
    """

    rgb: np.ndarray
    ray_depth: np.ndarray
    mask: np.ndarray
    geom_id: np.ndarray
    valid: np.ndarray
    T_world_cam: np.ndarray
    intr: FisheyeIntrinsics
    kind: str


class ScanRenderer:
    """Fisheye renders of one model with the parts of ``kind`` hidden (model copied once, GL context kept).

    Args:
        model: raw ``mujoco.MjModel`` of the square environment (not modified).
        kind: ``"scene"``, ``"static"`` or ``"nut"``.
        intr: fisheye intrinsics of the renders (e.g. :func:`umi_aug.square.camera.wrist_intrinsics`).
    """

    def __init__(self, model, kind: str, intr: FisheyeIntrinsics) -> None:
        self.kind = kind
        self.model = scan_model(model, kind)
        self.intr = intr
        # nearest depth, like the segmentation: no depths mixed across occlusion edges (point initialisation)
        self.renderer = FisheyeRenderer(self.model, intr, options=RasterOptions(near=NEAR_M, far=FAR_M),
                                        depth_interpolation="nearest")

    def render(self, state: np.ndarray, poses: np.ndarray, *, progress: bool = False) -> ScanFrames:
        """Render ``poses`` ``[V, 4, 4]`` of the scene at robomimic flat ``state``."""
        P = np.asarray(poses, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) == 0:
            raise SimError(f"scan: poses must be [V, 4, 4] with V >= 1, got shape {list(P.shape)}")
        data = data_at_state(self.model, state)
        rgb, depth, seg = [], [], []
        it = range(len(P))
        if progress:
            it = tqdm(it, desc=f"scan[{self.kind}]", unit="view", leave=False)
        for v in it:
            fr = self.renderer.render(P[v], data, rgb=True, depth=True, segmentation=True)
            rgb.append(fr.rgb)
            depth.append(fr.ray_depth)
            seg.append(fr.geom_id)
        geom_id = np.stack(seg)
        valid = self.renderer.valid_mask
        mask = (geom_id >= 0) & valid[None]
        ray_depth = np.where(mask, np.stack(depth), np.float32(0.0)).astype(np.float32)
        return ScanFrames(np.stack(rgb), ray_depth, mask, geom_id, valid.copy(), P.copy(), self.intr, self.kind)

    def close(self) -> None:
        """Free the GL context."""
        self.renderer.close()

    def __enter__(self) -> "ScanRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_scan(model, state: np.ndarray, poses: np.ndarray, intr: FisheyeIntrinsics, kind: str,
                *, progress: bool = False) -> ScanFrames:
    """One-shot :meth:`ScanRenderer.render` (creates and frees the GL context)."""
    with ScanRenderer(model, kind, intr) as r:
        return r.render(state, poses, progress=progress)


def scan_points(frames: ScanFrames, max_points: int, seed: int,
                T_frame_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Coloured 3D points from the scan's ray depth (masked pixels), a seeded random subset.

    Args:
        frames: the scan.
        max_points: at most this many points (>= 1).
        T_frame_world: np.ndarray | None,  # [4, 4] express the points in this frame (default: world)
    Returns:
        xyz: np.ndarray,  # [N, 3] metres
        rgb: np.ndarray,  # [N, 3] float in [0, 1]
    """
    intr = frames.intr
    vv, uu = np.mgrid[0:intr.height, 0:intr.width]
    rays, ok = unproject(np.stack([uu, vv], axis=-1).astype(np.float64), intr)
    sel = frames.mask & ok[None] & (frames.ray_depth > 0)
    v_idx, r_idx, c_idx = np.nonzero(sel)
    if v_idx.size == 0:
        raise SimError(f"scan_points: the {frames.kind!r} scan has no pixel with depth")
    rng = np.random.default_rng([int(seed), 0x9017])
    if v_idx.size > int(max_points):
        keep = np.sort(rng.choice(v_idx.size, int(max_points), replace=False))
        v_idx, r_idx, c_idx = v_idx[keep], r_idx[keep], c_idx[keep]
    p_cam = rays[r_idx, c_idx] * frames.ray_depth[v_idx, r_idx, c_idx, None].astype(np.float64)
    T = frames.T_world_cam[v_idx]
    xyz = np.einsum("nij,nj->ni", T[:, :3, :3], p_cam) + T[:, :3, 3]
    if T_frame_world is not None:
        F = np.asarray(T_frame_world, dtype=np.float64)
        xyz = xyz @ F[:3, :3].T + F[:3, 3]
    rgb = frames.rgb[v_idx, r_idx, c_idx].astype(np.float64) / 255.0
    return xyz, rgb
