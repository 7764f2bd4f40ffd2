"""``augment.prefetch.import_in_background``: imports the named modules on a thread, in order, and leaves a module
that fails to import to the stage that needs it (which then reports the error itself)."""

from __future__ import annotations

import sys

from umi_aug.augment.prefetch import import_in_background


def test_imports_on_a_thread_in_order_and_stops_at_a_failure(tmp_path, monkeypatch):
    order = []
    for name in ("prefetch_probe_a", "prefetch_probe_b", "prefetch_probe_c"):
        (tmp_path / f"{name}.py").write_text(f"import sys\nsys.modules['prefetch_probe_log'].append('{name}')\n")
    (tmp_path / "prefetch_probe_bad.py").write_text("raise ImportError('no such library')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(sys.modules, "prefetch_probe_log", order)
    th = import_in_background(["prefetch_probe_a", "prefetch_probe_b"])
    assert th.daemon
    th.join(timeout=600)
    assert not th.is_alive() and order == ["prefetch_probe_a", "prefetch_probe_b"]
    assert "prefetch_probe_a" in sys.modules
    th = import_in_background(["prefetch_probe_bad", "prefetch_probe_c"])
    th.join(timeout=600)
    assert not th.is_alive() and "prefetch_probe_c" not in sys.modules  # stopped at the failure, quietly
    for name in ("prefetch_probe_a", "prefetch_probe_b"):
        monkeypatch.delitem(sys.modules, name)
