"""Fixtures of the square benchmark's tests (umi_aug.square: simulator, demos, augmentation input, study). The GL
backend is chosen BEFORE MuJoCo is imported (umi_aug.sim.gl), as in tests/sim; the shared rendered demo
(``square_demo``) is in tests/conftest.py."""

from __future__ import annotations

import importlib.util
import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

_GL_ERROR: str | None = None
if importlib.util.find_spec("mujoco") is not None:
    from umi_aug.errors import SimError
    from umi_aug.sim.gl import select_gl_backend

    try:
        select_gl_backend()
    except SimError as exc:  # pragma: no cover - machine without any offscreen GL
        _GL_ERROR = str(exc)


@pytest.fixture
def gl():
    """Skip (with the backend error naming the fix) when no offscreen OpenGL backend works."""
    if _GL_ERROR:
        pytest.skip(_GL_ERROR)
