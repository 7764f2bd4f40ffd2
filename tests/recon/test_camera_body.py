"""Cloud points inside the camera's own path (``recon.cloud.inside_camera_body``): the fast KD-tree query against
its brute-force reference on fresh random inputs, the extreme cases, and bad input."""

import math

import numpy as np
import pytest

from tests.geometry._helpers import random_poses, rotvecs_with_angle
from umi_aug.errors import ReconError
from umi_aug.geometry.gripper import umi_camera_body_spheres, umi_gripper_spheres
from umi_aug.geometry.so3 import so3_exp
from umi_aug.recon.cloud import _inside_camera_body_reference, inside_camera_body


def _points_around(rng, T, n):
    """Points scattered around the body spheres of random poses: a mix inside, near the surface and outside."""
    sph = umi_camera_body_spheres()
    c = sph.world(T).reshape(-1, 3)
    pick = rng.integers(0, len(c), n)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c[pick] + d * rng.uniform(0.0, 0.08, (n, 1))


def test_fast_matches_the_reference_on_random_inputs(rng):
    T = random_poses(rng, 40)
    P = np.concatenate([_points_around(rng, T, 600), rng.normal(0, 0.5, (200, 3))])
    fast, ref = inside_camera_body(P, T), _inside_camera_body_reference(P, T)
    assert fast.dtype == bool and fast.shape == (len(P),)
    assert np.array_equal(fast, ref)
    assert 0 < fast.sum() < len(P)  # the draw has both kinds


@pytest.mark.parametrize("angle", [0.0, 1e-9, math.pi / 2, math.pi - 1e-9, math.pi])
def test_extreme_rotations_centres_and_surfaces(rng, angle):
    sph = umi_camera_body_spheres()
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, :3] = so3_exp(rotvecs_with_angle(rng, 3, angle))
    # poses 1 m apart (+ jitter): each probe point below is about one pose only. Within 0.3 m of each other, pose 2's
    # "5 cm in front of the lens" fell inside pose 1's body for some draws (CI seed 2465851722).
    T[:, :3, 3] = np.arange(3)[:, None] * np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.1, (3, 3))
    c = sph.world(T)  # [3, S, 3]
    u = rng.standard_normal(3)
    u /= np.linalg.norm(u)
    r0 = sph.radii[0]
    P = np.stack([c[1, 0],  # a sphere's centre (r -> 0)
                  c[1, 0] + u * r0 * (1 - 1e-6),  # just inside
                  c[1, 0] + u * r0 * (1 + 1e-6),  # just outside
                  T[2, :3, 3],  # the optical centre: inside the GoPro body
                  T[2, :3, 3] + T[2, :3, 2] * 0.05])  # 5 cm in front of the lens: outside the body
    fast, ref = inside_camera_body(P, T), _inside_camera_body_reference(P, T)
    assert np.array_equal(fast, ref)
    assert fast[0] and fast[1] and fast[3] and not fast[4]


def test_body_spheres_are_the_gripper_models_camera_and_mount():
    body, full = umi_camera_body_spheres(), umi_gripper_spheres()
    for name, c, r in zip(body.names, body.centers_cam, body.radii):
        i = full.names.index(name)
        assert name.startswith(("camera", "mount")) and np.allclose(full.centers_cam[i], c) and full.radii[i] == r
    assert len(body) == 3


def test_empty_inputs_and_bad_input():
    T = np.tile(np.eye(4), (2, 1, 1))
    assert inside_camera_body(np.zeros((0, 3)), T).shape == (0,)
    assert not inside_camera_body(np.zeros((4, 3)), np.zeros((0, 4, 4))).any()
    P = np.zeros((3, 3))
    P[1, 2] = np.nan
    with pytest.raises(ReconError, match="non-finite"):
        inside_camera_body(P, T)
    with pytest.raises(ReconError, match="non-finite"):
        inside_camera_body(np.zeros((2, 3)), np.full((1, 4, 4), np.inf))
