"""Collision spheres of the UMI gripper in the camera (= TCP-axes) frame, OpenCV axes: x right, y down,
z forward; metres.

The default set approximates the UMI gripper as built in the project's tabletop sim (``umi_aug.sim.scene``
``GripperSpec``) and in UMI's hardware: fin-ray fingers from z ≈ 0.07 m to the tips at z ≈ 0.226 m, centred at
UMI's ``cam_to_center_height`` (y = 0.086 m), inner faces at x = ±width/2, ≈ 34 mm deep at the base tapering to
the tip; carriages on the rail at z ≈ 0.012–0.07 m; the rail + housing below the camera (y ≈ 0.10–0.12 m,
x ±0.1 m); the GoPro body (≈ 71 × 55 × 34 mm) behind the optical centre, and its mount. Spheres over-cover each
part (they are the collision geometry, not a visual model).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from umi_aug.errors import GeometryError

__all__ = ["CollisionSpheres", "umi_gripper_spheres", "umi_camera_body_spheres"]

#: Finger spheres (z along the finger, radius): base → tip.
_FINGER_Z_R: tuple[tuple[float, float], ...] = (
    (0.088, 0.018), (0.122, 0.016), (0.156, 0.014), (0.190, 0.013), (0.214, 0.012))
_FINGER_Y: float = 0.086  #: UMI cam_to_center_height (fingers' mid-height), m
_CARRIAGE = ((0.020, 0.090, 0.040), 0.030)  #: (x offset beyond width/2, y, z), radius
_BODY: tuple[tuple[tuple[float, float, float], float], ...] = (
    # rail + housing below the camera
    ((-0.070, 0.108, 0.015), 0.032), ((-0.023, 0.108, 0.015), 0.032),
    ((0.023, 0.108, 0.015), 0.032), ((0.070, 0.108, 0.015), 0.032),
    # GoPro body behind the lens, and its mount
    ((-0.018, 0.0, -0.015), 0.030), ((0.018, 0.0, -0.015), 0.030),
    ((0.0, 0.035, -0.030), 0.025),
)


@dataclass(frozen=True)
class CollisionSpheres:
    """Spheres rigidly attached to the camera.

    Attributes:
        centers_cam: np.ndarray,  # [S, 3] camera frame (OpenCV axes), metres
        radii: np.ndarray,  # [S] metres > 0
        names: tuple[str, ...],  # [S] for reports
    """

    centers_cam: np.ndarray
    radii: np.ndarray
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        c = np.asarray(self.centers_cam, dtype=np.float64)
        r = np.asarray(self.radii, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 1 or r.shape != (c.shape[0],):
            raise GeometryError(f"CollisionSpheres: centers_cam {c.shape} / radii {r.shape}; expected [S, 3] / [S]")
        if not (np.isfinite(c).all() and np.isfinite(r).all()) or np.any(r <= 0):
            raise GeometryError("CollisionSpheres: centres must be finite and radii finite and > 0")
        if len(self.names) != c.shape[0]:
            raise GeometryError(f"CollisionSpheres: {len(self.names)} names for {c.shape[0]} spheres")
        object.__setattr__(self, "centers_cam", c)
        object.__setattr__(self, "radii", r)

    def __len__(self) -> int:
        return self.radii.shape[0]

    def world(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Sphere centres in the world for poses ``[..., 4, 4]`` → ``[..., S, 3]``."""
        return np.swapaxes(T_world_cam[..., :3, :3] @ self.centers_cam.T, -1, -2) + T_world_cam[..., None, :3, 3]

    @staticmethod
    def concat(sets: Sequence["CollisionSpheres"]) -> "CollisionSpheres":
        return CollisionSpheres(np.concatenate([s.centers_cam for s in sets]), np.concatenate([s.radii for s in sets]),
                                tuple(n for s in sets for n in s.names))


def umi_gripper_spheres(widths: float | Sequence[float] = 0.08, include_body: bool = True) -> CollisionSpheres:
    """Default UMI gripper sphere set with the fingers at the given opening width(s).

    Args:
        widths: finger opening(s) between the inner faces, metres (UMI: 0 = closed, ~0.09 max). Several widths
            (e.g. the min and max over the pre-contact segment) place a finger column at each, covering the
            fingers wherever they are while the width changes.
        include_body: add the camera body, mount, rail and housing spheres.
    Returns:
        CollisionSpheres (camera frame).
    """
    ws = np.atleast_1d(np.asarray(widths, dtype=np.float64))
    if ws.ndim != 1 or ws.size < 1 or not np.isfinite(ws).all() or np.any(ws < 0) or np.any(ws > 0.3):
        raise GeometryError(f"umi_gripper_spheres: widths {ws.tolist()} must be finite, in [0, 0.3] m")
    centers, radii, names = [], [], []
    for w in np.unique(ws):
        for side, sgn in (("left", -1.0), ("right", 1.0)):
            for i, (z, r) in enumerate(_FINGER_Z_R):
                centers.append((sgn * (0.5 * w + r), _FINGER_Y, z))
                radii.append(r)
                names.append(f"finger_{side}_{i}@{w * 1000:.0f}mm")
            (dx, y, z), r = _CARRIAGE
            centers.append((sgn * (0.5 * w + dx), y, z))
            radii.append(r)
            names.append(f"carriage_{side}@{w * 1000:.0f}mm")
    if include_body:
        for i, (c, r) in enumerate(_BODY):
            centers.append(c)
            radii.append(r)
            names.append(("rail", "rail", "rail", "rail", "camera", "camera", "mount")[i] + f"_{i}")
    return CollisionSpheres(np.array(centers), np.array(radii), tuple(names))


def umi_camera_body_spheres() -> CollisionSpheres:
    """The GoPro body behind the lens and its mount (camera frame, metres; the ``camera_*``/``mount_*`` spheres of
    :func:`umi_gripper_spheres`, same names). Unlike the fingers and the rail, nothing of the scene comes inside
    these while a demonstrator holds the gripper."""
    idx = range(4, len(_BODY))
    return CollisionSpheres(np.array([_BODY[i][0] for i in idx]), np.array([_BODY[i][1] for i in idx]),
                            tuple(("camera", "camera", "mount")[i - 4] + f"_{i}" for i in idx))
