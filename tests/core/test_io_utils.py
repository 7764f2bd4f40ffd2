"""Atomic writes: the destination is either the old content or the complete new content, never partial."""

from __future__ import annotations

import pytest

from umi_aug.io_utils import RunLockedError, atomic_path, atomic_write_bytes, atomic_write_text, exclusive_run_lock


def _leftovers(d):
    return [p.name for p in d.iterdir() if ".tmp-" in p.name]


def test_file_written_and_replaced(tmp_path):
    p = tmp_path / "a" / "x.txt"
    atomic_write_text(p, "one")
    assert p.read_text() == "one"
    atomic_write_bytes(p, b"two")
    assert p.read_bytes() == b"two"
    assert _leftovers(p.parent) == []


def test_failure_leaves_old_content_and_no_temporary(tmp_path):
    p = tmp_path / "x.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_directory_destination_is_swapped_whole(tmp_path):
    d = tmp_path / "store"
    d.mkdir()
    (d / "old.bin").write_bytes(b"0")
    with atomic_path(d) as tmp:
        tmp.mkdir()
        (tmp / "new.bin").write_bytes(b"1")
    assert sorted(x.name for x in d.iterdir()) == ["new.bin"]
    assert _leftovers(tmp_path) == []


def test_nothing_written_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing was written"):
        with atomic_path(tmp_path / "never"):
            pass
    assert not (tmp_path / "never").exists()


def test_overwrite_false_refuses_existing(tmp_path):
    p = tmp_path / "x"
    p.write_text("keep")
    with pytest.raises(FileExistsError):
        with atomic_path(p, overwrite=False) as tmp:
            tmp.write_text("new")
    assert p.read_text() == "keep"


def test_exclusive_run_lock_refuses_a_second_holder_and_frees_on_exit(tmp_path):
    lock = tmp_path / "out" / ".run.lock"
    with exclusive_run_lock(lock, "test job"):
        with pytest.raises(RunLockedError, match=r"another test job is running \(pid \d+") as ei:
            with exclusive_run_lock(lock, "test job"):
                pass
        assert str(lock) in str(ei.value)
    with exclusive_run_lock(lock, "test job"):  # released on exit
        pass


def test_exclusive_run_lock_of_a_killed_holder_is_free(tmp_path):
    """The kernel drops a dead holder's lock: a crashed run never blocks the next one (no stale-lock cleanup)."""
    import subprocess
    import sys
    import time

    lock = tmp_path / ".run.lock"
    code = ("import sys, time; from umi_aug.io_utils import exclusive_run_lock\n"
            "with exclusive_run_lock(sys.argv[1], 'holder'):\n    print('held', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(lock)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(RunLockedError, match=f"pid {proc.pid}"):
            with exclusive_run_lock(lock, "holder"):
                pass
    finally:
        proc.kill()
        proc.wait(timeout=30)
    t0 = time.monotonic()
    with exclusive_run_lock(lock, "holder"):
        assert time.monotonic() - t0 < 5
