"""Grouping a plain dataset's episodes by place (``umi_aug.augment.scene_grouping``): the epipolar test against its
slow reference, and the grouping on synthetic places whose texture is identical but whose geometry differs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.geometry._helpers import random_poses
from umi_aug.augment.scene_grouping import (_epipolar_inliers_reference, compare_episodes, epipolar_inliers,
                                            group_by_place, nearby_frame_pairs)
from umi_aug.errors import AugmentError


def _look_down_path(n: int, x0: float, y0: float, rng) -> np.ndarray:
    """``[n, 4, 4]`` cameras 0.35 m above the table looking down, moving 20 cm along x with a little wobble."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, 0, 3] = x0 + np.linspace(0, 0.2, n)
    T[:, 1, 3] = y0 + 0.01 * np.sin(np.linspace(0, 3, n))
    T[:, 2, 3] = 0.35 + rng.normal(0, 0.003, n)
    return T


class _Place:
    """Textured points on a table; ``features(T)`` gives the rays and descriptors a camera at ``T`` sees."""

    def __init__(self, points: np.ndarray, desc: np.ndarray, rng):
        self.points, self.desc, self.rng = points, desc, rng

    def features(self, T: np.ndarray):
        d = (self.points - T[:3, 3]) @ T[:3, :3]  # camera frame
        r = d / np.linalg.norm(d, axis=1, keepdims=True)
        keep = r[:, 2] > math.cos(math.radians(80))
        noise = self.rng.normal(0, 0.01, self.desc[keep].shape).astype(np.float32)
        return r[keep], (self.desc[keep] + noise).astype(np.float32)


def _places(rng):
    pts = np.column_stack([rng.uniform(-0.3, 0.6, 400), rng.uniform(-0.4, 0.4, 400), rng.uniform(0, 0.05, 400)])
    desc = rng.uniform(0, 1, (400, 128)).astype(np.float32)
    a = _Place(pts, desc, rng)
    # another place that looks exactly alike (the same texture) but lies elsewhere in its tag frame
    c, s = math.cos(math.radians(25)), math.sin(math.radians(25))
    moved = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [0.12, -0.05, 0.0]
    return a, _Place(moved, desc, rng)


def test_epipolar_fast_matches_reference(rng):
    for _ in range(20):
        Ta, Tb = random_poses(rng, 2)
        ra = rng.standard_normal((50, 3))
        rb = rng.standard_normal((50, 3))
        ra /= np.linalg.norm(ra, axis=1, keepdims=True)
        rb /= np.linalg.norm(rb, axis=1, keepdims=True)
        tol = float(rng.uniform(0.1, 60))
        assert np.array_equal(epipolar_inliers(ra, rb, Ta, Tb, tol), _epipolar_inliers_reference(ra, rb, Ta, Tb, tol))


def test_epipolar_true_matches_pass_random_ones_fail_zero_baseline_has_none(rng):
    Ta, Tb = random_poses(rng, 2)
    P = Ta[:3, 3] + rng.normal(0, 1, (200, 3))
    ra = (P - Ta[:3, 3]) @ Ta[:3, :3]
    rb = (P - Tb[:3, 3]) @ Tb[:3, :3]
    ra /= np.linalg.norm(ra, axis=1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    assert epipolar_inliers(ra, rb, Ta, Tb).all() and _epipolar_inliers_reference(ra, rb, Ta, Tb).all()
    assert epipolar_inliers(ra, rb[rng.permutation(200)], Ta, Tb).mean() < 0.1
    same = Ta.copy()  # no baseline: no epipolar plane, no evidence
    assert not epipolar_inliers(ra, ra, Ta, same).any() and not _epipolar_inliers_reference(ra, ra, Ta, same).any()


def test_nearby_frame_pairs_respect_the_limits(rng):
    Ta = _look_down_path(60, 0.0, 0.0, rng)
    pairs = nearby_frame_pairs(Ta, _look_down_path(50, 0.03, 0.02, rng))
    assert len(pairs) >= 4 and all(0 <= i < 60 and 0 <= j < 50 for i, j in pairs)
    assert nearby_frame_pairs(Ta, _look_down_path(50, 1.0, 0.0, rng)) == []  # a metre away: nothing to compare
    assert nearby_frame_pairs(Ta, Ta[:0]) == []


def test_groups_follow_geometry_not_texture(rng):
    a, b = _places(rng)
    paths = {0: _look_down_path(80, 0.0, 0.0, rng), 1: _look_down_path(70, 0.02, 0.03, rng),
             2: _look_down_path(90, -0.01, 0.01, rng), 3: _look_down_path(60, 0.03, -0.02, rng)}
    place = {0: a, 1: a, 2: b, 3: b}

    def features(e, f):
        return place[e].features(paths[e][f])

    same = compare_episodes(0, 1, paths[0], paths[1], features)
    other = compare_episodes(1, 2, paths[1], paths[2], features)
    assert same.same_place and same.median_inliers >= 50
    assert same.median_inlier_fraction > 0.9
    # alike texture: as many matches, but few on the epipolar planes of the (wrongly) shared frame
    assert not other.same_place and other.median_inlier_fraction < 0.2 and np.median(other.matches) >= 50

    groups, evidence = _group(paths, features)
    assert groups == {"place000000": [0, 1], "place000002": [2, 3]}
    assert {(ev.episode_a, ev.episode_b, ev.same_place) for ev in evidence} >= {(0, 1, True), (1, 2, False)}
    assert _group(paths, features, max_group=1)[0] == {f"place{e:06d}": [e] for e in range(4)}
    with pytest.raises(AugmentError, match="max_group"):
        _group(paths, features, max_group=0)


def _group(paths, features, **kw):
    """group_by_place with the synthetic features in place of SIFT on frames."""
    import umi_aug.augment.scene_grouping as sg

    class Fake:
        def __init__(self, *a):
            pass

        def __call__(self, e, f):
            return features(e, f)

    orig = sg._Features
    sg._Features = Fake
    try:
        return group_by_place(sorted(paths), paths, None, None, None, **kw)
    finally:
        sg._Features = orig


REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"


def test_real_episode_against_itself_in_its_own_frame_and_in_another(tmp_path):
    """The real episode compared with itself: in the same tag frame it is one place (matches on the epipolar planes
    of the recorded poses); with every pose moved as if its session's tag lay elsewhere (15° about z, 4 cm), the
    same frames match as well but no longer agree with the poses, so it is another place."""
    if not REAL.exists():
        pytest.fail(f"{REAL}: the real UMI episode is missing (../shared/realdata)")
    from umi_aug.augment.dataset_source import DatasetInput, _policy_intrinsics, check_dataset
    from umi_aug.data import ReplayBuffer
    from umi_aug.geometry.umi import camera_poses_from_tcp_poses
    from umi_aug.recon.pipeline import first_close_index
    from umi_aug.recon.sfm import feature_mask

    inp = DatasetInput()
    chk = check_dataset(REAL, 224, inp)
    T = camera_poses_from_tcp_poses(chk.T_world_tcp[0], inp.T_cam_tcp)[: first_close_index(chk.gripper_width[0])]
    # another tag frame: turned 15° about the vertical through the path's centre and moved 4 cm (the cameras stay
    # near the originals, so frames at nearby poses are compared)
    c, s = math.cos(math.radians(15)), math.sin(math.radians(15))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    m = T[:, :3, 3].mean(0)
    other = np.eye(4)
    other[:3, :3] = R
    other[:3, 3] = m - R @ m + [0.04, 0.0, 0.0]
    poses = {0: T, 1: T[::-1].copy(), 2: other @ T}  # 1: the same frames in reverse order (other nearest pairs)
    intr = _policy_intrinsics(224)
    with ReplayBuffer.open(REAL) as buf:
        frames = buf["camera0_rgb"]

        def read(e, f):
            return np.asarray(frames[int(f) if e != 1 else len(T) - 1 - int(f)])

        groups, evidence = group_by_place([0, 1, 2], poses, read, intr, feature_mask(intr), window=2)
    by = {(ev.episode_a, ev.episode_b): ev for ev in evidence}
    assert by[(0, 1)].same_place and by[(0, 1)].median_inlier_fraction > 0.5
    assert not by[(1, 2)].same_place and np.median(by[(1, 2)].matches) > 20  # the frames alike, the poses not
    assert groups == {"place000000": [0, 1], "place000002": [2]}


def test_auto_groups_in_prepare_dataset_plumbing(tmp_path):
    """``scene_group="auto"`` through :func:`scene_groups` with the dataset's own evidence: random frames share no
    place (one scene each), the evidence is written, a scene map still wins for the episodes it names; the CLI
    accepts ``auto`` and refuses anything else but an int >= 1."""
    from tests.augment.test_dataset_input import S, _episode, _write
    from umi_aug.augment.cli import _scene_group_arg
    from umi_aug.augment.dataset_source import DatasetInput, _groups_by_place, check_dataset, scene_groups

    rng = np.random.default_rng(0)
    path = _write(tmp_path / "d.zarr", [_episode(40, rng), _episode(50, rng, 0.01), _episode(30, rng, -0.01)])
    inp = DatasetInput(scene_group="auto", scene_map={"mine": [2]})
    chk = check_dataset(path, S, inp)
    work = tmp_path / "work"
    groups = scene_groups(3, [0, 1, 2], inp, lambda eps: _groups_by_place(path, work, chk, eps, S, inp, False))
    assert groups == {"place000000": [0], "place000001": [1], "mine": [2]}
    saved = json.loads((work / "scene_groups.json").read_text())
    assert saved["groups"] == {"place000000": [0], "place000001": [1]} and saved["evidence"]
    with pytest.raises(AugmentError, match="auto"):
        scene_groups(3, [0], DatasetInput(scene_group="nope"))
    with pytest.raises(AugmentError, match="by_place"):
        scene_groups(3, [0], DatasetInput(scene_group="auto"))
    assert [_scene_group_arg(v) for v in ("auto", "AUTO", "3", "0", "x", 2)] == ["auto", "auto", 3, None, None, 2]
