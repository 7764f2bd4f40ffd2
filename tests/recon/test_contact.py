"""Contact detection on a synthetic approach: min-jerk descent onto a bar, then the fingers close."""

import numpy as np
import pytest

from umi_aug.errors import ReconError
from umi_aug.geometry.sdf import BoxSDF, HalfSpaceSDF, SphereSDF, UnionSDF
from umi_aug.recon.contact import detect_contact, detect_contacts, gripper_clearance

FPS = 60.0


def _demo(contact=120, n=200):
    """Camera looking down (+z_cam = −z_world); descends min-jerk onto a thin vertical bar; closes at ``contact``."""
    s = np.clip(np.arange(n) / contact, 0, 1)
    mj = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # x right, y −y_world, z down
    z_end = 0.25  # fingertip spheres (cam z 0.214, r 0.012) end 2.4 cm above the table
    T[:, 2, 3] = 0.55 + (z_end - 0.55) * mj
    T[:, 1, 3] = -0.086  # the fingers' y offset puts the bar between the fingertips
    w = np.full(n, 0.08)
    k = np.arange(n) - contact
    c = np.clip(k / 30.0, 0, 1)
    w = 0.08 + (0.012 - 0.08) * (10 * c ** 3 - 15 * c ** 4 + 6 * c ** 5)
    return T, w


SCENE = UnionSDF([HalfSpaceSDF([0, 0, 0], [0, 0, 1]), BoxSDF([0, 0, 0.06], [0.005, 0.005, 0.06])])


def test_clearance_shapes_and_monotone_descent():
    T, w = _demo()
    cl, names = gripper_clearance(SCENE, T, w)
    assert cl.shape == (len(T),) and len(names) == len(T)
    assert np.all(np.diff(cl[:100]) <= 1e-9)


def test_grasp_onset_within_two_frames():
    T, w = _demo(contact=120)
    r = detect_contact(SCENE, T, w, FPS, threshold=0.03)
    assert r.proximity_index is not None and r.proximity_index < 120
    assert abs(r.contact_index - 120) <= 2 and r.grasp_onset_index == r.contact_index
    # the paper's plain proximity rule: the first frame within the threshold
    p = detect_contact(SCENE, T, w, FPS, threshold=0.03, rule="proximity")
    assert p.contact_index == r.proximity_index


def test_a_stray_point_passed_long_before_the_grasp_does_not_set_the_contact():
    """A sparse cloud's stray point beside the camera's path (the real episode without SIFT upscaling had one): the
    clearance dips below the threshold ~140 frames before the fingers close, then rises again. The approach that
    leads into the grasp gates the grasp search; the contact stays at the grasp onset."""
    T, w = _demo(contact=200, n=300)
    stray = SphereSDF([0.06, -0.086, T[60, 2, 3]], 0.001)  # beside the camera body as it passes, at frame ~60
    scene = UnionSDF([SCENE, stray])
    clean = detect_contact(SCENE, T, w, FPS, threshold=0.03)
    r = detect_contact(scene, T, w, FPS, threshold=0.03)
    cl, _ = gripper_clearance(scene, T, w)
    W = int(round(1.5 * FPS))
    p = r.proximity_index
    assert p + W < 200 and cl[p:p + W].max() > 0.06  # the premise: a pass-by, then away, then the approach
    assert r.contact_index == r.grasp_onset_index == clean.contact_index and abs(r.contact_index - 200) <= 2
    assert r.extra["gating_proximity_index"] == clean.proximity_index
    # the paper's plain rule still takes the first frame within the threshold
    assert detect_contact(scene, T, w, FPS, threshold=0.03, rule="proximity").contact_index == r.proximity_index


def test_override_no_contact_and_errors():
    T, w = _demo()
    r = detect_contacts(SCENE, [("a", T, w, FPS), ("b", T, w, FPS)], overrides={"b": 42}, threshold=0.03)
    assert r[1].contact_index == 42 and r[1].overridden and not r[0].overridden
    far = HalfSpaceSDF([0, 0, -5.0], [0, 0, 1])
    n = detect_contact(far, T, w, FPS)
    assert n.contact_index is None and "override" in n.message
    with pytest.raises(ReconError):
        detect_contact(SCENE, T, w, FPS, override=10_000)
    with pytest.raises(ReconError):
        detect_contact(SCENE, T, w[:-1], FPS)
    with pytest.raises(ReconError):
        detect_contact(SCENE, T, w, FPS, rule="nope")
