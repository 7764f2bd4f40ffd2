"""A plain dataset's scenes build as tasks of their own ahead of their episodes (issue #34 item 3): a Ray export
with two workers — two scenes built at once, one thread each — writes the same bytes as the one-process run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.augment.test_export import _all_arrays

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"


@pytest.fixture(scope="module")
def two_scene_dataset(tmp_path_factory) -> Path:
    """The real UMI episode twice: two episodes, so two scene groups (one scene per episode by default)."""
    if not REAL.exists():
        pytest.skip(f"{REAL}: the real UMI demonstration lives in ../shared/realdata next to the repository "
                    "(not part of a clone); CI has it")
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(REAL) as src:
        ep = src.get_episode(0)
    buf = ReplayBuffer.create()
    for _ in range(2):
        buf.add_episode(ep)
    return buf.save(tmp_path_factory.mktemp("two_scenes") / "two.zarr.zip")


def _cheap_export(dataset: Path, out: Path, **executor):
    from umi_aug.augment import AugmentConfig, SplatStageConfig
    from umi_aug.augment.dataset_source import DatasetInput
    from umi_aug.augment.exporter import export

    cfg = AugmentConfig(mode="freespace", n_per_demo=2, seed=0, **executor,
                        splat=SplatStageConfig(iterations=10, max_gaussians=1500, sh_degree=0,
                                               extra={"train_eval_views": 1, "sheet_views": 1}))
    inp = DatasetInput(sfm_stride=12, view_stride=6, background_points=200)
    return export(dataset, out, cfg, dataset_input=inp, progress=False, pictures=False)


@pytest.mark.slow
def test_ray_builds_the_scenes_in_parallel_and_writes_the_same_bytes(two_scene_dataset, tmp_path):
    pytest.importorskip("ray", reason="Ray is the optional scale-out executor (extra 'ray', in the README install)")
    one = _cheap_export(two_scene_dataset, tmp_path / "one.zarr")
    par = _cheap_export(two_scene_dataset, tmp_path / "ray.zarr", executor="ray", workers=2)
    for s in (one, par):
        assert s.n_failed == 0 and s.n_original == 2 and s.n_augmented == 4
        assert {"ep000000/scene", "ep000001/scene"} <= set(s.stages)
    assert par.timings_s["scene_s"] > 0  # the two builds' seconds reached the summary
    d1, m1 = _all_arrays(tmp_path / "one.zarr")
    d2, m2 = _all_arrays(tmp_path / "ray.zarr")
    assert d1.keys() == d2.keys() and m1.keys() == m2.keys()
    for k in d1:
        assert np.array_equal(d1[k], d2[k]), k  # scenes built on 1 thread each vs 2 threads: the same bytes
    for k in m1:
        assert np.array_equal(m1[k], m2[k]), k
    for g in ("ep000000", "ep000001"):  # and the same scene files (their manifests differ: seconds)
        for name in ("scene/scene_cloud.ply", "sdf/scene_sdf.npz", "contact/contacts.json", "splat/scene.ply",
                     "gripper_mask/mask.npy"):
            a = (tmp_path / "one.zarr.work" / "scenes" / g / name).read_bytes()
            b = (tmp_path / "ray.zarr.work" / "scenes" / g / name).read_bytes()
            assert a == b, (g, name)


def test_a_scene_built_where_this_machine_cannot_see_it_is_named(tmp_path):
    """A cluster node that built a scene into a work folder the driver does not share: one line naming both."""
    from umi_aug.augment.exporter import _check_scene_visible
    from umi_aug.errors import AugmentError

    _check_scene_visible("ep000000", {"folder": str(tmp_path), "host": "node7", "seconds": 1.0})  # visible: fine
    with pytest.raises(AugmentError, match=r"scene ep000001 was built on node7 into .*/elsewhere/ep000001, which "
                                           r"this machine .* cannot see: .*--work"):
        _check_scene_visible("ep000001", {"folder": str(tmp_path / "elsewhere" / "ep000001"), "host": "node7",
                                          "seconds": 1.0})
