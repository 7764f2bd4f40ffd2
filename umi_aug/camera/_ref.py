"""Slow references of the camera stage (gsplat ``_torch_impl`` style: private, for tests only).

* :func:`_remap_reference` mirrors :meth:`umi_aug.camera.cubemap.CubemapFisheyeRemap.remap` (cube faces →
  fisheye image) in float64 without the precomputed maps or the face atlas.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from umi_aug.camera.cubemap import FACE_NAMES, CubemapFisheyeRemap, _as_fill, _interp_flag, face_rotation
from umi_aug.camera.kb import unproject


def _remap_reference(
    remap: CubemapFisheyeRemap,
    faces: Mapping[str, np.ndarray],  # name -> [S, S, C] (or [S, S])
    fill: float | Sequence[float] = 0,
    interpolation: str = "linear",
) -> np.ndarray:
    """Slow, obviously-correct reference of :meth:`CubemapFisheyeRemap.remap` (tests compare the two).

    Recomputes everything in float64 without the precomputed maps or the atlas: unproject each fisheye pixel,
    pick the face whose normal is nearest the ray, project onto that face and sample in pure numpy. Bilinear
    taps that fall outside the face (within half a texel of an edge) take, with ``seam="blend"``, the
    bilinear sample of the face the tap's own ray points at (clamped to that face's texels; the face's own
    edge texel if that face is not rendered), and with ``seam="clamp"`` the face's own edge texel.

    Returns:
        ``[H, W, C]`` float64 (``[H, W]`` for 2-D faces); invalid pixels hold ``fill``.
    """
    _interp_flag(interpolation)
    arrs, c = remap._check_faces(faces)
    img = dict(zip(remap.faces_needed, (a.astype(np.float64) for a in arrs)))
    fillv = np.array(_as_fill(fill, c), dtype=np.float64)
    h, w = remap.output_shape
    s = remap.face_size
    f, cc = s / 2.0, (s - 1) / 2.0
    normals = np.stack([face_rotation(m)[:, 2] for m in FACE_NAMES])  # [6, 3]

    def bilinear_inside(name: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear sample of face ``name`` at ``(x, y)`` clamped to its own texels ``[0, S-1]``."""
        x = np.clip(x, 0.0, s - 1.0)
        y = np.clip(y, 0.0, s - 1.0)
        x0 = np.minimum(np.floor(x).astype(int), s - 2)
        y0 = np.minimum(np.floor(y).astype(int), s - 2)
        ax, ay = (x - x0)[:, None], (y - y0)[:, None]
        a = img[name]
        return (a[y0, x0] * (1 - ax) * (1 - ay) + a[y0, x0 + 1] * ax * (1 - ay)
                + a[y0 + 1, x0] * (1 - ax) * ay + a[y0 + 1, x0 + 1] * ax * ay)

    def texel(name: str, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Value of texel (row i, col j) of face ``name``, with i, j in [-1, S] (outside: see docstring)."""
        own = img[name][np.clip(i, 0, s - 1), np.clip(j, 0, s - 1)]
        outside = (i < 0) | (i >= s) | (j < 0) | (j >= s)
        if remap.seam == "clamp" or not outside.any():
            return own
        d = np.stack([(j[outside] - cc) / f, (i[outside] - cc) / f, np.ones(outside.sum())], -1)
        d = d @ face_rotation(name).T  # ray of the virtual texel, fisheye frame
        nb = np.argmax(d @ normals.T, axis=-1)
        for m in np.unique(nb):
            other = FACE_NAMES[m]
            if other not in img:
                continue
            sel = np.flatnonzero(outside)[nb == m]
            dm = d[nb == m] @ face_rotation(other)  # R^T d
            own[sel] = bilinear_inside(other, f * dm[:, 0] / dm[:, 2] + cc, f * dm[:, 1] / dm[:, 2] + cc)
        return own

    out = np.empty((h, w, c), dtype=np.float64)
    out[:] = fillv
    vv, uu = np.mgrid[0:h, 0:w]
    rays, valid = unproject(np.stack([uu, vv], -1).astype(np.float64), remap.intr)
    rays = np.asarray(rays, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    best = np.argmax(rays @ normals.T, axis=-1)
    for i, name in enumerate(FACE_NAMES):
        sel = valid & (best == i)
        if not sel.any():
            continue
        d = rays[sel] @ face_rotation(name)  # R^T d, row vectors
        assert np.all(d[:, 2] > 0)
        x = f * d[:, 0] / d[:, 2] + cc
        y = f * d[:, 1] / d[:, 2] + cc
        if interpolation == "nearest":
            xi = np.rint(np.clip(x, 0.0, s - 1.0)).astype(int)
            yi = np.rint(np.clip(y, 0.0, s - 1.0)).astype(int)
            out[sel] = img[name][yi, xi]
            continue
        lo, hi = (-0.5, s - 0.5) if remap.seam == "blend" else (0.0, s - 1.0)
        x, y = np.clip(x, lo, hi), np.clip(y, lo, hi)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        ax, ay = (x - x0)[:, None], (y - y0)[:, None]
        out[sel] = (texel(name, y0, x0) * (1 - ax) * (1 - ay) + texel(name, y0, x0 + 1) * ax * (1 - ay)
                    + texel(name, y0 + 1, x0) * (1 - ax) * ay + texel(name, y0 + 1, x0 + 1) * ax * ay)
    return out[..., 0] if np.asarray(faces[remap.faces_needed[0]]).ndim == 2 else out
