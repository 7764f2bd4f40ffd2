"""Shared pytest fixtures. Data is generated here; nothing is downloaded."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "2")

import zlib

import numpy as np
import pytest


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A fresh generator per test. Seeded from the test's name plus a per-run salt (env UMI_AUG_TEST_SEED,
    random when unset) so every CI run draws fresh inputs; the seed is printed on failure for replay."""
    salt = os.environ.get("UMI_AUG_TEST_SEED")
    if salt is None:
        salt = str(np.random.SeedSequence().entropy % (2**32))
        os.environ["UMI_AUG_TEST_SEED"] = salt
    seed = (zlib.crc32(request.node.nodeid.encode()) + int(salt)) % (2**32)
    print(f"[rng] UMI_AUG_TEST_SEED={salt} (test seed {seed})")
    return np.random.default_rng(seed)
