"""An analytic, ray-cast tabletop room: the built-in scene the demo renders until the MuJoCo scene and the
3DGS renderer exist. Exact colour and ray depth for any ray, so it doubles as ground truth in tests.

World frame: metres, z up; the table top is the plane z = 0 and fills the room's floor. The room is an
axis-aligned box; the camera must be inside it. Textures are flat (no lighting) but rich enough to see
the fisheye geometry: a checkerboard table with a plate and a mug-coloured disk, striped walls with a
different hue each, and a gridded ceiling.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Checker size on the table and grid spacing on walls/ceiling (metres).
TABLE_CHECKER_M = 0.05
WALL_STRIPE_M = 0.08


@dataclass(frozen=True)
class FlatDisk:
    """A coloured disk painted on the table (z = 0): centre (x, y) [m], radius [m], RGB in [0, 1]."""

    center_xy: tuple[float, float]
    radius: float
    rgb: tuple[float, float, float]


@dataclass(frozen=True)
class AnalyticRoom:
    """Box room ``[x_min, x_max] × [y_min, y_max] × [0, height]`` (metres, world z up).

    Faces: 0 = table (z = 0), 1 = ceiling, 2/3 = walls at x_min/x_max, 4/5 = walls at y_min/y_max.
    """

    half_extent_xy: tuple[float, float] = (0.9, 0.7)
    height: float = 1.2
    disks: tuple[FlatDisk, ...] = field(
        default_factory=lambda: (
            FlatDisk((0.0, 0.0), 0.11, (0.95, 0.95, 0.92)),  # plate
            FlatDisk((0.0, 0.0), 0.07, (0.80, 0.82, 0.86)),  # plate well
            FlatDisk((0.18, -0.12), 0.045, (0.85, 0.20, 0.15)),  # mug (seen from above)
            FlatDisk((-0.22, 0.16), 0.05, (0.15, 0.45, 0.85)),  # distractor
        )
    )

    def intersect(
        self,
        origins: np.ndarray,  # [..., 3] world, inside the room
        dirs: np.ndarray,  # [..., 3] world, unit
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exit intersection of rays with the room box.

        Returns:
            ray_depth: distance along the ray to the hit [m], ``[...]``.
            points: hit points in world [m], ``[..., 3]``.
            face: index of the face hit (see class docstring), ``[...]`` int.
        """
        lo = np.array([-self.half_extent_xy[0], -self.half_extent_xy[1], 0.0])
        hi = np.array([self.half_extent_xy[0], self.half_extent_xy[1], self.height])
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = np.where(d > 0, (hi - o) / np.where(d > 0, d, 1.0), np.inf)
            t_lo = np.where(d < 0, (lo - o) / np.where(d < 0, d, -1.0), np.inf)
        t_axes = np.minimum(t_hi, t_lo)  # [..., 3]
        axis = np.argmin(t_axes, axis=-1)
        t = np.take_along_axis(t_axes, axis[..., None], axis=-1)[..., 0]
        t = np.maximum(t, 0.0)
        points = o + t[..., None] * d
        positive = np.take_along_axis(d, axis[..., None], axis=-1)[..., 0] > 0
        # axis 2 (z): negative direction hits the table (0), positive the ceiling (1);
        # axis 0 (x): walls 2/3; axis 1 (y): walls 4/5.
        face = np.where(axis == 2, np.where(positive, 1, 0), np.where(axis == 0, 2, 4) + positive)
        return t, points, face

    def shade(self, points: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Colour [0, 1] RGB ``[..., 3]`` of world points on the given faces (flat textures)."""
        x, y, z = points[..., 0], points[..., 1], points[..., 2]
        rgb = np.zeros(points.shape, dtype=np.float64)

        # Table: light wood with a checkerboard and painted disks.
        checker = (np.floor(x / TABLE_CHECKER_M) + np.floor(y / TABLE_CHECKER_M)) % 2
        table = np.stack([0.72 + 0.10 * checker, 0.58 + 0.08 * checker, 0.40 + 0.05 * checker], axis=-1)
        for disk in self.disks:
            inside = (x - disk.center_xy[0]) ** 2 + (y - disk.center_xy[1]) ** 2 <= disk.radius**2
            table = np.where(inside[..., None], np.asarray(disk.rgb), table)
        # Ceiling: grey with a dark grid.
        gx = np.abs((x / WALL_STRIPE_M) - np.round(x / WALL_STRIPE_M)) < 0.08
        gy = np.abs((y / WALL_STRIPE_M) - np.round(y / WALL_STRIPE_M)) < 0.08
        ceiling = np.where((gx | gy)[..., None], 0.35, 0.85) * np.ones(3)
        # Walls: a hue per wall, vertical stripes along the wall, horizontal bands in height.
        along = np.where(face >= 4, x, y)
        stripes = (np.floor(along / WALL_STRIPE_M) % 2)[..., None]
        bands = (np.floor(z / (2 * WALL_STRIPE_M)) % 3)[..., None] / 3.0
        hues = np.array(
            [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.30, 0.55, 0.35], [0.55, 0.35, 0.55], [0.35, 0.45, 0.70], [0.70, 0.55, 0.30]]
        )
        wall = hues[face] * (0.7 + 0.3 * stripes) + 0.15 * bands

        rgb = np.where((face == 0)[..., None], table, rgb)
        rgb = np.where((face == 1)[..., None], ceiling, rgb)
        rgb = np.where((face >= 2)[..., None], wall, rgb)
        return np.clip(rgb, 0.0, 1.0)

    def render_rays(
        self,
        origins: np.ndarray,  # [..., 3] world
        dirs: np.ndarray,  # [..., 3] world, unit
    ) -> tuple[np.ndarray, np.ndarray]:
        """Colour ``[..., 3]`` in [0, 1] and ray depth ``[...]`` [m] of each ray."""
        depth, points, face = self.intersect(origins, dirs)
        return self.shade(points, face), depth

    def contains(self, point_world: np.ndarray, margin: float = 0.0) -> bool:
        """True if a world point lies inside the room (at least ``margin`` metres from every face)."""
        p = np.asarray(point_world, dtype=np.float64)
        return bool(
            np.all(np.abs(p[:2]) <= np.asarray(self.half_extent_xy) - margin)
            and margin <= p[2] <= self.height - margin
        )
