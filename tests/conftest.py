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


#: ``umi-aug demo`` as the tests run it (CI-sized: 1 augmented episode, 60 3DGS steps). tests/augment's training
#: test reuses its session and prepared stages with the same settings (AUG_SEED, image size 224, DEMO_SPLAT_*).
DEMO_SPLAT_ITERATIONS = 60
DEMO_SPLAT_MAX_GAUSSIANS = 25_000  # DemoConfig's default


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``umi-aug demo`` run once per test session (the most expensive pipeline run of the suite): the out folder,
    the arguments, the exit code and what it printed. tests/cli asserts on it (and reruns it); the training
    workspace test trains on a copy of its session and prepared stages instead of reconstructing again."""
    import contextlib
    import io
    from types import SimpleNamespace

    from umi_aug.cli import main

    out = tmp_path_factory.mktemp("demo_run") / "demo"
    args = ["demo", "--out", str(out), "--episodes", "1", "--mode", "freespace", "--scan-frames", "30",
            "--splat-iterations", str(DEMO_SPLAT_ITERATIONS)]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(args)
    return SimpleNamespace(out=out, args=args, rc=rc, printed=printed.getvalue())
