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


def test_geoms_in_view_never_drops_a_sphere_that_reaches_the_box():
    """geoms_in_view against brute force: points sampled in each bounding sphere (surface and inside); a sphere
    with any point in the box's frustum between the clip planes is kept. Spheres behind the camera, beside the
    box or past the far plane are dropped (the test is not vacuous); bound 0 (planes) is always kept. Random
    poses, rotations near π included."""
    from types import SimpleNamespace

    from umi_aug.sim.raster import geoms_in_view

    rng = np.random.default_rng(11)
    near, far = 0.01, 3.0
    n_dropped = 0
    for trial in range(12):
        T = np.eye(4)
        if trial < 3:  # rotations near π about a random axis
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            ang = math.pi - 1e-6 * trial
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            T[:3, :3] = np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K
        else:
            T[:3, :3] = random_rotation(rng)
        T[:3, 3] = rng.uniform(-1, 1, 3)
        x0, x1 = np.sort(rng.uniform(-1.2, 1.2, 2))
        y0, y1 = np.sort(rng.uniform(-1.2, 1.2, 2))
        n = 300
        centres_view = rng.uniform(-2.0, 2.0, (n, 3)) * np.array([1.0, 1.0, 2.0])
        radius = rng.uniform(0.005, 0.6, n)
        radius[:5] = 0.0  # planes
        centres_view[5] = [0.0, 0.0, -0.5]  # straight behind
        radius[5] = 0.3
        centres_view[6] = [0.0, 0.0, far + 0.5]  # past the far plane
        radius[6] = 0.2
        model = SimpleNamespace(geom_rbound=radius)
        data = SimpleNamespace(geom_xpos=centres_view @ T[:3, :3].T + T[:3, 3])
        keep = geoms_in_view(model, data, T, (x0, x1, y0, y1), near, far)
        assert keep.dtype == bool and keep.shape == (n,)
        assert keep[:5].all() and not keep[5] and not keep[6]
        u = rng.normal(size=(n, 4000, 3))
        u /= np.linalg.norm(u, axis=-1, keepdims=True)
        scale = np.concatenate([np.ones(2000), rng.random(2000) ** (1 / 3)])  # on the sphere and inside it
        pts = centres_view[:, None, :] + radius[:, None, None] * scale[None, :, None] * u
        z = pts[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px, py = pts[..., 0] / z, pts[..., 1] / z
        seen = ((z >= near) & (z <= far) & (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)).any(axis=1)
        assert not (seen & ~keep).any(), np.flatnonzero(seen & ~keep)
        n_dropped += int((~keep).sum())
    assert n_dropped > 12 * 100  # most random spheres lie outside a random box's frustum


@pytest.mark.parametrize("size", [84, 224])
def test_culled_render_is_the_unculled_render(gl, model0, size):
    """Per-face geom culling changes no output: rgb, ray depth and segmentation equal the render with every geom in
    every face (the reference), at random poses through the tabletop scene (the gripper in view, the table,
    distractors behind and beside the camera); at those poses some face leaves geoms out."""
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer, RasterOptions
    from umi_aug.sim.raster import geoms_in_view
    from umi_aug.sim.tabletop_state import TabletopState

    intr = gopro_intrinsics_2_7k().umi_policy(size)
    st = TabletopState(model0)
    rng = np.random.default_rng(5)
    opts = RasterOptions(near=0.005, far=10.0)
    n_left_out = 0
    groups = model0.geom_group.copy()
    with FisheyeRenderer(model0, intr, options=opts) as fast, \
            FisheyeRenderer(model0, intr, options=opts, cull_geoms=False) as ref:
        assert fast.cull_geoms and not ref.cull_geoms
        for _ in range(6):
            T = np.eye(4)
            T[:3, :3] = random_rotation(rng)
            T[:3, 3] = rng.uniform([-0.3, -0.3, 0.05], [0.3, 0.3, 0.5])
            st.set(T, float(rng.uniform(0.0, 0.08)))
            a = fast.render(T, st.data, segmentation=True)
            b = ref.render(T, st.data, segmentation=True)
            np.testing.assert_array_equal(a.rgb, b.rgb)
            np.testing.assert_array_equal(a.ray_depth, b.ray_depth)
            np.testing.assert_array_equal(a.depth_valid, b.depth_valid)
            np.testing.assert_array_equal(a.geom_id, b.geom_id)
            for n, Tf in fast.face_poses(T).items():
                n_left_out += int((~geoms_in_view(model0, st.data, Tf, fast.face_boxes[n], fast.near,
                                                  fast.far)).sum())
    np.testing.assert_array_equal(model0.geom_group, groups)  # restored after every face
    assert n_left_out > 0


def test_update_scene_rejects_a_geom_mask_of_the_wrong_length(gl, model0):
    from umi_aug.errors import SimError
    from umi_aug.sim.raster import PinholeRasterizer
    from umi_aug.sim.tabletop_state import TabletopState

    st = TabletopState(model0)
    with PinholeRasterizer(model0, 16) as r, pytest.raises(SimError, match="geom_mask must be"):
        r.update_scene(st.data, geom_mask=np.ones(model0.ngeom + 1, dtype=bool))
