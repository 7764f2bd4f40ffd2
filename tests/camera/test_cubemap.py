"""Cubemap → KB fisheye resampling: face geometry, analytic environment, fast vs reference, depth, errors."""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from umi_aug.camera._ref import _remap_reference
from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
from umi_aug.camera.cubemap import (
    FACE_NAMES,
    CubemapFisheyeRemap,
    default_face_size,
    face_intrinsics_matrix,
    face_pixel_rays,
    face_rotation,
)
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.kb import project, unproject
from umi_aug.errors import CameraError


@pytest.fixture(scope="module")
def gopro224() -> FisheyeIntrinsics:
    return gopro_intrinsics_2_7k().umi_policy(224)


@pytest.fixture(scope="module")
def remap224(gopro224) -> CubemapFisheyeRemap:
    return CubemapFisheyeRemap(gopro224)  # seam="blend"


@pytest.fixture(scope="module")
def remap224_clamp(gopro224) -> CubemapFisheyeRemap:
    return CubemapFisheyeRemap(gopro224, seam="clamp")


# ---------------------------------------------------------------------------------------------- helpers
def _render_faces(fn, remapper: CubemapFisheyeRemap, names=None) -> dict[str, np.ndarray]:
    """Render faces the way a renderer would: face camera rotation R_cam_face, pinhole K_face.

    ``fn`` maps ``[..., 3]`` unit rays in the fisheye camera frame to ``[..., C]`` values.
    """
    s = remapper.face_size
    k_inv = np.linalg.inv(remapper.face_intrinsics_matrix())
    vv, uu = np.mgrid[0:s, 0:s].astype(np.float64)
    pix = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    out = {}
    for name in names or remapper.faces_needed:
        d = pix @ k_inv.T @ face_rotation(name).T  # ray_cam = R_cam_face @ K^-1 [u, v, 1]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        out[name] = fn(d)
    return out


def _smooth_env(rng: np.random.Generator, r_world_cam: np.ndarray):
    """Low-order spherical-harmonic-like colour: degree ≤ 2 polynomial in the WORLD ray direction, in [0, 1]."""
    a = rng.normal(size=(3, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = rng.normal(size=(3, 3, 3))
    b = 0.5 * (b + b.transpose(0, 2, 1))
    b /= np.linalg.norm(b, axis=(1, 2), ord=2)[:, None, None]

    def fn(d_cam: np.ndarray) -> np.ndarray:
        d = d_cam @ r_world_cam.T
        lin = d @ a.T  # [..., 3]
        quad = np.einsum("...i,cij,...j->...c", d, b, d)
        return (0.5 + 0.3 * lin + 0.15 * quad).astype(np.float32)

    return fn


def _texels_from_seam(rays: np.ndarray, face_size: int) -> np.ndarray:
    """Distance (face texels) from each ray's point on its dominant face to the nearest face edge."""
    a = np.abs(rays)
    m = a.max(axis=-1)
    tan_max = np.sort(a, axis=-1)[..., 1] / m  # largest in-face tangent
    return (1.0 - tan_max) * face_size / 2.0


def _unproject_grid(intr: FisheyeIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
    return unproject(np.stack([uu, vv], -1).astype(np.float64), intr)


# ---------------------------------------------------------------------------------------------- geometry
def test_face_rotations_are_opencv_cameras():
    normals = {"front": (0, 0, 1), "back": (0, 0, -1), "right": (1, 0, 0), "left": (-1, 0, 0),
               "down": (0, 1, 0), "up": (0, -1, 0)}
    for name in FACE_NAMES:
        r = face_rotation(name)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(r), 1.0)
        np.testing.assert_array_equal(r[:, 2], normals[name])
    np.testing.assert_array_equal(face_rotation("front"), np.eye(3))
    # side faces keep the fisheye's image-down (+y); down/up faces keep its image-right (+x)
    for name in ("front", "back", "right", "left"):
        np.testing.assert_array_equal(face_rotation(name)[:, 1], (0, 1, 0))
    for name in ("down", "up"):
        np.testing.assert_array_equal(face_rotation(name)[:, 0], (1, 0, 0))
    with pytest.raises(CameraError, match="sideways"):
        face_rotation("sideways")


def test_face_intrinsics_and_pixel_rays():
    s = 64
    k = face_intrinsics_matrix(s)
    np.testing.assert_allclose(k, [[32, 0, 31.5], [0, 32, 31.5], [0, 0, 1]])
    assert CubemapFisheyeRemap.face_fovy_deg() == 90.0
    # 90° field of view: the outer pixel EDGES (-0.5, S-0.5) are at ±45°
    assert np.isclose(math.degrees(math.atan((s - 0.5 - k[0, 2]) / k[0, 0])), 45.0)
    for name in FACE_NAMES:
        d = face_pixel_rays(name, s)
        assert d.shape == (s, s, 3)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
        d_face = d @ face_rotation(name)  # R^T d
        uv = d_face[..., :2] / d_face[..., 2:] * k[0, 0] + k[0, 2]
        vv, uu = np.mgrid[0:s, 0:s]
        np.testing.assert_allclose(uv[..., 0], uu, atol=1e-9)
        np.testing.assert_allclose(uv[..., 1], vv, atol=1e-9)


def test_coverage_gopro_224(remap224, gopro224):
    r = remap224
    assert r.faces_needed == ("front", "right", "left", "down", "up")  # back never needed (θmax ≈ 104° < 135°)
    rep = r.coverage_report()
    print("\n[cubemap] GoPro 224² coverage:", rep)
    assert rep["face_size"] == r.face_size == default_face_size(gopro224, math.radians(rep["max_theta_deg"]))
    assert 170 <= r.face_size <= 180  # ≈ 2f (f = 88 px)
    assert 0.87 < rep["fraction_valid"] < 0.89  # notes: 87.9 % of 224² pixels inside the image circle
    assert 103 < rep["max_theta_deg"] < 104.5
    assert rep["pixels_per_face"]["back"] == 0 and sum(rep["pixels_per_face"].values()) == rep["n_valid"]
    assert r.valid_mask.shape == (224, 224) and r.valid_mask.dtype == bool
    assert r.face_of_pixel.dtype == np.int8
    assert np.all((r.face_of_pixel >= 0) == r.valid_mask)
    assert r.valid_mask[112, 112] and not r.valid_mask[0, 0]  # corners black
    assert r.face_of_pixel[112, 112] == FACE_NAMES.index("front")
    assert r.face_of_pixel[112, 2] == FACE_NAMES.index("left")
    assert r.face_of_pixel[112, 221] == FACE_NAMES.index("right")
    assert r.face_of_pixel[2, 112] == FACE_NAMES.index("up") and r.face_of_pixel[221, 112] == FACE_NAMES.index("down")


def test_faces_needed_narrow_and_ultrawide():
    narrow = FisheyeIntrinsics.equidistant(224, 224, 150.0, theta_limit=math.radians(30))
    r = CubemapFisheyeRemap(narrow)
    assert r.faces_needed == ("front",)
    assert r.face_size == 300  # 2 f for an equidistant lens
    assert not r.valid_mask[0, 0] and r.valid_mask[112, 112]
    wide = FisheyeIntrinsics.equidistant(96, 96, 96 / (2 * math.radians(170)), theta_limit=math.radians(170))
    assert set(CubemapFisheyeRemap(wide, face_size=16).faces_needed) == set(FACE_NAMES)


# ---------------------------------------------------------------------------------------------- analytic env
@pytest.mark.parametrize("seam", ["blend", "clamp"])
def test_analytic_environment(rng, remap224, remap224_clamp, gopro224, seam):
    """Faces rendered from a smooth function of the world ray; remap ≈ the function at the fisheye rays."""
    r = remap224 if seam == "blend" else remap224_clamp
    r_world_cam = Rotation.random(random_state=rng).as_matrix()
    fn = _smooth_env(rng, r_world_cam)
    faces = _render_faces(fn, r)
    out = r.remap(faces, fill=-1.0)
    rays, valid = _unproject_grid(gopro224)
    np.testing.assert_array_equal(valid, r.valid_mask)
    truth = fn(rays)
    err = np.abs(out - truth)[valid]
    theta = np.degrees(np.arccos(np.clip(rays[..., 2], -1, 1)))
    far = valid & (theta > 90)
    interior = valid & (_texels_from_seam(rays, r.face_size) > 1.0)
    print(
        f"\n[cubemap] analytic env 224² (S={r.face_size}, seam={seam}): max |err| = {err.max():.2e} "
        f"(= {err.max() * 255:.3f}/255), mean = {err.mean():.2e}, max at θ>90° ({far.sum()} px) = "
        f"{np.abs(out - truth)[far].max():.2e}, max > 1 texel from a seam = {np.abs(out - truth)[interior].max():.2e}"
    )
    assert far.sum() > 1000  # the ring past 90° is exercised
    # clamp: first-order error within half a texel of a seam; blend: second order everywhere
    assert err.max() < (1e-4 if seam == "blend" else 1.0 / 255)
    assert np.abs(out - truth)[interior].max() < 1e-4
    assert np.all(out[~valid] == -1.0)
    # uint8 faces: within one grey level (+ rounding of the faces themselves)
    faces8 = {n: np.round(f * 255).astype(np.uint8) for n, f in faces.items()}
    out8 = r.remap(faces8)
    assert out8.dtype == np.uint8 and out8.shape == (224, 224, 3)
    assert np.abs(out8.astype(np.float64) - truth * 255)[valid].max() < 1.5
    assert np.all(out8[~valid] == 0)


def test_analytic_environment_bright_spot_lands_at_projection(rng, gopro224):
    """A narrow Gaussian blob at a known direction (past 90° too) lands where kb.project puts it."""
    r = CubemapFisheyeRemap(gopro224)
    vv, uu = np.mgrid[0:224, 0:224]
    checked = 0
    for theta_deg in (0.0, 40.0, 75.0, 97.0):
        t = math.radians(theta_deg)
        for _ in range(50):  # an azimuth whose 12-px window lies inside the image circle
            phi = rng.uniform(0, 2 * np.pi)
            d0 = np.array([math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)])
            uv0, ok = project(d0[None], gopro224)
            uv0, ok = uv0[0], bool(ok[0])
            win = np.hypot(uu - uv0[0], vv - uv0[1]) < 12
            if ok and r.valid_mask[win].all() and win.sum() > 400:
                break
        else:
            continue
        sigma = 0.05  # rad
        blob = lambda d: np.exp(-np.sum((d - d0) ** 2, -1) / (2 * sigma**2))[..., None]  # noqa: E731
        img = r.remap(_render_faces(blob, r))[..., 0].astype(np.float64) * win
        centroid = np.array([(img * uu).sum(), (img * vv).sum()]) / img.sum()
        # the lens squeezes the blob anisotropically, so its image centroid sits a fraction of a pixel from
        # project(d0); the blob evaluated directly at the fisheye rays has the same centroid
        rays, _ = _unproject_grid(gopro224)
        truth = blob(rays)[..., 0] * win
        centroid_truth = np.array([(truth * uu).sum(), (truth * vv).sum()]) / truth.sum()
        assert np.linalg.norm(centroid - centroid_truth) < 0.02, (theta_deg, centroid, centroid_truth)
        assert np.linalg.norm(centroid - uv0) < 1.0, (theta_deg, centroid, uv0)
        checked += 1
    assert checked >= 3


# ---------------------------------------------------------------------------------------------- fast vs ref
@pytest.mark.parametrize("seam", ["blend", "clamp"])
def test_fast_matches_reference(rng, remap224, remap224_clamp, seam):
    r = remap224 if seam == "blend" else remap224_clamp
    s = r.face_size
    faces = {n: rng.random((s, s, 3), dtype=np.float32) for n in FACE_NAMES}  # all six: extras are ignored
    fast = r.remap(faces, fill=(0.1, 0.2, 0.3))
    ref = _remap_reference(r, faces, fill=(0.1, 0.2, 0.3))
    assert fast.shape == ref.shape == (224, 224, 3) and fast.dtype == np.float32
    diff = np.abs(fast - ref).max()
    print(f"\n[cubemap] fast vs reference (seam={seam}, float32 random faces): max |diff| = {diff:.2e}")
    # OpenCV >= 4.11 / 5.x remaps float32 images with exact float weights; older builds quantise to 1/32 px
    tol = 1e-4 if tuple(int(x) for x in cv2.__version__.split(".")[:2]) >= (4, 11) else 0.05
    assert diff < tol
    inv = ~r.valid_mask
    np.testing.assert_array_equal(fast[inv], np.broadcast_to(np.float32([0.1, 0.2, 0.3]), fast[inv].shape))
    # nearest: identical samples
    fast_n = r.remap(faces, interpolation="nearest")
    ref_n = _remap_reference(r, faces, interpolation="nearest")
    np.testing.assert_array_equal(fast_n, ref_n.astype(np.float32))
    # uint8, 2-D faces
    f8 = {n: rng.integers(0, 256, (s, s), dtype=np.uint8) for n in r.faces_needed}
    o8 = r.remap(f8)
    assert o8.shape == (224, 224) and o8.dtype == np.uint8
    assert np.abs(o8.astype(np.float64) - _remap_reference(r, f8)).max() <= 1.0
    for c in (2, 6):  # 2-channel chunks and float64 would take cv2's 1/32-px path: remap() avoids both
        fc = {n: rng.random((s, s, c)) for n in r.faces_needed}
        oc = r.remap(fc)
        assert oc.shape == (224, 224, c) and oc.dtype == np.float64
        assert np.abs(oc - _remap_reference(r, fc)).max() < tol


@pytest.mark.parametrize("size,seam", [(84, "blend"), (84, "clamp"), (224, "blend"), (96, "blend")])
def test_face_read_boxes_hold_every_texel_remap_reads(rng, size, seam):
    """Texels outside each face's read box are never sampled: replacing them with other random values changes no
    output of remap (linear, nearest, uint8) or remap_depth — GoPro at 84² and 224² (rays past 90°) and an
    ultrawide 170° lens that needs all six faces. The side faces' boxes leave a part out (not a vacuous box)."""
    if size == 96:
        intr = FisheyeIntrinsics.equidistant(96, 96, 96 / (2 * math.radians(170)), theta_limit=math.radians(170))
        r = CubemapFisheyeRemap(intr, face_size=24, seam=seam)
    else:
        r = CubemapFisheyeRemap(gopro_intrinsics_2_7k().umi_policy(size), seam=seam)
    s = r.face_size
    boxes = r.face_read_boxes()
    assert tuple(boxes) == r.faces_needed
    inside = {}
    for n, (c0, c1, r0, r1) in boxes.items():
        assert 0 <= c0 <= c1 < s and 0 <= r0 <= r1 < s, (n, boxes[n])
        m = np.zeros((s, s), dtype=bool)
        m[r0 : r1 + 1, c0 : c1 + 1] = True
        inside[n] = m
    if size != 96:  # the GoPro: the front face whole; each side face read on its band nearest the front only
        assert boxes["front"] == (0, s - 1, 0, s - 1)
        for n in ("right", "left", "down", "up"):
            assert 0.4 < inside[n].mean() < 0.8, (n, boxes[n])
    faces = {n: rng.random((s, s, 3), dtype=np.float32) for n in r.faces_needed}
    other = {n: np.where(inside[n][..., None], faces[n], rng.random((s, s, 3), dtype=np.float32))
             for n in r.faces_needed}
    assert all((other[n] != faces[n]).any() for n in r.faces_needed if not inside[n].all())
    for interp in ("linear", "nearest"):
        np.testing.assert_array_equal(r.remap(faces, interpolation=interp), r.remap(other, interpolation=interp))
    f8 = {n: (255 * a).astype(np.uint8) for n, a in faces.items()}
    o8 = {n: (255 * a).astype(np.uint8) for n, a in other.items()}
    np.testing.assert_array_equal(r.remap(f8), r.remap(o8))
    z = {n: 0.2 + a[..., 0] for n, a in faces.items()}
    zo = {n: np.where(inside[n], z[n], np.inf).astype(np.float32) for n in z}  # "no hit" outside the boxes
    np.testing.assert_array_equal(r.remap_depth(z), r.remap_depth(zo))
    np.testing.assert_array_equal(r.remap_depth(z, "nearest"), r.remap_depth(zo, "nearest"))


def test_faces_never_bleed(gopro224, remap224, remap224_clamp):
    """Each face constant: every valid pixel gets its own face's constant (clamp: exactly, everywhere; blend:
    exactly, away from the seams, and only values of the two or three faces meeting there near them)."""
    s = remap224.face_size
    faces = {n: np.full((s, s, 1), float(i + 1), np.float32) for i, n in enumerate(FACE_NAMES)}
    faces["back"][:] = 1000.0  # provided but not needed: must never show up
    v = remap224.valid_mask
    own = remap224.face_of_pixel[v].astype(np.float32) + 1
    out = remap224_clamp.remap(faces)[..., 0]
    np.testing.assert_array_equal(out[v], own)
    assert np.all(out[~v] == 0)
    out = remap224.remap(faces)[..., 0]
    rays, _ = _unproject_grid(gopro224)
    interior = (_texels_from_seam(rays, s) > 0.5)[v]
    np.testing.assert_array_equal(out[v][interior], own[interior])
    assert not interior.all()
    assert np.all((out[v] >= 1) & (out[v] <= 6))  # never the back face nor zeros from the atlas border
    assert np.all(out[~v] == 0)


# ---------------------------------------------------------------------------------------------- depth
def test_remap_depth_sphere_and_plane(rng, remap224, gopro224):
    rays, valid = _unproject_grid(gopro224)
    # camera inside an off-centre sphere: every ray hits, at t = d·c + sqrt((d·c)^2 - |c|^2 + R^2)
    c = rng.normal(size=3)
    c *= rng.uniform(0.2, 0.6) / np.linalg.norm(c)
    rad = rng.uniform(1.0, 2.0)

    def t_sphere(d):
        dc = d @ c
        return dc + np.sqrt(dc * dc - c @ c + rad * rad)

    def z_depth(face_t):
        out = {}
        for name in remap224.faces_needed:
            d = face_pixel_rays(name, remap224.face_size)
            out[name] = (face_t(d) * (d @ face_rotation(name)[:, 2])).astype(np.float32)  # z = t cos
        return out

    truth = t_sphere(rays)
    # Within half a texel of a face seam the sample is clamped to the edge texel (first-order error ~ 0.5 texel
    # × relative depth gradient); elsewhere linear interpolation is second order.
    interior = valid & (_texels_from_seam(rays, remap224.face_size) > 1.0)
    for interp, tol, tol_in in (("linear", 2e-4, 2e-4), ("nearest", 2e-2, 2e-2)):
        rd = remap224.remap_depth(z_depth(t_sphere), interpolation=interp)
        assert rd.shape == (224, 224) and rd.dtype == np.float32
        rel = np.abs(rd - truth) / truth
        print(
            f"\n[cubemap] sphere ray_depth ({interp}): max rel err = {rel[valid].max():.2e}, "
            f"> 1 texel from a seam = {rel[interior].max():.2e}"
        )
        assert rel[valid].max() < tol and rel[interior].max() < tol_in
        assert np.all(rd[~valid] == 0)
    # floor plane y = h (OpenCV y down): hit at t = h / d_y for d_y > 0, else no hit (+inf)
    h = rng.uniform(0.3, 1.0)
    with np.errstate(divide="ignore"):
        plane = lambda d: np.where(d[..., 1] > 0, h / np.where(d[..., 1] > 0, d[..., 1], 1.0), np.inf)  # noqa: E731
        rd = remap224.remap_depth(z_depth(plane))
    hit = valid & (rays[..., 1] > 0.3)
    miss = valid & (rays[..., 1] < -0.05)
    assert hit.sum() > 1000 and miss.sum() > 1000
    rel = np.abs(rd[hit] - h / rays[hit][:, 1]) / (h / rays[hit][:, 1])
    rel_in = rel[interior[hit]]
    print(f"[cubemap] plane ray_depth (linear): max rel err = {rel.max():.2e}, "
          f"> 1 texel from a seam = {rel_in.max():.2e}")
    assert rel.max() < 1e-3 and rel_in.max() < 1e-3
    assert np.all(np.isposinf(rd[miss]))
    assert not np.isnan(rd).any()


# ---------------------------------------------------------------------------------------------- errors
def test_bad_input_raises(remap224):
    s = remap224.face_size
    good = {n: np.zeros((s, s, 3), np.uint8) for n in remap224.faces_needed}
    missing = dict(good)
    del missing["up"]
    with pytest.raises(CameraError, match="'up'"):
        remap224.remap(missing)
    wrong = dict(good, left=np.zeros((s, s + 1, 3), np.uint8))
    with pytest.raises(CameraError, match=rf"'left'.*\({s}, {s + 1}, 3\)"):
        remap224.remap(wrong)
    with pytest.raises(CameraError, match="'right'"):
        remap224.remap(dict(good, right=np.zeros((s, s, 3), np.float32)))  # dtype differs from the others
    with pytest.raises(CameraError, match="'front'"):
        remap224.remap({n: np.zeros((s, s, 3), np.int64) for n in remap224.faces_needed})
    with pytest.raises(CameraError, match="interpolation"):
        remap224.remap(good, interpolation="cubic")
    with pytest.raises(CameraError, match="fill"):
        remap224.remap(good, fill=(1, 2))
    with pytest.raises(CameraError):
        remap224.remap([np.zeros((s, s, 3))])  # type: ignore[arg-type]
    depth = {n: np.ones((s, s), np.float32) for n in remap224.faces_needed}
    with pytest.raises(CameraError, match="'down'"):
        remap224.remap_depth(dict(depth, down=np.ones((s, s, 3), np.float32)))
    with pytest.raises(CameraError, match="dtype"):
        remap224.remap_depth({n: np.ones((s, s), np.int32) for n in remap224.faces_needed})
    depth["front"][3, 4] = -np.inf
    with pytest.raises(CameraError, match="'front'.*NaN"):
        remap224.remap_depth(depth)
    depth["front"][3, 4] = np.nan
    with pytest.raises(CameraError, match="NaN"):
        remap224.remap_depth(depth)
    for bad in (0, 4, 12.0, True):
        with pytest.raises(CameraError):
            CubemapFisheyeRemap(remap224.intr, face_size=bad)  # type: ignore[arg-type]
    with pytest.raises(CameraError):
        face_intrinsics_matrix(3)


# ---------------------------------------------------------------------------------------------- timing
def test_remap_timing(rng, remap224):
    """Timing only (printed, never asserted): 224² and 1024×768 fisheye, uint8 RGB faces."""
    big_intr = gopro_intrinsics_2_7k().scaled(1024, 768)
    t0 = time.perf_counter()
    big = CubemapFisheyeRemap(big_intr)
    t_init = time.perf_counter() - t0
    for name, r in (("224x224", remap224), ("1024x768", big)):
        s = r.face_size
        faces = {n: rng.integers(0, 256, (s, s, 3), dtype=np.uint8) for n in r.faces_needed}
        r.remap(faces)
        n = 20 if s < 300 else 5
        t0 = time.perf_counter()
        for _ in range(n):
            out = r.remap(faces)
        dt = (time.perf_counter() - t0) / n
        assert out.shape == (r.intr.height, r.intr.width, 3)
        print(f"\n[cubemap] remap {name}: face_size={s}, faces={len(r.faces_needed)}, {dt * 1e3:.2f} ms/frame")
    print(f"[cubemap] CubemapFisheyeRemap init 1024x768: {t_init * 1e3:.0f} ms")
