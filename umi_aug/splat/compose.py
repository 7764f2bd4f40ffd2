"""Scene + obstacle composition (issue #4 item 5; paper §3.2 obstacle augmentation) and a render cache.

:func:`render_composed` renders a scene plus N rigidly placed obstacle Gaussian sets without copying or
transforming the scene: every set is projected separately by the numba projection of the inference path, an
obstacle with the camera expressed in its own frame (``T_obj_cam = T_world_obj^-1 T_world_cam``). Projection is
invariant under a rigid motion of camera and Gaussians together (means, covariances, ray distances, culling), and
the view direction that feeds the SH colour is then the object-frame direction — exactly what a rigidly moved,
view-dependent Gaussian shows (its SH coefficients live in the object frame). Only the visible projected records
(``[V, 16]``, see :mod:`umi_aug.splat._kernels`) are merged before the depth sort, tile binning and
rasterisation, so the scene's parameter tensors are never concatenated or copied.

The reference is :func:`transform_gaussians` (means, rotations and SH coefficients moved into the world; SH by
the exact per-band rotation matrix of :func:`sh_rotation_matrices`) + :func:`Gaussians.cat` +
:func:`umi_aug.splat.render`; the tests compare the two.

:class:`RenderCache`: memory-bounded LRU of uint8 renders keyed by (scene key, pose, intrinsics, obstacles'
keys and poses, background, render settings), with an optional on-disk store (one ``.npy`` per key, atomic
renames, so several DataLoader workers may share one directory; each process keeps its own memory cache).
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SplatError
from umi_aug.geometry.se3_torch import matrix_to_quat_wxyz, quat_wxyz_to_matrix
from umi_aug.io_utils import atomic_path
from umi_aug.splat._constants import DEFAULT_FAR, DEFAULT_FILTER, DEFAULT_NEAR, SH_COEFFS, TRANSMITTANCE_THRESHOLD
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.sh import sh_basis

__all__ = [
    "PlacedGaussians",
    "render_composed",
    "transform_gaussians",
    "sh_rotation_matrices",
    "rgb_to_uint8",
    "render_cache_key",
    "RenderCache",
    "COMPOSE_RENDER_KWARGS",
]

log = logging.getLogger(__name__)

#: Keyword arguments of :func:`umi_aug.splat.render` that :func:`render_composed` accepts (inference path).
COMPOSE_RENDER_KWARGS: frozenset[str] = frozenset({"filter", "near", "far", "min_transmittance"})
#: Decimals to which poses are rounded in cache keys (1e-12 m / rad: float noise of a recomputed pose maps to the
#: same key; any real motion does not).
POSE_KEY_DECIMALS: int = 12
#: Bumped when the cached image content for a given key would change (renderer semantics).
CACHE_FORMAT_VERSION: str = "umi-aug-render-cache-v1"
#: Directions used to fit the per-band SH rotation matrices (Fibonacci sphere; well conditioned for degree 3).
_SH_FIT_DIRECTIONS: int = 64


def _as_pose64(T: Any, name: str) -> np.ndarray:
    if isinstance(T, torch.Tensor):
        T = T.detach().cpu().numpy()
    a = np.asarray(T, dtype=np.float64)
    if a.shape != (4, 4):
        raise SplatError(f"{name} must have shape [4, 4], got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise SplatError(f"{name} has non-finite entries: {a.tolist()}")
    return a


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


@dataclass(frozen=True)
class PlacedGaussians:
    """One obstacle Gaussian set at a rigid pose.

    Attributes:
        gaussians: the set in its object frame (metres; SH coefficients w.r.t. object-frame directions).
        T_world_obj: np.ndarray,  # [4, 4] rigid pose of the object frame in the world (rotation + translation)
        key: stable identity of ``gaussians`` for caching (e.g. asset name + content hash); the pose is NOT part
            of it (the cache adds the pose itself).
    """

    gaussians: Gaussians
    T_world_obj: np.ndarray
    key: str

    def __post_init__(self) -> None:
        if not isinstance(self.gaussians, Gaussians):
            raise SplatError(f"PlacedGaussians.gaussians must be Gaussians, got {type(self.gaussians).__name__}")
        T = _as_pose64(self.T_world_obj, f"PlacedGaussians({self.key!r}).T_world_obj")
        R = T[:3, :3]
        err = float(np.abs(R.T @ R - np.eye(3)).max())
        if err > 1e-6 or abs(float(np.linalg.det(R)) - 1.0) > 1e-6 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
            raise SplatError(
                f"PlacedGaussians({self.key!r}).T_world_obj must be rigid (orthonormal rotation, det +1, last row "
                f"0 0 0 1); |R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.6f}"
            )
        if not isinstance(self.key, str) or not self.key:
            raise SplatError(f"PlacedGaussians.key must be a non-empty str, got {self.key!r}")
        object.__setattr__(self, "T_world_obj", T)


# --------------------------------------------------------------------------------------------------------------
# Reference: move Gaussians into the world (means, rotations, SH)
# --------------------------------------------------------------------------------------------------------------
def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def sh_rotation_matrices(R: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per-band matrices that rotate real SH coefficients (INRIA basis and signs, :func:`umi_aug.splat.sh.sh_basis`).

    For a rotation ``R`` (object -> world), returns ``M_l`` ``[2l+1, 2l+1]`` for ``l = 1..degree`` such that
    ``sum_k Y_k(d) c_world[k] = sum_k Y_k(R^T d) c_obj[k]`` for every direction ``d`` with
    ``c_world[band l] = M_l @ c_obj[band l]``. Band ``l`` of the real SH is closed under rotation, so ``M_l`` is
    exact; it is solved in float64 by least squares on 64 Fibonacci directions (residual ~1e-15).

    Args:
        R: np.ndarray,  # [3, 3] rotation
        degree: 0..3.
    """
    R = np.asarray(R, dtype=np.float64)
    d = _fibonacci_sphere(_SH_FIT_DIRECTIONS)
    Y = sh_basis(degree, torch.as_tensor(d)).numpy()  # [M, K]
    Yr = sh_basis(degree, torch.as_tensor(d @ R)).numpy()  # Y(R^T d), rows d_i^T R = (R^T d_i)^T
    out = []
    for l in range(1, degree + 1):
        a, b = SH_COEFFS[l - 1], SH_COEFFS[l]
        # Y_l(R^T d) = D Y_l(d)  ->  rows: Yr = Y D^T  ->  D^T = lstsq(Y, Yr)
        Dt, *_ = np.linalg.lstsq(Y[:, a:b], Yr[:, a:b], rcond=None)
        out.append(Dt)  # c_world[j] = sum_k D[k, j] c_obj[k] = (D^T c_obj)[j]
    return out


def transform_gaussians(gaussians: Gaussians, T_world_obj: np.ndarray) -> Gaussians:
    """The set moved rigidly into the world (the slow, obviously-correct reference of the composition).

    Means ``R mu + t``; rotations ``R R_local`` (as unit wxyz quaternions); scales and opacities unchanged; SH
    bands rotated exactly (:func:`sh_rotation_matrices`) so that the colour seen along a world direction ``d``
    equals the object-frame colour along ``R^T d``. Computed in float64, returned in the input dtype.

    Args:
        gaussians: set in its object frame.
        T_world_obj: np.ndarray,  # [4, 4] rigid
    """
    T = _as_pose64(T_world_obj, "T_world_obj")
    g = gaussians.detach().to(torch.float64)
    R = torch.as_tensor(T[:3, :3])
    t = torch.as_tensor(T[:3, 3])
    means = g.means @ R.T + t
    quats = matrix_to_quat_wxyz(R @ quat_wxyz_to_matrix(g.quats_wxyz))
    rest = g.sh_rest.clone()
    for l, M in enumerate(sh_rotation_matrices(T[:3, :3], g.sh_degree), start=1):
        a, b = SH_COEFFS[l - 1] - 1, SH_COEFFS[l] - 1  # sh_rest excludes the DC term
        rest[:, a:b, :] = torch.einsum("jk,nkc->njc", torch.as_tensor(M), g.sh_rest[:, a:b, :])
    out = Gaussians(means, g.log_scales.clone(), quats, g.logit_opacities.clone(), g.sh0.clone(), rest)
    return out.to(gaussians.dtype)


# --------------------------------------------------------------------------------------------------------------
# Composition (inference path)
# --------------------------------------------------------------------------------------------------------------
def _render_settings(render_kwargs: dict[str, Any]) -> tuple[str, float, float, float]:
    unknown = set(render_kwargs) - COMPOSE_RENDER_KWARGS
    if unknown:
        raise SplatError(
            f"render_composed: unsupported keyword(s) {sorted(unknown)}; accepted: {sorted(COMPOSE_RENDER_KWARGS)} "
            f"(the composition is the no-grad inference path; use render() on transform_gaussians() for gradients)"
        )
    filt = str(render_kwargs.get("filter", DEFAULT_FILTER))
    near = float(render_kwargs.get("near", DEFAULT_NEAR))
    far = float(render_kwargs.get("far", DEFAULT_FAR))
    if not (0.0 <= near < far):
        raise SplatError(f"need 0 <= near < far, got near={near!r}, far={far!r}")
    from umi_aug.splat.renderer import check_min_transmittance  # lazy, start-up: numba

    t_min = check_min_transmittance(render_kwargs.get("min_transmittance", TRANSMITTANCE_THRESHOLD))
    return filt, near, far, t_min


def render_composed(
    scene: Gaussians,
    obstacles: Sequence[PlacedGaussians],
    T_world_cam: torch.Tensor | np.ndarray,  # [4, 4] camera pose (OpenCV camera frame), metres
    intr: FisheyeIntrinsics,
    background: torch.Tensor | np.ndarray | Sequence[float] | None = None,  # [3] or [H, W, 3]
    sh_degree: int | None = None,
    pixels: np.ndarray | None = None,
    **render_kwargs: Any,
):
    """Render ``scene`` plus rigidly placed obstacle sets from ``T_world_cam`` (CPU, numba, no gradients).

    Equivalent to ``render(Gaussians.cat([scene] + [transform_gaussians(o.gaussians, o.T_world_obj) ...]), ...)``
    (same pixels up to float rounding; same depth order, ties included) without building that set: each set is
    projected on its own (an obstacle with ``T_obj_cam = T_world_obj^-1 T_world_cam``, which also evaluates its
    SH along object-frame view directions), then only the visible projected records are merged and binned.
    Obstacles are cast to the scene's dtype.

    Args:
        scene: the scene Gaussians (world frame); float32 (fast) or float64.
        obstacles: placed obstacle sets (object frame + pose); may be empty.
        T_world_cam: camera pose ``[4, 4]``.
        intr: KB fisheye intrinsics (image size included).
        background: RGB behind everything (default black).
        sh_degree: SH degree to evaluate (default: each set's own; capped at each set's degree).
        pixels: ``[H, W]`` bool: composite only these pixels, the others are the background (``alpha`` 0), as
            :func:`umi_aug.splat.render`'s ``pixels`` (None: all).
        **render_kwargs: ``filter``, ``near``, ``far``, ``min_transmittance`` as in :func:`umi_aug.splat.render`.

    Returns:
        :class:`umi_aug.splat.renderer.RenderOutput`; ``meta["ids"]`` index the concatenation
        ``[scene, obstacle 0, obstacle 1, ...]`` (the reference's rows), ``meta["parts"]`` lists per set its key,
        size and visible count.
    """
    # lazy, start-up: numba, scipy
    from umi_aug.splat.renderer import (RenderOutput, _background, active_pixels, bin_gaussians,
                                        compose_background_numpy, project_numba, rasterize_packed)

    if not isinstance(scene, Gaussians):
        raise SplatError(f"render_composed expects the scene as Gaussians, got {type(scene).__name__}")
    if not isinstance(intr, FisheyeIntrinsics):
        raise SplatError(f"render_composed expects FisheyeIntrinsics, got {type(intr).__name__}")
    for i, ob in enumerate(obstacles):
        if not isinstance(ob, PlacedGaussians):
            raise SplatError(f"render_composed: obstacles[{i}] must be PlacedGaussians, got {type(ob).__name__}")
    dtype = scene.dtype
    if dtype not in (torch.float32, torch.float64):
        raise SplatError(f"render_composed supports float32 and float64 scenes, got {dtype}")
    filt, near, far, t_min = _render_settings(render_kwargs)
    if sh_degree is not None and not 0 <= int(sh_degree) <= 3:
        raise SplatError(f"sh_degree must be in [0, 3], got {sh_degree!r}")
    H, W = intr.height, intr.width
    bg = _background(background, dtype, H, W)
    T_wc = _as_pose64(T_world_cam, "T_world_cam")
    active = None if pixels is None else active_pixels(pixels, H, W)
    t0 = time.perf_counter()

    parts: list[tuple[str, Gaussians, np.ndarray]] = [("scene", scene, T_wc)]
    for ob in obstacles:
        g = ob.gaussians if ob.gaussians.dtype == dtype else ob.gaussians.to(dtype)
        parts.append((ob.key, g, _rigid_inverse(ob.T_world_obj) @ T_wc))
    packed_l, uv_l, depth_l, counts_l, ids_l, part_meta = [], [], [], [], [], []
    offset = 0
    with torch.no_grad():
        for key, g, T_pc in parts:
            deg = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
            packed, uv64, depth64, valid, counts = project_numba(g, T_pc, intr, deg, filt, near, far)
            rows = np.flatnonzero(valid)
            packed_l.append(packed[rows])
            uv_l.append(uv64[rows])
            depth_l.append(depth64[rows])
            counts_l.append(counts[rows])
            ids_l.append(rows + offset)
            part_meta.append({"key": key, "n": g.n, "n_visible": int(rows.size)})
            offset += g.n
    packed = np.concatenate(packed_l) if len(packed_l) > 1 else packed_l[0]
    uv64 = np.concatenate(uv_l) if len(uv_l) > 1 else uv_l[0]
    depth64 = np.concatenate(depth_l) if len(depth_l) > 1 else depth_l[0]
    counts = np.concatenate(counts_l) if len(counts_l) > 1 else counts_l[0]
    ids = np.concatenate(ids_l) if len(ids_l) > 1 else ids_l[0]
    V = packed.shape[0]
    t1 = time.perf_counter()
    binning = bin_gaussians(packed, np.arange(V, dtype=np.int64), depth64, W, H, counts)
    t2 = time.perf_counter()
    out = rasterize_packed(packed, binning, uv64, fused=True, min_transmittance=t_min, pixels=active)
    t3 = time.perf_counter()
    rgb, alpha, ray_depth = compose_background_numpy(out, bg)
    meta = {
        "ids": torch.from_numpy(ids),
        "means2d": torch.from_numpy(uv64).to(dtype),
        "n_visible": int(V),
        "n_isects": binning.n_isects,
        "n_evals": int(out["evals"].sum()),
        "tiles": (binning.tiles_x, binning.tiles_y),
        "parts": part_meta,
        "timings": {"project": t1 - t0, "bin": t2 - t1, "raster": t3 - t2, "total": time.perf_counter() - t0},
    }
    return RenderOutput(rgb=rgb, alpha=alpha, ray_depth=ray_depth, meta=meta)


# --------------------------------------------------------------------------------------------------------------
# Render cache
# --------------------------------------------------------------------------------------------------------------
def rgb_to_uint8(rgb: torch.Tensor | np.ndarray) -> np.ndarray:
    """Float RGB ``[H, W, 3]`` in [0, 1] -> uint8 (clipped, rounded to nearest)."""
    a = rgb.detach().cpu().numpy() if isinstance(rgb, torch.Tensor) else np.asarray(rgb)
    return np.clip(np.rint(np.asarray(a, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _f64_bytes(a: Any, decimals: int | None = None) -> bytes:
    x = np.asarray(a, dtype=np.float64)
    if decimals is not None:
        x = np.round(x, decimals)
    x = x + 0.0  # -0.0 -> 0.0
    return np.ascontiguousarray(x).tobytes()


def render_cache_key(
    scene_key: str,
    T_world_cam: Any,  # [4, 4]
    intr: FisheyeIntrinsics,
    obstacles: Sequence[PlacedGaussians] = (),
    background: Any = None,
    settings: dict[str, Any] | None = None,
) -> str:
    """Deterministic hex key (sha256) of a composed render: scene key, pose (float64, rounded to
    :data:`POSE_KEY_DECIMALS`), intrinsics (all fields), obstacles' keys and poses in order, background, settings.
    Same inputs -> same key in every process and run."""
    h = hashlib.sha256()

    def put(tag: str, b: bytes) -> None:
        h.update(tag.encode())
        h.update(len(b).to_bytes(8, "little"))
        h.update(b)

    put("v", CACHE_FORMAT_VERSION.encode())
    put("scene", str(scene_key).encode())
    put("pose", _f64_bytes(_as_pose64(T_world_cam, "T_world_cam"), POSE_KEY_DECIMALS))
    k = (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, *intr.k,
         -1.0 if intr.theta_limit is None else intr.theta_limit)
    put("intr", _f64_bytes(k))
    for ob in obstacles:
        put("obkey", ob.key.encode())
        put("obpose", _f64_bytes(ob.T_world_obj, POSE_KEY_DECIMALS))
    if background is None:
        put("bg", b"none")
    else:
        bgv = background.detach().cpu().numpy() if isinstance(background, torch.Tensor) else background
        put("bg", _f64_bytes(bgv))
    put("settings", repr(sorted((settings or {}).items())).encode())
    return h.hexdigest()


class RenderCache:
    """Memory-bounded LRU cache of composed uint8 renders, with an optional on-disk store.

    Keys come from :func:`render_cache_key`. The memory cache evicts least-recently-used images until the total
    image bytes fit ``max_bytes`` (an image larger than ``max_bytes`` is returned but not kept in memory). With
    ``disk_dir``, every rendered image is also written to ``disk_dir/<key>.npy`` (write to a temporary sibling,
    then rename: concurrent writers of the same key are harmless) and looked up there on a memory miss; an
    unreadable file counts as a miss and is rewritten.

    Each process (e.g. every DataLoader worker) has its own memory cache: pickling drops the memory entries and
    the statistics. Not meant for concurrent use from threads of one process beyond a coarse lock.

    Args:
        max_bytes: memory budget for cached images (bytes).
        disk_dir: optional folder of the on-disk store.
        render_kwargs: settings passed to :func:`render_composed` for every render (``sh_degree``, ``filter``,
            ``near``, ``far``, ``min_transmittance``); part of every key.
    """

    def __init__(self, max_bytes: int = 512 << 20, disk_dir: str | Path | None = None, *,
                 render_kwargs: dict[str, Any] | None = None) -> None:
        if int(max_bytes) < 0:
            raise SplatError(f"RenderCache: max_bytes must be >= 0, got {max_bytes!r}")
        self.max_bytes = int(max_bytes)
        self.disk_dir = None if disk_dir is None else Path(disk_dir)
        self.render_kwargs = dict(render_kwargs or {})
        allowed = COMPOSE_RENDER_KWARGS | {"sh_degree"}
        bad = set(self.render_kwargs) - allowed
        if bad:
            raise SplatError(f"RenderCache: unsupported render_kwargs {sorted(bad)}; accepted: {sorted(allowed)}")
        self._mem: OrderedDict[str, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._stats = {"hits": 0, "disk_hits": 0, "misses": 0, "evictions": 0, "renders_s": 0.0}

    # ------------------------------------------------------------------------------------------- pickling
    def __getstate__(self) -> dict[str, Any]:
        return {"max_bytes": self.max_bytes, "disk_dir": self.disk_dir, "render_kwargs": self.render_kwargs}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["max_bytes"], state["disk_dir"], render_kwargs=state["render_kwargs"])

    # --------------------------------------------------------------------------------------------- stats
    @property
    def stats(self) -> dict[str, Any]:
        """``hits`` (memory), ``disk_hits``, ``misses`` (rendered), ``evictions``, ``bytes`` and ``entries`` in
        memory, ``renders_s`` (seconds spent rendering)."""
        with self._lock:
            return {**self._stats, "bytes": self._bytes, "entries": len(self._mem)}

    def __len__(self) -> int:
        return len(self._mem)

    def clear(self) -> None:
        """Drop the memory entries (the disk store is kept)."""
        with self._lock:
            self._mem.clear()
            self._bytes = 0

    # ------------------------------------------------------------------------------------------- storage
    def _put_mem(self, key: str, img: np.ndarray) -> None:
        nb = int(img.nbytes)
        with self._lock:
            if key in self._mem:
                self._mem.move_to_end(key)
                return
            if nb > self.max_bytes:
                return
            self._mem[key] = img
            self._bytes += nb
            while self._bytes > self.max_bytes:
                _, old = self._mem.popitem(last=False)
                self._bytes -= int(old.nbytes)
                self._stats["evictions"] += 1

    def _disk_path(self, key: str) -> Path:
        assert self.disk_dir is not None
        return self.disk_dir / f"{key}.npy"

    def _read_disk(self, key: str, shape: tuple[int, int, int]) -> np.ndarray | None:
        p = self._disk_path(key)
        if not p.is_file():
            return None
        try:
            img = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            log.warning("render cache: unreadable %s (%s); re-rendering", p, exc)
            return None
        if img.dtype != np.uint8 or img.shape != shape:
            log.warning("render cache: %s holds %s %s, expected uint8 %s; re-rendering", p, img.dtype, img.shape,
                        shape)
            return None
        return img

    def _write_disk(self, key: str, img: np.ndarray) -> None:
        p = self._disk_path(key)
        with atomic_path(p) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, img, allow_pickle=False)

    # -------------------------------------------------------------------------------------------- render
    def key(self, scene_key: str, T_world_cam, intr: FisheyeIntrinsics,
            obstacles: Sequence[PlacedGaussians] = (), background=None) -> str:
        """The cache key of a render with this cache's settings."""
        return render_cache_key(scene_key, T_world_cam, intr, obstacles, background, self.render_kwargs)

    def render_rgb(
        self,
        scene: Gaussians,
        scene_key: str,
        T_world_cam: torch.Tensor | np.ndarray,  # [4, 4]
        intr: FisheyeIntrinsics,
        obstacles: Sequence[PlacedGaussians] = (),
        background=None,  # [3] or [H, W, 3]
    ) -> np.ndarray:
        """The composed render as uint8 RGB ``[H, W, 3]`` (cached; the returned array is read-only).

        ``scene_key`` must identify ``scene``'s content (e.g. the PLY path + its hash): the cache never looks at
        the Gaussians themselves.
        """
        k = self.key(scene_key, T_world_cam, intr, obstacles, background)
        with self._lock:
            img = self._mem.get(k)
            if img is not None:
                self._mem.move_to_end(k)
                self._stats["hits"] += 1
                return img
        shape = (intr.height, intr.width, 3)
        if self.disk_dir is not None:
            img = self._read_disk(k, shape)
            if img is not None:
                img.flags.writeable = False
                with self._lock:
                    self._stats["disk_hits"] += 1
                self._put_mem(k, img)
                return img
        t0 = time.perf_counter()
        out = render_composed(scene, obstacles, T_world_cam, intr, background, **self.render_kwargs)
        img = rgb_to_uint8(out.rgb)
        img.flags.writeable = False
        with self._lock:
            self._stats["misses"] += 1
            self._stats["renders_s"] += time.perf_counter() - t0
        if self.disk_dir is not None:
            self._write_disk(k, img)
        self._put_mem(k, img)
        return img
