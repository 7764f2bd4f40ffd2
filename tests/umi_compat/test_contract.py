"""Issue #30: the contract UMI's training path states for ``task.dataset`` (umi_stack.md §8), checked against
:class:`umi_aug.umi_compat.UmiAugDataset` — in CI from the facts, and against UMI's real classes where UMI's
``diffusion_policy`` package is importable (``conftest.UMI``)."""

from __future__ import annotations

import inspect
import pickle

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tests.umi_compat.conftest import LENGTHS, SIZE, UMI, umi_task_dataset_kwargs, write_dataset
from umi_aug.errors import PolicyError

#: UMI's ``UmiDataset.__init__`` parameters (name, default), in its order (umi_stack.md §8 + its signature)
UMI_PARAMS = [("shape_meta", inspect.Parameter.empty), ("dataset_path", inspect.Parameter.empty),
              ("cache_dir", None), ("pose_repr", {}), ("action_padding", False),
              ("temporally_independent_normalization", False), ("repeat_frame_prob", 0.0), ("seed", 42),
              ("val_ratio", 0.0), ("max_duration", None)]
STAT_NAMES = ("min", "max", "mean", "std")


def _cls():
    from umi_aug.umi_compat import UmiAugDataset

    return UmiAugDataset


def _instantiate(kwargs: dict, **extra):
    """Build the dataset as UMI's workspace does: ``hydra.utils.instantiate(cfg.task.dataset)`` on an OmegaConf
    node whose ``_target_`` is the one override."""
    import hydra
    from omegaconf import OmegaConf

    node = OmegaConf.create({"_target_": "umi_aug.umi_compat.UmiAugDataset", **kwargs, **extra})
    return hydra.utils.instantiate(node)


def _umi_val_mask(n_episodes: int, val_ratio: float, seed: int) -> np.ndarray:
    """UMI's ``get_val_mask`` as §8 states it: whole episodes, round(E·r) of them (at least 1, at most E-1),
    drawn with ``np.random.default_rng(seed).choice(E, n, replace=False)``."""
    mask = np.zeros(n_episodes, bool)
    if val_ratio <= 0:
        return mask
    n_val = min(max(1, round(n_episodes * val_ratio)), n_episodes - 1)
    mask[np.random.default_rng(seed=seed).choice(n_episodes, size=n_val, replace=False)] = True
    return mask


def _raw(path):
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(path) as buf:
        return {k: np.asarray(buf[k][:]) for k in buf.keys()}, buf.episode_ends


def _rel(pos: np.ndarray, rotvec: np.ndarray, base: np.ndarray) -> np.ndarray:
    """pos + rot6d (first two ROWS of R) of ``inv(T_base) @ T`` for 6-vectors ``[pos, rotvec]`` (float64)."""
    def mat(p, r):
        T = np.zeros(p.shape[:-1] + (4, 4))
        T[..., :3, :3] = Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(p.shape[:-1] + (3, 3))
        T[..., :3, 3] = p
        T[..., 3, 3] = 1
        return T

    rel = np.linalg.inv(mat(base[:3], base[3:])) @ mat(pos, rotvec)
    return np.concatenate([rel[..., :3, 3], rel[..., :2, :3].reshape(rel.shape[:-2] + (6,))], axis=-1)


# ---------------------------------------------------------------------------------------------- construction
def test_constructor_is_umis_signature_plus_keyword_only_aug_arguments():
    params = list(inspect.signature(_cls().__init__).parameters.values())[1:]
    head = [(p.name, p.default) for p in params[: len(UMI_PARAMS)]]
    assert head == UMI_PARAMS
    assert all(p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD for p in params[: len(UMI_PARAMS)])
    rest = params[len(UMI_PARAMS):]
    assert rest and all(p.kind is inspect.Parameter.KEYWORD_ONLY and p.default is not inspect.Parameter.empty
                        for p in rest)
    assert {"aug", "aug_ratio", "session_dir", "split_by"} <= {p.name for p in rest}
    if UMI:
        from diffusion_policy.dataset.umi_dataset import UmiDataset

        theirs = list(inspect.signature(UmiDataset.__init__).parameters.values())[1:]
        assert [(p.name, p.default) for p in theirs] == head


def test_task_umi_yaml_kwargs_build_it_and_pass_umis_type_check(umi_zip):
    ds = _instantiate(umi_task_dataset_kwargs(umi_zip))
    assert isinstance(ds, torch.utils.data.Dataset) and len(ds) > 0
    for name in ("get_validation_dataset", "get_normalizer", "get_all_actions", "__len__", "__getitem__"):
        assert callable(getattr(ds, name))
    if UMI:  # the workspace's own assertion, on UMI's real base classes
        from diffusion_policy.dataset.base_dataset import BaseDataset, BaseImageDataset

        assert isinstance(ds, BaseImageDataset) or isinstance(ds, BaseDataset)
    acts = ds.get_all_actions()
    assert acts.dtype == torch.float32 and tuple(acts.shape) == (len(ds), 16, 10)


# ---------------------------------------------------------------------------------------------- normaliser
def test_normalizer_has_umis_layout_and_values(umi_zip):
    ds = _instantiate(umi_task_dataset_kwargs(umi_zip))
    norm = ds.get_normalizer()
    if UMI:
        from diffusion_policy.model.common.normalizer import LinearNormalizer

        assert isinstance(norm, LinearNormalizer)
    sd = norm.state_dict()
    keys = ["action", "robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width",
            "robot0_eef_rot_axis_angle_wrt_start", "camera0_rgb"]
    want = {f"params_dict.{k}.{n}" for k in keys for n in ("scale", "offset")}
    want |= {f"params_dict.{k}.input_stats.{s}" for k in keys for s in STAT_NAMES}
    assert set(sd) == want
    assert all(v.dtype == torch.float32 for v in sd.values())
    dims = {"action": 10, "robot0_eef_pos": 3, "robot0_eef_rot_axis_angle": 6, "robot0_gripper_width": 1,
            "robot0_eef_rot_axis_angle_wrt_start": 6, "camera0_rgb": 1}
    for k, d in dims.items():
        assert all(sd[f"params_dict.{k}.{n}"].shape == (d,) for n in ("scale", "offset")), k
    # image identity
    img = {n: sd[f"params_dict.camera0_rgb.{n}"].tolist() for n in ("scale", "offset")}
    img.update({s: sd[f"params_dict.camera0_rgb.input_stats.{s}"].tolist() for s in STAT_NAMES})
    assert img["scale"] == [1.0] and img["offset"] == [0.0] and img["min"] == [0.0] and img["max"] == [1.0]
    assert img["mean"] == [0.5] and img["std"] == pytest.approx([np.sqrt(1 / 12)], rel=1e-6)
    # values: pooled over every (sample, time step) of the training split, as UMI's get_normalizer does
    pooled = {k: [] for k in dims if k != "camera0_rgb"}
    for i in range(len(ds)):
        s = ds[i]
        pooled["action"].append(s["action"].numpy())
        for k in pooled:
            if k != "action":
                pooled[k].append(s["obs"][k].numpy())
    pooled = {k: np.concatenate(v) for k, v in pooled.items()}  # [B·T, D]
    assert pooled["action"].shape == (len(ds) * 16, 10) and pooled["robot0_eef_pos"].shape == (len(ds) * 2, 3)
    for k, x in pooled.items():
        scale = sd[f"params_dict.{k}.scale"].numpy()
        offset = sd[f"params_dict.{k}.offset"].numpy()
        ranged = np.zeros(x.shape[1], bool)
        if k == "action":
            ranged[[0, 1, 2, 9]] = True
        elif k in ("robot0_eef_pos", "robot0_gripper_width"):
            ranged[:] = True
        if k != "robot0_eef_rot_axis_angle_wrt_start":  # its stats include UMI's random start-pose noise
            np.testing.assert_allclose(sd[f"params_dict.{k}.input_stats.min"].numpy(), x.min(0), atol=1e-6)
            np.testing.assert_allclose(sd[f"params_dict.{k}.input_stats.max"].numpy(), x.max(0), atol=1e-6)
            np.testing.assert_allclose(sd[f"params_dict.{k}.input_stats.mean"].numpy(), x.mean(0), atol=1e-5)
            np.testing.assert_allclose(sd[f"params_dict.{k}.input_stats.std"].numpy(), x.std(0), atol=1e-5)
        y = x * scale + offset
        const = (x.max(0) - x.min(0)) < 1e-7
        rng_dims = ranged & ~const
        np.testing.assert_allclose(y.min(0)[rng_dims], -1.0, atol=1e-4)  # pos / gripper → [-1, 1]
        np.testing.assert_allclose(y.max(0)[rng_dims], 1.0, atol=1e-4)
        assert np.all(scale[~ranged] == 1.0) and np.all(offset[~ranged] == 0.0), k  # rotation: identity
    # the state dict loads into a fresh normaliser of the same class (what the policy does), and pickles
    fresh = type(norm)()
    fresh.load_state_dict(sd)
    assert set(fresh.state_dict()) == set(sd)
    x = torch.from_numpy(pooled["action"][:5])
    np.testing.assert_allclose(fresh.normalize({"action": x})["action"].numpy(),
                               pooled["action"][:5] * sd["params_dict.action.scale"].numpy()
                               + sd["params_dict.action.offset"].numpy(), rtol=1e-6, atol=1e-6)
    again = pickle.loads(pickle.dumps(norm))
    assert all(torch.equal(again.state_dict()[k], v) for k, v in sd.items())


def test_own_normalizer_state_dict_loads_into_umis_layout_and_back():
    """Without UMI the class is umi-aug's; its state dict is UMI's layout, so one loads into the other."""
    from umi_aug.umi_compat.normalizer import UmiLayoutNormalizer, image_identity_field

    ours = UmiLayoutNormalizer()
    ours.set_field("camera0_rgb", image_identity_field())
    ours.set_field("x", {"scale": np.array([2.0, 1.0]), "offset": np.array([-1.0, 0.0]), "min": np.zeros(2),
                         "max": np.ones(2), "mean": np.full(2, 0.5), "std": np.full(2, 0.1)})
    sd = ours.state_dict()
    assert "params_dict.x.input_stats.std" in sd and "params_dict.camera0_rgb.scale" in sd
    back = UmiLayoutNormalizer()
    back.load_state_dict(sd)
    assert back.normalize(torch.tensor([[1.0, 3.0]]), "x").tolist() == [[1.0, 3.0]]
    if UMI:
        from diffusion_policy.model.common.normalizer import LinearNormalizer

        theirs = LinearNormalizer()
        theirs.load_state_dict(sd)
        assert theirs.normalize({"x": torch.tensor([[1.0, 3.0]])})["x"].tolist() == [[1.0, 3.0]]
        back2 = UmiLayoutNormalizer()
        back2.load_state_dict(theirs.state_dict())
        assert set(back2.state_dict()) == set(sd)


# ---------------------------------------------------------------------------------------------- samples
def test_samples_have_umis_format_and_relative_poses(umi_zip):
    ds = _instantiate(umi_task_dataset_kwargs(umi_zip))
    raw, ends = _raw(umi_zip)
    pose6 = np.concatenate([raw["robot0_eef_pos"], raw["robot0_eef_rot_axis_angle"]], 1).astype(np.float64)
    for i in (0, len(ds) // 2, len(ds) - 1):
        s = ds[i]
        assert set(s) == {"obs", "action"}
        obs = s["obs"]
        assert set(obs) == {"camera0_rgb", "robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width",
                            "robot0_eef_rot_axis_angle_wrt_start"}
        shapes = {k: tuple(v.shape) for k, v in obs.items()}
        assert shapes == {"camera0_rgb": (2, 3, SIZE, SIZE), "robot0_eef_pos": (2, 3),
                          "robot0_eef_rot_axis_angle": (2, 6), "robot0_gripper_width": (2, 1),
                          "robot0_eef_rot_axis_angle_wrt_start": (2, 6)}
        assert all(v.dtype == torch.float32 for v in obs.values()) and s["action"].dtype == torch.float32
        assert tuple(s["action"].shape) == (16, 10)
        img = obs["camera0_rgb"]
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
        # which raw row is "current": the last obs step's relative pose is the identity
        np.testing.assert_allclose(obs["robot0_eef_pos"][-1].numpy(), 0.0, atol=1e-6)
        np.testing.assert_allclose(obs["robot0_eef_rot_axis_angle"][-1].numpy(), [1, 0, 0, 0, 1, 0], atol=1e-6)
        cur = int(ds._train.indices[i, 0])
        start = int(ds._train.indices[i, 1])
        rows = np.clip([cur - 3, cur], start, None)
        want_obs = _rel(pose6[rows, :3], pose6[rows, 3:], pose6[cur])
        np.testing.assert_allclose(obs["robot0_eef_pos"].numpy(), want_obs[:, :3], atol=1e-5)
        np.testing.assert_allclose(obs["robot0_eef_rot_axis_angle"].numpy(), want_obs[:, 3:], atol=1e-5)
        np.testing.assert_allclose(obs["robot0_gripper_width"].numpy(), raw["robot0_gripper_width"][rows], atol=1e-7)
        a_rows = cur + 3 * np.arange(16)
        want_act = _rel(pose6[a_rows, :3], pose6[a_rows, 3:], pose6[cur])  # UMI: actions relative to T_cur
        np.testing.assert_allclose(s["action"][:, :9].numpy(), want_act, atol=1e-5)
        np.testing.assert_allclose(s["action"][:, 9].numpy(), raw["robot0_gripper_width"][a_rows, 0], atol=1e-7)
        # images: frames cur-3, cur (the first repeated at an episode start), channel-first, /255
        img_rows = [max(cur - 3, start) if cur - 3 >= start else cur, cur]
        np.testing.assert_allclose(img.numpy(), raw["camera0_rgb"][img_rows].transpose(0, 3, 1, 2) / 255.0,
                                   atol=1e-6)
        # wrt_start: rotation of the pose relative to the (noisy) demo start pose
        noise_free = _rel(pose6[rows, :3], pose6[rows, 3:], raw["robot0_demo_start_pose"][cur])[:, 3:]
        assert np.abs(obs["robot0_eef_rot_axis_angle_wrt_start"].numpy() - noise_free).max() < 0.6


# ---------------------------------------------------------------------------------------------- split
def test_split_is_umis_episode_split_and_validation_is_the_same_type(umi_zip):
    ds = _instantiate(umi_task_dataset_kwargs(umi_zip))
    val = ds.get_validation_dataset()
    assert type(val) is type(ds) and val.n_augmented == 0 and len(val) > 0
    ends = np.cumsum(LENGTHS)
    ep_of = lambda rows: set(np.searchsorted(ends, rows, side="right").tolist())  # noqa: E731
    train_eps, val_eps = ep_of(ds._train.indices[:, 0]), ep_of(val._train.indices[:, 0])
    mask = _umi_val_mask(len(LENGTHS), 0.05, 42)
    assert val_eps == set(np.flatnonzero(mask).tolist())
    assert train_eps == set(np.flatnonzero(~mask).tolist())
    span = 15 * 3 + 1
    assert len(ds) == sum(n - span + 1 for n, m in zip(LENGTHS, mask) if not m)
    s = val[0]
    assert tuple(s["action"].shape) == (16, 10)


def test_split_by_source_demo_keeps_a_demo_and_its_augmentations_together(tmp_path, rng):
    """Issue #30 item 5: UMI's seed-42 episode split can put the only original of a small export into validation;
    ``split_by="source_demo"`` splits whole source demos (``meta/aug_source_episode``)."""
    lengths = (50,) * 9
    path = write_dataset(tmp_path / "export.zarr.zip", rng, lengths=lengths, source_episode=[0] * 9)
    by_episode = _instantiate(umi_task_dataset_kwargs(path))
    val_eps = set(np.flatnonzero(_umi_val_mask(9, 0.05, 42)).tolist())
    assert val_eps == {0}  # the export's original demo (episode 0) is UMI's validation episode
    assert len(by_episode.get_validation_dataset()) == 5 * len(val_eps)  # some episode of the one demo in val
    by_source = _instantiate(umi_task_dataset_kwargs(path), split_by="source_demo")
    assert len(by_source) == 9 * 5 and len(by_source.get_validation_dataset()) == 0  # one source: all train
    path2 = write_dataset(tmp_path / "export2.zarr.zip", rng, lengths=lengths, source_episode=[0, 1, 2] * 3)
    two = _instantiate(umi_task_dataset_kwargs(path2), split_by="source_demo")
    val_src = np.flatnonzero(_umi_val_mask(3, 0.05, 42))
    assert len(val_src) == 1
    v = two.get_validation_dataset()
    assert len(v) == 3 * 5 and len(two) == 6 * 5
    rows = v._train.indices[:, 0]
    assert set((rows // 50 % 3).tolist()) == set(val_src.tolist())  # episode e has source e % 3


# ---------------------------------------------------------------------------------------------- options
@pytest.mark.parametrize("override, name", [
    ({"max_duration": 10.0}, "max_duration"),
    ({"temporally_independent_normalization": True}, "temporally_independent_normalization"),
    ({"pose_repr": {"obs_pose_repr": "rel", "action_pose_repr": "rel"}}, "pose_repr.obs_pose_repr"),
    ({"pose_repr": {}}, "pose_repr.obs_pose_repr"),
    ({"shape_meta.obs.robot0_eef_pos.latency_steps": 2.0}, "shape_meta.obs.robot0_eef_pos.latency_steps"),
    ({"shape_meta.obs.robot0_eef_pos_wrt1": {"shape": [3], "horizon": 2, "latency_steps": 0,
                                             "down_sample_steps": 3, "type": "low_dim"}},
     "shape_meta.obs.robot0_eef_pos_wrt1"),
    ({"shape_meta.action.down_sample_steps": 1}, "down_sample_steps"),
    ({"repeat_frame_prob": 1.5}, "repeat_frame_prob"),
])
def test_unimplemented_umi_options_are_refused_with_one_error(umi_zip, override, name):
    kw = umi_task_dataset_kwargs(umi_zip)
    for k, v in override.items():
        if k.startswith("shape_meta."):
            *path, last = k.split(".")[1:]
            node = kw["shape_meta"]
            for p in path:
                node = node[p]
            node[last] = v
        else:
            kw[k] = v
    with pytest.raises(PolicyError, match=name.replace(".", r"\.")):
        _cls()(**kw)


def test_repeat_frame_prob_repeats_the_current_step_before_the_first_grasp(umi_zip):
    ds = _instantiate(umi_task_dataset_kwargs(umi_zip), repeat_frame_prob=1.0)
    plain = _instantiate(umi_task_dataset_kwargs(umi_zip))
    flags = ds._before_grasp
    assert flags.any() and (~flags).any()
    for i in (int(np.flatnonzero(flags)[-1]), int(np.flatnonzero(~flags)[0])):
        s, p = ds[i], plain[i]
        for k, v in s["obs"].items():
            if k.endswith("wrt_start"):
                continue  # noisy
            want = p["obs"][k][-1:].expand_as(v) if flags[i] else p["obs"][k]
            torch.testing.assert_close(v, want, atol=1e-6, rtol=0)
        torch.testing.assert_close(s["action"], p["action"])
        # UMI's rule: a grasp is a robot0 width < 0.08 m at or before the current row
        cur, start = ds._train.indices[i, :2]
        assert flags[i] == bool(np.all(ds._train.gripper[0][start:cur + 1, 0] >= 0.08))


def test_cache_dir_copies_the_zip_once_and_gives_the_same_samples(umi_zip, tmp_path):
    kw = umi_task_dataset_kwargs(umi_zip)
    cached = _cls()(**{**kw, "cache_dir": str(tmp_path / "cache")})
    made = sorted(p.name for p in (tmp_path / "cache").iterdir() if p.name.endswith(".zarr"))
    assert len(made) == 1 and made[0].startswith("dataset_")
    plain = _cls()(**kw)
    assert len(cached) == len(plain)
    torch.testing.assert_close(cached[3]["obs"]["camera0_rgb"], plain[3]["obs"]["camera0_rgb"])
    _cls()(**{**kw, "cache_dir": str(tmp_path / "cache")})  # reused, not copied again
    assert sorted(p.name for p in (tmp_path / "cache").iterdir() if p.name.endswith(".zarr")) == made


# ---------------------------------------------------------------------------------------------- UMI's own class
@pytest.mark.skipif(not UMI, reason="UMI's diffusion_policy is not importable (put a UMI checkout on PYTHONPATH)")
def test_same_samples_split_and_normalizer_as_umis_own_umidataset(umi_zip):
    from diffusion_policy.dataset.umi_dataset import UmiDataset

    kw = umi_task_dataset_kwargs(umi_zip)
    ours, theirs = _instantiate(kw), UmiDataset(**kw)
    assert len(ours) == len(theirs)
    assert np.array_equal(ours._train.val_mask, theirs.val_mask)
    assert len(ours.get_validation_dataset()) == len(theirs.get_validation_dataset())
    for i in (0, 7, len(ours) - 1):
        a, b = ours[i], theirs[i]
        assert set(a["obs"]) == set(b["obs"])
        for k in a["obs"]:
            assert a["obs"][k].dtype == b["obs"][k].dtype and a["obs"][k].shape == b["obs"][k].shape, k
            if not k.endswith("wrt_start"):  # noisy on both sides
                torch.testing.assert_close(a["obs"][k], b["obs"][k], atol=2e-6, rtol=0)
        torch.testing.assert_close(a["action"], b["action"], atol=2e-6, rtol=0)
    import diffusion_policy.dataset.umi_dataset as umi_mod

    # UMI's get_normalizer iterates with 32 DataLoader workers; one process here (same batches, same result)
    orig_loader = torch.utils.data.DataLoader
    umi_mod.torch.utils.data.DataLoader = lambda dataset, **k: orig_loader(dataset, **{**k, "num_workers": 0})
    try:
        n_theirs = theirs.get_normalizer().state_dict()
    finally:
        umi_mod.torch.utils.data.DataLoader = orig_loader
    n_ours = ours.get_normalizer().state_dict()
    assert set(n_ours) == set(n_theirs)
    worst = 0.0
    for k, v in n_theirs.items():
        if "wrt_start.input_stats" in k:  # statistics of UMI's random start-pose noise
            continue
        worst = max(worst, float((n_ours[k] - v).abs().max()))
        torch.testing.assert_close(n_ours[k], v, atol=1e-5, rtol=1e-5, msg=k)
    print(f"normaliser max |ours - UMI's| = {worst:.3g}")


# ---------------------------------------------------------------------------------------------- epochs
class _FakeAugmented:
    """The part of :class:`AugmentedUmiDataset` that :class:`UmiAugDataset` draws augmented slots from, without a
    prepared session: an augmented sample is an original one whose action holds the drawn augmentation id."""

    def __init__(self, original, n_augmented: int) -> None:
        from types import SimpleNamespace

        self.original, self.n_augmented = original, n_augmented
        self.demos, self.modes, self.n_aug_per_demo, self.seed = [0, 1], ("freespace",), 1000, 0
        self.assets = SimpleNamespace(umi_episode=lambda ep, d: {"robot0_gripper_width": np.full((60, 1), 0.085)})

    def draw(self, rng):
        return (self.demos[int(rng.integers(len(self.demos)))], int(rng.integers(self.n_aug_per_demo)),
                self.modes[int(rng.integers(len(self.modes)))])

    def planned(self, demo, aug_id, mode):
        from types import SimpleNamespace

        return SimpleNamespace(n_frames=60, episode=None, demo_index=demo)

    def n_current_steps(self, n_frames: int) -> int:
        return n_frames - 45

    def augmented_sample(self, demo, aug_id, mode, cur, rng):
        s = self.original[0]
        s["action"] = torch.full_like(s["action"], float(aug_id))
        return s

    def normalizer_dataset(self):
        return self.original


def _with_fake_aug(ds, n: int):
    ds._aug = _FakeAugmented(ds._train, n)
    ds._visits = torch.zeros(n, dtype=torch.int64).share_memory_()
    return ds


@pytest.mark.parametrize("workers", [0, 1])
def test_augmented_draws_advance_every_epoch_without_set_epoch(umi_zip, workers):
    """UMI's workspace builds its DataLoader once (persistent workers) and never calls set_epoch: each pass over
    the data must still draw new augmented samples (the per-slot visit counter lives in shared memory)."""
    n_aug = 6
    ds = _with_fake_aug(_instantiate(umi_task_dataset_kwargs(umi_zip)), n_aug)
    n_orig = len(ds) - n_aug
    assert ds.epoch == 0
    # as UMI's workspace: one shuffled loader, persistent workers, three passes, nothing called between them
    loader = torch.utils.data.DataLoader(ds, batch_size=16, shuffle=True, num_workers=workers,
                                         persistent_workers=workers > 0)
    for epoch in range(3):
        for _ in loader:
            pass
        assert ds.epoch == epoch + 1  # every slot drawn once more, counted in this process too
    # the draws of slots 0..5 in three passes (an ordered loader over the augmented slots only)
    ds.set_epoch(0)
    order = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, range(n_orig, len(ds))), batch_size=n_aug,
                                        num_workers=workers, persistent_workers=workers > 0)
    per_epoch = [next(iter(order))["action"][:, 0, 0].tolist() for _ in range(3)]
    assert per_epoch[0] != per_epoch[1] and per_epoch[1] != per_epoch[2]  # new draws each pass
    assert ds.epoch == 3
    ds.set_epoch(1)  # the same pass draws the same samples again
    assert next(iter(order))["action"][:, 0, 0].tolist() == per_epoch[1]


def test_configs_umi_dataset_block_names_every_argument_with_its_default():
    """configs/umi/umi_aug_dataset.yaml (the block a UMI user pastes over task/umi.yaml's) stays in step with the
    class: every constructor argument, UMI's with task/umi.yaml's values, umi-aug's with their defaults."""
    from pathlib import Path

    from omegaconf import OmegaConf

    node = OmegaConf.load(Path(__file__).parents[2] / "configs" / "umi" / "umi_aug_dataset.yaml")["dataset"]
    raw = OmegaConf.to_container(node, resolve=False)
    assert raw.pop("_target_") == "umi_aug.umi_compat.UmiAugDataset"
    params = list(inspect.signature(_cls().__init__).parameters.values())[1:]
    assert sorted(raw) == sorted(p.name for p in params)  # (task/umi.yaml lists max_duration before seed)
    assert raw["shape_meta"] == "${task.shape_meta}" and raw["pose_repr"] == "${task.pose_repr}"
    task_values = {k: v for k, v in umi_task_dataset_kwargs("x").items() if k not in ("shape_meta", "pose_repr")}
    for p in params:
        if p.name in ("shape_meta", "pose_repr", "dataset_path"):
            continue
        want = task_values[p.name] if p.name in task_values else p.default
        assert raw[p.name] == want, p.name
