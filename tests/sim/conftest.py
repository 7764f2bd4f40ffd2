"""Fixtures of the sim tests. The GL backend is chosen BEFORE MuJoCo is imported (umi_aug.sim.gl)."""

from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")

_MUJOCO = importlib.util.find_spec("mujoco") is not None
_GL_ERROR: str | None = None
if _MUJOCO:
    from umi_aug.errors import SimError
    from umi_aug.sim.gl import select_gl_backend

    try:
        select_gl_backend()
    except SimError as exc:  # pragma: no cover - machine without any offscreen GL
        _GL_ERROR = str(exc)


def pytest_collection_modifyitems(config, items):
    if _MUJOCO:
        return
    here = os.path.dirname(__file__)
    for item in items:
        if str(item.fspath).startswith(here) and not item.name.startswith("test_gl_"):
            item.add_marker(pytest.mark.skip(reason="mujoco not installed (pip install 'umi-aug[sim]')"))


@pytest.fixture
def gl():
    """Skip (with the backend error naming the fix) when no offscreen OpenGL backend works."""
    if _GL_ERROR:
        pytest.skip(_GL_ERROR)


@pytest.fixture(scope="session")
def gopro224():
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k

    return gopro_intrinsics_2_7k().umi_policy(224)


@pytest.fixture(scope="session")
def scene0():
    from umi_aug.sim.scene import build_tabletop_scene

    return build_tabletop_scene(0)


@pytest.fixture(scope="session")
def model0(scene0):
    return scene0.compile()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
