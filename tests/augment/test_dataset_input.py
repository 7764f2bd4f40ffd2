"""A plain UMI replay buffer as augmentation input (issue #13): bad input gets one clear error before any compute
and nothing is written; scene groups / episode selection; the real demonstration end to end (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from umi_aug.errors import AugmentError

S = 32
REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"


def _episode(n: int, rng: np.random.Generator, x0: float = 0.0) -> dict:
    from umi_aug.data import make_umi_episode
    from umi_aug.geometry import pos_rotvec_to_pose

    t = np.linspace(0, 1, n)
    p6 = np.zeros((n, 6))
    p6[:, 0] = x0 + 0.2 * t
    p6[:, 2] = 0.3 - 0.2 * t
    p6[:, 3] = np.pi
    w = np.where(t < 0.6, 0.08, 0.04)
    img = rng.integers(0, 255, (n, S, S, 3), dtype=np.uint8)
    return make_umi_episode(pos_rotvec_to_pose(p6), w, images={0: img})


def _write(path: Path, eps: list[dict], poke: tuple[str, int, int, float] | None = None) -> Path:
    """Save episodes; ``poke = (key, row, column, value)`` then writes a value the writer refuses (NaN/Inf)
    straight into the stored array (a zarr directory)."""
    from umi_aug.data import ReplayBuffer

    buf = ReplayBuffer.create()
    for e in eps:
        buf.add_episode(e)
    buf.save(path)
    if poke is not None:
        with ReplayBuffer.open(path, mode="a") as b:
            k, r, c, v = poke
            row = b[k][r]
            row[c] = v
            b[k][r] = row
    return path


@pytest.fixture()
def good(tmp_path):
    rng = np.random.default_rng(0)
    return [_episode(40, rng), _episode(50, rng, 0.1), _episode(30, rng, -0.1)]


def _check(path, **kw):
    from umi_aug.augment.dataset_source import DatasetInput, check_dataset

    return check_dataset(path, S, DatasetInput(**kw))


def test_good_dataset_passes(tmp_path, good):
    from umi_aug.augment.dataset_source import is_dataset_path

    p = _write(tmp_path / "ok.zarr.zip", good)
    assert is_dataset_path(p) and not is_dataset_path(tmp_path)
    chk = _check(p)
    assert chk.n_episodes == 3 and sorted(chk.T_world_tcp) == [0, 1, 2]
    assert chk.T_world_tcp[1].shape == (50, 4, 4) and np.isfinite(chk.T_world_tcp[1]).all()
    assert sorted(_check(p, episodes=(2,)).T_world_tcp) == [2]


@pytest.mark.parametrize("case, needle", [
    ("nan", "episode 1"), ("missing", "robot0_gripper_width"), ("size", "camera0_rgb"), ("jump", "lost-tracking"),
    ("frozen", "frozen"), ("short", "episode 2"),
])
def test_bad_dataset_one_clear_error(tmp_path, good, case, needle):
    eps = [dict(e) for e in good]
    poke = None
    if case == "nan":
        poke = ("robot0_eef_pos", 40 + 7, 1, np.nan)
    elif case == "missing":
        for e in eps:
            del e["robot0_gripper_width"]
    elif case == "size":
        for e in eps:
            e["camera0_rgb"] = np.zeros((len(e["camera0_rgb"]), S, S + 8, 3), np.uint8)
    elif case == "jump":
        eps[1]["robot0_eef_pos"] = eps[1]["robot0_eef_pos"].copy()
        eps[1]["robot0_eef_pos"][25:] += np.float32(0.3)
    elif case == "frozen":
        eps[1]["robot0_eef_pos"] = eps[1]["robot0_eef_pos"].copy()
        eps[1]["robot0_eef_rot_axis_angle"] = eps[1]["robot0_eef_rot_axis_angle"].copy()
        eps[1]["robot0_eef_pos"][35:] = eps[1]["robot0_eef_pos"][35]
        eps[1]["robot0_eef_rot_axis_angle"][35:] = eps[1]["robot0_eef_rot_axis_angle"][35]
    elif case == "short":
        eps[2] = {k: v[:8] for k, v in eps[2].items()}
    p = _write(tmp_path / "bad.zarr", eps, poke)
    with pytest.raises(AugmentError) as ei:
        _check(p)
    assert needle in str(ei.value) and str(p) in str(ei.value)
    if case in ("nan", "jump", "frozen"):
        assert "episode 1" in str(ei.value)
    if case in ("jump", "frozen", "short"):  # not augmented, only copied: fine
        _check(p, episodes=(0,))
    elif case == "nan":  # copied into the output all the same: refused
        with pytest.raises(AugmentError, match="episode 1"):
            _check(p, episodes=(0,))


def test_bad_dataset_export_writes_nothing(tmp_path, good):
    """The export refuses a bad dataset before any stage runs: no output, no work folder, an old output kept."""
    from umi_aug.augment import AugmentConfig
    from umi_aug.augment.exporter import export

    p = _write(tmp_path / "bad.zarr", good, ("robot0_eef_rot_axis_angle", 3, 0, np.inf))
    out = tmp_path / "out.zarr.zip"
    out.write_bytes(b"previous export")
    with pytest.raises(AugmentError, match="episode 0"):
        export(p, out, AugmentConfig(image_size=S), resume=False)
    assert out.read_bytes() == b"previous export"
    work = tmp_path / "out.zarr.zip.work"  # may hold the run's lock file, never a stage
    assert not (work / "scenes").exists() and not (work / "obstacles").exists()
    assert not (tmp_path / "out.zarr.zip.partial").exists()


def test_episode_selection_and_groups(tmp_path):
    from umi_aug.augment.dataset_source import DatasetInput, load_scene_map, parse_episodes, scene_groups

    assert parse_episodes("0:3") == (0, 1, 2) and parse_episodes("5,1:3") == (1, 2, 5) and parse_episodes("") is None
    for bad in ("3:1", "a", "1:"):
        with pytest.raises(AugmentError, match="--episodes"):
            parse_episodes(bad)
    assert scene_groups(10, [0, 1, 2], DatasetInput()) == {"ep000000": [0], "ep000001": [1], "ep000002": [2]}
    g = scene_groups(10, [0, 1, 2, 3, 4], DatasetInput(scene_group=2))
    assert list(g.values()) == [[0, 1], [2, 3], [4]]
    m = tmp_path / "map.json"
    m.write_text(json.dumps({"kitchen": [0, 3], "desk": [1]}))
    g = scene_groups(10, [0, 1, 2, 3], DatasetInput(scene_map=load_scene_map(m)))
    assert g == {"kitchen": [0, 3], "desk": [1], "ep000002": [2]}
    m.write_text(json.dumps({"a": [0], "b": [0]}))
    with pytest.raises(AugmentError, match="episode 0 is in groups"):
        scene_groups(10, [0], DatasetInput(scene_map=load_scene_map(m)))
    m.write_text(json.dumps({"a": [12]}))
    with pytest.raises(AugmentError, match="outside"):
        scene_groups(10, [0], DatasetInput(scene_map=load_scene_map(m)))


def test_background_shell_in_front_of_cameras():
    from umi_aug.augment.dataset_source import background_shell_points
    from umi_aug.geometry import pos_rotvec_to_pose

    p6 = np.zeros((20, 6))
    p6[:, 0] = np.linspace(0, 0.4, 20)
    T = pos_rotvec_to_pose(p6)  # optical axes +z
    pts = background_shell_points(T, 500, 8.0, np.random.default_rng(0))
    c = T[:, :3, 3].mean(0)
    r = np.linalg.norm(pts - c, axis=1)
    assert len(pts) == 500 and np.allclose(r, r[0]) and r[0] == pytest.approx(8.0 * 0.5)  # spread 0.2 < 0.5 floor
    assert ((pts - c) @ np.array([0, 0, 1.0]) > -0.2 * r).all()


@pytest.mark.slow
def test_real_demonstration_end_to_end(tmp_path):
    """The real UMI episode → 1 free-space episode, validated: keys/dtypes/chunks kept, records, original copied,
    replayed tail. Cheap settings (the path, not the quality: benchmarks/real_umi.py measures that): a sparse
    triangulation (every 8th pre-closing frame), a 20-step 3DGS of ≤ 2000 Gaussians on every 4th
    view, a zarr directory output (no final zip rewrite)."""
    if not REAL.exists():
        pytest.skip(f"{REAL}: the real UMI demonstration lives in ../shared/realdata next to the repository "
                    "(not part of a clone); CI has it")
    from umi_aug.augment import AugmentConfig, SplatStageConfig
    from umi_aug.augment.dataset_source import DatasetInput
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.augment.exporter import export
    from umi_aug.data import ReplayBuffer, validate_replay_buffer

    out = tmp_path / "real_aug.zarr"
    cfg = AugmentConfig(mode="freespace", n_per_demo=1, seed=0,
                        splat=SplatStageConfig(iterations=20, max_gaussians=2000, sh_degree=0,
                                               extra={"train_eval_views": 2, "sheet_views": 1}))
    inp = DatasetInput(sfm_stride=8, view_stride=4, background_points=300)
    s = export(REAL, out, cfg, dataset_input=inp, progress=False)
    assert s.stages["ep000000/scene"]["skipped"] is False and s.stages["ep000000/splat"]["skipped"] is False
    # even 20 steps learn the scene: held-out (every 8th view, masked) ~15 dB; a constant mean colour scores ~10 dB,
    # a black render ~6.5 dB on these frames
    splat = json.loads((out.with_name(out.name + ".work") / "scenes/ep000000/splat/manifest.json").read_text())
    assert splat["info"]["trained"] and splat["info"]["heldout_psnr"] > 12.0
    assert s.n_failed == 0 and s.n_original == 1 and s.n_augmented == 1
    rep = validate_replay_buffer(out)
    assert rep.n_episodes == 2
    rec = read_episode_records(out)
    assert rec["aug_mode"].tolist() == [0, 1] and rec["aug_source_episode"].tolist() == [0, 0]
    with ReplayBuffer.open(REAL) as src, ReplayBuffer.open(out) as dst:
        assert dst.keys() == src.keys()
        for k in src.keys():
            assert dst[k].dtype == src[k].dtype and dst[k].chunks[1:] == src[k].chunks[1:], k
        assert dst["camera0_rgb"].chunks == src["camera0_rgb"].chunks
        np.testing.assert_array_equal(dst["camera0_rgb"][:400:50], src["camera0_rgb"][::50])
        np.testing.assert_array_equal(dst["robot0_eef_pos"][:400], src["robot0_eef_pos"][:])
        sl = dst.get_episode_slice(1)  # read what is checked, not the whole episode's frames (~3 s of decoding)
        new_pos = dst["robot0_eef_pos"][sl]
        splice = int(rec["aug_splice_index"][1])
        assert np.isfinite(new_pos).all() and dst["camera0_rgb"][sl.start:sl.start + splice:4].std() > 5
        # the augmented episode starts elsewhere and ends on the demonstration's replayed tail
        np.testing.assert_allclose(new_pos[-1], src["robot0_eef_pos"][399], atol=1e-5)
    assert Path(s.pictures["contact_sheet"]).is_file()


def _augment_parser_and_inputs(tmp_path):
    """``umi-aug augment``'s parser, an (empty) plain dataset file and a session folder, for config_from_args."""
    import argparse

    from umi_aug.augment.cli import add_augment_parser

    parser = argparse.ArgumentParser()
    add_augment_parser(parser.add_subparsers())
    ds = tmp_path / "dataset.zarr.zip"
    ds.write_bytes(b"")
    session = tmp_path / "session"
    (session / "demos").mkdir(parents=True)
    return parser, ds, session


def test_cli_3dgs_defaults_depend_on_the_input_kind(tmp_path):
    """A plain dataset gets the measured episode-frame 3DGS defaults, a session the scan defaults; explicit flags
    win over both."""
    from umi_aug.augment.cli import config_from_args
    from umi_aug.augment.config import (DATASET_SPLAT_COARSE_DOWNSCALE, DATASET_SPLAT_EVALUATION,
                                        DATASET_SPLAT_ITERATIONS, DATASET_SPLAT_MAX_GAUSSIANS,
                                        DATASET_SPLAT_SCALE_REG, DATASET_SPLAT_SCHEDULE, SESSION_SPLAT_SCALE_REG,
                                        AugmentConfig)
    from umi_aug.splat.train import SplatTrainConfig

    parser, ds, session = _augment_parser_and_inputs(tmp_path)
    base = AugmentConfig().splat
    cfg = config_from_args(parser.parse_args(["augment", str(ds), "--out", str(tmp_path / "o.zarr.zip")]))
    assert (cfg.splat.iterations, cfg.splat.max_gaussians) == (DATASET_SPLAT_ITERATIONS, DATASET_SPLAT_MAX_GAUSSIANS)
    assert cfg.splat.scale_reg == DATASET_SPLAT_SCALE_REG
    assert cfg.splat.coarse_downscale == DATASET_SPLAT_COARSE_DOWNSCALE == 2
    # the short schedule reaches the trainer, and it is a valid one
    tcfg = SplatTrainConfig(**cfg.splat.train_kwargs())
    tcfg.check()
    assert {k: getattr(tcfg, k) for k, _ in DATASET_SPLAT_SCHEDULE} == dict(DATASET_SPLAT_SCHEDULE)
    assert tcfg.lr_sh0 > SplatTrainConfig.lr_sh0 and tcfg.refine_every < SplatTrainConfig.refine_every
    assert (tcfg.eval_every, tcfg.eval_at_start) == (0, False)  # evaluated once, after the last step
    cfg = config_from_args(parser.parse_args(["augment", str(session), "--out", str(tmp_path / "o.zarr.zip")]))
    assert (cfg.splat.iterations, cfg.splat.max_gaussians) == (base.iterations, base.max_gaussians)
    assert cfg.splat.scale_reg == base.scale_reg == SESSION_SPLAT_SCALE_REG
    assert cfg.splat.coarse_downscale == base.coarse_downscale == 1
    assert cfg.splat.extra == {} and cfg.splat == base  # a session's scan keeps the trainer's schedule
    cfg = config_from_args(parser.parse_args(["augment", str(ds), "--out", "o.zarr.zip",
                                              "--splat-coarse-downscale", "1"]))
    assert cfg.splat.coarse_downscale == 1
    cfg = config_from_args(parser.parse_args(["augment", str(ds), "--out", "o.zarr.zip", "--splat-iterations", "7",
                                              "--splat-max-gaussians", "900"]))
    assert (cfg.splat.iterations, cfg.splat.max_gaussians) == (7, 900)
    # the flags change the steps, not the schedule or when it is evaluated
    assert cfg.splat.extra == {**dict(DATASET_SPLAT_SCHEDULE), **dict(DATASET_SPLAT_EVALUATION)}


def test_dataset_splat_stage_lays_given_fields_over_the_dataset_defaults():
    from umi_aug.augment.config import (DATASET_SPLAT_EVALUATION, DATASET_SPLAT_ITERATIONS, DATASET_SPLAT_SCHEDULE,
                                        dataset_splat_stage)

    assert dataset_splat_stage().iterations == DATASET_SPLAT_ITERATIONS
    assert dataset_splat_stage(iterations=None, coarse_downscale=None) == dataset_splat_stage()
    st = dataset_splat_stage(iterations=0, extra={"lr_sh0": 0.5, "seed": 3})
    assert st.iterations == 0  # 0 is given (the untrained init), not the default
    assert st.extra == {**dict(DATASET_SPLAT_SCHEDULE), **dict(DATASET_SPLAT_EVALUATION), "lr_sh0": 0.5, "seed": 3}
    assert dataset_splat_stage(extra={"eval_every": 100}).extra["eval_every"] == 100
    assert dataset_splat_stage().extra is not dataset_splat_stage().extra  # no shared mutable default


def test_train_py_aug_builds_the_scene_umi_aug_augment_builds(tmp_path):
    """``train.py aug=freespace`` (``aug.splat_*`` at their null defaults) trains each input's scene with exactly the
    3DGS stage ``umi-aug augment`` trains without 3DGS flags — the same stage key, so one cached scene serves both —
    and a given ``aug.splat_*`` value wins as the command line's flag does."""
    from umi_aug.augment.cli import config_from_args
    from umi_aug.augment.config import splat_key
    from umi_aug.policy.config import AugConfig
    from umi_aug.policy.workspace import aug_splat_stage

    parser, ds, session = _augment_parser_and_inputs(tmp_path)
    for src, plain in ((ds, True), (session, False)):
        cli = config_from_args(parser.parse_args(["augment", str(src), "--out", str(tmp_path / "o.zarr.zip")]))
        assert aug_splat_stage(AugConfig(), plain) == cli.splat
        assert splat_key(aug_splat_stage(AugConfig(), plain)) == splat_key(cli.splat)
        cli = config_from_args(parser.parse_args(["augment", str(src), "--out", "o.zarr.zip", "--splat-iterations",
                                                  "7", "--splat-coarse-downscale", "1"]))
        assert aug_splat_stage(AugConfig(splat_iterations=7, splat_coarse_downscale=1), plain) == cli.splat
    st = aug_splat_stage(AugConfig(splat_scale_reg=0.5, splat_max_gaussians=900), True)
    assert (st.scale_reg, st.max_gaussians, st.iterations) == (0.5, 900, aug_splat_stage(AugConfig(), True).iterations)


@pytest.mark.parametrize("group, pose_pairs, expected_m", [
    (1, None, 0.0),  # the default: sequential and loop-grid pairs only
    (2, None, 0.0),  # pooled episodes too (the loop grid spans them)
    (1, True, 0.25),  # asked for: every two frames within SfmConfig.pose_pair_max_dist_m
    (2, True, 0.25),
])
def test_triangulation_pose_pairs_only_when_asked(tmp_path, monkeypatch, good, group, pose_pairs, expected_m):
    """``DatasetInput.sfm_pose_pairs``: a dataset scene's known-pose triangulation (one episode or pooled) matches
    no pose pairs unless asked to (``SfmConfig.pose_pair_max_dist_m`` 0), whatever the caller's SfM config says."""
    import umi_aug.augment.dataset_source as ds
    from umi_aug.augment.config import AugmentConfig

    seen = []

    class Stop(Exception):
        pass

    def fake_run_sfm(paths, names, intr, work, cfg, **kw):
        seen.append((cfg.mode, cfg.pose_pair_max_dist_m, cfg.pose_pair_max_angle_deg))
        raise Stop

    monkeypatch.setattr(ds, "run_sfm", fake_run_sfm)
    path = _write(tmp_path / "d.zarr.zip", good[:2])
    with pytest.raises(Stop):
        ds.prepare_dataset(path, tmp_path / "work", AugmentConfig(image_size=S),
                           ds.DatasetInput(scene_group=group, background_points=0,
                                           **({} if pose_pairs is None else {"sfm_pose_pairs": pose_pairs})),
                           progress=False)
    assert seen[0] == ("known_poses", expected_m, 45.0)


@pytest.mark.parametrize("flag, expected", [(None, False), (True, True), (False, False)])
def test_triangulation_verifies_matches_by_the_known_poses_when_asked(tmp_path, monkeypatch, good, flag,
                                                                        expected):
    """``DatasetInput.sfm_known_pose_verification`` (default False: COLMAP's two-view RANSAC, the caller's
    ``SfmConfig`` default) reaches the triangulation's ``SfmConfig`` when asked for."""
    import umi_aug.augment.dataset_source as ds
    from umi_aug.augment.config import AugmentConfig

    seen = []

    class Stop(Exception):
        pass

    def fake_run_sfm(paths, names, intr, work, cfg, **kw):
        seen.append((cfg.mode, cfg.known_pose_verification))
        raise Stop

    monkeypatch.setattr(ds, "run_sfm", fake_run_sfm)
    path = _write(tmp_path / "d.zarr.zip", good[:2])
    with pytest.raises(Stop):
        ds.prepare_dataset(path, tmp_path / "work", AugmentConfig(image_size=S),
                           ds.DatasetInput(background_points=0,
                                           **({} if flag is None else {"sfm_known_pose_verification": flag})),
                           progress=False)
    assert seen[0] == ("known_poses", expected)
