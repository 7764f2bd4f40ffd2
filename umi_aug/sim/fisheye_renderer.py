"""True Kannala–Brandt fisheye rendering of any MuJoCo model: pinhole cube faces + one precomputed remap.

MuJoCo (fixed-function OpenGL) only renders pinhole views, and no pinhole reaches the UMI GoPro's rays past 90°
(up to ~104°). :class:`FisheyeRenderer` renders the 90° cube faces the lens actually sees
(``CubemapFisheyeRemap.faces_needed``: five for the GoPro, never ``back``) from the camera centre and resamples
them into the fisheye image with :class:`umi_aug.camera.cubemap.CubemapFisheyeRemap` (maps built once).

Frames: the camera pose ``T_world_cam`` is 4×4 with OpenCV axes (x right, y down, z forward), metres. Face ``i``
is rendered at ``T_world_cam @ R_cam_face(i)``; the OpenCV→MuJoCo axis flip happens in
:func:`umi_aug.sim.camera_frames.opencv_to_mujoco_camera` only. Depth is returned as ``ray_depth``: metres along
each pixel's ray, not z.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from umi_aug.camera.cubemap import CubemapFisheyeRemap, face_rotation
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SimError
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.raster import PinholeRasterizer, RasterOptions, geoms_in_view

__all__ = ["FisheyeFrame", "FisheyeRenderer", "RasterOptions"]

log = logging.getLogger(__name__)

#: Segmentation value of pixels that see no geom (or lie outside the image circle).
NO_GEOM: int = -1


@dataclass
class FisheyeFrame:
    """One rendered fisheye frame (arrays are ``None`` when not requested).

    Attributes:
        rgb: ``[H, W, 3]`` uint8 RGB; black outside the image circle.
        ray_depth: ``[H, W]`` float32 metres along each pixel's ray; 0 where ``depth_valid`` is False.
        depth_valid: ``[H, W]`` bool: inside the image circle and some geometry was hit (before the far plane).
        geom_id: ``[H, W]`` int32 MuJoCo geom id seen by each pixel (nearest-texel), −1 for none / outside.
    """

    rgb: np.ndarray | None = None
    ray_depth: np.ndarray | None = None
    depth_valid: np.ndarray | None = None
    geom_id: np.ndarray | None = None


class FisheyeRenderer:
    """Render RGB / ray depth / geom segmentation through a KB fisheye lens at any ``T_world_cam``.

    Args:
        model: ``mujoco.MjModel``.
        intr: :class:`FisheyeIntrinsics` of the output image.
        face_size: cube-face size in pixels; ``None`` → matched to the lens's centre pixel density
            (``umi_aug.camera.cubemap.default_face_size``; 177 px for the GoPro at 224²).
        options: :class:`RasterOptions` (shadows off, no MSAA by default; near/far planes).
        depth_interpolation: ``"linear"`` (smooth surfaces, mixes depths across occlusion edges) or ``"nearest"``.
        cull_geoms: render each face with only the geoms whose bounding spheres reach the texels of that face the
            fisheye image reads (``CubemapFisheyeRemap.face_read_boxes``, :func:`umi_aug.sim.raster.geoms_in_view`):
            the same fisheye image, bit for bit, for less work — on CPU (llvmpipe) a face costs mostly its
            triangles, and a side face reads only the band nearest the front (the robot's arm behind the camera is
            left out). ``False`` renders every geom in every face: the reference it is tested against.

    The renderer keeps its own ``MjData`` (``model`` at ``qpos0`` after ``mj_forward``) for calls without ``data``.
    Timings of every call accumulate in :meth:`timing_report` (per face: render+readback; remap per output).
    """

    def __init__(
        self,
        model,
        intr: FisheyeIntrinsics,
        face_size: int | None = None,
        options: RasterOptions | None = None,
        depth_interpolation: str = "linear",
        cull_geoms: bool = True,
    ) -> None:
        self._mj = mujoco = import_mujoco()
        if not isinstance(intr, FisheyeIntrinsics):
            raise SimError(f"FisheyeRenderer: intr must be FisheyeIntrinsics, got {type(intr).__name__}")
        self.model = model
        self.intr = intr
        self.cubemap = CubemapFisheyeRemap(intr, face_size)
        self.face_size: int = self.cubemap.face_size
        self.faces_needed: tuple[str, ...] = self.cubemap.faces_needed
        self.valid_mask: np.ndarray = self.cubemap.valid_mask
        self.depth_interpolation = depth_interpolation
        self._R_cam_face = {n: face_rotation(n) for n in self.faces_needed}
        self._raster = PinholeRasterizer(model, self.face_size, options)
        self._fov = float(self.cubemap.face_fovy_deg())
        self.cull_geoms = bool(cull_geoms)
        # per face, the image-plane box (x/z, y/z; face pixel j covers [(j - 0.5 - c)/f, (j + 0.5 - c)/f]) of the
        # texels the fisheye image reads: what geoms_in_view tests each geom against
        f, c = self.face_size / 2.0, (self.face_size - 1) / 2.0
        self.face_boxes: dict[str, tuple[float, float, float, float]] = {
            n: ((c0 - 0.5 - c) / f, (c1 + 0.5 - c) / f, (r0 - 0.5 - c) / f, (r1 + 0.5 - c) / f)
            for n, (c0, c1, r0, r1) in self.cubemap.face_read_boxes().items()}
        self._own_data = mujoco.MjData(model)
        mujoco.mj_forward(model, self._own_data)
        self._t: dict[str, float] = defaultdict(float)
        self._n_frames = 0

    # ----------------------------------------------------------------------------------------- properties
    @property
    def near(self) -> float:
        """Near clip plane, metres (geometry closer to the camera centre than this along a face axis is cut)."""
        return self._raster.near

    @property
    def far(self) -> float:
        """Far clip plane, metres."""
        return self._raster.far

    def face_poses(self, T_world_cam: np.ndarray) -> dict[str, np.ndarray]:
        """World poses of the needed cube-face cameras (OpenCV axes): ``T_world_cam @ [R_cam_face | 0]``.

        Args:
            T_world_cam: np.ndarray,  # [4, 4]
        Returns:
            {face name: np.ndarray [4, 4]}
        """
        T = _check_pose(T_world_cam)
        out = {}
        for n, R in self._R_cam_face.items():
            Tf = T.copy()
            Tf[:3, :3] = T[:3, :3] @ R
            out[n] = Tf
        return out

    # ------------------------------------------------------------------------------------------- render
    def render(
        self,
        T_world_cam: np.ndarray,
        data=None,
        *,
        rgb: bool = True,
        depth: bool = True,
        segmentation: bool = False,
    ) -> FisheyeFrame:
        """Render one fisheye frame.

        Args:
            T_world_cam: np.ndarray,  # [4, 4] camera pose, OpenCV axes, metres
            data: ``mujoco.MjData`` with up-to-date kinematics (``mj_forward``/``mj_kinematics`` done); ``None``
                uses the model's rest state.
            rgb, depth, segmentation: which outputs to produce (segmentation is a second, cheap flat pass).
        Returns:
            :class:`FisheyeFrame`.
        """
        mj_data = self._own_data if data is None else data
        faces = self.face_poses(T_world_cam)
        t0 = time.perf_counter()
        if not self.cull_geoms:
            self._raster.update_scene(mj_data, T_world_cam)
        self._t["update_scene"] += time.perf_counter() - t0
        rgb_faces: dict[str, np.ndarray] = {}
        z_faces: dict[str, np.ndarray] = {}
        seg_faces: dict[str, np.ndarray] = {}
        for n, Tf in faces.items():
            if self.cull_geoms:
                t0 = time.perf_counter()
                seen = geoms_in_view(self.model, mj_data, Tf, self.face_boxes[n], self.near, self.far)
                self._raster.update_scene(mj_data, T_world_cam, geom_mask=seen)
                self._t["update_scene"] += time.perf_counter() - t0
            ta = time.perf_counter()
            if rgb or depth:
                c, z = self._raster.render(Tf, self._fov, rgb=rgb, depth=depth)
                if rgb:
                    rgb_faces[n] = c
                if depth:
                    z_faces[n] = z
            tb = time.perf_counter()
            self._t[f"render/{n}"] += tb - ta
            if segmentation:
                seg_faces[n] = self._raster.render_segmentation(Tf, self._fov).astype(np.float32)
                self._t[f"segment/{n}"] += time.perf_counter() - tb
        out = FisheyeFrame()
        t2 = time.perf_counter()
        if rgb:
            out.rgb = self.cubemap.remap(rgb_faces, fill=0, interpolation="linear")
        t3 = time.perf_counter()
        self._t["remap/rgb"] += t3 - t2
        if depth:
            far = np.float32(self._raster.far * (1.0 - 1e-4))
            zf = {n: np.where(z >= far, np.float32(np.inf), z) for n, z in z_faces.items()}
            rd = self.cubemap.remap_depth(zf, interpolation=self.depth_interpolation)
            ok = self.valid_mask & np.isfinite(rd) & (rd > 0)
            out.ray_depth = np.where(ok, rd, np.float32(0.0)).astype(np.float32)
            out.depth_valid = ok
        t4 = time.perf_counter()
        self._t["remap/depth"] += t4 - t3
        if segmentation:
            seg = self.cubemap.remap(seg_faces, fill=float(NO_GEOM), interpolation="nearest")
            out.geom_id = np.rint(seg).astype(np.int32)
            self._t["remap/segmentation"] += time.perf_counter() - t4
        self._n_frames += 1
        return out

    # ------------------------------------------------------------------------------------------ timings
    def timing_report(self) -> dict[str, float]:
        """Mean milliseconds per rendered frame, per stage: ``update_scene``, ``render/<face>`` (render +
        readback of that face), ``segment/<face>``, ``remap/rgb``, ``remap/depth``, ``remap/segmentation``,
        and the sums ``render_total``, ``remap_total``, ``total``. Empty before the first frame."""
        n = max(self._n_frames, 1)
        if self._n_frames == 0:
            return {}
        rep = {k: 1000.0 * v / n for k, v in sorted(self._t.items())}
        rep["render_total"] = sum(v for k, v in rep.items() if k.startswith(("render/", "segment/", "update")))
        rep["remap_total"] = sum(v for k, v in rep.items() if k.startswith("remap/"))
        rep["total"] = rep["render_total"] + rep["remap_total"]
        rep["frames"] = float(self._n_frames)
        return rep

    def reset_timings(self) -> None:
        """Clear the accumulated timings."""
        self._t.clear()
        self._n_frames = 0

    # ---------------------------------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Free the GL context (idempotent)."""
        self._raster.close()

    def __enter__(self) -> "FisheyeRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SimError(f"T_world_cam must be a finite [4, 4] pose, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise SimError("T_world_cam rotation block is not a rotation matrix (orthonormal, det +1)")
    return T
