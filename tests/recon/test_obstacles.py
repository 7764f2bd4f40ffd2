import numpy as np
import pytest

pytest.importorskip("trimesh")

from umi_aug.errors import ReconError
from umi_aug.geometry.sdf import HalfSpaceSDF
from umi_aug.recon.obstacles import (PROCEDURAL_ASSETS, obstacle_hull_sdf, packaged_mesh_assets, procedural_asset,
                                     sample_obstacle_placement)


def _demo(n=150, contact=100):
    """Camera looking down-forward, moving from high/near to low/far, then lifting after contact."""
    from umi_aug.geometry import look_at_rotation, make_pose

    T = np.empty((n, 4, 4))
    for i in range(n):
        s = min(i / contact, 1.0)
        p = np.array([0.0, -0.25 + 0.25 * s, 0.45 - 0.2 * s]) + (0 if i <= contact else
                                                                  np.array([0, 0, 0.002 * (i - contact)]))
        T[i] = make_pose(look_at_rotation(p, p + np.array([0, 0.3, -0.5]), np.array([0, 1.0, 0])), p)
    return T, np.full(n, 0.08)


@pytest.mark.parametrize("name", PROCEDURAL_ASSETS)
def test_assets_and_inflated_hull(name):
    a = procedural_asset(name)
    assert a.mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9) and a.height > 0.05
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.0]
    sdf, hull = obstacle_hull_sdf(a, T, inflation=0.01)
    pts = a.surface_points(500) + T[:3, 3]
    d, _ = sdf.distance_and_gradient(pts)
    assert np.all(d <= -0.01 + 1e-9)  # every surface point is inside the hull, inflated by 1 cm
    d_far, _ = sdf.distance_and_gradient(np.array([[0.1, 0.2, 1.0]]))
    assert d_far[0] > 0.5


def test_placement_blocks_approach_keeps_precontact_free():
    T, w = _demo()
    a = procedural_asset("bottle", scale=1.2)
    pl = sample_obstacle_placement(a, T, w, 100, rng=0, scene_sdf=HalfSpaceSDF([0, 0, -0.001], [0, 0, 1]))
    assert pl.blocked_min_clearance < 0 and pl.precontact_min_clearance >= 0.015
    pl2 = sample_obstacle_placement(a, T, w, 100, rng=0, scene_sdf=HalfSpaceSDF([0, 0, -0.001], [0, 0, 1]))
    np.testing.assert_array_equal(pl.T_world_obj, pl2.T_world_obj)  # same seed → same placement
    with pytest.raises(ReconError, match="no placement"):
        sample_obstacle_placement(procedural_asset("box", scale=0.1), T, w, 100, rng=0, max_tries=20)


def test_packaged_meshes_listing_does_not_download():
    assert isinstance(packaged_mesh_assets(), dict)
    with pytest.raises(ReconError):
        procedural_asset("teapot")
