"""Shared pytest fixtures. Data is generated here; nothing is downloaded."""

from __future__ import annotations

import importlib.util
import os

# The suite runs on pytest-xdist workers (pyproject: ``-n auto --dist loadgroup``): each worker gets its share of the
# cores for torch/OpenMP so that two workers on 2 cores do not oversubscribe them (numba kernels already run on one
# thread: tests/augment/conftest.py). Without xdist (``-n 0``) the process keeps both cores.
_N_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
if "OMP_NUM_THREADS" not in os.environ or os.environ.get("UMI_AUG_TESTS_SET_OMP") == "1":  # not the user's own
    os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 2) // _N_WORKERS))
    os.environ["UMI_AUG_TESTS_SET_OMP"] = "1"  # the controller's value, inherited by xdist workers: theirs replaces it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "2")
# torch 2.13's oneDNN AVX-512 JIT kernel for the backward of a 1x1 convolution segfaults on this project's AVX-512
# machines for the tiny ResNet at 224² of tests/augment/test_dataset.py::test_train_workspace_with_aug_freespace
# (gdb: jit_avx512_common_1x1_convolution_bwd_weights_t::execute_backward_weights; reproducible, passes with AVX2
# kernels). Read by oneDNN at its first primitive, so set before any test trains. Not a umi-aug bug; README,
# "Known issue", tells users the same workaround.
os.environ.setdefault("DNNL_MAX_CPU_ISA", "AVX2")
# no background kernel compile (umi_aug.splat.warmup) next to the tests: they compile what they call themselves,
# and a child compiling beside them on 2 cores would only make their timings noisier (tests/splat/test_warmup.py
# runs it on purpose)
os.environ.setdefault("UMI_AUG_NO_WARMUP", "1")

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
#: the demo's mapping scan: 40 frames, the synthetic session tests/recon reconstructs (full SfM of the 30-frame scan
#: of this seed does not align to the SLAM path: docs/throughput.md)
DEMO_SCAN_FRAMES = 40


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``umi-aug demo`` run once per test session (the most expensive pipeline run of the suite): the out folder,
    the arguments, the exit code and what it printed. tests/cli asserts on it (and reruns it); the training
    workspace test trains on a copy of its session and prepared stages instead of reconstructing again; the
    reconstruction tests read its session (``DEMO_SCAN_FRAMES``: the session tests/recon needs, rendered once)."""
    import contextlib
    import io
    from types import SimpleNamespace

    from umi_aug.cli import main

    out = tmp_path_factory.mktemp("demo_run") / "demo"
    args = ["demo", "--out", str(out), "--episodes", "1", "--mode", "freespace", "--scan-frames", str(DEMO_SCAN_FRAMES),
            "--splat-iterations", str(DEMO_SPLAT_ITERATIONS)]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(args)
    return SimpleNamespace(out=out, args=args, rc=rc, printed=printed.getvalue())


#: the shared square demo (tests/square: demo data, augmentation source): seed and image side
SQUARE_DEMO_SEED = 7
SQUARE_DEMO_SIZE = 84


@pytest.fixture(scope="session")
def square_demo(tmp_path_factory):
    """One rendered scripted-expert square demo (``umi-aug square-demos --n 1``, seed 7, 84²; ~20 s on 2 cores),
    generated once per test session: ``(folder, report)``. Tests only read it (a resumed generate writes nothing)."""
    pytest.importorskip("robosuite")
    from umi_aug.square.generate import DemoConfig, generate_demos

    out = tmp_path_factory.mktemp("square_demos")
    report = generate_demos(out, DemoConfig(n=1, image_size=SQUARE_DEMO_SIZE, workers=1,
                                            start_seed=SQUARE_DEMO_SEED))
    return out, report


# --- the small synthetic UMI session shared by tests/augment and tests/policy (settings: tests/augment/conftest.py)
@pytest.fixture(scope="session")
def aug_session(tmp_path_factory):
    """Synthetic UMI session: 30 scan frames + 1 demo at 320x240, dataset at 64² (~20 s on 2 cores)."""
    if importlib.util.find_spec("mujoco") is None:  # MuJoCo must be imported through umi_aug.sim.gl
        pytest.skip("mujoco (sim extra) not installed")
    from umi_aug.sim.gl import import_mujoco

    import_mujoco()
    from umi_aug.sim.session import make_session

    out = tmp_path_factory.mktemp("aug_session") / "session"
    from tests.augment.conftest import SIZE

    make_session(out, 0, n_demos=1, scan_frames=30, policy_size=SIZE, benchmark_frames=0, progress=False)
    return out


@pytest.fixture(scope="session")
def aug_work(tmp_path_factory):
    return tmp_path_factory.mktemp("aug_work")


@pytest.fixture(scope="session")
def aug_assets(aug_session, aug_work):
    """All session stages of the small config (reconstruction ~25 s, the rest a few seconds)."""
    from umi_aug.augment import prepare_session

    from tests.augment.conftest import small_config

    return prepare_session(aug_session, aug_work, small_config(), progress=False)


# --- pytest-xdist: tests that share an expensive fixture run on one worker -------------------------------------------
# ``--dist loadgroup`` cannot be fed by xdist_group marks on pytest 9.2 (xdist 3.8 still rewrites the removed
# ``Item._nodeid``: pytest-dev/pytest-xdist#1386), so the grouping is done here: every worker computes the groups of
# its (identical) collection and writes them to a file the controller named; the controller's scheduler reads it.
_GROUPS_ENV = "UMI_AUG_XDIST_GROUPS"


def _shared_fixture_keys(item) -> list[str]:
    """The non-function-scoped fixtures of this project (not pytest's own) that ``item`` uses, as keys naming one
    fixture *instance*: a session-scoped fixture is one instance per worker, a module-scoped one per module."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return []
    keys = []
    for name, defs in info.name2fixturedefs.items():
        fixturedef = defs[-1]
        if fixturedef.scope == "function" or not fixturedef.baseid.startswith("tests"):
            continue
        where = fixturedef.baseid if fixturedef.scope in ("session", "package") else item.module.__name__
        keys.append(f"{name}:{where}")
    return keys


def xdist_groups(items) -> dict[str, str]:
    """nodeid -> group name: the connected components of "uses the same shared fixture instance" (union-find), so
    that every session/module fixture is built on one worker only instead of once per worker (``umi-aug demo``
    once, not twice). Tests that share nothing are left out (scheduled one by one)."""
    parent: dict[str, str] = {}

    def find(x: str) -> str:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    uses = {item.nodeid: _shared_fixture_keys(item) for item in items}
    for keys in uses.values():
        for a, b in zip(keys, keys[1:]):
            parent[find(a)] = find(b)
    return {nodeid: find(keys[0]) for nodeid, keys in uses.items() if keys}


def pytest_configure(config):
    """Controller of an xdist run: name the file the workers write the fixture groups to."""
    import tempfile

    if (config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput")
            and config.getoption("dist", "no") == "loadgroup" and _GROUPS_ENV not in os.environ):
        folder = tempfile.mkdtemp(prefix="umi_aug_xdist_")
        os.environ[_GROUPS_ENV] = os.path.join(folder, "groups.json")  # inherited by the workers started next
        config._umi_aug_groups_dir = folder


def pytest_unconfigure(config):
    import shutil

    folder = getattr(config, "_umi_aug_groups_dir", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(_GROUPS_ENV, None)


def pytest_collection_modifyitems(config, items):
    path = os.environ.get(_GROUPS_ENV)
    if not path or not hasattr(config, "workerinput"):
        return
    import json

    tmp = f"{path}.{config.workerinput['workerid']}.tmp"
    with open(tmp, "w") as f:
        json.dump(xdist_groups(items), f)
    os.replace(tmp, path)  # every worker writes the same map; the last complete one stays


def pytest_xdist_make_scheduler(config, log):
    if config.getoption("dist", "no") != "loadgroup" or _GROUPS_ENV not in os.environ:
        return None
    from xdist.scheduler import LoadScopeScheduling

    class FixtureGroupScheduling(LoadScopeScheduling):
        """Load-scope scheduling whose scopes are :func:`xdist_groups` (largest first); other tests one by one."""

        _groups: dict[str, str] | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self._groups is None:
                import json

                with open(os.environ[_GROUPS_ENV]) as f:  # written before the workers reported their collection
                    self._groups = json.load(f)
            group = self._groups.get(nodeid)
            return f"group {group}" if group else nodeid

    return FixtureGroupScheduling(config, log)
