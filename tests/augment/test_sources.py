"""The input-source seam (issue #33 item 1): the registry picks one :class:`InputSource` per path, the built-in
kinds and the square demos' (registered by ``umi_aug.square.source``, item 2) satisfy the protocol, and a kind
registered from outside is asked before the default (a UMI session)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture
def kinds(monkeypatch):
    """The registry, restored after the test."""
    from umi_aug.augment.sources import base

    monkeypatch.setattr(base, "_KINDS", list(base._KINDS))
    return base


def _square_folder(root: Path) -> Path:
    root.mkdir()
    (root / "report.json").write_text(json.dumps({"paths": {"hdf5": "d.hdf5", "zarr": "d.zarr.zip"}}))
    return root


def test_built_in_kinds_are_detected_in_order(tmp_path):
    from umi_aug.augment.dataset_source import DatasetInput
    from umi_aug.augment.sources import InputSource, open_source, source_kind, source_kinds
    from umi_aug.augment.sources.dataset import DatasetSource
    from umi_aug.augment.sources.session import SessionSource
    from umi_aug.square.source import SquareInput, SquareSource  # registers the kind "square"

    assert source_kinds() == ["dataset", "square", "session"]
    ds = tmp_path / "d.zarr.zip"
    ds.write_bytes(b"")
    session = tmp_path / "session"
    (session / "demos").mkdir(parents=True)
    square = _square_folder(tmp_path / "square")
    assert [source_kind(p) for p in (ds, square, session, tmp_path / "missing")] == [
        "dataset", "square", "session", "session"]  # anything no kind claims: the session (its check says why not)
    inp = DatasetInput(episodes=(1,))
    src = open_source(ds, inp)
    assert isinstance(src, DatasetSource) and src.inp is inp and src.reads() == (ds,) and src.n_augment(5) == 1
    assert isinstance(open_source(square, SquareInput(episodes=(0, 2))), SquareSource)
    sess = open_source(session)
    assert isinstance(sess, SessionSource) and sess.dataset == session / "dataset.zarr.zip"
    assert sess.reads() == (session / "demos", session / "calibration", session / "dataset.zarr.zip")
    assert SessionSource(tmp_path).reads() == (tmp_path,)  # no session: nothing inside may be written
    for s in (src, sess, open_source(square)):  # the protocol's members (not isinstance: `dataset` reads files)
        assert all(hasattr(type(s), m) for m in dir(InputSource) if not m.startswith("_")), type(s)


def test_settings_of_another_kind_are_refused(tmp_path):
    from umi_aug.augment.dataset_source import DatasetInput
    from umi_aug.augment.sources import open_source
    from umi_aug.errors import AugmentError
    from umi_aug.square.source import SquareInput

    ds = tmp_path / "d.zarr.zip"
    ds.write_bytes(b"")
    with pytest.raises(AugmentError, match="takes DatasetInput settings, not SquareInput"):
        open_source(ds, SquareInput())
    with pytest.raises(AugmentError, match="takes SquareInput settings, not DatasetInput"):
        open_source(_square_folder(tmp_path / "sq"), DatasetInput())


def test_a_registered_kind_is_asked_before_the_default(kinds, tmp_path):
    from umi_aug.augment.sources import open_source, register_source, source_kind, source_kinds
    from umi_aug.errors import AugmentError

    class _Marked:
        def __init__(self, path, settings):
            self.path, self.settings = Path(path), settings

    register_source("marked", lambda p: (p / "MARK").is_file(), _Marked)
    folder = tmp_path / "x"
    folder.mkdir()
    assert source_kind(folder) == "session"
    (folder / "MARK").write_text("")
    assert source_kind(folder) == "marked" and source_kinds()[-2:] == ["marked", "session"]
    s = open_source(folder, {"a": 1})
    assert isinstance(s, _Marked) and s.settings == {"a": 1}
    with pytest.raises(AugmentError, match="a default input kind is registered already"):
        register_source("other", None, _Marked)


def test_export_checks_through_the_source(tmp_path):
    """A plain dataset's problem is named by its source's check, before anything is written."""
    from umi_aug.augment import AugmentConfig, export
    from umi_aug.errors import AugmentError

    missing = tmp_path / "nothing.zarr.zip"
    missing.write_bytes(b"not a zip")
    out = tmp_path / "o.zarr"
    with pytest.raises(AugmentError, match="not a readable UMI replay buffer"):
        export(missing, out, AugmentConfig(image_size=64), progress=False, pictures=False)
    assert not out.exists() and not (tmp_path / "o.zarr.work").exists()


def test_the_square_kind_is_registered_by_the_square_package(tmp_path):
    """augment/ registers no square kind (issue #33 item 2): importing ``umi_aug.square.source`` adds it after
    ``dataset``, and ``umi-aug augment`` imports it, so its flag check names a square folder as before."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    code = ("from umi_aug.augment.sources import source_kinds; before = source_kinds(); "
            "import umi_aug.square.source; print(before, source_kinds())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root,
                         env=env).stdout
    assert out.strip() == "['dataset', 'session'] ['dataset', 'square', 'session']"
    square = _square_folder(tmp_path / "sq")
    res = subprocess.run([sys.executable, "-m", "umi_aug", "augment", str(square), "--out", str(tmp_path / "o.zarr"),
                          "--tcp-offset", "0.2"], capture_output=True, text=True, cwd=root, env=env)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines()[-1] == (f"umi-aug augment: error: --tcp-offset: {square} is a square demo "
                                                   "folder; --tcp-offset applies to a plain dataset input: drop it")
