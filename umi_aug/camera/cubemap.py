"""Cubemap → Kannala–Brandt fisheye resampling for simulated fisheye images.

Pinhole renderers (MuJoCo, OpenGL) cannot render a fisheye whose field of view reaches past 90° from the axis (the
UMI GoPro lens reaches ~104°). Instead a renderer draws up to six 90° pinhole *cube faces* around the camera centre
and :class:`CubemapFisheyeRemap` resamples them into the true KB fisheye image (traj_sdf_sim_notes.md §4). All the
geometry is precomputed once per intrinsics; each frame then costs one ``cv2.remap`` over a face atlas (plus a
tiny one that fills each face's one-texel border from its neighbours, so bilinear sampling is seamless across face
edges: ``seam="blend"``; ``seam="clamp"`` clamps to each face's own texels instead).

Frames and faces
----------------
Everything here is in the fisheye camera's OpenCV frame (x right, y down, z forward). Each cube face is itself an
OpenCV pinhole camera at the same centre: z = the face normal, right-handed. The face names, normals and the
in-plane orientation chosen for each face (columns of ``R_cam_face`` = face x, y, z axes in the fisheye frame):

============  =========  ===========  ===========  ==============================================
face          normal z   face x       face y       i.e. the fisheye camera ...
============  =========  ===========  ===========  ==============================================
``front``     +z         +x           +y           itself (R = I)
``back``      −z         −x           +y           yawed 180° about its y axis
``right``     +x         −z           +y           yawed 90° to its right (about +y)
``left``      −x         +z           +y           yawed 90° to its left
``down``      +y         +x           −z           pitched 90° down (image top points forward)
``up``        −y         +x           +z           pitched 90° up (image bottom points forward)
============  =========  ===========  ===========  ==============================================

So the four side faces keep the fisheye's "down" (+y) as their image-down, and the down/up faces keep its "right"
(+x) as their image-right. A renderer places face camera ``i`` at
``T_world_face = T_world_cam @ [[R_cam_face, 0], [0, 1]]`` (OpenCV axes; ``sim/`` converts to MuJoCo's −z/+y-up
convention). Each face is a 90° pinhole of ``S × S`` pixels: ``f_face = S / 2``, principal point
``c = (S − 1) / 2`` (pixel centres at integer coordinates), i.e. MuJoCo ``fovy = 90``.

Depth from the faces is z-depth (along the face normal); :meth:`CubemapFisheyeRemap.remap_depth` converts it to
``ray_depth`` (distance along the fisheye pixel's ray), as the conventions require.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from umi_aug.camera.kb import kb_dtheta_d, kb_theta_d, unproject
from umi_aug.errors import CameraError

if TYPE_CHECKING:  # pragma: no cover
    from umi_aug.camera.intrinsics import FisheyeIntrinsics

logger = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------------------------
# Named constants
# ---------------------------------------------------------------------------------------------------------------
#: Face names; ``face_of_pixel`` stores indices into this tuple.
FACE_NAMES: tuple[str, ...] = ("front", "back", "right", "left", "down", "up")

#: (face x axis, face y axis, face z axis = normal) in the fisheye camera's OpenCV frame, per face.
_FACE_AXES: dict[str, tuple[tuple[float, float, float], ...]] = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "back": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "right": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "left": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
    "down": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "up": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
}

#: Cube faces are 90° pinholes (MuJoCo ``fovy``).
FACE_FOVY_DEG: float = 90.0
#: Smallest face size accepted / chosen, pixels.
MIN_FACE_SIZE: int = 8
#: Border texels around each face in the atlas. ``seam="blend"`` fills them, every frame, with bilinear samples of
#: the neighbouring face at the border texel's own ray, so bilinear sampling is seamless across face edges;
#: ``seam="clamp"`` leaves them zero and clamps coordinates to the face's own ``[0, S−1]`` (never sampled).
ATLAS_PAD_PX: int = 1
#: Seam handling modes of :class:`CubemapFisheyeRemap`.
SEAM_MODES: tuple[str, ...] = ("blend", "clamp")
#: Map coordinate given to invalid fisheye pixels: far outside the atlas, so cv2 returns the border (fill) value.
INVALID_MAP_COORD: float = -64.0
#: ``remap_depth``: smallest bilinear weight on hit (finite-depth) texels for a fisheye pixel to count as a hit.
DEPTH_MIN_HIT_WEIGHT: float = 0.5
#: θ samples used to find the lens's maximum angular pixel density.
DENSITY_THETA_SAMPLES: int = 4096
#: Sample-interpolation names → cv2 flags.
INTERPOLATIONS: dict[str, int] = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}
#: Image dtypes cv2.remap handles.
_REMAP_DTYPES = (np.uint8, np.uint16, np.int16, np.float32, np.float64)
#: cv2.remap handles at most this many channels per call (see ``_channel_chunks``).
_CV_MAX_CHANNELS: int = 4


# ---------------------------------------------------------------------------------------------------------------
# Face geometry
# ---------------------------------------------------------------------------------------------------------------
def face_rotation(name: str) -> np.ndarray:
    """Rotation of a cube face camera relative to the fisheye camera.

    Args:
        name: one of :data:`FACE_NAMES`.

    Returns:
        ``R_cam_face`` ``[3, 3]`` float64: columns are the face camera's x, y, z axes expressed in the fisheye
        camera's OpenCV frame (z = face normal); ``det = +1``. ``p_cam = R_cam_face @ p_face``.
    """
    if name not in _FACE_AXES:
        raise CameraError(f"unknown cube face {name!r}; expected one of {FACE_NAMES}")
    return np.array(_FACE_AXES[name], dtype=np.float64).T


def _all_rotations() -> np.ndarray:
    """``[6, 3, 3]`` ``R_cam_face`` in :data:`FACE_NAMES` order."""
    return np.stack([face_rotation(n) for n in FACE_NAMES])


def _check_face_size(face_size: Any) -> int:
    if isinstance(face_size, bool) or not isinstance(face_size, (int, np.integer)) or face_size < MIN_FACE_SIZE:
        raise CameraError(f"face_size must be an int >= {MIN_FACE_SIZE}, got {face_size!r}")
    return int(face_size)


def face_intrinsics_matrix(face_size: int) -> np.ndarray:
    """Pinhole intrinsics of a 90° cube face of ``face_size × face_size`` pixels.

    Returns:
        ``K_face`` ``[3, 3]`` float64 with ``fx = fy = S / 2`` and ``cx = cy = (S − 1) / 2`` (pixel centres at
        integer coordinates), in pixels.
    """
    s = _check_face_size(face_size)
    f, c = s / 2.0, (s - 1) / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def face_pixel_rays(name: str, face_size: int) -> np.ndarray:
    """Unit viewing rays of every pixel centre of one cube face, in the fisheye camera's OpenCV frame.

    Useful for ray-traced renderers and tests: a face image is ``colour(face_pixel_rays(name, S))``.

    Returns:
        ``[S, S, 3]`` float64 unit vectors; ``[row, col]`` indexing.
    """
    s = _check_face_size(face_size)
    f, c = s / 2.0, (s - 1) / 2.0
    idx = (np.arange(s, dtype=np.float64) - c) / f
    x, y = np.meshgrid(idx, idx)  # x varies along columns, y along rows
    d_face = np.stack([x, y, np.ones_like(x)], axis=-1)
    d_face /= np.linalg.norm(d_face, axis=-1, keepdims=True)
    return d_face @ face_rotation(name).T


def _dominant_face(rays: np.ndarray) -> np.ndarray:
    """Index into :data:`FACE_NAMES` of the face whose normal is closest to each ray.

    Args:
        rays: ``[..., 3]`` directions in the fisheye camera frame (need not be unit).

    Returns:
        ``[...]`` int64. Ties go to the first face in :data:`FACE_NAMES` order.
    """
    normals = _all_rotations()[:, :, 2]  # [6, 3]
    return np.argmax(rays @ normals.T, axis=-1)


def _lens_density(intr: FisheyeIntrinsics, theta_max: float) -> tuple[float, float]:
    """Maximum angular pixel densities (pixels per radian) of the KB lens over ``θ ∈ [0, theta_max]``.

    Returns:
        ``(radial, tangential)``: ``f · max dθ_d/dθ`` and ``f · max θ_d / sin θ`` with ``f = max(fx, fy)``.
    """
    t = np.linspace(0.0, max(float(theta_max), 1e-6), DENSITY_THETA_SAMPLES)
    dtd = kb_dtheta_d(t, intr.k)
    td = kb_theta_d(t, intr.k)
    s = np.sin(t)
    ok = s > 1e-6
    tang = np.ones_like(t)
    tang[ok] = td[ok] / s[ok]
    f = max(float(intr.fx), float(intr.fy))
    return f * float(dtd.max()), f * float(tang.max())


def default_face_size(intr: FisheyeIntrinsics, theta_max: float | None = None) -> int:
    """Smallest face size whose pinhole centre density matches the fisheye's maximum radial density.

    A 90° face of ``S`` pixels has ``S / 2`` pixels per radian at its centre (and more elsewhere). The fisheye has
    ``f · dθ_d/dθ`` pixels per radian radially; so ``S = ceil(2 · f · max_{θ ≤ θmax} dθ_d/dθ)`` (≈ 2f for the
    GoPro lens, whose density peaks at the centre: 177 px at 224²). The tangential density ``f · θ_d / sin θ``
    exceeds this near the rim of wide lenses (×1.33 at 90° for the GoPro); those rim pixels are then slightly
    upsampled from the faces — see ``coverage_report()["face_size_no_upsampling"]``.

    Args:
        intr: fisheye intrinsics.
        theta_max: largest ray angle (radians) actually seen; defaults to ``intr.theta_max`` (capped at π).

    Returns:
        Face size in pixels (``>= MIN_FACE_SIZE``).
    """
    tm = float(intr.theta_max) if theta_max is None else float(theta_max)
    radial, _ = _lens_density(intr, min(tm, math.pi))
    return max(MIN_FACE_SIZE, int(math.ceil(2.0 * radial - 1e-9)))


def _face_uv(rays: np.ndarray, face_idx: np.ndarray, face_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face pixel coordinates of rays on their assigned faces.

    Args:
        rays: ``[N, 3]`` float64 unit rays, fisheye camera frame.
        face_idx: ``[N]`` indices into :data:`FACE_NAMES`.
        face_size: S.

    Returns:
        ``(u, v, cos)``: ``[N]`` float64 face pixel coordinates (unclamped) and the cosine between each ray and
        its face normal.
    """
    r = _all_rotations()[face_idx]  # [N, 3, 3]
    d_face = np.einsum("nji,nj->ni", r, rays)  # R^T d
    z = d_face[:, 2]
    f, c = face_size / 2.0, (face_size - 1) / 2.0
    return f * d_face[:, 0] / z + c, f * d_face[:, 1] / z + c, z / np.linalg.norm(rays, axis=-1)


# ---------------------------------------------------------------------------------------------------------------
# The remapper
# ---------------------------------------------------------------------------------------------------------------
def _as_fill(fill: float | Sequence[float], n_channels: int) -> tuple[float, ...]:
    if np.isscalar(fill):
        return (float(fill),) * n_channels  # type: ignore[arg-type]
    vals = tuple(float(v) for v in fill)  # type: ignore[union-attr]
    if len(vals) == 1:
        return vals * n_channels
    if len(vals) != n_channels:
        raise CameraError(f"fill has {len(vals)} values but the faces have {n_channels} channels")
    return vals


def _channel_chunks(n_channels: int) -> list[tuple[int, int]]:
    """Split channels into cv2.remap calls of 4, 3 or 1 channels: OpenCV 5.0 remaps 1/3/4-channel float32 with
    exact float weights but 2-channel images through a 1/32-px fixed-point path."""
    out, c0 = [], 0
    while c0 < n_channels:
        left = n_channels - c0
        step = _CV_MAX_CHANNELS if left >= _CV_MAX_CHANNELS else (3 if left == 3 else 1)
        out.append((c0, c0 + step))
        c0 += step
    return out


def _remap_channels(
    src: np.ndarray,  # [h, w, C]
    map_x: np.ndarray,  # [H, W] float32
    map_y: np.ndarray,  # [H, W] float32
    flag: int,
    fill: tuple[float, ...],  # [C]
) -> np.ndarray:
    """``cv2.remap`` of any number of channels (chunks of 4/3/1), constant border ``fill``. Returns ``[H, W, C]``.

    float64 sources are remapped in float32: OpenCV 5.0 quantises bilinear weights to 1/32 px for float64 (and for
    2-channel images) but uses exact float weights for 1/3/4-channel float32.
    """
    if src.dtype == np.float64:
        src = src.astype(np.float32)
    chunks = []
    for c0, c1 in _channel_chunks(src.shape[2]):
        part = np.ascontiguousarray(src[:, :, c0:c1])
        border = tuple(fill[c0:c1]) + (0.0,) * (_CV_MAX_CHANNELS - (c1 - c0))
        r = cv2.remap(part, map_x, map_y, flag, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
        chunks.append(r.reshape(r.shape[0], r.shape[1], -1))
    return chunks[0] if len(chunks) == 1 else np.concatenate(chunks, axis=2)


def _interp_flag(interpolation: str) -> int:
    if interpolation not in INTERPOLATIONS:
        raise CameraError(f"interpolation must be one of {tuple(INTERPOLATIONS)}, got {interpolation!r}")
    return INTERPOLATIONS[interpolation]


class CubemapFisheyeRemap:
    """Resample 90° pinhole cube faces into a Kannala–Brandt fisheye image. Build once per intrinsics.

    Construction unprojects every fisheye pixel (``umi_aug.camera.kb.unproject``), assigns each valid ray to the
    face of its dominant axis and precomputes one map into a face *atlas* (the needed faces side by side, each
    with a one-texel border), so :meth:`remap` is one ``cv2.remap`` (plus a tiny one that fills the borders).

    Seams: a ray near a face edge lands within half a texel of the edge, where bilinear sampling needs a texel
    beyond the face. ``seam="blend"`` (default) takes it from the neighbouring face (bilinear sample at that
    border texel's ray), so sampling is seamless; ``seam="clamp"`` clamps to the face's own edge texel (what a
    plain cubemap lookup does; first-order error within half a texel of every seam). Neither ever mixes in an
    unrelated face.

    Attributes:
        intr: the fisheye intrinsics (resolution ``H × W``).
        face_size: S, pixels per face side.
        seam: ``"blend"`` or ``"clamp"``.
        faces_needed: names of the faces some valid pixel samples (in :data:`FACE_NAMES` order) — render only
            these. GoPro at 224²: the five non-back faces.
        valid_mask: ``[H, W]`` bool, pixels whose ray is valid (inside the image circle, before KB fold-over).
        face_of_pixel: ``[H, W]`` int8 index into :data:`FACE_NAMES`, −1 where invalid.
        ray_cos: ``[H, W]`` float32 cosine between each pixel's ray and its face normal (0 where invalid).
        theta: ``[H, W]`` float32 angle of each pixel's ray from the optical axis, radians (0 where invalid).
    """

    def __init__(self, intr: FisheyeIntrinsics, face_size: int | None = None, seam: str = "blend") -> None:
        """Args:
        intr: fisheye intrinsics (``umi_aug.camera.intrinsics.FisheyeIntrinsics``).
        face_size: cube face size S in pixels; ``None`` → :func:`default_face_size` over the θ range seen.
        seam: ``"blend"`` (seamless, default) or ``"clamp"`` (see the class docstring).
        """
        if seam not in SEAM_MODES:
            raise CameraError(f"seam must be one of {SEAM_MODES}, got {seam!r}")
        self.intr = intr
        self.seam = seam
        h, w = int(intr.height), int(intr.width)
        if h <= 0 or w <= 0:
            raise CameraError(f"intrinsics have an empty image size {w}x{h}")
        vv, uu = np.mgrid[0:h, 0:w]
        uv = np.stack([uu, vv], axis=-1).astype(np.float64)
        rays, valid = unproject(uv, intr)
        rays = np.asarray(rays, dtype=np.float64).reshape(h, w, 3)
        valid = np.asarray(valid, dtype=bool).reshape(h, w) & np.all(np.isfinite(rays), axis=-1)
        if not valid.any():
            raise CameraError(f"no valid fisheye pixel for intrinsics {intr!r}")
        norms = np.linalg.norm(rays, axis=-1, keepdims=True)
        rays = rays / np.where(norms > 0, norms, 1.0)

        face = np.full((h, w), -1, dtype=np.int8)
        rv = rays[valid]
        fidx = _dominant_face(rv)
        face[valid] = fidx.astype(np.int8)
        theta = np.zeros((h, w), dtype=np.float64)
        theta[valid] = np.arccos(np.clip(rv[:, 2], -1.0, 1.0))
        self._theta_max_seen = float(theta[valid].max())

        self.face_size = _check_face_size(
            default_face_size(intr, self._theta_max_seen) if face_size is None else face_size
        )
        s = self.face_size
        self.faces_needed: tuple[str, ...] = tuple(n for i, n in enumerate(FACE_NAMES) if np.any(fidx == i))
        self.valid_mask: np.ndarray = valid
        self.face_of_pixel: np.ndarray = face
        self.theta: np.ndarray = theta.astype(np.float32)

        pad = ATLAS_PAD_PX
        pitch = s + 2 * pad
        self._pitch = pitch
        self._slot_of_face = np.full(len(FACE_NAMES), -1, dtype=np.int64)
        for k, n in enumerate(self.faces_needed):
            self._slot_of_face[FACE_NAMES.index(n)] = k
        self._atlas_shape = (pitch, len(self.faces_needed) * pitch)

        u, v, cos = _face_uv(rv, fidx, s)
        lo, hi = (-0.5, s - 0.5) if seam == "blend" else (0.0, s - 1.0)  # blend reads the border texels
        x0 = self._slot_of_face[fidx] * pitch + pad
        self._map_x = self._full_map(valid, np.clip(u, lo, hi) + x0)
        self._map_y = self._full_map(valid, np.clip(v, lo, hi) + pad)
        # nearest: round once here, inside the face's own texels
        self._map_x_nearest = self._full_map(valid, np.rint(np.clip(u, 0.0, s - 1.0)) + x0)
        self._map_y_nearest = self._full_map(valid, np.rint(np.clip(v, 0.0, s - 1.0)) + pad)
        if seam == "blend":
            self._ring_dst, self._ring_map_x, self._ring_map_y = self._border_sources()
        ray_cos = np.zeros((h, w), dtype=np.float64)
        ray_cos[valid] = cos
        self.ray_cos: np.ndarray = ray_cos.astype(np.float32)
        self._secant: np.ndarray | None = None  # built on first remap_depth
        self._read_boxes: dict[str, tuple[int, int, int, int]] | None = None  # built on first face_read_boxes
        logger.debug(
            "cubemap remap %dx%d: face_size=%d faces=%s seam=%s valid=%.3f theta_max=%.1f deg",
            w, h, s, self.faces_needed, seam, valid.mean(), math.degrees(self._theta_max_seen),
        )

    @staticmethod
    def _full_map(valid: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``[H, W]`` float32 map: ``values`` at valid pixels, :data:`INVALID_MAP_COORD` elsewhere."""
        m = np.full(valid.shape, INVALID_MAP_COORD, dtype=np.float64)
        m[valid] = values
        return m.astype(np.float32)

    def _border_sources(self) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
        """Where each atlas border texel is sampled from (``seam="blend"``).

        Returns:
            ``((rows, cols), map_x, map_y)``: int64 ``[N]`` atlas positions of the border texels of every needed
            face and float32 ``[1, N]`` atlas coordinates of their sources — the bilinear sample of the
            neighbouring face at the border texel's ray (clamped to that face's own texels), or the face's own
            nearest edge texel when that neighbour is not rendered.
        """
        s, pad, pitch = self.face_size, ATLAS_PAD_PX, self._pitch
        f, c = s / 2.0, (s - 1) / 2.0
        full = np.arange(-1, s + 1)
        inner = np.arange(0, s)
        ii = np.concatenate([np.full(s + 2, -1), np.full(s + 2, s), inner, inner])
        jj = np.concatenate([full, full, np.full(s, -1), np.full(s, s)])
        d_face = np.stack([(jj - c) / f, (ii - c) / f, np.ones(ii.shape)], axis=-1)
        rows, cols, mx, my = [], [], [], []
        for k, name in enumerate(self.faces_needed):
            d = d_face @ face_rotation(name).T
            nb = _dominant_face(d)
            nb_slot = self._slot_of_face[nb]
            u, v, _ = _face_uv(d, nb, s)
            rendered = nb_slot >= 0
            own_x = np.clip(jj, 0, s - 1) + k * pitch + pad
            own_y = np.clip(ii, 0, s - 1) + pad
            mx.append(np.where(rendered, np.clip(u, 0.0, s - 1.0) + nb_slot * pitch + pad, own_x))
            my.append(np.where(rendered, np.clip(v, 0.0, s - 1.0) + pad, own_y))
            rows.append(ii + pad)
            cols.append(jj + pad + k * pitch)
        return (
            (np.concatenate(rows), np.concatenate(cols)),
            np.concatenate(mx).astype(np.float32)[None],
            np.concatenate(my).astype(np.float32)[None],
        )

    # -- which texels matter ---------------------------------------------------------------------------------
    def face_read_boxes(self) -> dict[str, tuple[int, int, int, int]]:
        """Per needed face, the texels :meth:`remap` and :meth:`remap_depth` can read, as an inclusive box
        ``(col_min, col_max, row_min, row_max)`` in face pixels (row 0 at the top, OpenCV face axes); built once.

        A texel outside its face's box never reaches the fisheye image, with either interpolation: a renderer may
        leave out whatever projects only outside it (``umi_aug.sim.fisheye_renderer``: geometry culled per face).
        Counted: the bilinear footprint of every valid pixel's map coordinate (linear and nearest maps) and, with
        ``seam="blend"``, of the neighbour sample behind every border texel such a footprint touches (cv2 rounds a
        map coordinate to 1/32 texel before it takes the floor: both roundings are counted).
        """
        if self._read_boxes is None:
            h, w = self._atlas_shape
            read = np.zeros((h, w), dtype=bool)

            def touch(map_x: np.ndarray, map_y: np.ndarray) -> None:
                # cv2 rounds a coordinate to 1/32 texel, then reads floor and floor + 1: count either rounding
                tol = 1.0 / 32.0
                mx, my = np.asarray(map_x, dtype=np.float64), np.asarray(map_y, dtype=np.float64)
                for x0 in (np.floor(mx - tol), np.floor(mx + tol)):
                    for y0 in (np.floor(my - tol), np.floor(my + tol)):
                        xi, yi = x0.astype(np.int64), y0.astype(np.int64)
                        for dy in (0, 1):
                            for dx in (0, 1):
                                read[np.clip(yi + dy, 0, h - 1), np.clip(xi + dx, 0, w - 1)] = True

            v = self.valid_mask
            touch(self._map_x[v], self._map_y[v])
            touch(self._map_x_nearest[v], self._map_y_nearest[v])
            if self.seam == "blend":  # border texels read above take their values from a neighbour's texels
                need = read[self._ring_dst]
                touch(self._ring_map_x[0][need], self._ring_map_y[0][need])
            s, pad, pitch = self.face_size, ATLAS_PAD_PX, self._pitch
            boxes: dict[str, tuple[int, int, int, int]] = {}
            for k, name in enumerate(self.faces_needed):
                texels = read[pad : pad + s, k * pitch + pad : k * pitch + pad + s]
                rows, cols = np.flatnonzero(texels.any(axis=1)), np.flatnonzero(texels.any(axis=0))
                boxes[name] = (int(cols[0]), int(cols[-1]), int(rows[0]), int(rows[-1]))
            self._read_boxes = boxes
        return dict(self._read_boxes)

    # -- face camera -----------------------------------------------------------------------------------------
    def face_intrinsics_matrix(self) -> np.ndarray:
        """``K_face`` ``[3, 3]`` of every cube face (pixels): ``f = S/2``, ``c = (S−1)/2``."""
        return face_intrinsics_matrix(self.face_size)

    @staticmethod
    def face_fovy_deg() -> float:
        """Vertical (and horizontal) field of view of each face, degrees: 90 (MuJoCo camera ``fovy``)."""
        return FACE_FOVY_DEG

    @property
    def output_shape(self) -> tuple[int, int]:
        """Fisheye image size ``(H, W)``."""
        return int(self.intr.height), int(self.intr.width)

    def coverage_report(self) -> dict[str, Any]:
        """Summary of what the cubemap covers.

        Returns:
            dict with ``face_size`` (px), ``faces_needed``, ``pixels_per_face`` {name: count of fisheye pixels},
            ``n_valid``, ``fraction_valid``, ``max_theta_deg`` (largest ray angle seen, degrees),
            ``lens_max_density_radial_px_per_rad`` / ``lens_max_density_tangential_px_per_rad`` (fisheye pixels per
            radian over the θ range seen), ``face_centre_density_px_per_rad`` (= S/2) and
            ``face_size_no_upsampling`` (the S at which no fisheye pixel is denser than the faces in any
            direction).
        """
        radial, tang = _lens_density(self.intr, self._theta_max_seen)
        counts = np.bincount(self.face_of_pixel[self.valid_mask].astype(np.int64), minlength=len(FACE_NAMES))
        return {
            "face_size": self.face_size,
            "faces_needed": list(self.faces_needed),
            "pixels_per_face": {n: int(counts[i]) for i, n in enumerate(FACE_NAMES)},
            "n_valid": int(self.valid_mask.sum()),
            "fraction_valid": float(self.valid_mask.mean()),
            "max_theta_deg": math.degrees(self._theta_max_seen),
            "lens_max_density_radial_px_per_rad": radial,
            "lens_max_density_tangential_px_per_rad": tang,
            "face_centre_density_px_per_rad": self.face_size / 2.0,
            "face_size_no_upsampling": int(math.ceil(2.0 * max(radial, tang) - 1e-9)),
        }

    # -- input checks ----------------------------------------------------------------------------------------
    def _check_faces(self, faces: Mapping[str, np.ndarray], depth: bool = False) -> tuple[list[np.ndarray], int]:
        """Validate the needed faces; return them (in ``faces_needed`` order, as 3-D arrays) and the channels."""
        if not isinstance(faces, Mapping):
            raise CameraError(f"faces must be a mapping face name -> image, got {type(faces).__name__}")
        s = self.face_size
        out: list[np.ndarray] = []
        ref: tuple[tuple[int, ...], np.dtype] | None = None
        for name in self.faces_needed:
            if name not in faces:
                raise CameraError(
                    f"cube face {name!r} is needed but missing (got {sorted(faces)}; needed {list(self.faces_needed)})"
                )
            a = np.asarray(faces[name])
            if depth:
                if a.ndim == 3 and a.shape[2] == 1:
                    a = a[..., 0]
                if a.shape != (s, s):
                    raise CameraError(f"depth face {name!r} has shape {a.shape}, expected ({s}, {s})")
                if not np.issubdtype(a.dtype, np.floating):
                    raise CameraError(f"depth face {name!r} has dtype {a.dtype}; expected float metres")
                a = a.astype(np.float32, copy=False)
                if np.isnan(a).any() or np.isneginf(a).any():
                    raise CameraError(f"depth face {name!r} contains NaN or -inf (use +inf for 'no hit')")
            else:
                if a.ndim not in (2, 3) or a.shape[:2] != (s, s) or (a.ndim == 3 and a.shape[2] < 1):
                    raise CameraError(f"cube face {name!r} has shape {a.shape}, expected ({s}, {s}, C) or ({s}, {s})")
                if a.dtype == np.float16:
                    a = a.astype(np.float32)
                if a.dtype.type not in _REMAP_DTYPES:
                    raise CameraError(
                        f"cube face {name!r} has dtype {a.dtype}; use uint8, uint16, int16, float32 or float64"
                    )
            a3 = a if a.ndim == 3 else a[..., None]
            key = (a3.shape, a3.dtype)
            if ref is None:
                ref = key
            elif key != ref:
                raise CameraError(
                    f"cube face {name!r} has shape {a.shape} / dtype {a.dtype}, but {self.faces_needed[0]!r} has "
                    f"shape {ref[0]} / dtype {ref[1]}; all faces must match"
                )
            out.append(a3)
        assert ref is not None
        return out, ref[0][2]

    def _atlas(self, faces: list[np.ndarray]) -> np.ndarray:
        """Faces side by side, each inside a one-texel border: ``[S+2, n·(S+2), C]``.

        Borders are zero (``seam="clamp"``) or filled from the neighbouring faces (``seam="blend"``).
        """
        s, pad, pitch = self.face_size, ATLAS_PAD_PX, self._pitch
        dtype = np.float32 if faces[0].dtype == np.float64 else faces[0].dtype  # see _remap_atlas
        atlas = np.zeros(self._atlas_shape + (faces[0].shape[2],), dtype=dtype)
        for k, a in enumerate(faces):
            atlas[pad : pad + s, k * pitch + pad : k * pitch + pad + s] = a
        if self.seam == "blend":
            zeros = (0.0,) * atlas.shape[2]
            border = _remap_channels(atlas, self._ring_map_x, self._ring_map_y, cv2.INTER_LINEAR, zeros)
            atlas[self._ring_dst] = border[0]
        return atlas

    def _remap_atlas(self, atlas: np.ndarray, fill: tuple[float, ...], flag: int, dtype: np.dtype) -> np.ndarray:
        nearest = flag == cv2.INTER_NEAREST
        mx = self._map_x_nearest if nearest else self._map_x
        my = self._map_y_nearest if nearest else self._map_y
        return _remap_channels(atlas, mx, my, flag, fill).astype(dtype, copy=False)

    # -- remap -----------------------------------------------------------------------------------------------
    def remap(
        self,
        faces: Mapping[str, np.ndarray],  # name -> [S, S, C] (or [S, S]) uint8 / float
        fill: float | Sequence[float] = 0,
        interpolation: str = "linear",
    ) -> np.ndarray:
        """Resample cube-face images into the fisheye image (fast path: one ``cv2.remap`` over a face atlas).

        Args:
            faces: ``{name: [S, S, C]}`` images for at least :attr:`faces_needed` (others are ignored), all the
                same shape and dtype (uint8, uint16, int16, float32 or float64). ``[S, S]`` is accepted too.
            fill: value for invalid fisheye pixels (outside the image circle), scalar or one per channel.
            interpolation: ``"linear"`` (bilinear; across face edges as set by ``seam``) or ``"nearest"`` (the
                nearest texel of the pixel's own face).

        Returns:
            ``[H, W, C]`` (``[H, W]`` for 2-D faces), the faces' dtype (uint8 rounds; float64 is resampled in
            float32, see ``_remap_channels``).
        """
        flag = _interp_flag(interpolation)
        arrs, c = self._check_faces(faces)
        out = self._remap_atlas(self._atlas(arrs), _as_fill(fill, c), flag, arrs[0].dtype)
        return out[..., 0] if np.asarray(faces[self.faces_needed[0]]).ndim == 2 else out

    def remap_depth(
        self,
        faces_z_depth: Mapping[str, np.ndarray],  # name -> [S, S] float, z-depth along the face normal (m)
        interpolation: str = "linear",
    ) -> np.ndarray:
        """Resample cube-face z-depth into fisheye ``ray_depth`` (distance along each fisheye pixel's ray).

        Each face texel's z-depth is first converted to the distance along that texel's own ray (divided by the
        cosine between the texel ray and the face normal, ``sqrt(1 + x² + y²)`` in normalised face coordinates);
        the ray distances are then resampled like :meth:`remap`. Ray distance is continuous across face seams
        (z-depth has a kink there), so seam blending stays accurate. ``"nearest"`` never mixes depths across
        occlusion edges; ``"linear"`` is smoother on surfaces.

        "No hit" texels (``+inf``) are handled by weight: a fisheye pixel whose bilinear weight on hit texels is
        at least :data:`DEPTH_MIN_HIT_WEIGHT` gets the weighted mean over its hit texels, otherwise ``+inf``.

        Args:
            faces_z_depth: ``{name: [S, S]}`` (or ``[S, S, 1]``) z-depth in metres along each face's normal, for at
                least :attr:`faces_needed`; ``+inf`` = no hit. NaN or ``-inf`` raise.
            interpolation: ``"linear"`` or ``"nearest"``.

        Returns:
            ``ray_depth`` ``[H, W]`` float32 metres (``+inf`` = no hit); invalid fisheye pixels (outside the image
            circle) hold ``0``.
        """
        flag = _interp_flag(interpolation)
        arrs, _ = self._check_faces(faces_z_depth, depth=True)
        sec = self._face_texel_secant()
        stacked = []
        for a in arrs:
            hit = np.isfinite(a)
            stacked.append(np.concatenate([np.where(hit, a * sec, 0.0), hit.astype(np.float32)], axis=2))
        both = self._remap_atlas(self._atlas(stacked), (0.0, 0.0), flag, np.dtype(np.float32))
        dist, weight = both[..., 0], both[..., 1]
        ok = self.valid_mask & (weight >= DEPTH_MIN_HIT_WEIGHT)
        ray_depth = np.zeros(self.output_shape, dtype=np.float32)
        ray_depth[ok] = dist[ok] / weight[ok]
        ray_depth[self.valid_mask & ~ok] = np.inf
        return ray_depth

    def _face_texel_secant(self) -> np.ndarray:
        """``[S, S, 1]`` float32: 1 / cos(texel ray, face normal), identical for every face."""
        if self._secant is None:
            s = self.face_size
            q = (np.arange(s, dtype=np.float64) - (s - 1) / 2.0) / (s / 2.0)
            self._secant = np.sqrt(1.0 + q[None, :] ** 2 + q[:, None] ** 2).astype(np.float32)[..., None]
        return self._secant
