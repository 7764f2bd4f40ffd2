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
