"""The analytic room used by the demo: exact ray depths against hand-computed intersections."""

from __future__ import annotations

import numpy as np

from umi_aug.demo.room import AnalyticRoom


def test_axis_rays_hit_expected_faces_at_expected_depth():
    room = AnalyticRoom(half_extent_xy=(1.0, 0.5), height=2.0)
    o = np.array([0.2, 0.1, 0.5])
    dirs = np.array([[0, 0, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0]], float)
    depth, pts, face = room.intersect(np.broadcast_to(o, dirs.shape), dirs)
    np.testing.assert_allclose(depth, [0.5, 1.5, 1.2, 0.8, 0.6, 0.4])
    assert face.tolist() == [0, 1, 2, 3, 4, 5]


def test_random_rays_land_on_the_box_surface(rng):
    room = AnalyticRoom()
    o = np.array([0.05, -0.1, 0.4])
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb, depth = room.render_rays(np.broadcast_to(o, d.shape), d)
    p = o + depth[:, None] * d
    hx, hy = room.half_extent_xy
    on_surface = np.isclose(np.abs(p[:, 0]), hx) | np.isclose(np.abs(p[:, 1]), hy) | np.isclose(p[:, 2], 0) | np.isclose(p[:, 2], room.height)
    assert on_surface.all()
    assert np.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1).all()
    assert room.contains(o) and not room.contains(np.array([5.0, 0, 0.5]))
