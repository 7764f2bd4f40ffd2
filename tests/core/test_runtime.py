"""Thread configuration respects user choices and keeps OpenBLAS single-threaded."""

from __future__ import annotations

import os
import subprocess
import sys


def _run(env_extra: dict[str, str]) -> str:
    code = "from umi_aug.runtime import configure_threads; import os; n = configure_threads(3); print(n, os.environ['OMP_NUM_THREADS'], os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env.update(env_extra)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()


def test_defaults_applied_when_unset():
    assert _run({}) == ["3", "3", "1"]


def test_user_values_win():
    assert _run({"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "2"}) == ["1", "1", "2"]


def test_a_library_user_never_sees_numbas_old_tbb_notice():
    """numba warns on its first parallel kernel when an old TBB is loaded (open3d brings one) and then uses OpenMP:
    a notice nobody can act on. A library user who never calls configure_threads must not see it either."""
    import pytest

    pytest.importorskip("open3d")
    code = ("import warnings; warnings.simplefilter('default'); import open3d, torch\n"
            "from umi_aug.splat.losses import photometric_loss_fused\n"
            "p = torch.rand(20, 20, 3, requires_grad=True)\n"
            "loss, _ = photometric_loss_fused(p, torch.rand(20, 20, 3)); loss.backward(); print('done')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "done" in out.stdout, out.stderr[-2000:]
    assert "TBB" not in out.stderr, out.stderr[-2000:]
