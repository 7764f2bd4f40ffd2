"""The suite's xdist grouping (tests/conftest.py): tests sharing a fixture instance land in one group."""

from __future__ import annotations

from types import SimpleNamespace

from tests.conftest import xdist_groups


def _item(nodeid: str, module: str, fixtures: dict[str, tuple[str, str]]):
    """A stand-in for a pytest item: ``fixtures`` maps name -> (scope, baseid of the defining conftest/module)."""
    defs = {name: [SimpleNamespace(scope=scope, baseid=baseid)] for name, (scope, baseid) in fixtures.items()}
    return SimpleNamespace(nodeid=nodeid, module=SimpleNamespace(__name__=module),
                           _fixtureinfo=SimpleNamespace(name2fixturedefs=defs))


def test_groups_are_the_connected_components_of_shared_fixtures():
    items = [
        _item("a.py::t1", "a", {"demo_run": ("session", "tests"), "tmp_path": ("function", "")}),
        _item("b.py::t2", "b", {"demo_run": ("session", "tests"), "aug_session": ("session", "tests")}),
        _item("c.py::t3", "c", {"aug_session": ("session", "tests")}),
        _item("c.py::t4", "c", {"tmp_path_factory": ("session", ""), "rng": ("function", "tests")}),  # nothing shared
        _item("d.py::t5", "d", {"video": ("module", "tests/d.py")}),
        _item("d.py::t6", "d", {"video": ("module", "tests/d.py")}),
        _item("e.py::t7", "e", {"ckpt": ("module", "tests/sub")}),  # a conftest's module fixture: one per module
        _item("f.py::t8", "f", {"ckpt": ("module", "tests/sub")}),
    ]
    g = xdist_groups(items)
    assert g["a.py::t1"] == g["b.py::t2"] == g["c.py::t3"]  # chained through b
    assert "c.py::t4" not in g  # pytest's own session fixtures do not group
    assert g["d.py::t5"] == g["d.py::t6"] != g["a.py::t1"]
    assert g["e.py::t7"] != g["f.py::t8"]
    assert all("@" not in name for name in g.values())  # xdist splits node ids at "@"
