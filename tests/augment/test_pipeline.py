"""Session stages, per-episode planning and rendering on the small synthetic session."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.augment.conftest import SIZE, small_config


def test_stages_are_cached_and_skipped(aug_assets, aug_session, aug_work):
    from umi_aug.augment import prepare_session

    assert set(aug_assets.stages) == {"reconstruct", "contact", "splat", "gripper_mask"}
    assert "obstacle_work" in aug_assets.paths  # obstacle Gaussians: fitted per asset on first use
    prepare_session(aug_session, aug_work, small_config(), progress=False)  # other tests may have used other configs
    again = prepare_session(aug_session, aug_work, small_config(), progress=False)
    assert all(r.skipped for r in again.stages.values())
    assert {k: r.key for k, r in again.stages.items()} == {k: r.key for k, r in aug_assets.stages.items()}
    # a free-space run does not need (and does not run) the obstacle stage
    free = prepare_session(aug_session, aug_work, small_config(mode="freespace"), progress=False)
    assert "obstacle_work" not in free.paths and all(r.skipped for r in free.stages.values())
    # changing only the overlay settings reruns only the mask stage
    from umi_aug.augment import OverlayConfig

    other = prepare_session(aug_session, aug_work, small_config(mode="freespace",
                            overlay=OverlayConfig(mask="estimated")), progress=False)
    assert [k for k, r in other.stages.items() if not r.skipped] == ["gripper_mask"]
    assert other.mask_info["source"] == "estimated" and other.gripper_mask.shape == (SIZE, SIZE)


def test_obstacle_gaussians_fitted_per_asset_on_first_use(aug_session, aug_assets, aug_work, tmp_path):
    """Only the assets an episode renders are fitted; once, cached across handles and processes' copies; a bad
    asset name fails up front; an asset outside the run's list is refused. Starts from a copy of the shared work
    folder without its obstacles (the session's stages are cache hits: the obstacle mode shares their keys)."""
    import dataclasses
    import shutil

    from umi_aug.augment import prepare_session
    from umi_aug.augment.obstacle_stage import obstacle_stage
    from umi_aug.errors import AugmentError

    work = Path(shutil.copytree(aug_work, tmp_path / "work", ignore=shutil.ignore_patterns("obstacles")))
    cfg = small_config(mode="obstacle", splat=small_config().splat)
    assets = prepare_session(aug_session, work, cfg, progress=False)
    assert assets.stages["reconstruct"].skipped and assets.stages["splat"].skipped  # (the overlay's may be redone)
    assert not (work / "obstacles").exists()  # nothing fitted yet
    g = assets.obstacle_gaussians("box")
    assert g.n > 0 and g.means.isfinite().all()
    fitted = sorted(p.name for p in (work / "obstacles").iterdir() if p.is_dir())
    assert len(fitted) == 1 and fitted[0].startswith("box-")  # bottle untouched
    copy = pickle.loads(pickle.dumps(assets))
    copy.memo = {}  # a fresh process: reads the stage's cache
    assert copy.obstacle_gaussians("box").n == g.n
    assert obstacle_stage(work, cfg, "box").skipped
    with pytest.raises(AugmentError, match="no obstacle Gaussians for asset 'sphere'"):
        assets.obstacle_gaussians("sphere")
    with pytest.raises(AugmentError, match="obstacle asset 'no-such-asset'"):
        prepare_session(aug_session, work, small_config(mode="obstacle", obstacle=dataclasses.replace(
            cfg.obstacle, assets=("box", "no-such-asset"))), progress=False)
    shutil.rmtree(work / "obstacles")


def test_predicted_obstacle_asset_is_the_first_attempts_draw(aug_assets):
    """The asset the exporter has fitted ahead of time is the one the planner's first attempt places."""
    from umi_aug.augment.plan import first_attempt_obstacle_asset, first_attempt_obstacle_assets, try_plan_episode

    cfg = aug_assets.cfg
    predicted = [first_attempt_obstacle_asset(cfg, 0, a) for a in range(4)]
    assert set(predicted) <= set(cfg.obstacle.assets)
    assert first_attempt_obstacle_assets(cfg, [0]) == list(dict.fromkeys(predicted[:cfg.n_per_demo]))
    first_tries = 0
    for aug_id in range(4):
        out = try_plan_episode(aug_assets, 0, aug_id, "obstacle")
        if out.planned is not None and out.attempts == 1:
            assert out.planned.obstacle.asset == predicted[aug_id], aug_id
            first_tries += 1
    assert first_tries > 0
    import dataclasses

    assert first_attempt_obstacle_assets(dataclasses.replace(cfg, mode="freespace"), [0]) == []


@pytest.mark.slow  # a real (short: 40 steps) fit in a nice-10 child (~5-10 s on 2 busy cores)
def test_obstacle_prefit_in_a_background_process(aug_session, tmp_path, monkeypatch):
    """start_obstacle_prefit fits the named assets in a low-priority child (the stage the episodes then read
    from the cache), and starts nothing when every stage is cached, fitting is off, or it is turned off."""
    import dataclasses

    from umi_aug.augment.obstacle_stage import obstacle_stage, obstacle_stage_folder, start_obstacle_prefit

    base = small_config(mode="obstacle")
    cfg = dataclasses.replace(base, obstacle=dataclasses.replace(base.obstacle, fit_gaussians=True, n_gaussians=150,
                                                                 fit_iterations=40))
    work = tmp_path / "work"
    priority = os.getpriority(os.PRIO_PROCESS, 0)  # (the suite itself may run niced)
    child = start_obstacle_prefit(work, cfg, ["box"])
    assert child is not None and child.wait(timeout=300) == 0, (work / "obstacles" / "prefit.log").read_text()
    st = obstacle_stage(work, cfg, "box")
    assert st.skipped and st.info["gaussians"] == 150  # fitted by the child, read from the cache here
    assert os.getpriority(os.PRIO_PROCESS, 0) == priority  # the parent's priority is untouched
    assert start_obstacle_prefit(work, cfg, ["box"]) is None  # cached
    assert start_obstacle_prefit(work, base, ["bottle"]) is None  # fit_gaussians off: nothing worth a process
    monkeypatch.setenv("UMI_AUG_NO_OBSTACLE_PREFIT", "1")
    assert start_obstacle_prefit(work, cfg, ["bottle"]) is None
    left = {p.name for p in (work / "obstacles").iterdir() if not p.name.endswith(".lock")}
    assert left == {"prefit.log", obstacle_stage_folder("box")[10:]}  # nothing else written (config went on stdin)
    assert not (work / obstacle_stage_folder("bottle")).exists()


def test_assets_pickle_light(aug_assets):
    _ = aug_assets.sdf, aug_assets.gaussians  # load the heavy members
    blob = pickle.dumps(aug_assets)
    assert len(blob) < 2_000_000
    back = pickle.loads(blob)
    assert back.memo == {} and back.paths == aug_assets.paths
    d = aug_assets.demos[0]
    assert d.contact_index is not None and 0 < d.contact_index < len(d.T_world_cam)


def test_original_buffer_reopened_in_a_forked_child(aug_assets, monkeypatch):
    """A forked DataLoader worker must not read through the parent's zip handle (a shared read offset): the
    original buffer is opened once per process, and a real forked child reads the same frames."""
    import multiprocessing as mp
    import os

    first = aug_assets.original
    want = aug_assets.original_frames(0, slice(0, 4))
    assert aug_assets.original is first  # same process: cached
    ctx = mp.get_context("fork")
    with ctx.Pool(2) as pool:  # children read while the parent reads too
        got = pool.starmap(_frames_checksum, [(aug_assets, k) for k in range(4)])
        mine = [int(aug_assets.original_frames(0, slice(k, k + 1)).sum()) for k in range(4)]
    assert got == mine == [int(want[k].sum()) for k in range(4)]
    pid = os.getpid()
    monkeypatch.setattr(os, "getpid", lambda: pid + 1)  # as a forked child sees it
    assert aug_assets.original is not first
    np.testing.assert_array_equal(aug_assets.original_frames(0, slice(0, 4)), want)


def _frames_checksum(assets, k: int) -> int:
    return int(assets.original_frames(0, slice(k, k + 1)).sum())


def _episode_bytes(planned, frames) -> bytes:
    ep = planned.episode
    return b"".join(np.ascontiguousarray(a).tobytes() for a in
                    (ep.T_world_cam, ep.actions, ep.gripper_width, ep.timestamps, frames))


def test_plan_and_render_are_deterministic_across_processes(aug_assets, tmp_path):
    from umi_aug.augment import plan_episode, render_episode_frames

    p1 = plan_episode(aug_assets, 0, 1, "freespace")
    assert p1 is not None and p1.attempts >= 1
    idx = [0, p1.splice_index // 2, p1.splice_index - 1, p1.splice_index, p1.n_frames - 1]
    f1 = render_episode_frames(aug_assets, p1, idx)
    assert f1.shape == (5, SIZE, SIZE, 3) and f1.dtype == np.uint8
    # order independence: another episode first, then the same one again
    plan_episode(aug_assets, 0, 0, "freespace")
    p2 = plan_episode(aug_assets, 0, 1, "freespace")
    assert _episode_bytes(p1, f1) == _episode_bytes(p2, render_episode_frames(aug_assets, p2, idx))
    assert not np.array_equal(plan_episode(aug_assets, 0, 0, "freespace").episode.T_world_cam[0],
                              p1.episode.T_world_cam[0])
    # another process, from the pickled handle
    (tmp_path / "assets.pkl").write_bytes(pickle.dumps(aug_assets))
    code = textwrap.dedent(f"""
        import pickle, sys, numpy as np
        from umi_aug.augment import plan_episode, render_episode_frames
        a = pickle.load(open(sys.argv[1], "rb"))
        p = plan_episode(a, 0, 1, "freespace")
        f = render_episode_frames(a, p, {idx})
        ep = p.episode
        sys.stdout.buffer.write(b"".join(np.ascontiguousarray(x).tobytes()
                                for x in (ep.T_world_cam, ep.actions, ep.gripper_width, ep.timestamps, f)))
    """)
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "assets.pkl")], capture_output=True,
                         check=True, timeout=300)
    assert out.stdout == _episode_bytes(p1, f1)


def test_rendered_frames_carry_the_original_gripper_and_original_tail(aug_assets):
    from umi_aug.augment import plan_episode, render_episode_frames
    from umi_aug.augment.render import overlay_sources

    p = plan_episode(aug_assets, 0, 0, "freespace")
    ep = p.episode
    new = np.arange(0, p.splice_index, 7)
    frames = render_episode_frames(aug_assets, p, new)
    src = aug_assets.original_frames(0, overlay_sources(aug_assets, p, new))
    m = aug_assets.gripper_mask
    assert m.any()
    assert np.array_equal(frames[:, m], src[:, m])  # exactly the original gripper pixels in the mask
    assert not np.array_equal(frames[:, ~m], src[:, ~m])  # the rest is rendered
    # the overlay source has the closest width among the pre-contact frames
    d = aug_assets.demos[0]
    widths = d.gripper_width[: d.contact_index + 1]
    chosen = widths[overlay_sources(aug_assets, p, new)]
    assert np.all(np.abs(chosen - ep.gripper_width[new]) <= np.abs(widths[None] - ep.gripper_width[new, None]).min(1)
                  + 5e-4)
    # after the splice: the original frames, untouched
    old = np.arange(p.splice_index, p.n_frames, 25)
    orig = aug_assets.original_frames(0, ep.source_contact_index + (old - p.splice_index))
    assert np.array_equal(render_episode_frames(aug_assets, p, old), orig)
    # the actions keep the original gripper width after the splice, poses replay the demo
    assert np.allclose(ep.gripper_width[p.splice_index:], d.gripper_width[ep.source_contact_index:])
    assert np.array_equal(ep.T_world_cam[p.splice_index:], d.T_world_cam[ep.source_contact_index:])


def test_obstacle_mode_never_emits_a_pose_inside_the_hull(aug_assets):
    from umi_aug.augment import plan_episode, render_episode_frames
    from umi_aug.traj import ConvexObstacle

    n_checked = 0
    for aug_id in range(2):
        p = plan_episode(aug_assets, 0, aug_id, "obstacle")
        assert p is not None, f"obstacle episode {aug_id} failed"
        ob = p.obstacle
        assert ob is not None and ob.asset in ("box", "bottle")
        T = p.episode.T_world_cam
        prob = aug_assets.traj_problem(0)
        spheres = prob.sphere_points(T)  # [N, S, 3]
        inflated = ob.convex_obstacle()
        bare = ConvexObstacle(ob.hull_world, 0.0)
        assert not bare.contains(T[:, :3, 3]).any()  # no camera centre inside the hull
        assert not inflated.contains(spheres, prob.spheres.radii).any()  # no gripper sphere touches it
        # the obstacle blocks the straight approach: the path really goes around it
        assert inflated.plane_values(spheres).min() > 0
        n_checked += len(T)
    assert n_checked > 0
    # obstacle frames: obstacle composited; gripper pixels exact in new frames
    p = plan_episode(aug_assets, 0, 0, "obstacle")
    k = [0, p.splice_index - 1, p.splice_index + 5]
    frames = render_episode_frames(aug_assets, p, k)
    m = aug_assets.gripper_mask
    from umi_aug.augment.render import overlay_sources

    src = aug_assets.original_frames(0, overlay_sources(aug_assets, p, k[:2]))
    assert np.array_equal(frames[:2][:, m], src[:, m])
    free = render_episode_frames(aug_assets, p.__class__(**{**p.__dict__, "obstacle": None}), k)
    assert not np.array_equal(frames, free)  # the obstacle is visible somewhere


def test_errors_name_the_problem(aug_assets):
    from umi_aug.augment import plan_episode, render_episode_frames
    from umi_aug.errors import AugmentError

    with pytest.raises(AugmentError, match="mode"):
        plan_episode(aug_assets, 0, 0, "sideways")
    with pytest.raises(AugmentError, match="out of range"):
        plan_episode(aug_assets, 5, 0, "freespace")
    p = plan_episode(aug_assets, 0, 0, "freespace")
    with pytest.raises(AugmentError, match="outside"):
        render_episode_frames(aug_assets, p, [p.n_frames])


@pytest.mark.slow  # 5-40 s on 2 shared cores, depending on load
def test_real_3dgs_training_stage(aug_assets, aug_session, aug_work, tmp_path, monkeypatch):
    """The splat stage with the fisheye 3DGS trainer (a 40-step fit), reusing the cached reconstruction; the
    obstacle prefit starts right before the training, and not when the stage is cached."""
    import math
    import shutil

    from umi_aug.augment import SplatStageConfig, plan_episode, prepare_session, render_episode_frames
    from umi_aug.augment.sources import session as session_source

    prefits = []
    monkeypatch.setattr(session_source, "start_obstacle_prefit", lambda work, cfg, names: prefits.append(names))
    for stage in ("reconstruct", "contact"):
        shutil.copytree(aug_work / stage, tmp_path / stage)
    cfg = small_config(mode="both", splat=SplatStageConfig(
        iterations=40, max_gaussians=3000, sh_degree=0, image_size=160,
        extra={"eval_every": 40, "checkpoint_every": 40, "refine_start": 10, "refine_every": 10,
               "train_eval_views": 2, "sheet_views": 1}))
    a = prepare_session(aug_session, tmp_path, cfg, progress=False, prefit_obstacles=("box", "not-configured"))
    assert a.stages["reconstruct"].skipped and a.stages["contact"].skipped and not a.stages["splat"].skipped
    assert prefits == [["box"]]  # configured assets only
    info = a.stages["splat"].info
    assert info["trained"] and math.isfinite(info["heldout_psnr"]) and 0 < info["gaussians"] <= 3000
    again = prepare_session(aug_session, tmp_path, cfg, progress=False, prefit_obstacles=("box",))
    assert again.stages["splat"].skipped
    assert prefits == [["box"]]  # cached scene: no prefit
    p = plan_episode(a, 0, 0, "freespace")
    frames = render_episode_frames(a, p, [0, p.splice_index // 2])
    assert frames[:, ~a.gripper_mask].std() > 5.0  # a scene, not a blank image
