"""MUJOCO_GL selection: respects the user, probes egl then osmesa, one clear error naming the fix."""

from __future__ import annotations

import pytest

from umi_aug.errors import SimError
from umi_aug.sim.gl import CANDIDATE_BACKENDS, choose_backend


def test_gl_respects_user_value():
    calls = []
    assert choose_backend("osmesa", False, probe=lambda b: calls.append(b) or (True, "")) == "osmesa"
    assert calls == []


def test_gl_keeps_backend_of_imported_mujoco():
    assert choose_backend("", True, probe=lambda b: (False, "x")) == "glfw"


def test_gl_tries_in_order_and_takes_first_working():
    tried = []

    def probe(b):
        tried.append(b)
        return (b == "osmesa", "libEGL not found")

    assert choose_backend("", False, probe=probe) == "osmesa"
    assert tried == ["egl", "osmesa"]
    assert CANDIDATE_BACKENDS == ("egl", "osmesa")


def test_gl_error_names_attempts_and_fix():
    with pytest.raises(SimError) as ei:
        choose_backend("", False, probe=lambda b: (False, f"{b} broken"))
    msg = str(ei.value)
    assert "MUJOCO_GL=egl: egl broken" in msg and "MUJOCO_GL=osmesa: osmesa broken" in msg
    assert "libosmesa6" in msg and "apt-get" in msg


def test_gl_import_of_sim_package_does_no_work():
    import subprocess
    import sys

    code = "import sys, umi_aug.sim; print('mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
