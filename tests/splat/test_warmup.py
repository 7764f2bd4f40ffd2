"""The background kernel compile: its child process runs the pipeline's kernels through the public API and exits
cleanly (a failure there would silently cost the first run its head start), and the switch that turns it off."""

from __future__ import annotations

import pytest


def test_background_compile_child_succeeds(monkeypatch):
    from umi_aug.splat.warmup import start_background_compile

    monkeypatch.delenv("UMI_AUG_NO_WARMUP", raising=False)
    proc = start_background_compile(force=True)
    assert proc is not None
    assert proc.wait(timeout=600) == 0, "run `python -m umi_aug.splat.warmup` to see the child's error"


@pytest.mark.parametrize("value", ["1", "yes"])
def test_background_compile_can_be_turned_off(monkeypatch, value):
    from umi_aug.splat.warmup import start_background_compile

    monkeypatch.setenv("UMI_AUG_NO_WARMUP", value)
    assert start_background_compile(force=True) is None


def test_cache_probe_follows_numba_cache_dir(tmp_path, monkeypatch):
    from umi_aug.splat.warmup import _PROBE_KERNELS, kernel_cache_is_warm

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not kernel_cache_is_warm()
    sub = tmp_path / "x" / "splat"
    sub.mkdir(parents=True)
    for name in _PROBE_KERNELS[:-1]:
        (sub / f"_kernels.{name}-10.py311.nbi").write_bytes(b"")
    assert not kernel_cache_is_warm()  # one kernel still missing
    (sub / f"_kernels.{_PROBE_KERNELS[-1]}-10.py311.nbi").write_bytes(b"")
    assert kernel_cache_is_warm()
