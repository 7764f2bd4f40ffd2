"""Square evaluation start configurations: DLS IK accuracy, cone sampling, determinism, file round trip."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("robosuite")

from umi_aug.geometry import rotation_geodesic_distance  # noqa: E402
from umi_aug.square.env import GRIP_SITE, SquareEnv  # noqa: E402
from umi_aug.square.ik import PandaIK  # noqa: E402
from umi_aug.square.init_configs import (  # noqa: E402
    InitConfigSpec, apply_init_config, load_init_configs, sample_init_configs, source_states_from_seeds,
    write_init_configs)


@pytest.fixture(scope="module")
def env():
    e = SquareEnv(image_size=None)
    yield e
    e.close()


@pytest.fixture(scope="module")
def sources(env):
    return source_states_from_seeds(env, [0, 1])


def test_ik_reaches_random_nearby_poses(env, rng):
    """Targets the Panda can reach by construction: the grip site of random joints near the reset's (inside the
    limits, free of collisions). A random Cartesian offset can ask for a wrist beyond joint 6's limit (it did: ~2 %
    of draws of ±8 cm / ±0.4 rad per axis, found by the per-run seed), which no IK can reach."""
    env.reset(seed=int(rng.integers(1 << 30)))
    ik = PandaIK(env.model)
    T0 = env.site_pose(GRIP_SITE)
    q0 = np.asarray(env.data.qpos[ik.qadr], dtype=np.float64).copy()
    margin = np.radians(5.0)
    targets = []
    while len(targets) < 3:
        q = np.clip(q0 + rng.uniform(-0.25, 0.25, 7), ik.lo + margin, ik.hi - margin)
        if not ik.collisions(env.data, q):
            targets.append(ik.site_pose(q, env.data))
    assert max(np.linalg.norm(T[:3, 3] - T0[:3, 3]) for T in targets) > 0.01  # not the start pose again
    for T in targets:
        res = ik.solve(env.data, T, rng=rng)
        assert res.ok, res
        Tq = ik.site_pose(res.q, env.data)
        assert np.linalg.norm(Tq[:3, 3] - T[:3, 3]) < 1e-4
        assert rotation_geodesic_distance(Tq[:3, :3], T[:3, :3]) < np.radians(0.05)
    np.testing.assert_array_equal(env.site_pose(GRIP_SITE), T0)  # the env's own state is untouched


def test_ik_reports_unreachable(env):
    env.reset(seed=0)
    ik = PandaIK(env.model)
    T = env.site_pose(GRIP_SITE)
    T[:3, 3] += np.array([2.0, 0.0, 0.0])  # 2 m away: beyond the Panda's reach
    res = ik.solve(env.data, T, rng=0, restarts=1)
    assert not res.reachable and not res.ok and res.pos_err > 0.5


def test_init_configs_pose_error_and_cone(env, sources, rng, tmp_path):
    seed = int(rng.integers(1 << 30))
    spec = InitConfigSpec(n=4, theta_deg=50.0, radius=0.15, seed=seed)
    c = sample_init_configs(env, sources, spec, progress=False)
    assert c["states"].shape == (4, sources.shape[1])
    np.testing.assert_array_equal(c["source_index"], [0, 1, 0, 1])
    path = write_init_configs(tmp_path / "init.npz", c, env.env_meta)
    loaded = load_init_configs(path)
    np.testing.assert_array_equal(loaded["states"], c["states"])
    assert loaded["report"]["spec"]["seed"] == seed
    for i in range(4):
        apply_init_config(env, loaded, i)
        T = env.site_pose(GRIP_SITE)
        tgt = loaded["T_world_site_target"][i]
        assert np.linalg.norm(T[:3, 3] - tgt[:3, 3]) < 1e-3  # < 1 mm
        assert rotation_geodesic_distance(T[:3, :3], tgt[:3, :3]) < np.radians(0.5)  # < 0.5°
        # the camera sits on the sampled cone: r from the pivot, within θ of the reference direction
        env.reset_to(sources[i % 2])
        T_ref = env.wrist_pose()
        pivot = T_ref[:3, 3] + 0.15 * T_ref[:3, 2]
        cam = loaded["T_world_cam"][i]
        assert np.linalg.norm(cam[:3, 3] - pivot) == pytest.approx(0.15, abs=1e-9)
        cosang = np.dot(cam[:3, 3] - pivot, -T_ref[:3, 2]) / 0.15
        assert cosang >= np.cos(np.radians(50.0)) - 1e-9
        np.testing.assert_allclose(cam[:3, 2], (pivot - cam[:3, 3]) / 0.15, atol=1e-9)  # looks at the pivot
        # objects unchanged: nut/peg part of the state equals the source
        apply_init_config(env, loaded, i)
        nut_now = env.body_pose("SquareNut_main")
        env.reset_to(sources[i % 2])
        np.testing.assert_allclose(nut_now, env.body_pose("SquareNut_main"), atol=1e-12)


def test_init_configs_same_seed_same_bytes(env, sources):
    spec = InitConfigSpec(n=2, seed=11)
    a = sample_init_configs(env, sources, spec, progress=False)
    b = sample_init_configs(env, sources, spec, progress=False)
    np.testing.assert_array_equal(a["states"], b["states"])
    np.testing.assert_array_equal(a["T_world_cam"], b["T_world_cam"])


def test_reset_configs_are_the_seeded_resets(env, tmp_path):
    """``--no-cone`` sets (the demos' own start distribution): each configuration restores its seeded reset exactly,
    the recorded camera pose is that reset's wrist camera, and the file round-trips through the eval loader."""
    from umi_aug.cli import main
    from umi_aug.square.init_configs import reset_init_configs

    seeds = [7, 3]
    states = source_states_from_seeds(env, seeds)
    c = reset_init_configs(env, states, seeds)
    assert c["report"]["spec"] == {"n": 2, "kind": "reset", "seeds": seeds}
    out = tmp_path / "reset.npz"
    assert main(["square-init-configs", "--no-cone", "--n", "2", "--first-seed", "3", "--out", str(out)]) == 0
    loaded = load_init_configs(out)
    np.testing.assert_array_equal(loaded["states"][0], states[1])  # seed 3 comes first in the file
    for i, seed in enumerate(seeds):
        apply_init_config(env, c, i)
        np.testing.assert_array_equal(env.get_state(), states[i])
        np.testing.assert_allclose(c["T_world_cam"][i], env.wrist_pose(), atol=1e-12)
        env.reset(seed=seed)
        np.testing.assert_array_equal(env.get_state(), c["states"][i])
    with pytest.raises(Exception, match="sources must be"):
        reset_init_configs(env, np.zeros((0, 3)))
    assert main(["square-init-configs", "--no-cone", "--hdf5", "x.hdf5", "--n", "1", "--out",
                 str(tmp_path / "bad.npz")]) == 2
    assert not (tmp_path / "bad.npz").exists()
