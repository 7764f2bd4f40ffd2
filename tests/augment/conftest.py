"""One small synthetic session and its prepared assets, shared by every augment test (built once per session)."""

from __future__ import annotations

import os


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


# the session fixtures built from it (aug_session, aug_work, aug_assets) live in tests/conftest.py so that tests
# outside tests/augment (tests/policy) share the same instances instead of building them again
