"""Bad-input suite, outputs (issue #18 cases 1, 2, 5 and the free-space check): never delete or overwrite anything
umi-aug did not create, one run per output, no worker outlives its parent, Ctrl-C ends in one line.

Every case asserts the exact message and that the inputs and any previous output are byte-identical afterwards.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from tests.robustness.conftest import Reached, small_cfg, snapshot

ROOT = Path(__file__).resolve().parents[2]


def _own_export(path: Path, key: str = "an-older-key") -> Path:
    """A tiny store that umi-aug wrote (root attribute ``umi_aug_export``); a ``.zip`` name gives a zip."""
    import zarr

    store = zarr.ZipStore(str(path), mode="w") if path.name.endswith(".zip") else zarr.DirectoryStore(str(path))
    root = zarr.group(store)
    root.create_group("data")
    root.create_group("meta").array("episode_ends", np.array([3]), compressor=None)
    root.attrs["umi_aug_export"] = {"key": key}
    if hasattr(store, "close"):
        store.close()
    return path


# ------------------------------------------------------------------------------------------- 1: --restart
def test_restart_refuses_the_session_dataset_as_output(session, tmp_path, stop_before_stages):
    from umi_aug.errors import AugmentError

    before = snapshot(session)
    out = session / "dataset.zarr.zip"
    with pytest.raises(AugmentError) as e:
        stop_before_stages.export(session, out, small_cfg(), resume=False, work_dir=tmp_path / "w", progress=False)
    assert str(e.value) == (f"--out {out}: is, contains or lies inside the input {session}; umi-aug never writes "
                            f"into or deletes its inputs: choose another --out")
    assert snapshot(session) == before


@pytest.mark.parametrize("where", ["out in demos", "work = session"])
def test_output_or_work_dir_inside_the_session_is_refused(session, tmp_path, stop_before_stages, where):
    from umi_aug.errors import AugmentError

    before = snapshot(session)
    out, work, what, p = tmp_path / "o.zarr", session, "--work", session
    if where == "out in demos":
        out = p = session / "demos" / "x.zarr"
        what = "--out"
    with pytest.raises(AugmentError) as e:
        stop_before_stages.export(session, out, small_cfg(), work_dir=work, progress=False)
    assert str(e.value) == (f"{what} {p}: is, contains or lies inside the input {session}; umi-aug never writes "
                            f"into or deletes its inputs: choose another {what}")
    assert snapshot(session) == before and not out.exists()


def test_restart_refuses_a_folder_umi_aug_did_not_write(session, tmp_path, stop_before_stages):
    from umi_aug.errors import AugmentError

    out = tmp_path / "my_results"
    out.mkdir()
    (out / "notes.txt").write_text("months of work")
    (out / "sub").mkdir()
    (out / "sub" / "table.csv").write_text("a,b\n1,2\n")
    before = snapshot(session, out)
    with pytest.raises(AugmentError) as e:
        stop_before_stages.export(session, out, small_cfg(), resume=False, work_dir=tmp_path / "w", progress=False)
    assert str(e.value) == (f"{out}: exists and is not an umi-aug export (no attribute 'umi_aug_export'); --restart "
                            f"deletes only umi-aug's own outputs: move it away yourself or choose another --out")
    assert snapshot(session, out) == before


def test_restart_removes_only_umi_augs_own_previous_export(session, tmp_path, stop_before_stages):
    out = _own_export(tmp_path / "aug.zarr.zip")
    partial = _own_export(tmp_path / "aug.zarr.zip.partial")
    neighbour = tmp_path / "aug.zarr.zip.notes.txt"
    neighbour.write_text("keep me")
    before = snapshot(session, neighbour)
    with pytest.raises(Reached):  # the previous export is discarded, the run goes on to the stages
        stop_before_stages.export(session, out, small_cfg(), resume=False, work_dir=tmp_path / "w", progress=False)
    assert not out.exists() and not partial.exists()
    assert snapshot(session, neighbour) == before


# ------------------------------------------------------------------------------------------- 2: the lock
_HOLD = textwrap.dedent("""
    import sys, time
    from umi_aug.io_utils import PathLock
    lock = PathLock(sys.argv[1], inside=sys.argv[2] == "inside").acquire()
    print("locked", flush=True)
    time.sleep(60)
""")


def _hold_lock(path: Path, inside: bool = False) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(path), "inside" if inside else "next"],
                         stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert p.stdout.readline().strip() == "locked"
    return p


@pytest.mark.parametrize("which", ["output", "work dir"])
def test_second_run_on_a_locked_output_fails_at_once_naming_the_pid(session, tmp_path, stop_before_stages, which):
    from umi_aug.errors import AugmentError

    out, work = tmp_path / "aug.zarr", tmp_path / "w"
    _own_export(out, "k")
    before = snapshot(session, out)
    holder = _hold_lock(out) if which == "output" else _hold_lock(work, inside=True)
    try:
        # at once: a run that waited for the lock would get it only when the holder exits (after 60 s) and then
        # reach the stages, which raise ``Reached``, not this error
        with pytest.raises(AugmentError) as e:
            stop_before_stages.export(session, out, small_cfg(), work_dir=work, progress=False)
        path, lock = (out, f"{out}.lock") if which == "output" else (work, f"{work}/.umi_aug.lock")
        assert str(e.value) == (f"{path}: the {which} is in use by another umi-aug run (PID {holder.pid}, lock "
                                f"{lock}); wait for it to finish, stop it (kill {holder.pid}), or choose "
                                f"another path")
    finally:
        holder.kill()
        holder.wait()
    assert snapshot(session, out) == before


def test_a_stale_lock_of_a_dead_run_is_taken_over(session, tmp_path, stop_before_stages):
    out = tmp_path / "aug.zarr"
    Path(f"{out}.lock").write_text("999999\n")  # left by a killed run: the kernel dropped its flock
    with pytest.raises(Reached):
        stop_before_stages.export(session, out, small_cfg(), work_dir=tmp_path / "w", progress=False)
    assert not Path(f"{out}.lock").exists()  # released at the end


# ------------------------------------------------------------------------------------------- free space
def test_zip_output_checks_free_space_before_any_work(session, tmp_path, stop_before_stages, monkeypatch):
    import shutil
    from collections import namedtuple

    import umi_aug.io_utils as io
    from umi_aug.errors import AugmentError

    usage = namedtuple("usage", "total used free")
    real_disk_usage = shutil.disk_usage
    monkeypatch.setattr(io.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 50_000, 50_000))
    out = tmp_path / "aug.zarr.zip"
    before = snapshot(session)
    ds_bytes = (session / "dataset.zarr.zip").stat().st_size
    need = 2 * ds_bytes * (1 + 2)  # (1 original + 2 new episodes) x the dataset's bytes per episode, twice for a zip
    with pytest.raises(AugmentError) as e:
        stop_before_stages.export(session, out, small_cfg(), work_dir=tmp_path / "w", progress=False)
    msg = str(e.value)
    assert msg.startswith(f"{out}: not enough free disk space on {tmp_path}: writing aug.zarr.zip (about 2 new "
                          f"episodes + a .zarr.zip copy of the working store) needs about {io.human_bytes(need)}, "
                          f"48.8 KiB free"), msg
    assert not out.exists() and not Path(f"{out}.partial").exists()
    assert snapshot(session) == before
    monkeypatch.setattr(io.shutil, "disk_usage", real_disk_usage)
    with pytest.raises(Reached):  # enough space: the run goes on
        stop_before_stages.export(session, out, small_cfg(), work_dir=tmp_path / "w", progress=False)


# ------------------------------------------------------------------------------------------- 5: kills
def test_kill_during_final_cleanup_does_not_block_the_rerun(session, tmp_path, stop_before_stages):
    from umi_aug.augment.sources.session import session_fingerprint

    cfg = small_cfg()
    key = stop_before_stages._run_key(cfg, session_fingerprint(session))
    out = _own_export(tmp_path / "aug.zarr.zip", key)  # the finished .zarr.zip of this configuration
    partial = tmp_path / "aug.zarr.zip.partial"  # half deleted when the kill came: .zgroup/.zattrs already gone
    (partial / "data" / "camera0_rgb").mkdir(parents=True)
    (partial / "data" / "camera0_rgb" / "0.0.0.0").write_bytes(b"x" * 100)
    before = snapshot(session, out)
    with pytest.raises(Reached):  # on to "nothing to do" (the finished export), not an error about .partial
        stop_before_stages.export(session, out, cfg, work_dir=tmp_path / "w", progress=False)
    assert not partial.exists()
    assert snapshot(session, out) == before


def test_leftover_temporaries_of_killed_writes_are_removed_and_nothing_else(session, tmp_path, stop_before_stages):
    out = tmp_path / "aug.zarr.zip"
    zip_tmp = tmp_path / "aug.zarr.zip.tmp-0a1b2c3d"  # a .zarr.zip write killed half way (disk full)
    zip_tmp.write_bytes(b"z" * 1000)
    trash = tmp_path / "aug.zarr.zip.partial.tmp-deadbeef"  # a clean-up killed half way
    (trash / "data").mkdir(parents=True)
    keep = [tmp_path / "aug.zarr.zip.tmp-notes.txt", tmp_path / "other.zarr.zip.tmp-0a1b2c3d"]
    for k in keep:
        k.write_text("not umi-aug's")
    before = snapshot(session, *keep)
    with pytest.raises(Reached):
        stop_before_stages.export(session, out, small_cfg(), work_dir=tmp_path / "w", progress=False)
    assert not zip_tmp.exists() and not trash.exists()
    assert snapshot(session, *keep) == before


def test_remove_tree_atomically_leaves_all_or_nothing(tmp_path, monkeypatch):
    import umi_aug.io_utils as io

    d = tmp_path / "x.partial"
    (d / "a").mkdir(parents=True)
    (d / "a" / "f").write_text("1")

    def killed(p, ignore_errors=False):
        raise KeyboardInterrupt

    monkeypatch.setattr(io.shutil, "rmtree", killed)
    with pytest.raises(KeyboardInterrupt):
        io.remove_tree_atomically(d)
    assert not d.exists()  # the name is gone at once; only <name>.tmp-* is left


_PARENT = textwrap.dedent("""
    import sys
    from umi_aug.augment.executor import map_ordered
    from tests.robustness.workers import sleep_and_report
    for _ in map_ordered(sleep_and_report, [sys.argv[1]] * 2, workers=2, threads_per_worker=1):
        pass
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux (prctl)")
def test_no_worker_outlives_its_killed_parent(tmp_path):
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, str(tmp_path)], cwd=ROOT)
    pids: list[int] = []
    try:
        t0 = time.time()
        while len(pids) < 2 and time.time() - t0 < 60:
            pids = [int(p.stem) for p in tmp_path.glob("*.pid")]
            time.sleep(0.1)
        assert len(pids) == 2, "workers did not start"
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        t0 = time.time()
        while any(_alive(p) for p in pids) and time.time() - t0 < 10:
            time.sleep(0.1)
        assert not [p for p in pids if _alive(p)], "workers outlived their parent"
    finally:
        parent.kill()
        for p in pids:
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_ctrl_c_ends_in_one_line_exit_130(tmp_path, monkeypatch, capsys):
    import umi_aug.data
    from umi_aug.cli import main

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(umi_aug.data, "validate_replay_buffer", interrupted)
    assert main(["validate", str(tmp_path / "x.zarr")]) == 130
    err = capsys.readouterr().err
    assert err == ("umi-aug validate: interrupted (Ctrl-C); nothing half-written is kept — rerun the same command "
                   "to resume\n")
