"""Square pinhole rasteriser for any MuJoCo model, posed freely with OpenCV camera axes.

One :class:`PinholeRasterizer` owns an offscreen GL context, an ``MjrContext`` and an ``MjvScene``. Per frame the
model geometry is pushed once (:meth:`PinholeRasterizer.update_scene`); then any number of views are rendered
from the same geometry by overwriting the scene's GL camera (``mjvGLCamera``: position, forward, up, frustum),
which allows arbitrary roll (MuJoCo's free camera has none) and needs no camera in the model. Colour and depth
come from ONE render pass (``mjr_readPixels`` reads both buffers). This mirrors what ``mujoco.Renderer`` does
internally (same GL context, same reverse-Z depth linearisation) but avoids a second pass for depth.

Image convention of every output: row 0 is the top of the image, ``(u, v)`` = (column, row), pixel centres at
integers, OpenCV camera axes (x right, y down, z forward); a ``size × size`` view with vertical/horizontal field
of view ``fov`` has ``f = (size/2)/tan(fov/2)``, ``c = (size−1)/2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from umi_aug.errors import SimError
from umi_aug.sim.camera_frames import mujoco_camera_vectors
from umi_aug.sim.gl import create_gl_context, import_mujoco

__all__ = ["RasterOptions", "PinholeRasterizer", "geoms_in_view"]


@dataclass(frozen=True)
class RasterOptions:
    """Render settings (defaults chosen for speed on CPU/llvmpipe; see environment.md "MuJoCo rendering on CPU").

    Attributes:
        shadows: shadow mapping (by far the largest cost on CPU; off by default).
        reflections: planar reflections of reflective materials (a second scene pass; off by default).
        skybox: draw the model's skybox (if any).
        offsamples: multisample anti-aliasing samples of the offscreen buffer (0: none, exact depth edges).
        near, far: clip planes in metres; ``None`` = MuJoCo's ``model.vis.map.znear/zfar × model.stat.extent``.
        max_geom: capacity of the abstract scene.
    """

    shadows: bool = False
    reflections: bool = False
    skybox: bool = True
    offsamples: int = 0
    near: float | None = None
    far: float | None = None
    max_geom: int = 10000


def geoms_in_view(model, data, T_world_view: np.ndarray, box: tuple[float, float, float, float], near: float,
                  far: float) -> np.ndarray:
    """Which geoms may cover a pixel of a pinhole view's image-plane box: their bounding spheres
    (``data.geom_xpos``, ``model.geom_rbound``) are not wholly outside the box's frustum between the clip planes.

    Conservative: a geom left out has no point whose projection falls inside the box in front of the near plane
    and before the far plane, so nothing it would draw lands there. Geoms without a bound (``geom_rbound`` 0:
    planes) are always in.

    Args:
        model, data: ``mujoco.MjModel`` / ``mujoco.MjData`` (kinematics up to date).
        T_world_view: np.ndarray,  # [4, 4] view pose, OpenCV axes (x right, y down, z forward), metres
        box: ``(x_min, x_max, y_min, y_max)``, the image-plane region (normalised coordinates ``x/z``, ``y/z``) whose
            pixels matter, pixel edges included.
        near, far: clip planes, metres along the view's z.
    Returns:
        np.ndarray,  # [ngeom] bool, True = may be seen
    """
    T = np.asarray(T_world_view, dtype=np.float64)
    centres = (np.asarray(data.geom_xpos, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]  # view coordinates
    x, y, z = centres[:, 0], centres[:, 1], centres[:, 2]
    radius = np.asarray(model.geom_rbound, dtype=np.float64)
    slack = radius * (1.0 + 1e-6) + 1e-9  # round-off never culls a sphere that touches the frustum
    x0, x1, y0, y1 = (float(b) for b in box)
    outside = ((x - x1 * z) / math.hypot(1.0, x1) > slack) | ((x0 * z - x) / math.hypot(1.0, x0) > slack)
    outside |= ((y - y1 * z) / math.hypot(1.0, y1) > slack) | ((y0 * z - y) / math.hypot(1.0, y0) > slack)
    outside |= (float(near) - z > slack) | (z - float(far) > slack)
    return ~outside | (radius <= 0.0)


class PinholeRasterizer:
    """Renders square pinhole views (RGB uint8 + z-depth float32, optional geom segmentation) of a MuJoCo model.

    Args:
        model: ``mujoco.MjModel`` (not modified, except that ``vis.global_.offwidth/offheight`` and
            ``vis.quality.offsamples`` are set while the GL buffers are created and restored afterwards).
        size: view size ``S`` in pixels (views are ``S × S``).
        options: :class:`RasterOptions`.
    """

    def __init__(self, model, size: int, options: RasterOptions | None = None) -> None:
        self._mj = mujoco = import_mujoco()
        self.options = opts = options or RasterOptions()
        self.size = S = int(size)
        if S < 2:
            raise SimError(f"PinholeRasterizer: size must be >= 2 pixels, got {size!r}")
        self.model = model
        extent = float(model.stat.extent)
        self.near = float(opts.near) if opts.near is not None else float(model.vis.map.znear) * extent
        self.far = float(opts.far) if opts.far is not None else float(model.vis.map.zfar) * extent
        if not (0.0 < self.near < self.far and math.isfinite(self.far)):
            raise SimError(f"PinholeRasterizer: need 0 < near < far, got near={self.near}, far={self.far}")
        self._ctx = None
        self._con = None
        self._ctx = create_gl_context(S, S)
        saved = (model.vis.global_.offwidth, model.vis.global_.offheight, model.vis.quality.offsamples)
        try:
            model.vis.global_.offwidth = max(S, saved[0])
            model.vis.global_.offheight = max(S, saved[1])
            model.vis.quality.offsamples = int(opts.offsamples)
            self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        finally:
            model.vis.global_.offwidth, model.vis.global_.offheight, model.vis.quality.offsamples = saved
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=int(opts.max_geom))
        self._option = mujoco.MjvOption()
        hidden = [g for g in range(len(self._option.geomgroup)) if not self._option.geomgroup[g]]
        self._hidden_group: int | None = hidden[-1] if hidden else None  # where update_scene parks left-out geoms
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        self._rect = mujoco.MjrRect(0, 0, S, S)
        flags = self._scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(opts.shadows)
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = bool(opts.reflections)
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = bool(opts.skybox)
        self._rgb = np.empty((S, S, 3), dtype=np.uint8)
        self._depth = np.empty((S, S), dtype=np.float32)
        # reverse-Z linearisation constants (float32, as glFrustum), see mujoco.Renderer.render
        zf, zn = np.float32(self.far), np.float32(self.near)
        c = -(zf + zn) / (zf - zn)
        d = -(np.float32(2) * zf * zn) / (zf - zn)
        self._c_coef = float(np.float32(-0.5) * c - np.float32(0.5))
        self._d_coef = float(np.float32(-0.5) * d)

    # ------------------------------------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        if self._ctx is not None:
            try:
                self._ctx.make_current()
            except Exception:  # noqa: BLE001 - best effort at teardown
                pass
        if self._con is not None:
            self._con.free()
            self._con = None
        if self._ctx is not None:
            try:
                self._ctx.free()
            except Exception:  # noqa: BLE001 - EGL may already be torn down at interpreter exit
                pass
            self._ctx = None

    def __enter__(self) -> "PinholeRasterizer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - GC path
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass

    # -------------------------------------------------------------------------------------------- per frame
    def update_scene(self, data, T_world_cam: np.ndarray | None = None, geom_mask: np.ndarray | None = None) -> None:
        """Push the geometry of ``data`` (after ``mj_forward``/``mj_kinematics``) into the abstract scene.

        Args:
            data: ``mujoco.MjData`` of :attr:`model`.
            T_world_cam: np.ndarray | None,  # [4, 4] OpenCV axes; places MuJoCo's headlight (if the model has
                one) at this camera, looking along its optical axis, for every view rendered from this update.
            geom_mask: np.ndarray | None,  # [ngeom] bool; geoms marked False are left out of the scene (e.g. the
                ones :func:`geoms_in_view` finds outside the views to render). The model's ``geom_group`` of those
                geoms is set to a group the scene hides for the update and restored before returning (the
                default scene option hides groups 3–5; one that showed every group would leave them in).
        """
        mujoco = self._mj
        if geom_mask is not None:
            keep = np.asarray(geom_mask, dtype=bool)
            if keep.shape != (self.model.ngeom,):
                raise SimError(f"PinholeRasterizer.update_scene: geom_mask must be [{self.model.ngeom}] bool, got "
                               f"shape {keep.shape}")
            if self._hidden_group is not None and not keep.all():
                groups = self.model.geom_group
                saved = groups.copy()
                groups[~keep] = self._hidden_group
                try:
                    self.update_scene(data, T_world_cam)
                finally:
                    groups[:] = saved
                return
        cam = self._cam
        if T_world_cam is not None:
            T = np.asarray(T_world_cam, dtype=np.float64)
            fwd, _ = mujoco_camera_vectors(T[:3, :3])
            dist = 1.0
            cam.lookat[:] = T[:3, 3] + dist * fwd
            cam.distance = dist
            cam.azimuth = math.degrees(math.atan2(fwd[1], fwd[0]))
            cam.elevation = math.degrees(math.asin(float(np.clip(fwd[2], -1.0, 1.0))))
        else:
            mujoco.mjv_defaultFreeCamera(self.model, cam)
        mujoco.mjv_updateScene(
            self.model, data, self._option, None, cam, mujoco.mjtCatBit.mjCAT_ALL.value, self._scene
        )

    def _set_view(self, T_world_view: np.ndarray, fov_deg: float) -> None:
        R = np.asarray(T_world_view, dtype=np.float64)[:3, :3]
        pos = np.asarray(T_world_view, dtype=np.float64)[:3, 3]
        fwd, up = mujoco_camera_vectors(R)
        half = self.near * math.tan(math.radians(float(fov_deg)) / 2.0)
        for i in range(2):  # mono rendering averages the two (stereo) GL cameras: set both
            gc = self._scene.camera[i]
            gc.pos[:] = pos
            gc.forward[:] = fwd
            gc.up[:] = up
            gc.frustum_center = 0.0
            gc.frustum_width = 0.0  # 0: half-width follows the (square) viewport aspect
            gc.frustum_bottom = -half
            gc.frustum_top = half
            gc.frustum_near = self.near
            gc.frustum_far = self.far
            gc.orthographic = 0

    def render(
        self, T_world_view: np.ndarray, fov_deg: float = 90.0, rgb: bool = True, depth: bool = True
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Render one square view of the geometry pushed by the last :meth:`update_scene`.

        Args:
            T_world_view: np.ndarray,  # [4, 4] view pose, OpenCV axes (x right, y down, z forward), metres
            fov_deg: full field of view (vertical = horizontal), degrees, < 180.
            rgb, depth: which buffers to read.
        Returns:
            rgb: np.ndarray | None,      # [S, S, 3] uint8 RGB (a new array)
            z_depth: np.ndarray | None,  # [S, S] float32 metres along the view's optical axis (z, NOT ray length);
                                         # ``far`` where nothing was hit
        """
        if self._con is None:
            raise SimError("PinholeRasterizer.render called after close()")
        if not (0.0 < fov_deg < 180.0):
            raise SimError(f"PinholeRasterizer.render: fov_deg must be in (0, 180), got {fov_deg!r}")
        mujoco = self._mj
        self._ctx.make_current()
        self._set_view(T_world_view, fov_deg)
        mujoco.mjr_render(self._rect, self._scene, self._con)
        mujoco.mjr_readPixels(self._rgb if rgb else None, self._depth if depth else None, self._rect, self._con)
        out_rgb = np.ascontiguousarray(self._rgb[::-1]) if rgb else None
        out_depth = None
        if depth:
            raw = self._depth[::-1].astype(np.float64)
            out_depth = (self._d_coef / (raw + self._c_coef)).astype(np.float32)
            np.minimum(out_depth, np.float32(self.far), out=out_depth)
        return out_rgb, out_depth

    def render_segmentation(self, T_world_view: np.ndarray, fov_deg: float = 90.0) -> np.ndarray:
        """Render geom ids of one view (flat-coloured segmentation pass, no lighting or textures).

        Returns:
            geom_id: np.ndarray,  # [S, S] int32 MuJoCo geom id per pixel, −1 for background / non-geom objects
        """
        if self._con is None:
            raise SimError("PinholeRasterizer.render_segmentation called after close()")
        mujoco = self._mj
        self._ctx.make_current()
        flags = self._scene.flags
        saved = flags.copy()
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            self._set_view(T_world_view, fov_deg)
            mujoco.mjr_render(self._rect, self._scene, self._con)
            mujoco.mjr_readPixels(self._rgb, None, self._rect, self._con)
        finally:
            np.copyto(flags, saved)
        img = self._rgb[::-1].astype(np.int64)
        segid = img[..., 0] + img[..., 1] * 256 + img[..., 2] * 65536  # 0 = background, else scene-geom index + 1
        n = self._scene.ngeom
        lut = np.full(n + 1, -1, dtype=np.int32)
        geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
        for g in self._scene.geoms[:n]:
            if g.segid >= 0 and g.objtype == geom_type and g.segid + 1 <= n:
                lut[g.segid + 1] = g.objid
        segid = np.where(segid <= n, segid, 0)
        return lut[segid]
