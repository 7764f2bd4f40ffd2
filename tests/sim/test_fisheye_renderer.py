"""True-fisheye rendering: markers land on their KB-projected pixels (incl. 95° off axis); ray depth is exact."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.sim.conftest import random_rotation
from umi_aug.camera import kb


def _direction(theta_deg: float, phi_deg: float) -> np.ndarray:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


#: (theta, phi) of the markers in the camera frame: centre, face seams (45°), wide angles, and past 90°.
MARKERS = [(0, 0), (30, 20), (45, 0), (45, 90), (60, 200), (75, 250), (88, 300), (95, 45), (95, 135), (96, 225)]


@pytest.fixture(scope="module")
def marker_render(gopro224):
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer, RasterOptions
    from umi_aug.sim.gl import import_mujoco, select_gl_backend

    select_gl_backend()
    mujoco = import_mujoco()
    rng = np.random.default_rng(7)
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = [0.1, -0.2, 0.3]
    dist = 0.6
    ang_radius = math.radians(2.0)
    geoms, dirs = [], []
    for i, (th, ph) in enumerate(MARKERS):
        d = _direction(th, ph)
        dirs.append(d)
        p = T[:3, 3] + T[:3, :3] @ (dist * d)
        geoms.append(f'<geom name="m{i}" type="sphere" size="{dist * math.sin(ang_radius)}" '
                     f'pos="{p[0]} {p[1]} {p[2]}" rgba="{(i % 3 == 0) * 1.0} {(i % 3 == 1) * 1.0} '
                     f'{(i % 3 == 2) * 1.0} 1" material="em"/>')
    xml = ('<mujoco><asset><material name="em" emission="1" specular="0"/></asset>'
           '<visual><headlight active="0"/></visual><worldbody>' + "".join(geoms) + "</worldbody></mujoco>")
    model = mujoco.MjModel.from_xml_string(xml)
    with FisheyeRenderer(model, gopro224, options=RasterOptions(near=0.01, far=10.0)) as r:
        frame = r.render(T, segmentation=True)
        faces = r.faces_needed
    return frame, np.array(dirs), dist, ang_radius, faces


def test_marker_pixels_match_kb_projection(marker_render, gopro224, gl):
    frame, dirs, _, _, faces = marker_render
    assert faces == ("front", "right", "left", "down", "up")  # never "back" for the GoPro lens
    uv, valid = kb.project(dirs, gopro224)
    assert valid.all()
    for i, ((th, ph), p) in enumerate(zip(MARKERS, uv)):
        assert 0 <= p[0] <= 223 and 0 <= p[1] <= 223, (th, ph, p)
        vs, us = np.nonzero(frame.geom_id == i)
        assert len(us) >= 5, f"marker {i} at theta={th} deg not visible"
        centroid = np.array([us.mean(), vs.mean()])
        err = np.linalg.norm(centroid - p)
        assert err < 1.0, f"marker {i} (theta={th} deg, phi={ph} deg): centroid {centroid} vs KB {p}: {err:.2f} px"
        # the RGB image shows the marker's colour at its projected pixel
        col = frame.rgb[int(round(p[1])), int(round(p[0]))]
        assert col[i % 3] > 200 and np.delete(col, i % 3).max() < 60, (i, col)


def test_marker_95_degrees_off_axis(marker_render, gopro224, gl):
    frame, dirs, _, _, _ = marker_render
    for i, (th, _) in enumerate(MARKERS):
        if th < 95:
            continue
        assert dirs[i][2] < 0  # behind the image plane: no pinhole could see it
        uv, valid = kb.project(dirs[i], gopro224)
        vs, us = np.nonzero(frame.geom_id == i)
        assert valid and np.hypot(us.mean() - uv[0], vs.mean() - uv[1]) < 1.0


def test_marker_depth(marker_render, gopro224, gl):
    frame, dirs, dist, ang_radius, _ = marker_render
    uv, _ = kb.project(dirs, gopro224)
    r = dist * math.sin(ang_radius)
    for i, p in enumerate(uv):
        d = frame.ray_depth[int(round(p[1])), int(round(p[0]))]
        # nearest surface point of the sphere along (almost) its centre ray
        assert abs(d - (dist - r)) < 2e-3, (i, d, dist - r)


def _box_room_xml(half: tuple[float, float, float]) -> str:
    a, b, c = half
    t = 0.01
    walls = [((a + t, 0, 0), (t, b + 2 * t, c + 2 * t)), ((-a - t, 0, 0), (t, b + 2 * t, c + 2 * t)),
             ((0, b + t, 0), (a + 2 * t, t, c + 2 * t)), ((0, -b - t, 0), (a + 2 * t, t, c + 2 * t)),
             ((0, 0, c + t), (a + 2 * t, b + 2 * t, t)), ((0, 0, -c - t), (a + 2 * t, b + 2 * t, t))]
    g = "".join(f'<geom type="box" pos="{p[0]} {p[1]} {p[2]}" size="{s[0]} {s[1]} {s[2]}" rgba=".6 .6 .6 1"/>'
                for p, s in walls)
    return f"<mujoco><worldbody><light pos='0 0 0.5'/>{g}</worldbody></mujoco>"


def test_ray_depth_matches_box_room_geometry(gopro224, gl):
    """Camera inside an axis-aligned box room at a random pose: every valid pixel's ray depth equals the analytic
    ray–plane distance (rays past 90° included), so depth is distance along the ray, not z."""
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer, RasterOptions
    from umi_aug.sim.gl import import_mujoco

    mujoco = import_mujoco()
    half = (0.9, 0.7, 0.5)
    model = mujoco.MjModel.from_xml_string(_box_room_xml(half))
    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = [0.2, -0.1, 0.05]
    with FisheyeRenderer(model, gopro224, options=RasterOptions(near=0.01, far=10.0)) as r:
        fr = r.render(T)
    vv, uu = np.mgrid[0:224, 0:224]
    rays, valid = kb.unproject(np.stack([uu, vv], -1).astype(float), gopro224)
    d = rays @ T[:3, :3].T
    p = T[:3, 3]
    with np.errstate(divide="ignore"):
        ts = np.stack([np.where(d[..., k] > 0, (half[k] - p[k]) / d[..., k], (-half[k] - p[k]) / d[..., k])
                       for k in range(3)], -1)
    ts_sorted = np.sort(ts, axis=-1)
    expected = ts_sorted[..., 0]
    away_from_edges = ts_sorted[..., 1] > 1.03 * ts_sorted[..., 0]
    sel = valid & fr.depth_valid & away_from_edges
    assert fr.depth_valid[valid].mean() > 0.99
    theta = np.degrees(np.arccos(np.clip(rays[..., 2], -1, 1)))
    assert (sel & (theta > 90)).sum() > 500  # the ring past 90° is checked too
    rel = np.abs(fr.ray_depth[sel] - expected[sel]) / expected[sel]
    assert rel.max() < 2e-3, rel.max()
    assert np.median(rel) < 2e-4
    # outside the image circle: zero depth, invalid, black
    assert not fr.depth_valid[~valid].any() and (fr.ray_depth[~valid] == 0).all() and (fr.rgb[~valid] == 0).all()


def test_timing_report_has_per_face_breakdown(gopro224, gl, model0):
    from umi_aug.sim.bench import benchmark_fisheye_render
    from umi_aug.sim.tabletop_state import TabletopState

    st = TabletopState(model0)
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.0, 0.2, 0.45]
    st.set(T, 0.08)
    rep = benchmark_fisheye_render(model0, st.data, gopro224, np.stack([T] * 4), warmup=1)
    assert rep["resolution"] == "224x224" and rep["face_size"] == 177
    for face in ("front", "right", "left", "down", "up"):
        assert rep["breakdown_ms"][f"render/{face}"] > 0
    assert "render/back" not in rep["breakdown_ms"]
    assert rep["breakdown_ms"]["remap/rgb"] > 0 and rep["ms_per_frame"] > 0
