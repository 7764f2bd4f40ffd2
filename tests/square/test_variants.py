"""The square study's variants (issue #15) from one export: ``ours``, ``gt_render`` and ``action_only`` share every
pose/width/record array and differ only in the new frames; ``none`` is the source demos; ``spartn`` labels bring
the perturbed pose back onto the original trajectory. The export here is hand-built (same layout and records as
:func:`umi_aug.augment.export` writes), so the test needs no scene model."""

from __future__ import annotations

import numpy as np
import pytest

S = 32
T_CAM_TCP = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0.05], [0, 0, 1.0, 0.097], [0, 0, 0, 1.0]])


def _fresh_rng():
    seed = int(np.random.SeedSequence().entropy % (2**32))
    print(f"seed {seed}")
    return np.random.default_rng(seed)


def _frames(rng, n: int, tag: int) -> np.ndarray:
    yy, xx = np.mgrid[0:S, 0:S] / S
    out = np.empty((n, S, S, 3), np.uint8)
    for i in range(n):
        base = np.stack([np.sin((2 + c + tag) * 2 * np.pi * xx + (1 + i % 5) * yy + c) for c in range(3)], -1)
        out[i] = np.clip(127.5 * (base + 1) + rng.normal(0, 4, base.shape), 0, 255).astype(np.uint8)
    return out


def _camera_path(rng, n: int) -> np.ndarray:
    from umi_aug.geometry import so3_exp

    T = np.tile(np.eye(4), (n, 1, 1))
    p0, p1 = rng.uniform(-0.2, 0.2, 3) + [0, 0, 1.0], rng.uniform(-0.1, 0.1, 3) + [0, 0, 0.9]
    w0 = rng.normal(size=3)
    for i in range(n):
        s = i / max(1, n - 1)
        T[i, :3, 3] = (1 - s) * p0 + s * p1
        T[i, :3, :3] = so3_exp(w0 * 0.3 * (1 - s)) @ np.diag([1.0, -1.0, -1.0])
    return T


def _episode(T_cam: np.ndarray, width: np.ndarray, frames: np.ndarray) -> dict:
    from umi_aug.data import make_umi_episode
    from umi_aug.geometry.umi import tcp_poses_from_camera_poses

    return make_umi_episode(tcp_poses_from_camera_poses(T_cam, T_CAM_TCP), width, {0: frames})


@pytest.fixture()
def fake_export(tmp_path):
    """3 source demos + 2 augmented episodes each: records as the exporter writes them."""
    from umi_aug.augment.export_store import RECORD_CHUNK, RECORD_KEYS
    from umi_aug.data import ReplayBuffer

    rng = _fresh_rng()
    buf = ReplayBuffer.create()
    demos, rec = [], {k: [] for k in RECORD_KEYS}
    for d in range(3):
        n, s = 40 + 3 * d, 20 + d
        T, w = _camera_path(rng, n), np.full(n, 0.08)
        w[s + 3:] = 0.02
        F = _frames(rng, n, d)
        buf.add_episode(_episode(T, w, F))
        demos.append((T, w, F, s))
        for k, v in {"aug_source_episode": d, "aug_mode": 0, "aug_id": -1, "aug_seed": 0, "aug_attempts": 1,
                     "aug_splice_index": s, "aug_job": -1}.items():
            rec[k].append(v)
    job = 0
    for d, (T, w, F, s) in enumerate(demos):
        for a in range(2):
            k_new = 12 + a
            Tn = np.concatenate([_camera_path(rng, k_new), T[s:]])
            wn = np.concatenate([np.full(k_new, w[s]), w[s:]])
            Fn = np.concatenate([_frames(rng, k_new, 7 + a), F[s:]])
            buf.add_episode(_episode(Tn, wn, Fn))
            for k, v in {"aug_source_episode": d, "aug_mode": 0, "aug_id": a, "aug_seed": 123 + a,
                         "aug_attempts": 1, "aug_splice_index": k_new, "aug_job": job}.items():
                rec[k].append(v)
            job += 1
    for k, dt in RECORD_KEYS.items():
        buf.meta.array(k, np.asarray(rec[k], dtype=dt), chunks=(RECORD_CHUNK,), compressor=None)
    buf.root.attrs["T_cam_tcp"] = T_CAM_TCP.tolist()
    path = tmp_path / "ours_export.zarr.zip"
    buf.save(path)
    return path, demos


def _read(path):
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(path) as b:
        data = {k: np.asarray(b[k][:]) for k in b.keys()}
        ends = np.asarray(b.episode_ends)
        attrs = dict(b.root.attrs)
    return data, ends, read_episode_records(path), attrs


def _stored_chunks(path, key="camera0_rgb") -> list[bytes]:
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(path) as b:
        a = b[key]
        return [a.store[a._chunk_key((i, 0, 0, 0))] for i in range(a.shape[0])]


def test_variants_share_poses_and_differ_only_in_new_frames(fake_export, tmp_path):
    from umi_aug.square.variants import action_only_sources, write_variant

    src, demos = fake_export
    gt_calls = []

    def gt_render(e, info):  # the simulator's frames in the study; here a recognisable constant
        gt_calls.append((e, info["n_new"]))
        assert info["T_world_cam"].shape == (len(info["rows"]), 4, 4)
        return np.full((info["n_new"], S, S, 3), 200, np.uint8)

    out = {v: tmp_path / f"{v}.zarr.zip" for v in ("none", "ours", "gt_render", "action_only")}
    for v, p in out.items():
        write_variant(v, src, p, 2, render_new=gt_render if v == "gt_render" else None, progress=False)
    full = {v: _read(p) for v, p in out.items()}
    d_ours, e_ours, r_ours, _ = full["ours"]
    assert len(e_ours) == 2 + 4  # 2 source demos + their 2 augmentations each
    for v in ("gt_render", "action_only"):
        d, e, r, attrs = full[v]
        np.testing.assert_array_equal(e, e_ours)
        for k in d_ours:
            if k != "camera0_rgb":
                np.testing.assert_array_equal(d[k], d_ours[k], err_msg=f"{v}: {k}")
        for k in r_ours:
            np.testing.assert_array_equal(r[k], r_ours[k])
        assert attrs["umi_aug_variant"]["variant"] == v
    # images: equal outside the augmented episodes' new frames, different inside
    starts = np.concatenate([[0], e_ours[:-1]])
    new_rows = np.concatenate([np.arange(starts[i], starts[i] + r_ours["aug_splice_index"][i])
                               for i in range(len(e_ours)) if r_ours["aug_id"][i] >= 0])
    same = np.setdiff1d(np.arange(e_ours[-1]), new_rows)
    chunks = {v: _stored_chunks(p) for v, p in out.items()}
    for v in ("gt_render", "action_only"):
        assert all(chunks[v][i] == chunks["ours"][i] for i in same), v  # copied as stored
        assert not np.array_equal(full[v][0]["camera0_rgb"][new_rows], d_ours["camera0_rgb"][new_rows])
    assert (np.abs(full["gt_render"][0]["camera0_rgb"][new_rows].astype(int) - 200) <= 3).all()
    assert sorted(gt_calls) == [(3, 12), (4, 13), (5, 12), (6, 13)]  # export rows of demos 0, 1
    # action_only shows the source demo's frame at the same progress (its stored chunk)
    for i in range(len(e_ours)):
        if r_ours["aug_id"][i] < 0:
            continue
        o = int(r_ours["aug_source_episode"][i])
        src_rows = starts[o] + action_only_sources(int(r_ours["aug_splice_index"][i]), demos[o][3])
        for k, row in zip(range(starts[i], starts[i] + len(src_rows)), src_rows):
            assert chunks["action_only"][k] == chunks["ours"][row]
    # none: the source demos only, byte-identical
    d_none, e_none, r_none, _ = full["none"]
    np.testing.assert_array_equal(e_none, e_ours[:2])
    assert chunks["none"] == chunks["ours"][: e_ours[1]]
    assert (r_none["aug_id"] < 0).all()


def test_action_only_sources_map_progress():
    from umi_aug.square.variants import action_only_sources

    np.testing.assert_array_equal(action_only_sources(4, 8), [0, 2, 4, 6])
    np.testing.assert_array_equal(action_only_sources(5, 2), [0, 0, 1, 1, 2])  # round half to even
    assert action_only_sources(0, 9).shape == (0,)


def test_spartn_labels_bring_the_perturbed_pose_back_onto_the_trajectory(fake_export, tmp_path):
    from umi_aug.geometry import pos_rotvec_to_pose, so3_log
    from umi_aug.geometry.umi import camera_poses_from_tcp_poses
    from umi_aug.square.variants import SpartnConfig, spartn_perturbation, write_variant

    src, demos = fake_export
    cfg = SpartnConfig(stride=3, per_step=2, trans_m=0.03, rot_deg=15.0, obs_horizon=2, action_horizon=16, seed=5)
    seen = []

    def render(e, info):
        seen.append((e, info["overlay_rows"].tolist()))
        return np.full((len(info["T_world_cam"]), S, S, 3), 50, np.uint8)

    out = tmp_path / "spartn.zarr.zip"
    summ = write_variant("spartn", src, out, 2, render_new=render, spartn=cfg, progress=False)
    d, ends, rec, attrs = _read(out)
    starts = np.concatenate([[0], ends[:-1]])
    T = camera_poses_from_tcp_poses(pos_rotvec_to_pose(np.concatenate(
        [d["robot0_eef_pos"], d["robot0_eef_rot_axis_angle"]], 1).astype(np.float64)), T_CAM_TCP)
    steps = {0: range(1, demos[0][3], 3), 1: range(1, demos[1][3], 3)}
    n_expect = sum(len(v) for v in steps.values()) * cfg.per_step
    assert (rec["aug_id"] == -2).sum() == n_expect == summ["augmented"]
    assert len(seen) == n_expect
    i = 0
    for demo in (0, 1):
        T_o = demos[demo][0]
        assert rec["aug_id"][i] == -1 and rec["aug_source_episode"][i] == demo  # the demo, then its SPARTN ones
        i += 1
        for t in steps[demo]:
            for j in range(cfg.per_step):
                a, b = starts[i], ends[i]
                assert b - a == cfg.obs_horizon - 1 + cfg.action_horizon
                delta = spartn_perturbation(cfg, demo, t, j)
                assert np.linalg.norm(delta[:3, 3]) <= cfg.trans_m + 1e-9
                assert np.linalg.norm(so3_log(delta[:3, :3])) <= np.deg2rad(cfg.rot_deg) + 1e-9
                # observed frames t-1, t: perturbed (float32 storage: ~1e-6 m)
                np.testing.assert_allclose(T[a:a + 2], T_o[t - 1:t + 1] @ delta, atol=2e-5)
                # the action targets 1.. (rows t+1 ..): the ORIGINAL trajectory, relative to the perturbed pose
                rel = np.linalg.inv(T[a + 1]) @ T[a + 2:b]
                np.testing.assert_allclose(T[a + 1] @ rel, T_o[t + 1:t + cfg.action_horizon], atol=2e-5)
                np.testing.assert_allclose(T[a + 2:b], T_o[t + 1:t + cfg.action_horizon], atol=2e-5)
                # perturbed frames are the renders, the rest the demo's own frames
                assert (np.abs(d["camera0_rgb"][a:a + 2].astype(int) - 50) <= 3).all()
                i += 1
    assert i == len(ends)


def _episodes(path) -> list[dict[str, np.ndarray]]:
    """Every episode of a variant dataset: its data arrays, its records and its sample step."""
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.schema import SAMPLE_STEP_KEY

    d, ends, rec, _ = _read(path)
    with ReplayBuffer.open(path) as b:
        steps = (np.asarray(b.meta[SAMPLE_STEP_KEY][:]) if SAMPLE_STEP_KEY in set(b.meta.array_keys())
                 else np.full(len(ends), -1))
    starts = np.concatenate([[0], ends[:-1]])
    return [{**{k: v[a:b] for k, v in d.items()}, **{f"rec/{k}": np.asarray(v[e]) for k, v in rec.items()},
             "step": np.asarray(steps[e])} for e, (a, b) in enumerate(zip(starts, ends))]


def test_ours_spartn_is_ours_plus_the_spartn_samples_byte_for_byte(fake_export, tmp_path):
    from umi_aug.square.variants import SpartnConfig, write_variant

    src, demos = fake_export
    cfg = SpartnConfig(stride=2, per_step=2, seed=11)
    render = lambda e, info: np.full((len(info["T_world_cam"]), S, S, 3), 70, np.uint8)  # noqa: E731
    paths = {v: tmp_path / f"{v}.zarr.zip" for v in ("ours", "spartn", "ours_spartn")}
    summ = {v: write_variant(v, src, p, 2, render_new=render if v != "ours" else None, spartn=cfg, progress=False)
            for v, p in paths.items()}
    eps = {v: _episodes(p) for v, p in paths.items()}
    both = eps["ours_spartn"]
    samples = [e for e in both if e["rec/aug_id"] == -2]
    assert len(samples) > 0 and summ["ours_spartn"]["frames_new"] == summ["spartn"]["frames_new"] > 0
    assert summ["ours_spartn"]["augmented"] == summ["ours"]["augmented"] + summ["spartn"]["augmented"]
    for got, want in ((
            [e for e in both if e["rec/aug_id"] != -2], eps["ours"]),
            (samples, [e for e in eps["spartn"] if e["rec/aug_id"] == -2])):
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert g.keys() == w.keys()
            for k in g:
                np.testing.assert_array_equal(g[k], w[k], err_msg=k)
    assert all(e["step"] >= 0 for e in samples) and all(e["step"] == -1 for e in both if e["rec/aug_id"] != -2)
    with pytest.raises(Exception, match="needs render_new"):
        write_variant("ours_spartn", src, tmp_path / "x.zarr.zip", 2, progress=False)


def test_spartn_window_of_the_policy_dataset_is_corrective(fake_export, tmp_path):
    """Through the training dataset itself: at the perturbed current step, target 0 is the perturbed pose and
    targets 1.. lie on the original trajectory (relative pose representation composed back)."""
    from umi_aug.geometry import pos_rotvec_to_pose
    from umi_aug.geometry.umi import tcp_poses_from_camera_poses
    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.pose_repr import model_actions_to_abs
    from umi_aug.square.variants import SpartnConfig, write_variant

    src, demos = fake_export
    cfg = SpartnConfig(stride=50, per_step=1, obs_horizon=2, action_horizon=16, seed=1)
    out = tmp_path / "spartn.zarr.zip"
    write_variant("spartn", src, out, 1, render_new=lambda e, info: np.zeros((2, S, S, 3), np.uint8), spartn=cfg,
                  progress=False)
    task = TaskConfig(dataset_path=str(out), image_size=S, obs_down_sample_steps=1, val_ratio=0.0)
    ds = UmiPolicyDataset(out, task, split="all")
    ends = np.asarray(ds.episode_ends)
    idx = np.flatnonzero(ds.indices[:, 0] == ends[0] + 1)  # current row = the perturbed frame t of the 1st one
    assert len(idx) == 1
    # each SPARTN short episode is ONE sample (its perturbed step), the source demo one per step
    starts = np.concatenate([[0], ends[:-1]])
    per_episode = np.bincount(np.searchsorted(ends, ds.indices[:, 0], side="right"), minlength=len(ends))
    assert per_episode[0] == ends[0] - (task.action_horizon - 1) * (1 - task.action_padding) \
        and (per_episode[1:] == 1).all() and len(ends) > 1
    assert set(ds.indices[:, 0][np.searchsorted(ends, ds.indices[:, 0], side="right") > 0]) == set(starts[1:] + 1)
    # the marker survives a data-size cut and is checked when read
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.schema import SAMPLE_STEP_KEY
    from umi_aug.errors import PolicyError
    from umi_aug.square.variants import subset_variant

    cut = tmp_path / "cut.zarr.zip"
    subset_variant(out, cut, 1, progress=False)
    assert np.array_equal(UmiPolicyDataset(cut, task, split="all").indices, ds.indices)
    b2 = ReplayBuffer.open(out, mode="a", load_to_memory=True)  # writable in-memory copy
    steps = np.asarray(b2.meta[SAMPLE_STEP_KEY][:])
    steps[-1] = 40
    b2.meta[SAMPLE_STEP_KEY][:] = steps
    bad = tmp_path / "bad.zarr.zip"
    b2.save(bad)
    with pytest.raises(PolicyError, match=rf"'meta/{SAMPLE_STEP_KEY}'\[{len(ends) - 1}\] = 40 is not a step"):
        UmiPolicyDataset(bad, task, split="all")
    action = ds.lowdim_batch(idx)["action"][0]  # [16, 10] relative to the (perturbed) current pose
    d, _, _, _ = _read(out)
    T_tcp = pos_rotvec_to_pose(np.concatenate([d["robot0_eef_pos"], d["robot0_eef_rot_axis_angle"]], 1)
                               .astype(np.float64))
    T_cur = T_tcp[ends[0] + 1]
    absolute = model_actions_to_abs(action, T_cur)  # [16, 7] pos, rotvec, width
    T_abs = pos_rotvec_to_pose(absolute[:, :6])
    T_demo_tcp = tcp_poses_from_camera_poses(demos[0][0], T_CAM_TCP)
    t = 1  # first perturbed step of demo 0 (obs_horizon - 1)
    np.testing.assert_allclose(T_abs[0], T_cur, atol=1e-5)  # target 0: the perturbed current pose
    np.testing.assert_allclose(T_abs[1:], T_demo_tcp[t + 1:t + 16], atol=5e-5)  # back on the demo
    assert np.linalg.norm(T_cur[:3, 3] - T_demo_tcp[t][:3, 3]) > 1e-4  # and the current pose was really off it


def test_variant_refuses_to_overwrite_its_source(fake_export):
    from umi_aug.errors import AugmentError
    from umi_aug.square.variants import write_variant

    src, _ = fake_export
    before = src.read_bytes()
    with pytest.raises(AugmentError, match="is the source export itself"):
        write_variant("ours", src, src, 1, progress=False)
    with pytest.raises(AugmentError, match="variant 'oracle'"):
        write_variant("oracle", src, src.with_name("x.zarr.zip"), 1, progress=False)
    with pytest.raises(AugmentError, match="n_demos = 4; the export holds 3"):
        write_variant("none", src, src.with_name("x.zarr.zip"), 4, progress=False)
    assert src.read_bytes() == before and not src.with_name("x.zarr.zip").exists()


def test_subset_of_a_variant_equals_the_variant_of_fewer_demos(fake_export, tmp_path):
    """A smaller data size cut from a larger variant dataset holds the same bytes as that variant written for the
    smaller size directly (so the study renders gt_render / spartn once, for its largest size)."""
    from umi_aug.square.variants import SpartnConfig, subset_variant, write_variant

    src, _ = fake_export
    cfg = SpartnConfig(stride=4, seed=2)
    render = {"gt_render": lambda e, info: np.full((info["n_new"], S, S, 3), 90, np.uint8),
              "spartn": lambda e, info: np.full((len(info["T_world_cam"]), S, S, 3), 40, np.uint8),
              "ours_spartn": lambda e, info: np.full((len(info["T_world_cam"]), S, S, 3), 45, np.uint8),
              "action_only": None}
    for v, fn in render.items():
        big, direct, cut = (tmp_path / f"{v}_{k}.zarr.zip" for k in ("n3", "n2", "cut2"))
        write_variant(v, src, big, 3, render_new=fn, spartn=cfg, progress=False)
        write_variant(v, src, direct, 2, render_new=fn, spartn=cfg, progress=False)
        summ = subset_variant(big, cut, 2, progress=False)
        assert summ["variant"] == v and summ["n_demos"] == 2
        a, b = _read(direct), _read(cut)
        np.testing.assert_array_equal(a[1], b[1])
        for k in a[0]:
            np.testing.assert_array_equal(a[0][k], b[0][k], err_msg=f"{v}: {k}")
        for k in a[2]:
            np.testing.assert_array_equal(a[2][k], b[2][k])
        assert _stored_chunks(direct) == _stored_chunks(cut)


def test_ours_with_fewer_augmented_episodes_per_demo(fake_export, tmp_path):
    """``per_demo=k`` keeps every demo and each demo's first k augmented episodes, episode for episode the bytes of
    the full ``ours``; ``per_demo=0`` is ``none``; a negative count is refused."""
    from umi_aug.errors import AugmentError
    from umi_aug.square.variants import write_variant

    src, _ = fake_export
    full, one, zero, none = (tmp_path / f"{k}.zarr.zip" for k in ("full", "k1", "k0", "none"))
    write_variant("ours", src, full, 3, progress=False)
    summ = write_variant("ours", src, one, 3, progress=False, per_demo=1)
    write_variant("ours", src, zero, 3, progress=False, per_demo=0)
    write_variant("none", src, none, 3, progress=False)
    a, k1 = _read(full), _read(one)
    assert summ["per_demo"] == 1 and summ["augmented"] == 3 and summ["episodes"] == 6
    kept = [e for e in range(len(a[1])) if a[2]["aug_id"][e] < 1]
    assert list(k1[2]["aug_id"]) == [a[2]["aug_id"][e] for e in kept]
    starts = np.concatenate([[0], a[1][:-1]])
    rows = np.concatenate([np.arange(starts[e], a[1][e]) for e in kept])
    for k in a[0]:
        np.testing.assert_array_equal(k1[0][k], a[0][k][rows], err_msg=k)
    z, n = _read(zero), _read(none)
    np.testing.assert_array_equal(z[1], n[1])
    for k in n[0]:
        np.testing.assert_array_equal(z[0][k], n[0][k])
    with pytest.raises(AugmentError, match="per_demo = -1"):
        write_variant("ours", src, tmp_path / "bad.zarr.zip", 3, progress=False, per_demo=-1)
    assert not (tmp_path / "bad.zarr.zip").exists()


def test_frames_sheet_pairs_the_right_frames(fake_export, tmp_path):
    """The study's picture of what each variant trains on: the panels are the datasets' own frames, and each SPARTN
    perturbed frame is shown beside the source frame it perturbs (checked through the stored poses)."""
    from umi_aug.data import ReplayBuffer
    from umi_aug.geometry import pos_rotvec_to_pose
    from umi_aug.geometry.umi import camera_poses_from_tcp_poses
    from umi_aug.square.report import frames_sheet_panels, write_frames_sheet
    from umi_aug.square.study import StudyConfig
    from umi_aug.square.variants import SpartnConfig, spartn_perturbation, write_variant

    src, demos = fake_export
    cfg = StudyConfig(out_dir=str(tmp_path / "study"), sizes=[3], report_png=str(tmp_path / "fig.png"))
    data = cfg.out / "data"
    data.mkdir(parents=True)
    sp = SpartnConfig(stride=3, per_step=2, seed=4)
    const = {"gt_render": 200, "spartn": 50}
    assert frames_sheet_panels(cfg) is None  # nothing written yet
    for v in ("ours", "gt_render", "action_only", "spartn"):
        write_variant(v, src, data / f"{v}_n3.zarr.zip", 3, spartn=sp, progress=False,
                      render_new=None if v in ("ours", "action_only") else
                      (lambda e, info, c=const[v]: np.full((info.get("n_new", len(info["T_world_cam"])), S, S, 3), c,
                                                           np.uint8)))
        if v == "ours":
            assert frames_sheet_panels(cfg) is None  # ours without its oracle: nothing to compare
        if v == "gt_render":  # the later variants' datasets are not there yet: their panels are left out
            early = frames_sheet_panels(cfg)
            assert len(early) == 3 and all(len(row) == 2 * 3 for row in early)
            assert {p["title"].split(": ")[1] for row in early for p in row} == {"ours", "gt_render", "|ours-gt| x3"}
    panels = frames_sheet_panels(cfg)
    assert [len(row) for row in panels[:3]] == [2 * 4] * 3
    for row, row_early in zip(panels[:3], early):  # the same episodes and frames, with action_only added
        kept = [p for p in row if not p["title"].endswith("action_only")]
        assert [p["title"] for p in kept] == [p["title"] for p in row_early]
        for p, q in zip(kept, row_early):
            np.testing.assert_array_equal(p["image"], q["image"])
    assert len(panels) == 4  # 3 demos with augmented episodes + the SPARTN row
    for row in panels[:3]:
        gt = [p for p in row if p["title"].endswith("gt_render")]
        assert len(gt) == 2 and all(np.abs(p["image"].astype(int) - 200).max() <= 2 for p in gt)  # lossy codec
    spartn = panels[-1]
    with ReplayBuffer.open(data / "spartn_n3.zarr.zip") as b, ReplayBuffer.open(src) as s:
        ends = np.asarray(b.episode_ends)
        pose = lambda buf, r: camera_poses_from_tcp_poses(pos_rotvec_to_pose(np.concatenate(  # noqa: E731
            [buf["robot0_eef_pos"][r], buf["robot0_eef_rot_axis_angle"][r]])[None].astype(np.float64)), T_CAM_TCP)[0]
        s_ends = np.asarray(s.episode_ends)
        for orig, pert in zip(spartn[0::2], spartn[1::2]):
            assert orig["kind"] == "original" and pert["kind"] == "perturbed"
            assert np.abs(pert["image"].astype(int) - 50).max() <= 2
            d, t, e = orig["demo"], orig["t"], orig["episode"]
            row0 = int(s_ends[d - 1]) if d else 0
            np.testing.assert_array_equal(orig["image"], np.asarray(s["camera0_rgb"][row0 + t]))
            start = int(ends[e - 1]) if e else 0
            delta = spartn_perturbation(sp, d, t, orig["j"])
            np.testing.assert_allclose(pose(b, start + sp.obs_horizon - 1), demos[d][0][t] @ delta, atol=2e-5)
    out = write_frames_sheet(cfg)
    assert out is not None and out.endswith("fig_frames.jpg")
    from PIL import Image

    assert Image.open(out).size[0] > 800


def test_fidelity_compares_the_same_new_frames(fake_export, tmp_path):
    """``ours`` vs ``gt_render`` fidelity (the study's rendering-quality numbers): PSNR / SSIM over exactly the new
    frames of the episodes both datasets hold, paired by (source demo, augmentation id); against a plain numpy
    PSNR over the image circle, and with the gt datasets' episodes in another order."""
    from umi_aug.camera.kb import unproject
    from umi_aug.data import ReplayBuffer
    from umi_aug.square.camera import wrist_intrinsics
    from umi_aug.square.report import fidelity
    from umi_aug.square.variants import write_variant

    src, demos = fake_export
    ours, gt = tmp_path / "ours.zarr.zip", tmp_path / "gt.zarr.zip"
    rng = _fresh_rng()
    write_variant("ours", src, ours, 3, progress=False)
    write_variant("gt_render", src, gt, 3, progress=False,
                  render_new=lambda e, info: np.clip(_frames(rng, info["n_new"], 3).astype(int)
                                                     + rng.integers(-40, 40, (info["n_new"], S, S, 3)), 0, 255
                                                     ).astype(np.uint8))
    intr = wrist_intrinsics(S)
    vv, uu = np.mgrid[0:S, 0:S]
    circle = unproject(np.stack([uu, vv], -1).astype(np.float64), intr)[1]
    ref = []
    with ReplayBuffer.open(ours) as a, ReplayBuffer.open(gt) as b:
        ends = np.asarray(a.episode_ends)
        np.testing.assert_array_equal(ends, np.asarray(b.episode_ends))
        _, _, rec, _ = _read(ours)
        for e in range(len(ends)):
            if rec["aug_id"][e] < 0:
                continue
            s0 = int(ends[e - 1]) if e else 0
            for r in range(s0, s0 + int(rec["aug_splice_index"][e])):
                d = (np.asarray(a["camera0_rgb"][r], np.float64) - np.asarray(b["camera0_rgb"][r], np.float64)) / 255
                ref.append(-10 * np.log10(np.mean(d[circle] ** 2)))
    got = fidelity(ours, gt, max_frames=10_000)
    assert got["frames"] == len(ref) == 6 * 12 + 3  # 2 augmentations of 12 / 13 new frames per demo
    assert got["psnr_median"] == pytest.approx(np.median(ref), abs=1e-9)
    assert got["psnr_p5"] == pytest.approx(np.percentile(ref, 5), abs=1e-9)
    assert 0 < got["ssim_p5"] <= got["ssim_median"] < 0.99
    same = fidelity(ours, ours)
    assert same["psnr_median"] == same["psnr_p5"] == float("inf") and same["ssim_p5"] == pytest.approx(1.0)
    # pairing is by (source demo, aug id), not by row: the demo-0-only gt dataset pairs its own 25 new frames
    write_variant("gt_render", src, tmp_path / "gt1.zarr.zip", 1, progress=False,
                  render_new=lambda e, info: np.zeros((info["n_new"], S, S, 3), np.uint8))
    assert fidelity(ours, tmp_path / "gt1.zarr.zip")["frames"] == 25


def test_ours_rerender_adds_each_demo_again_as_rendered_and_skips_its_replayed_tail(fake_export, tmp_path):
    """``ours_rerender`` = ``ours`` + each source demo once more, right after it: the same low-dim rows and
    records but ``aug_mode`` 3 / ``aug_id`` 0, its pre-splice frames from ``render_new`` at the demo's own poses
    (with the gripper of the same frames), the rest copied as stored; the training dataset leaves out its
    replayed-tail samples like an augmented episode's, and keeps its rendered approach."""
    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset, replayed_tail_first_sample
    from umi_aug.square.variants import RERENDER_MODE_CODE, subset_variant, write_variant

    src, demos = fake_export
    calls = []

    def render(source, info):
        calls.append(source)
        np.testing.assert_allclose(info["T_world_cam"], demos[source][0][: info["splice"]], atol=1e-5)
        np.testing.assert_array_equal(info["overlay_rows"], np.arange(info["splice"]))
        return np.full((len(info["T_world_cam"]), S, S, 3), 90, np.uint8)

    paths = {v: tmp_path / f"{v}.zarr.zip" for v in ("ours", "ours_rerender")}
    summ = {v: write_variant(v, src, p, 2, render_new=render if v == "ours_rerender" else None, progress=False)
            for v, p in paths.items()}
    assert calls == [0, 1]
    ours, rr = _episodes(paths["ours"]), _episodes(paths["ours_rerender"])
    extra = [i for i, e in enumerate(rr) if e["rec/aug_mode"] == RERENDER_MODE_CODE]
    assert extra == [1, 3] and len(rr) == len(ours) + 2  # each right after its source demo
    assert summ["ours_rerender"]["frames_new"] == sum(d[3] for d in demos[:2])
    assert summ["ours_rerender"]["augmented"] == summ["ours"]["augmented"] + 2
    rest = [e for i, e in enumerate(rr) if i not in extra]
    for g, w in zip(rest, ours):  # ours, episode for episode
        for k in w:
            np.testing.assert_array_equal(g[k], w[k], err_msg=k)
    chunks_rr, chunks_ours = _stored_chunks(paths["ours_rerender"]), _stored_chunks(paths["ours"])
    d_rr, ends_rr, _, _ = _read(paths["ours_rerender"])
    starts_rr = np.concatenate([[0], ends_rr[:-1]])
    for i, d in zip(extra, (0, 1)):
        e, orig, s = rr[i], rr[i - 1], demos[d][3]
        assert int(e["rec/aug_source_episode"]) == d and int(e["rec/aug_id"]) == 0
        assert int(e["rec/aug_splice_index"]) == s and int(e["step"]) == -1
        for k in e:
            if k != "camera0_rgb" and not k.startswith("rec/") and k != "step":
                np.testing.assert_array_equal(e[k], orig[k], err_msg=k)
        assert (np.abs(e["camera0_rgb"][:s].astype(int) - 90) <= 3).all()
        assert not np.array_equal(e["camera0_rgb"][:s], orig["camera0_rgb"][:s])
        o0 = starts_rr[i - 1]
        assert all(chunks_rr[starts_rr[i] + t] == chunks_rr[o0 + t] for t in range(s, len(e["camera0_rgb"])))
    assert chunks_rr[: ends_rr[0]] == chunks_ours[: ends_rr[0]]
    # the policy dataset: its tail is the source's; without re-sampled tails only its approach is sampled
    task = TaskConfig(dataset_path=str(paths["ours_rerender"]), image_size=S, obs_down_sample_steps=1,
                      val_ratio=0.0, sample_replayed_tails=False)
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(paths["ours_rerender"]) as b:
        first, source = replayed_tail_first_sample(b, paths["ours_rerender"], task)
    assert list(source[extra]) == [0, 2] and (first[extra] > 0).all()
    ds = UmiPolicyDataset(paths["ours_rerender"], task, split="all")
    ep_of = np.searchsorted(ends_rr, ds.indices[:, 0], side="right")
    for i in extra:
        cur = ds.indices[ep_of == i, 0] - starts_rr[i]
        assert len(cur) > 0 and cur.max() < first[i] and cur.min() == 0
    # a data-size cut keeps them (every episode of the first demos, as stored)
    cut = tmp_path / "cut.zarr.zip"
    subset_variant(paths["ours_rerender"], cut, 1, progress=False)
    assert [int(e["rec/aug_mode"]) for e in _episodes(cut)].count(RERENDER_MODE_CODE) == 1
    with pytest.raises(Exception, match="needs render_new"):
        write_variant("ours_rerender", src, tmp_path / "x.zarr.zip", 2, progress=False)
