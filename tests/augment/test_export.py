"""Offline export: UMI-compatible output, per-episode records, resume after a killed export."""

from __future__ import annotations

import numpy as np
import pytest

from tests.augment.conftest import SIZE, small_config


def _cfg():
    return small_config(mode="freespace", n_per_demo=3)


def _all_arrays(path):
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(path) as buf:
        data = {k: np.asarray(buf[k][:]) for k in buf.keys()}
        meta = {k: np.asarray(buf.meta[k][:]) for k in buf.meta.array_keys()}
    return data, meta


@pytest.fixture(scope="module")
def clean_export(aug_session, aug_work, tmp_path_factory):
    """An uninterrupted export (directory store) of 1 original + 3 free-space episodes."""
    from umi_aug.augment import export

    out = tmp_path_factory.mktemp("export_clean") / "aug.zarr"
    summary = export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=False)
    return out, summary


def test_export_is_umi_compatible_with_records(clean_export, aug_session):
    from umi_aug.augment import read_episode_records
    from umi_aug.data import ReplayBuffer, validate_replay_buffer

    out, s = clean_export
    assert (s.n_original, s.n_augmented, s.n_failed, s.n_jobs) == (1, 3, 0, 3)
    report = validate_replay_buffer(out)
    assert report.n_episodes == 4
    rec = read_episode_records(out)
    assert rec["aug_mode"].tolist() == [0, 1, 1, 1]
    assert rec["aug_id"].tolist() == [-1, 0, 1, 2] and rec["aug_source_episode"].tolist() == [0, 0, 0, 0]
    assert rec["aug_job"].tolist() == [-1, 0, 1, 2] and np.all(rec["aug_attempts"] >= 1)
    assert len(set(rec["aug_seed"][1:].tolist())) == 3
    with ReplayBuffer.open(out) as buf, ReplayBuffer.open(aug_session / "dataset.zarr.zip") as src:
        assert sorted(buf.keys()) == sorted(src.keys())  # UMI's keys only in data/
        assert buf["camera0_rgb"].shape[1:] == (SIZE, SIZE, 3)
        orig = src.get_episode(0)
        got = buf.get_episode(0)
        for k in orig:
            assert np.array_equal(orig[k], got[k]), k  # the original episode copied exactly
        for e in (1, 2, 3):  # the replayed tail shows the original frames
            ep = buf.get_episode(e, ["camera0_rgb", "robot0_gripper_width"])
            sp = int(rec["aug_splice_index"][e])
            n_tail = len(ep["camera0_rgb"]) - sp
            assert np.array_equal(ep["camera0_rgb"][sp:], orig["camera0_rgb"][-n_tail:])
            assert np.array_equal(ep["robot0_gripper_width"][sp:], orig["robot0_gripper_width"][-n_tail:])


def test_resume_after_killed_export_has_no_duplicate_or_missing_episode(clean_export, aug_session, aug_work,
                                                                       tmp_path, monkeypatch):
    from umi_aug.augment import export
    from umi_aug.data import ReplayBuffer

    out = tmp_path / "aug.zarr.zip"
    partial = tmp_path / "aug.zarr.zip.partial"
    calls = {"n": 0}
    orig_commit = ReplayBuffer._commit_episode_end

    def killed(self, new_end):
        calls["n"] += 1
        if calls["n"] == 2:  # the 2nd augmented episode: data written, episode end never committed
            raise KeyboardInterrupt("killed mid-append")
        return orig_commit(self, new_end)

    with monkeypatch.context() as m:
        m.setattr(ReplayBuffer, "_commit_episode_end", killed)
        with pytest.raises(KeyboardInterrupt):
            export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=False)
    assert partial.is_dir() and not out.exists()
    import zarr

    root = zarr.open_group(str(partial), mode="r")
    ends = root["meta/episode_ends"][:]
    assert len(ends) == 2  # original + one committed augmented episode
    assert root["data/camera0_rgb"].shape[0] > ends[-1]  # a truncated append is left behind
    assert root["meta/aug_job"].shape[0] == 3  # and its record

    s = export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=False)
    assert s.resumed_jobs == 1 and s.n_augmented == 3 and not partial.exists()
    d_clean, m_clean = _all_arrays(clean_export[0])
    d_res, m_res = _all_arrays(out)
    assert sorted(d_clean) == sorted(d_res) and sorted(m_clean) == sorted(m_res)
    for k in d_clean:
        assert np.array_equal(d_clean[k], d_res[k]), k  # same bytes as the uninterrupted export
    for k in m_clean:
        assert np.array_equal(m_clean[k], m_res[k]), k
    # a second run finds the finished export and does nothing
    again = export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=False)
    assert again.resumed_jobs == again.n_jobs == 3 and again.n_augmented == 3


def test_resume_after_an_exception_between_episodes(aug_session, aug_work, tmp_path, monkeypatch):
    import importlib

    from umi_aug.augment import read_episode_records

    ex = importlib.import_module("umi_aug.augment.exporter")  # the module (the package re-exports `export`)

    out = tmp_path / "aug.zarr"
    calls = {"n": 0}
    real = ex.render_episode_frames

    def dying(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("worker died")
        return real(*a, **k)

    with monkeypatch.context() as m:
        m.setattr(ex, "render_episode_frames", dying)
        with pytest.raises(RuntimeError):
            ex.export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=False)
    assert read_episode_records(out)["aug_job"].tolist() == [-1, 0, 1]
    s = ex.export(aug_session, out, _cfg(), work_dir=aug_work, progress=False, pictures=True)
    assert s.resumed_jobs == 2 and read_episode_records(out)["aug_job"].tolist() == [-1, 0, 1, 2]
    assert {"contact_sheet"} <= set(s.pictures) and any(k.startswith("trajectories/") for k in s.pictures)
    assert (tmp_path / "aug.zarr.summary.json").is_file()


def test_export_refuses_another_configuration(clean_export, aug_session, aug_work):
    from umi_aug.augment import export
    from umi_aug.errors import AugmentError

    with pytest.raises(AugmentError, match="another configuration"):
        export(aug_session, clean_export[0], small_config(mode="freespace", n_per_demo=3, seed=99),
               work_dir=aug_work, progress=False, pictures=False)


def test_rerender_originals_adds_each_demo_again_with_its_approach_rendered(clean_export, aug_session, aug_work,
                                                                            tmp_path):
    """``rerender_originals``: per augmentable demo one more episode ahead of its augmented ones (records: mode 3,
    ``aug_id`` 0, its contact frame as splice), whose low-dim rows are the original's exactly, whose frames from
    the splice on are the original's stored chunks, and whose approach frames are the scene model's renders at the
    demo's own poses (JPEG-XL decoded: near the render, not the recorded frame); the augmented episode of the same
    job is the one exported without it; the policy dataset leaves its replayed tail out."""
    from umi_aug.augment import export, prepare_session, read_episode_records
    from umi_aug.augment.plan import MODE_CODES, rerender_episode
    from umi_aug.augment.render import render_episode_frames
    from umi_aug.data import ReplayBuffer, validate_replay_buffer
    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import first_tail_only_step, replayed_tail_first_sample

    cfg = small_config(mode="freespace", n_per_demo=1, rerender_originals=True)
    out = tmp_path / "rr.zarr"
    s = export(aug_session, out, cfg, work_dir=aug_work, progress=False, pictures=False)
    assert (s.n_original, s.n_rerendered, s.n_augmented, s.n_failed, s.n_jobs) == (1, 1, 1, 0, 2)
    assert validate_replay_buffer(out).n_episodes == 3
    rec = read_episode_records(out)
    assert rec["aug_mode"].tolist() == [0, MODE_CODES["rerender"], MODE_CODES["freespace"]]
    assert rec["aug_id"].tolist() == [-1, 0, 0] and rec["aug_job"].tolist() == [-1, 0, 1]
    assets = prepare_session(aug_session, aug_work, cfg, progress=False)
    c = int(assets.demos[0].contact_index)
    assert rec["aug_splice_index"][1] == c == rec["aug_splice_index"][0]
    with ReplayBuffer.open(out) as buf, ReplayBuffer.open(aug_session / "dataset.zarr.zip") as src, \
            ReplayBuffer.open(clean_export[0]) as clean:
        orig, again = src.get_episode(0), buf.get_episode(1)
        for k in orig:
            if k != "camera0_rgb":
                assert again[k].dtype == orig[k].dtype and np.array_equal(again[k], orig[k]), k
        assert np.array_equal(again["camera0_rgb"][c:], orig["camera0_rgb"][c:])
        sl_b, sl_s = buf.get_episode_slice(1), src.get_episode_slice(0)
        for i in (c, sl_s.stop - sl_s.start - 1):  # the tail's chunks copied as stored
            assert (buf["camera0_rgb"].store[buf["camera0_rgb"]._chunk_key((sl_b.start + i, 0, 0, 0))]
                    == src["camera0_rgb"].store[src["camera0_rgb"]._chunk_key((sl_s.start + i, 0, 0, 0))])
        rendered = render_episode_frames(assets, rerender_episode(assets, 0), range(c)).astype(np.float64)
        got = again["camera0_rgb"][:c].astype(np.float64)
        to_render = np.abs(got - rendered).mean()
        to_recorded = np.abs(got - orig["camera0_rgb"][:c]).mean()
        assert np.isfinite(to_render) and to_render < 3.0 and to_recorded > 2.0 * to_render, (to_render, to_recorded)
        first_aug, clean_aug = buf.get_episode(2), clean.get_episode(1)  # job (0, freespace, 0) in both
        for k in first_aug:
            assert np.array_equal(first_aug[k], clean_aug[k]), k
        task = TaskConfig(dataset_path=str(out), image_size=SIZE, sample_replayed_tails=False)
        first, source = replayed_tail_first_sample(buf, out, task)
    assert source.tolist() == [-1, 0, 0] and first[1] == first_tail_only_step(task, c)
    with pytest.raises(Exception, match="another configuration"):  # the option is part of the run's key
        export(aug_session, out, small_config(mode="freespace", n_per_demo=1), work_dir=aug_work, progress=False,
               pictures=False)


def test_cli_parses_into_a_config():
    import argparse

    from umi_aug.augment.cli import add_augment_parser, config_from_args

    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers()
    add_augment_parser(sub)
    args = ap.parse_args(["augment", "S", "--mode", "both", "-n", "7", "--out", "o.zarr.zip", "--seed", "5",
                          "--image-size", "96", "--obstacle", "box", "--obstacle", "mug", "--splat-iterations", "0"])
    cfg = config_from_args(args)
    assert (cfg.mode, cfg.n_per_demo, cfg.seed, cfg.image_size) == ("both", 7, 5, 96)
    assert cfg.obstacle.assets == ("box", "mug") and cfg.splat.iterations == 0
    assert args.func.__name__ == "cmd_augment" and not cfg.rerender_originals
    rr = config_from_args(ap.parse_args(["augment", "S", "--out", "o.zarr", "--rerender-originals"]))
    assert rr.rerender_originals


@pytest.mark.slow  # spawns 2 worker processes (torch + numba imports)
def test_two_worker_processes_write_the_same_dataset(clean_export, aug_session, aug_work, tmp_path):
    from umi_aug.augment import export

    out = tmp_path / "aug.zarr"
    cfg = small_config(mode="freespace", n_per_demo=3, workers=2)
    s = export(aug_session, out, cfg, work_dir=aug_work, progress=False, pictures=False)
    assert s.n_augmented == 3
    d_clean, m_clean = _all_arrays(clean_export[0])
    d_par, m_par = _all_arrays(out)
    for k in d_clean:
        assert np.array_equal(d_clean[k], d_par[k]), k
    for k in m_clean:
        assert np.array_equal(m_clean[k], m_par[k]), k


@pytest.mark.slow  # starts a local Ray cluster (~5 s) with 2 worker processes
def test_ray_executor_writes_the_same_dataset(clean_export, aug_session, aug_work, tmp_path):
    pytest.importorskip("ray", reason="Ray is the optional scale-out executor (extra 'ray', in the README install)")
    from umi_aug.augment import export

    out = tmp_path / "aug_ray.zarr"
    cfg = small_config(mode="freespace", n_per_demo=3, executor="ray", workers=2)
    s = export(aug_session, out, cfg, work_dir=aug_work, progress=False, pictures=False)
    assert s.n_augmented == 3
    d_clean, m_clean = _all_arrays(clean_export[0])
    d_ray, m_ray = _all_arrays(out)
    assert d_clean.keys() == d_ray.keys() and m_clean.keys() == m_ray.keys()
    for k in d_clean:
        assert np.array_equal(d_clean[k], d_ray[k]), k
    for k in m_clean:
        assert np.array_equal(m_clean[k], m_ray[k]), k
