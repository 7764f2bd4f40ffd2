"""One small synthetic session and its prepared assets, shared by every augment test (built once per session)."""

from __future__ import annotations

import importlib.util
import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

#: Policy image side of the test session (small: renders and JPEG-XL encodes stay cheap).
SIZE = 64


def small_config(**kw):
    """The tests' :class:`AugmentConfig`: untrained SfM-initialised scene, 64² images, a box obstacle."""
    from umi_aug.augment import AugmentConfig, ObstacleConfig, SplatStageConfig
    from umi_aug.recon import ReconConfig, SfmConfig

    base = dict(mode="both", n_per_demo=2, seed=3, image_size=SIZE, max_attempts=6,
                splat=SplatStageConfig(iterations=0, sh_degree=0),
                recon=ReconConfig(sfm=SfmConfig(mode="known_poses", max_num_features=512), scan_stride=1,
                                  demo_stride=8, max_voxels=400_000),
                obstacle=ObstacleConfig(assets=("box", "bottle"), fit_gaussians=False, n_gaussians=800))
    base.update(kw)
    return AugmentConfig(**base)


@pytest.fixture(scope="session")
def aug_session(tmp_path_factory):
    """Synthetic UMI session: 30 scan frames + 1 demo at 320x240, dataset at 64² (~20 s on 2 cores)."""
    if importlib.util.find_spec("mujoco") is None:  # MuJoCo must be imported through umi_aug.sim.gl
        pytest.skip("mujoco (sim extra) not installed")
    from umi_aug.sim.gl import import_mujoco

    import_mujoco()
    from umi_aug.sim.session import make_session

    out = tmp_path_factory.mktemp("aug_session") / "session"
    make_session(out, 0, n_demos=1, scan_frames=30, policy_size=SIZE, benchmark_frames=0, progress=False)
    return out


@pytest.fixture(scope="session")
def aug_work(tmp_path_factory):
    return tmp_path_factory.mktemp("aug_work")


@pytest.fixture(scope="session")
def aug_assets(aug_session, aug_work):
    """All session stages of the small config (reconstruction ~25 s, the rest a few seconds)."""
    from umi_aug.augment import prepare_session

    return prepare_session(aug_session, aug_work, small_config(), progress=False)
