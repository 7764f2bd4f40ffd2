"""Every compiled function of the 3DGS kernels gets the same code whichever kernel compiles it first.

numba compiles a helper on its first call with the fastmath flags of the caller that made that call, unless the
helper states its own, and keeps (and caches on disk) that one compilation for every later caller. The fused
inference kernels use fastmath, the training kernels do not: helpers shared by both must state ``fastmath=False`` or
the training's arithmetic depends on which kernel a process (or an old ``__pycache__``) compiled first."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

from numba.core.registry import CPUDispatcher

MODULES = ["umi_aug.splat._kernels", "umi_aug.splat._project_kernels", "umi_aug.splat._loss_kernels",
           "umi_aug.splat._optim_kernels"]
ROOT = Path(__file__).resolve().parents[2]


def _dispatchers():
    for name in MODULES:
        mod = importlib.import_module(name)
        for attr, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name:
                yield f"{name}.{attr}", obj


def test_every_function_not_inlined_states_its_fastmath():
    found = dict(_dispatchers())
    assert len(found) > 40
    missing = [n for n, d in found.items()
               if d.targetoptions.get("inline") != "always" and "fastmath" not in d.targetoptions]
    assert missing == []
    # the fused kernels keep their flags; every other kernel states none
    fused = {n for n, d in found.items() if d.targetoptions.get("fastmath")}
    assert fused == {"umi_aug.splat._kernels.project_kernel", "umi_aug.splat._kernels.raster_fwd_fused_kernel"}


_PROBE = r"""
import json, sys
import numba
import numpy as np
from umi_aug.splat import _kernels as K
first = sys.argv[1]
rng = np.random.default_rng(0)
pts = rng.normal(size=(64, 3)) * [0.3, 0.3, 1.0] + [0.0, 0.0, 0.2]   # some behind the camera, some past 90 deg
cam = (400.0, 410.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.0003)

def caller(p, c):
    out = np.empty((p.shape[0], 10))
    for i in range(p.shape[0]):
        ok, th, u, v, a, b, d, e, f, g = K._kb_project_jacobian(p[i, 0], p[i, 1], p[i, 2], c[0], c[1], c[2], c[3],
                                                               c[4], c[5], c[6], c[7])
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4] = 1.0 if ok else 0.0, th, u, v, a
        out[i, 5], out[i, 6], out[i, 7], out[i, 8], out[i, 9] = b, d, e, f, g
    return out

fused_caller = numba.njit(fastmath={"nsz", "arcp", "contract", "afn"})(caller)  # project_kernel's flags
plain_caller = numba.njit(caller)

c = np.array(cam)
if first == "fused":
    fused_caller(pts, c)
out = plain_caller(pts, c)
llvm = "".join(K._kb_project_jacobian.inspect_llvm().values())
print(json.dumps({"values": out.tobytes().hex(), "contract": llvm.count(" contract ") + llvm.count(" fast ")}))
"""


def test_a_fastmath_caller_first_leaves_the_shared_helper_exact(tmp_path):
    """In fresh processes with an empty numba cache: a fastmath caller compiling ``_kb_project_jacobian`` first leaves
    it without contracted or fast instructions, and a plain caller then gets the same bits as in a process where
    it came first (before the fix the first order gave fused multiply-adds)."""
    runs = {}
    for order in ("fused", "plain"):
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / order), PYTHONPATH=str(ROOT))
        res = subprocess.run([sys.executable, "-c", _PROBE, order], capture_output=True, text=True, env=env,
                             cwd=ROOT)
        assert res.returncode == 0, res.stderr[-2000:]
        runs[order] = json.loads(res.stdout.strip().splitlines()[-1])
    assert runs["fused"]["contract"] == 0 and runs["plain"]["contract"] == 0
    assert runs["fused"]["values"] == runs["plain"]["values"]


def test_every_kernel_is_stamped_with_every_kernel_source(tmp_path, monkeypatch):
    """Each kernel-module function's numba cache is located by :mod:`umi_aug.splat._numba_cache`, whose stamp changes
    when any file of ``KERNEL_SOURCES`` changes (not only the function's own file); the kernel modules import names
    from no ``umi_aug`` module outside that set; a function of another file keeps numba's own locator."""
    import ast

    import numba
    from numba.core import caching

    from umi_aug.splat import _numba_cache as NC

    for name, d in _dispatchers():
        assert isinstance(d._cache._impl._locator, NC.KernelInTreeCacheLocator), name
    sources = {p.resolve() for p in NC.KERNEL_SOURCES}
    assert all(p.exists() for p in sources)
    for name in MODULES:
        tree = ast.parse(Path(importlib.import_module(name).__file__).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("umi_aug.") \
                    and node.module != "umi_aug.splat._numba_cache":  # the locators themselves compile nothing
                dep = ROOT / (node.module.replace(".", "/") + ".py")
                assert dep.resolve() in sources, f"{name} imports {node.module}, not in KERNEL_SOURCES"
    from umi_aug.splat import _optim_kernels as OK

    loc = NC.KernelInTreeCacheLocator.from_function(OK._sigmoid.py_func, OK.__file__)
    before = loc.get_source_stamp()
    assert loc.get_source_stamp() == before
    extra = tmp_path / "constants_of_a_helper.py"
    extra.write_text("A = 1\n")
    monkeypatch.setattr(NC, "KERNEL_SOURCES", NC.KERNEL_SOURCES + (extra,))
    one = loc.get_source_stamp()
    extra.write_text("A = 2\n")  # another file of the set edited: a new stamp
    assert one != before and loc.get_source_stamp() != one
    other = tmp_path / "elsewhere.py"
    other.write_text("def f(x):\n    return x\n")
    ns: dict = {}
    exec(compile(other.read_text(), str(other), "exec"), ns)
    assert NC.KernelInTreeCacheLocator.from_function(ns["f"], str(other)) is None
    assert type(numba.njit(cache=True)(ns["f"])._cache._impl._locator) is caching.InTreeCacheLocator
