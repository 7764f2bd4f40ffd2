"""Bad-input suite, round two (issue #32): data checks of ``umi-aug validate`` and of the CLI's flags.

Every case asserts the message and that the inputs are byte-identical afterwards.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.robustness.conftest import snapshot, write_dataset


@pytest.fixture
def ds(tmp_path):
    """A 2-episode (10 + 10 steps) zarr directory dataset."""
    return write_dataset(tmp_path / "ds.zarr", lengths=(10, 10))


def _edit(path: Path, key: str, fn) -> None:
    import zarr

    a = zarr.open_group(str(path), mode="r+")[f"data/{key}"]
    a[:] = fn(a[:])


def _validate(capsys, path: Path) -> tuple[int, list[str], str]:
    from umi_aug.cli import main

    rc = main(["validate", str(path)])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, [ln for ln in cap.err.splitlines() if ln.startswith("umi-aug")], cap.out


# ------------------------------------------------------------------------------------------- validate: values
@pytest.mark.parametrize("value, row, shown", [(-0.03, 12, "-0.03"), (5.0, 3, "5")])
def test_validate_refuses_gripper_widths_outside_the_grippers_range(ds, capsys, value, row, shown):
    """Before: ``OK — 2 episodes`` (training then ran on them)."""
    import zarr

    def poke(w):
        w[row] = value
        return w

    _edit(ds, "robot0_gripper_width", poke)
    w = zarr.open_group(str(ds), mode="r")["data/robot0_gripper_width"][:, 0].astype(np.float64)
    before = snapshot(ds)
    rc, err, _ = _validate(capsys, ds)
    assert rc == 2
    assert err == [f"umi-aug validate: error: {ds}: key 'data/robot0_gripper_width' = {shown} m at row {row} "
                   f"(episode {row // 10}) is outside the gripper's range [0.0, 0.2] m (1 of 20 rows, range "
                   f"{w.min():.6g}..{w.max():.6g} m); widths are metres between the fingers: a unit (mm?) or "
                   "gripper-calibration error — re-create the dataset"]
    assert snapshot(ds) == before


def test_validate_refuses_a_dataset_without_a_required_umi_key(ds, capsys):
    shutil.rmtree(ds / "data" / "robot0_eef_rot_axis_angle")
    before = snapshot(ds)
    rc, err, _ = _validate(capsys, ds)
    assert rc == 2
    assert err == [f"umi-aug validate: error: {ds}: required key(s) 'data/robot0_eef_rot_axis_angle' missing; a UMI "
                   "dataset holds robot<i>_eef_pos, robot<i>_eef_rot_axis_angle, robot<i>_gripper_width for every "
                   "arm and camera<j>_rgb frames (UMI's 07_generate_replay_buffer.py writes them all)"]
    assert snapshot(ds) == before


def _freeze(ds: Path, episode: int, n: int = 10) -> None:
    """Episode ``episode`` holds one pose on every step; its rotation vector makes ``arccos`` of the relative
    rotation's trace 2e-6 deg, not 0 (the round-off the old ``== 0.0`` check missed)."""
    sl = slice(n * episode, n * episode + n)

    def pos(a):
        a[sl] = [0.1, 0.2, 0.3]
        return a

    def rot(a):
        a[sl] = [2.9, 0.1, 0.4]
        return a

    _edit(ds, "robot0_eef_pos", pos)
    _edit(ds, "robot0_eef_rot_axis_angle", rot)


def test_validate_warns_on_a_frozen_episode(ds, capsys):
    _freeze(ds, 1)
    rc, err, out = _validate(capsys, ds)
    assert rc == 0 and not err
    assert (f"warning: {ds}: episode 1: keys 'data/robot0_eef_pos'/'robot0_eef_rot_axis_angle' are frozen (the same "
            "pose within 1e-06 m / 1e-05 rad) from step 0 for >= 8 steps (row 10)") in out


def test_augment_refuses_a_plain_dataset_whose_poses_are_frozen_by_round_off(tmp_path):
    """Before: passed the check (angles compared with ``== 0.0``) and failed minutes later in SfM."""
    from umi_aug.augment.dataset_source import DatasetInput, check_dataset
    from umi_aug.errors import AugmentError

    ds = write_dataset(tmp_path / "long.zarr", lengths=(20, 20))
    _freeze(ds, 1, n=20)
    before = snapshot(ds)
    with pytest.raises(AugmentError) as e:
        check_dataset(ds, 32, DatasetInput(episodes=(1,)))
    assert str(e.value) == (f"{ds}: episode 1 (rows 20..39): key 'data/robot0_eef_pos' is frozen (identical poses "
                            "within 1e-06 m / 1e-05 rad) from step 0 for >= 8 frames: tracking was lost and the last "
                            "pose held; drop the episode (--episodes)")
    assert snapshot(ds) == before


def test_frozen_check_tolerates_round_off_but_not_motion():
    from umi_aug.data.validate import first_frozen_step, relative_turn_rad

    rot = np.tile([2.9, 0.1, 0.4], (12, 1))
    assert np.all(relative_turn_rad(rot) < 1e-7)
    pos = np.tile([0.1, 0.2, 0.3], (12, 1))
    assert first_frozen_step(pos, rot) == 0
    moving = pos + np.arange(12)[:, None] * [1e-4, 0, 0]  # 0.1 mm per frame: a slow hand, not frozen
    assert first_frozen_step(moving, rot) is None
    turning = rot * (1 + np.arange(12)[:, None] * 1e-4)
    assert first_frozen_step(pos, turning) is None


# ------------------------------------------------------------------------------------------- validate: layout hints
def test_validate_a_session_folder_suggests_its_dataset(tmp_path, capsys):
    sess = tmp_path / "session"
    (sess / "demos").mkdir(parents=True)
    write_dataset(sess / "dataset.zarr.zip")
    before = snapshot(sess)
    rc, err, _ = _validate(capsys, sess)
    assert rc == 2 and len(err) == 1
    assert err[0].startswith(f"umi-aug validate: error: {sess}: not a zarr group (")
    assert err[0].endswith(f"; did you mean {sess / 'dataset.zarr.zip'}? ({sess} looks like a UMI session folder)")
    assert snapshot(sess) == before


@pytest.mark.skipif(shutil.which("zip") is None, reason="needs the zip command")
def test_validate_a_zip_r_archive_names_the_folder_prefix(ds, tmp_path, capsys):
    z = tmp_path / "ds.zarr.zip"
    subprocess.run(["zip", "-qr", str(z), ds.name], cwd=tmp_path, check=True)
    before = snapshot(z)
    rc, err, _ = _validate(capsys, z)
    assert rc == 2 and len(err) == 1
    assert err[0].endswith("; the entries sit under ds.zarr/ (a zip made with `zip -r ds.zarr.zip ds.zarr`), but the "
                           "store must be at the zip's root: unzip it and pass the folder ds.zarr (zarr directories "
                           "are read too), or zip the folder's contents into a new file: cd ds.zarr && zip -r -0 "
                           "../new.zarr.zip ."), err
    assert snapshot(z) == before
    fixed = tmp_path / "new.zarr.zip"  # the advice works
    subprocess.run(["zip", "-qr0", str(fixed), "."], cwd=ds, check=True)
    assert _validate(capsys, fixed)[0] == 0


def test_validate_broken_array_metadata_is_not_called_a_missing_codec(ds, capsys):
    """Before: "codec ? is not available … install and register it"."""
    (ds / "data" / "robot0_eef_pos" / ".zarray").write_text("{broken")
    rc, err, _ = _validate(capsys, ds)
    assert rc == 2
    assert err == [f"umi-aug validate: error: {ds}: key 'data/robot0_eef_pos': its metadata file "
                   "'data/robot0_eef_pos/.zarray' is not valid JSON (Expecting property name enclosed in double "
                   "quotes: line 1 column 2 (char 1)); the dataset is damaged: re-copy or re-create it"]


def _rewrite_zip(ds: Path, key: str, fn) -> None:
    """Edit ``data/<key>`` of the ``.zarr.zip`` ``ds`` (via a directory copy)."""
    import zarr

    tmp = ds.parent / "edit.zarr"
    zarr.copy_store(zarr.ZipStore(str(ds), mode="r"), zarr.DirectoryStore(str(tmp)))
    _edit(tmp, key, fn)
    ds.unlink()
    zs = zarr.ZipStore(str(ds), mode="w")
    zarr.copy_store(zarr.DirectoryStore(str(tmp)), zs)
    zs.close()
    shutil.rmtree(tmp)


def test_session_negative_gripper_widths_are_refused_up_front(session):
    """Before: 16x ``TrajError: … gripper_width must be finite, >= 0`` after 232 s of reconstruction."""
    from umi_aug.augment.preflight import check_session_inputs
    from umi_aug.errors import AugmentError

    ds = session / "dataset.zarr.zip"
    _rewrite_zip(ds, "robot0_gripper_width", lambda w: -np.abs(w) - 0.01)
    before = snapshot(session)
    with pytest.raises(AugmentError) as e:
        check_session_inputs(session)
    assert str(e.value).startswith(f"{ds}: key 'data/robot0_gripper_width' = -")
    assert " m at row 0 (episode 0) is outside the gripper's range [0.0, 0.2] m (8 of 8 rows, range " in str(e.value)
    assert snapshot(session) == before


def test_plain_dataset_gripper_widths_in_mm_are_refused(tmp_path):
    from umi_aug.augment.dataset_source import DatasetInput, check_dataset
    from umi_aug.errors import AugmentError

    ds = write_dataset(tmp_path / "mm.zarr", lengths=(20, 20))
    _edit(ds, "robot0_gripper_width", lambda w: w * 1000 + 1)  # millimetres
    before = snapshot(ds)
    with pytest.raises(AugmentError) as e:
        check_dataset(ds, 32, DatasetInput(episodes=(1,)))
    assert str(e.value).startswith(f"{ds}: key 'data/robot0_gripper_width' = ")
    assert "m at row 0 (episode 0) is outside the gripper's range [0.0, 0.2] m (40 of 40 rows" in str(e.value)
    assert snapshot(ds) == before


# ------------------------------------------------------------------------------------------- fixes that exist
def _append_rows(path: Path, n: int) -> None:
    """Rows beyond ``episode_ends[-1]`` in every ``data/*`` array: an append killed before its episode end."""
    import zarr

    from umi_aug.data import register_codecs

    register_codecs()
    data = zarr.open_group(str(path), mode="r+")["data"]
    for k in data.array_keys():
        a = data[k]
        a.resize((a.shape[0] + n,) + a.shape[1:])


def test_validate_names_the_repair_command_not_a_python_api(ds, capsys):
    _append_rows(ds, 3)
    rc, err, _ = _validate(capsys, ds)
    assert rc == 2
    assert err == [f"umi-aug validate: error: {ds}: key 'data/camera0_rgb' has length 23 but episode_ends[-1] = 20: "
                   f"extra trailing data beyond episode_ends[-1] (an interrupted append?); `umi-aug repair {ds} --out "
                   "<new path>` writes a copy cut back to the last complete episode (this one is not changed)"]
    assert "repair=True" not in err[0]


@pytest.mark.parametrize("out_name", ["fixed.zarr.zip", "fixed.zarr"])
def test_repair_writes_a_repaired_copy_and_never_changes_the_input(ds, tmp_path, capsys, out_name):
    from umi_aug.cli import main
    from umi_aug.data import ReplayBuffer

    _append_rows(ds, 3)
    before = snapshot(ds)
    out = tmp_path / out_name
    assert main(["repair", str(ds), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"  {out}: repair truncated key 'data/camera0_rgb' from 23 to 20 rows (data of an interrupted append)" \
        in text
    assert text.rstrip().endswith(f"{out}: repaired copy written (6 change(s) above) — 2 episodes, 20 steps; {ds} "
                                  "unchanged")
    assert snapshot(ds) == before
    with ReplayBuffer.open(out) as buf:
        assert buf.n_episodes == 2 and buf["camera0_rgb"].shape[0] == 20
    assert not list(tmp_path.glob("*.tmp-*"))
    # a second run never replaces the copy; an --out inside the input is refused
    assert main(["repair", str(ds), "--out", str(out)]) == 2
    assert main(["repair", str(ds), "--out", str(ds / "x.zarr")]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("umi-aug")]
    assert err == [f"umi-aug repair: error: --out {out}: exists; repair writes a new copy and never replaces "
                   "anything: choose a path that does not exist",
                   f"umi-aug repair: error: --out {ds / 'x.zarr'}: is, contains or lies inside the input {ds}; the "
                   "repaired copy goes next to it: choose another --out"]
    assert snapshot(ds) == before


def test_repair_refuses_a_copy_without_rows_when_episode_ends_is_the_damage(ds, tmp_path, capsys):
    """The issue's case: with a damaged ``episode_ends`` the in-place repair truncated every row of every key to 0."""
    import zarr

    ends = zarr.open_group(str(ds), mode="r+")["meta/episode_ends"]
    ends.resize(1)
    ends[:] = [0]  # a zeroed episode end: the repair drops it, nothing is left
    before = snapshot(ds)
    from umi_aug.cli import main

    assert main(["repair", str(ds), "--out", str(tmp_path / "fixed.zarr")]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("umi-aug")]
    assert err == [f"umi-aug repair: error: {ds}: the repaired copy would hold no step: meta/episode_ends ends at 0 "
                   "after the repair, and cutting the data to it drops every row (20 rows per key); episode_ends is "
                   "the damaged part, not the data: re-create the dataset (nothing was written)"]
    assert snapshot(ds) == before
    assert not (tmp_path / "fixed.zarr").exists() and not list(tmp_path.glob("fixed.zarr*"))


def test_messages_name_flags_not_python_apis():
    """``resume=False`` / ``overwrite=True`` / ``repair=True`` in a user-facing message named no existing flag:
    no string of umi_aug's code (docstrings aside) names them, except the API's own argument check."""
    import ast

    root = Path(__file__).resolve().parents[2] / "umi_aug"
    bad = []
    for p in sorted(root.rglob("*.py")):
        tree = ast.parse(p.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
                and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        for n in ast.walk(tree):
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs:
                if any(api in n.value for api in ("resume=False", "overwrite=True", "repair=True")) and \
                        "repair=True needs mode='a'" not in n.value:
                    bad.append(f"{p.relative_to(root)}:{n.lineno}: {n.value[:70]!r}")
    assert not bad, bad


def test_make_session_message_names_the_overwrite_flag(tmp_path):
    from umi_aug.errors import SimError
    from umi_aug.sim.session import make_session

    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep")
    before = snapshot(out)
    with pytest.raises(SimError) as e:
        make_session(out)
    assert str(e.value) == (f"{out} exists and is not empty; choose another --out, or rerun with --overwrite to "
                            "replace it (its contents are deleted)")
    assert snapshot(out) == before


def test_augment_into_a_plain_dataset_names_no_python_api(tmp_path, stop_before_stages):
    """A user's dataset given as ``--out`` (a directory store): it is not umi-aug's, so neither "delete it" nor
    ``resume=False`` (or --restart, which refuses it) is the fix."""
    from tests.robustness.conftest import build_session, small_cfg
    from umi_aug.errors import AugmentError

    session = build_session(tmp_path / "session")
    out = write_dataset(tmp_path / "mine.zarr", lengths=(4,))
    before = snapshot(out)
    with pytest.raises(AugmentError) as e:
        stop_before_stages.export(session, out, small_cfg(), work_dir=tmp_path / "w", progress=False)
    assert str(e.value) == (f"{out}: exists and is not an umi-aug export (no attribute 'umi_aug_export'; a dataset of "
                            "yours?); umi-aug never writes into it, and --restart deletes only umi-aug's own outputs: "
                            "choose another --out")
    assert snapshot(out) == before


# ------------------------------------------------------------------------------------------- CLI flags
def _cli(capsys, *argv: str) -> tuple[int, list[str], str]:
    from umi_aug.cli import main

    rc = main(list(argv))
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, [ln for ln in cap.err.splitlines() if ln.startswith("umi-aug")], cap.out


def _no_export(monkeypatch) -> None:
    import umi_aug.augment.exporter as ex

    def no_work(*a, **k):
        raise AssertionError("export started")

    monkeypatch.setattr(ex, "export", no_work)


def test_augment_refuses_dataset_only_flags_on_a_session(session, tmp_path, capsys, monkeypatch):
    """Before: ``augment S --episodes 5:9 --tcp-offset -3 --scene-group 7`` exited 0, the three flags ignored."""
    _no_export(monkeypatch)
    before = snapshot(session)
    out = tmp_path / "o.zarr"
    rc, err, _ = _cli(capsys, "augment", str(session), "--out", str(out), "--episodes", "5:9", "--tcp-offset", "-3",
                      "--scene-group", "7")
    assert rc == 2
    assert err == [f"umi-aug augment: error: --episodes, --scene-group, --tcp-offset: {session} is a UMI session "
                   "folder (all its demos are augmented); --episodes applies to a plain dataset or a square demo "
                   "folder input; --scene-group applies to a plain dataset input; --tcp-offset applies to a plain "
                   "dataset input: drop them"]
    rc, err, _ = _cli(capsys, "augment", str(session), "--out", str(out), "--no-embodiment")
    assert err == [f"umi-aug augment: error: --no-embodiment: {session} is a UMI session folder (all its demos are "
                   "augmented); --no-embodiment applies to a square demo folder input: drop it"]
    assert snapshot(session) == before
    assert not list(tmp_path.glob("o.zarr*"))  # neither the output nor its .work/ nor a lock


@pytest.mark.parametrize("flag, value, msg", [
    ("--tcp-offset", "-0.2", "--tcp-offset -0.2: must be in [0.02, 0.5] m (UMI's gripper: 0.205 m, the distance "
                             "from the camera to the fingertips' TCP along its axis)"),
    ("--tcp-offset", "1000", "--tcp-offset 1000.0: must be in [0.02, 0.5] m (UMI's gripper: 0.205 m, the distance "
                             "from the camera to the fingertips' TCP along its axis)"),
    ("--cone-radius", "0", "--cone-radius 0.0: must be in (0, 10) metres"),
    ("--workers", "0", "--workers 0: must be >= 1"),
    ("--splat-coarse-downscale", "0", "--splat-coarse-downscale 0: must be >= 1 and divide --image-size 224 (1 = "
                                      "full size)"),
    ("--splat-coarse-downscale", "3", "--splat-coarse-downscale 3: must be >= 1 and divide --image-size 224 (1 = "
                                      "full size)"),
    ("--jpegxl-effort", "12", "--jpegxl-effort 12: expected an int in 1..9 or 'default'"),
])
def test_augment_flag_ranges_are_checked_before_any_work(tmp_path, capsys, monkeypatch, flag, value, msg):
    """Before: ``--tcp-offset -0.2`` failed after 58 s ("no splice frame"), ``1000`` after 20 s, the offset unnamed."""
    _no_export(monkeypatch)
    ds = write_dataset(tmp_path / "ds.zarr", lengths=(20,))
    before = snapshot(ds)
    rc, err, _ = _cli(capsys, "augment", str(ds), "--out", str(tmp_path / "o.zarr"), flag, value)
    assert rc == 2 and err == [f"umi-aug augment: error: {msg}"]
    assert snapshot(ds) == before and not list(tmp_path.glob("o.zarr*"))


def test_reconstruct_voxel_mm_is_checked_before_sfm(session, tmp_path, capsys, monkeypatch):
    """Before: ``--voxel-mm -3`` was refused only after SfM (87 s), leaving a partial folder."""
    import umi_aug.recon.pipeline as rp

    def no_work(*a, **k):
        raise AssertionError("reconstruction started")

    monkeypatch.setattr(rp, "reconstruct_session", no_work)
    before = snapshot(session)
    rc, err, _ = _cli(capsys, "reconstruct", str(session), "--voxel-mm", "-3", "--out", str(tmp_path / "rec"))
    assert rc == 2
    assert err == ["umi-aug reconstruct: error: --voxel-mm -3.0: must be in [0.5, 200] mm (the SDF voxel; omit it to "
                   "choose one from the region)"]
    assert snapshot(session) == before and not (tmp_path / "rec").exists()


def test_intrinsics_warns_on_a_principal_point_outside_the_image_and_a_360_degree_fov(tmp_path, capsys):
    import json

    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json

    ok = save_umi_intrinsics_json(gopro_intrinsics_2_7k(), tmp_path / "ok.json") or tmp_path / "ok.json"
    rc, err, out = _cli(capsys, "intrinsics", str(ok))
    assert rc == 0 and "warning" not in out
    d = json.loads(ok.read_text())
    d["intrinsics"]["principal_pt_x"] = 5000.0
    for i in range(1, 5):
        d["intrinsics"][f"radial_distortion_{i}"] = 0.0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(d))
    rc, err, out = _cli(capsys, "intrinsics", str(bad))
    assert rc == 0 and not err
    warnings = [ln for ln in out.splitlines() if ln.startswith("warning:")]
    assert warnings == [f"warning: {bad}: principal point (cx, cy) = (5000.0, 1011.5) px lies outside the 2704x2028 "
                        "image",
                        f"warning: {bad}: valid FOV = 360.00° is more than a fisheye lens sees (GoPro: about 155°; "
                        "UMI's calibration folds over at 104° from the axis): the distortion coefficients k = (0.0, "
                        "0.0, 0.0, 0.0) never fold over — a calibration of another camera model?"]


def test_a_failed_up_front_check_leaves_no_empty_work_dir(tmp_path):
    """Before: a plain dataset refused by its up-front check left an empty ``<out>.work/`` (the work-dir lock's)."""
    from tests.robustness.conftest import small_cfg
    from umi_aug.augment.exporter import export
    from umi_aug.errors import AugmentError

    ds = write_dataset(tmp_path / "ds.zarr", lengths=(6,))  # too short to augment
    before = snapshot(ds)
    with pytest.raises(AugmentError, match="an augmentable episode needs"):
        export(ds, tmp_path / "o.zarr", small_cfg(), progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds.zarr"]
    assert snapshot(ds) == before
    kept = tmp_path / "mine.work"  # a work dir the user made is never removed, even when empty
    kept.mkdir()
    with pytest.raises(AugmentError, match="an augmentable episode needs"):
        export(ds, tmp_path / "o.zarr", small_cfg(), work_dir=kept, progress=False)
    assert kept.is_dir() and not any(kept.iterdir())


# ------------------------------------------------------------------------------------------- SIGTERM
def test_sigterm_ends_in_one_line_exit_143(tmp_path, monkeypatch, capsys):
    """``timeout``/``kill`` (SIGTERM) is handled like Ctrl-C: one line, its own exit code, the handler put back."""
    import signal
    import time

    import umi_aug.data
    from umi_aug.cli import main

    def killed(*a, **k):
        os.kill(os.getpid(), signal.SIGTERM)  # delivered to this (main) thread before the next bytecode
        time.sleep(30)
        raise AssertionError("SIGTERM not handled")

    monkeypatch.setattr(umi_aug.data, "validate_replay_buffer", killed)
    before = signal.getsignal(signal.SIGTERM)
    assert main(["validate", str(tmp_path / "x.zarr")]) == 143
    err = capsys.readouterr().err
    assert err == ("umi-aug validate: interrupted (SIGTERM); nothing half-written is kept — rerun the same command "
                   "to resume\n")
    assert signal.getsignal(signal.SIGTERM) == before


def test_sigterm_after_pycolmap_is_imported_is_still_ours():
    """pycolmap's glog replaced the SIGTERM handler at import: a ``timeout`` during reconstruction printed its
    21-frame native stack trace and no "interrupted" line (rc 143)."""
    pytest.importorskip("pycolmap")
    code = ("import os, signal, time\n"
            "from umi_aug.runtime import Terminated, terminate_like_ctrl_c\n"
            "with terminate_like_ctrl_c():\n"
            "    from umi_aug.recon.sfm import _pycolmap\n"
            "    _pycolmap()\n"
            "    try:\n"
            "        os.kill(os.getpid(), signal.SIGTERM)\n"
            "        time.sleep(30)\n"
            "    except Terminated:\n"
            "        print('terminated like ctrl-c')\n")
    root = Path(__file__).resolve().parents[2]
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=root,
                         env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)})
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "terminated like ctrl-c" and "stack trace" not in res.stderr


def test_a_half_written_episode_end_points_at_the_repair_command(ds, tmp_path, capsys):
    import zarr

    _append_rows(ds, 3)
    ends = zarr.open_group(str(ds), mode="r+")["meta/episode_ends"]
    ends.resize(3)  # grown, value not yet written: [10, 20, 0]
    before = snapshot(ds)
    rc, err, _ = _validate(capsys, ds)
    assert rc == 2
    assert err == [f"umi-aug validate: error: {ds}: key 'meta/episode_ends' must be strictly increasing: "
                   "episode_ends[2] = 0 <= episode_ends[1] = 20; a half-written last entry (an interrupted append?): "
                   f"`umi-aug repair {ds} --out <new path>` writes a copy without it (this one is not changed)"]
    rc, _, out = _cli(capsys, "repair", str(ds), "--out", str(tmp_path / "fixed.zarr.zip"))
    assert rc == 0 and "2 episodes, 20 steps" in out
    assert snapshot(ds) == before


# ------------------------------------------------------------------------------------------- session inputs (rest)
def _edit_csv(csv: Path, fn) -> None:
    from umi_aug.data.trajectory_csv import read_camera_trajectory_csv, write_camera_trajectory_csv

    traj = read_camera_trajectory_csv(csv)
    fn(traj)
    write_camera_trajectory_csv(csv, traj)


def _augment_refused(capsys, session: Path, tmp_path: Path, stop_before_stages) -> str:
    """``umi-aug augment SESSION`` → exit 2 with one ``error:`` line before any stage, nothing created; the line."""
    from tests.robustness.conftest import S

    before = snapshot(session)
    out = tmp_path / "out.zarr"
    rc, err, _ = _cli(capsys, "augment", str(session), "--out", str(out), "--image-size", str(S), "--no-pictures")
    assert rc == 2 and len(err) == 1 and err[0].startswith("umi-aug augment: error: ")
    assert not out.exists() and not Path(f"{out}.work").exists()
    assert snapshot(session) == before
    return err[0][len("umi-aug augment: error: "):]


@pytest.mark.parametrize("lost, frames, lines", [(slice(None), "0..7", "2..9"), (slice(2, 5), "2..4", "4..6")])
def test_lost_csv_rows_in_an_episode_are_named_not_called_a_collision(session, tmp_path, capsys, stop_before_stages,
                                                                      lost, frames, lines):
    """Before: all rows lost → exit 0 with a WARNING "not augmented"; 60 lost rows in the approach → the demo failed
    8x as "collision" (exit 3): the lost rows' placeholder poses (the origin) were planned through."""
    from tests.robustness.conftest import N_DEMO

    csv = session / "demos" / "demo_00" / "camera_trajectory.csv"

    def lose(t):
        t.is_lost[lost] = True
        t.T_world_cam[lost] = np.eye(4)

    _edit_csv(csv, lose)
    n = len(range(N_DEMO)[lost])
    assert _augment_refused(capsys, session, tmp_path, stop_before_stages) == (
        f"{csv}: {n} of the {N_DEMO} rows of the dataset episode's frames are lost by SLAM (is_lost=true): frames "
        f"{frames} (CSV lines {lines}); a lost row has no pose (augmenting would plan through the placeholder at the "
        "origin): re-create dataset.zarr.zip with UMI's pipeline (its episodes are the tracked segments: "
        "06_generate_dataset_plan), or remove demos/demo_00 and its episode")


def test_a_5_m_jump_in_a_demo_csv_names_the_row_and_the_jump(session, tmp_path, capsys, stop_before_stages):
    """Before: exit 3, every attempt a "collision"."""
    csv = session / "demos" / "demo_00" / "camera_trajectory.csv"

    def jump(t):
        t.T_world_cam[5:, 1, 3] += 5.0

    _edit_csv(csv, jump)
    msg = _augment_refused(capsys, session, tmp_path, stop_before_stages)
    assert msg.startswith(f"{csv}: line 7 (frame 5): the camera pose jumps 5.000 m / 0.0 deg from frame 4 (limits "
                          "0.05 m, 20.0 deg per frame: faster than a hand moves the gripper — a SLAM relocalisation "
                          "error): re-run UMI's SLAM for demos/demo_00"), msg


def test_a_smooth_demo_csv_passes_the_trajectory_check(session):
    """The checks' limits leave a real hand-held motion alone (the template's demo moves 14 mm per frame)."""
    from umi_aug.augment.preflight import check_session_inputs

    check_session_inputs(session)


def test_a_missing_raw_video_is_named_as_the_cause(session, tmp_path, capsys, stop_before_stages):
    """Before: a WARNING "no raw_video.mp4; demo skipped", then the error line blamed the pose matching ("episode 0
    matches no tracked segment … add UMI's dataset_plan.pkl")."""
    video = session / "demos" / "demo_00" / "raw_video.mp4"
    video.unlink()
    msg = _augment_refused(capsys, session, tmp_path, stop_before_stages)
    assert msg == (f"{video}: missing; without it the episodes of {session / 'dataset.zarr.zip'} cannot all be matched "
                   "to the demo videos (each episode is a segment of one demo's raw_video.mp4 with its "
                   "camera_trajectory.csv): restore the missing file(s), or remove that demo folder and re-create "
                   "dataset.zarr.zip with UMI")
    assert "dataset_plan.pkl" not in msg and "matches no tracked segment" not in msg


@pytest.mark.parametrize("content", [b"garbage\x00\x01", None])
def test_a_garbage_dataset_plan_is_refused_even_when_episodes_are_whole_videos(session, tmp_path, capsys,
                                                                               stop_before_stages, content):
    """Before: ignored (the episodes happened to match the whole videos, so the plan was never read)."""
    import pickle

    plan = session / "dataset_plan.pkl"
    plan.write_bytes(content if content is not None else pickle.dumps({"not": "a plan"}))
    msg = _augment_refused(capsys, session, tmp_path, stop_before_stages)
    if content is not None:
        assert msg == (f"{plan}: unreadable (UnpicklingError: pickle data was truncated); re-run UMI's "
                       "06_generate_dataset_plan or remove it (episodes are then matched by their TCP poses)")
    else:
        assert msg == (f"{plan}: dict planned episodes but {session / 'dataset.zarr.zip'} has 1; the plan belongs to "
                       "another dataset (07_generate_replay_buffer writes one episode per plan entry)")


def test_a_valid_dataset_plan_of_whole_video_episodes_is_used(session):
    """The plan is now read for whole-video episodes too: a correct one (UMI's TCP poses) still loads."""
    import pickle

    from tests.robustness.conftest import N_DEMO, S
    from umi_aug.data import ReplayBuffer, make_umi_episode, read_camera_trajectory_csv
    from umi_aug.geometry.umi import umi_T_cam_tcp
    from umi_aug.recon.session_io import load_session

    T = read_camera_trajectory_csv(session / "demos" / "demo_00" / "camera_trajectory.csv").T_world_cam
    buf = ReplayBuffer.create()  # tx_slam_tag = identity: the TCP in the tag frame is the CSV pose @ T_cam_tcp
    buf.add_episode(make_umi_episode(T @ umi_T_cam_tcp(), np.full(N_DEMO, 0.05),
                                     {0: np.zeros((N_DEMO, S, S, 3), np.uint8)}))
    (session / "dataset.zarr.zip").unlink()
    buf.save(session / "dataset.zarr.zip")
    (session / "dataset_plan.pkl").write_bytes(pickle.dumps(
        [{"cameras": [{"video_path": "demo_00/raw_video.mp4", "video_start_end": (0, N_DEMO)}]}]))
    sess = load_session(session)
    assert [(d.name, d.n_frames, d.frame_offset) for d in sess.demos] == [("demo_00", N_DEMO, 0)]


# ------------------------------------------------------------------------------------------- disk full, interrupted export
class _Disk:
    """zarr's directory-store writer (``DirectoryStore._tofile``) on a disk that fills up: once ``fill()`` was called,
    ``room`` more chunk/metadata files are written, then every write raises ``OSError(ENOSPC)`` as ``write()`` does
    on a full disk (no file name) — until ``free()``."""

    def __init__(self, monkeypatch):
        import zarr

        self.real, self.room, self.filled = zarr.storage.DirectoryStore._tofile, None, False
        monkeypatch.setattr(zarr.storage.DirectoryStore, "_tofile", staticmethod(self._tofile))

    def _tofile(self, a, fn):
        import errno

        if self.room is not None:
            if self.room <= 0:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.room -= 1
        return self.real(a, fn)

    def fill(self, room: int) -> None:
        self.room, self.filled = room, True

    def free(self) -> None:
        self.room = None


def _light_stages(monkeypatch, session: Path, disk: _Disk, fill_on_job: int):
    """``augment``'s stages and per-episode planning/rendering replaced by the session dataset's own episode (its
    frames and poses as the "augmented" episode): the export's real store, records, commit order, disk-full handling
    and resume run on it in well under a second. The disk fills (once) while job ``fill_on_job``'s episode is
    written."""
    import types

    import umi_aug.augment.exporter as ex
    import umi_aug.augment.sources.session as session_source
    from umi_aug.data import ReplayBuffer

    ds = session / "dataset.zarr.zip"
    src = ReplayBuffer.open(ds)
    ep = src.get_episode(0)
    lowdim = {k: v for k, v in ep.items() if k != "camera0_rgb"}

    def prepare_session(session_dir, work, cfg, **kw):
        return types.SimpleNamespace(
            cfg=cfg, paths={"dataset": str(ds)}, demos=[types.SimpleNamespace(index=0, name="demo_00",
                                                                              contact_index=2)],
            augmentable=[0], original=src, stages={}, work_dir=Path(work),
            umi_episode=lambda episode, d=None: {k: v.copy() for k, v in lowdim.items()},
            scene_to_build=lambda d: None)  # a session's one scene: nothing left to build per episode

    def job_task(args):
        _, j, job, *_ = args
        planned = types.SimpleNamespace(splice_index=0, seed=100 + j, attempts=1, episode=None,
                                        n_frames=len(ep["camera0_rgb"]), obstacle=None)
        return ex._JobResult(j, planned, 1, [], ep["camera0_rgb"].copy(), False, 0.0, 0.0)

    real_append = ex.append_episode

    def append(buf, *a, **k):
        if not disk.filled and int(buf.meta["aug_job"][-1]) == fill_on_job:  # its record is in: its data is next
            disk.fill(room=3)
        return real_append(buf, *a, **k)

    monkeypatch.setattr(session_source, "prepare_session", prepare_session)
    monkeypatch.setattr(ex, "_job_task", job_task)
    monkeypatch.setattr(ex, "append_episode", append)
    return src


@pytest.mark.parametrize("name", ["out.zarr", "out.zarr.zip"])
def test_disk_full_names_the_path_and_validate_says_the_export_is_interrupted(session, tmp_path, capsys, monkeypatch,
                                                                               name):
    """Before: ``error: No space left on device`` (no path), and ``umi-aug validate out.zarr`` said ``OK — 2
    episodes`` for an export that should have 4. Now the path, the free space and what is kept; validate names the
    export as interrupted (2 of 4, from its own records) and the command that resumes it — which the test runs."""
    import shlex

    from tests.robustness.conftest import N_DEMO, S
    from umi_aug.data import ReplayBuffer

    monkeypatch.chdir(tmp_path)
    disk = _Disk(monkeypatch)
    src = _light_stages(monkeypatch, session, disk, fill_on_job=1)
    before = snapshot(session)
    out = tmp_path / name
    wpath = out.with_name(out.name + ".partial") if name.endswith(".zip") else out
    argv = ["augment", str(session), "--out", str(out), "-n", "3", "--image-size", str(S), "--no-pictures"]
    rc, err, _ = _cli(capsys, *argv, "--restart")  # --restart: not part of the command that resumes
    assert rc == 2 and len(err) == 1, err
    what = "the export" if wpath == out else "the export's working store"
    assert err[0].startswith(f"umi-aug augment: error: {wpath}: disk full while writing {what} (No space left on "
                             "device; "), err[0]
    assert err[0].endswith(f" free on it); 2 of the 4 planned episodes are written and kept in {wpath}: free some "
                           "space (or choose --out/--work on another disk) and rerun the same command to resume")
    disk.free()

    rc, err, out_text = _cli(capsys, "validate", str(out))
    cmd = shlex.join(["umi-aug", *argv])
    head = (f"{out}: an interrupted umi-aug export, not complete: it holds" if wpath == out else
            f"{out}: not written yet — the export was interrupted; its working store {wpath} holds")
    assert rc == 2 and err == [f"umi-aug validate: error: {head} 2 of the 4 planned episodes (1 original + 1 "
                               f"augmented; 1 of 3 augmentation jobs finished); resume it with `{cmd}`: it continues "
                               "after the last finished job"], err
    assert "OK" not in out_text

    rc, err, _ = _cli(capsys, *shlex.split(cmd)[1:])  # the advice, followed
    assert rc == 0, err
    rc, err, out_text = _cli(capsys, "validate", str(out))
    assert rc == 0 and err == [] and out_text.startswith(f"{out}: OK — 4 episodes, {4 * N_DEMO} steps")
    with ReplayBuffer.open(out) as buf:
        orig = src.get_episode(0)
        eps = [buf.get_episode(e) for e in range(4)]
        for got in eps:  # every episode whole, none twice (the episode the disk cut was written again)
            assert all(np.array_equal(got[k], orig[k]) for k in orig if k != "camera0_rgb")
        assert np.array_equal(eps[0]["camera0_rgb"], orig["camera0_rgb"])  # the original: copied as stored
        for got in eps[2:]:  # the new frames: JPEG-XL encoded alike, whether before or after the full disk
            assert np.array_equal(got["camera0_rgb"], eps[1]["camera0_rgb"])
        assert buf.meta["aug_job"][:].tolist() == [-1, 0, 1, 2]
    assert snapshot(session) == before


def test_disk_full_in_the_stage_cache_names_the_work_dir(session, tmp_path, capsys, monkeypatch):
    import errno

    import umi_aug.augment.sources.session as session_source
    from tests.robustness.conftest import S

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(session_source, "prepare_session", full)
    out = tmp_path / "out.zarr"
    rc, err, _ = _cli(capsys, "augment", str(session), "--out", str(out), "--image-size", str(S))
    assert rc == 2 and len(err) == 1
    assert err[0].startswith(f"umi-aug augment: error: {out}.work: disk full while writing the stage cache (--work) "
                             "(No space left on device; ")
    assert err[0].endswith("free on it); nothing half-written is kept: free some space (or choose --out/--work on "
                           "another disk) and rerun the same command to resume")


def test_a_full_disk_while_caching_a_plan_names_the_file(tmp_path, monkeypatch):
    """The plan cache is written on the workers: its ``write()`` names no file, the error now does."""
    import errno
    import pickle

    import umi_aug.augment.exporter as ex

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pickle, "dump", full)
    target = tmp_path / "plans" / "k" / "freespace_d000_a00000.pkl"
    with pytest.raises(OSError) as e:
        ex._save_planned(target, object())
    assert (e.value.errno, e.value.filename) == (errno.ENOSPC, str(target))
    assert not target.exists() and not any(p.is_file() for p in tmp_path.rglob("*"))  # no temporary left


def test_validate_an_interrupted_export_of_the_python_api_names_the_cli_way_to_resume(tmp_path):
    """An export without a recorded command (made before this round, or through ``export()``) still reads as
    interrupted, with the CLI way to resume."""
    import zarr

    from umi_aug.augment.export_store import interrupted_export_message

    ds = write_dataset(tmp_path / "x.zarr", lengths=(10,))
    root = zarr.open_group(str(ds), mode="r+")
    root.attrs["umi_aug_export"] = {"key": "k", "n_jobs": 4, "n_original": 1, "last_job_done": 0, "failures": [
        {"job": 0}]}
    assert interrupted_export_message(ds) == (
        f"{ds}: an interrupted umi-aug export, not complete: it holds 1 of the 5 planned episodes (1 original + 0 "
        "augmented; 1 of 4 augmentation jobs finished, 1 failed); resume it by rerunning the `umi-aug augment` command "
        "that wrote it (the same input, --out and flags, without --restart): it continues after the last finished job")
    root.attrs["umi_aug_export"] = {"key": "k", "n_jobs": 4, "n_original": 1, "last_job_done": 3, "failures": []}
    assert interrupted_export_message(ds) is None  # complete
    assert interrupted_export_message(write_dataset(tmp_path / "plain.zarr", lengths=(10,))) is None


def test_a_missing_demo_csv_is_named_when_episodes_are_segments(session, tmp_path, capsys, stop_before_stages):
    """The same kind as a missing video: episodes shorter than their videos are matched by pose, and a demo without
    its CSV made that matching fail ("matches no tracked segment") instead of naming the CSV."""
    csv = session / "demos" / "demo_00" / "camera_trajectory.csv"
    (session / "dataset.zarr.zip").unlink()
    write_dataset(session / "dataset.zarr.zip", lengths=(6,))  # a segment of the 8-frame video
    csv.unlink()
    msg = _augment_refused(capsys, session, tmp_path, stop_before_stages)
    assert msg.startswith(f"{csv}: missing; without it the episodes of {session / 'dataset.zarr.zip'} cannot all be "
                          "matched to the demo videos"), msg


def test_a_mapping_csv_without_one_tracked_row_is_refused(session, tmp_path, capsys, stop_before_stages):
    """Before: accepted; the scan's reconstruction then had no pose to start from."""
    csv = session / "demos" / "mapping" / "mapping_camera_trajectory.csv"

    def lose(t):
        t.is_lost[:] = True
        t.T_world_cam[:] = np.eye(4)

    _edit_csv(csv, lose)
    assert _augment_refused(capsys, session, tmp_path, stop_before_stages) == (
        f"{csv}: all 6 rows are lost by SLAM (is_lost=true): the scan has no camera pose to reconstruct from; re-run "
        "UMI's SLAM mapping")
