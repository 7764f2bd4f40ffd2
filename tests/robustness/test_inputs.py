"""Bad-input suite, inputs (issue #18 cases 3, 4, 6, 7): caches keyed by content, image chunks validated, each
session-dataset / CSV / intrinsics problem named by its own message before any compute, an interrupted stage of
another configuration cleared instead of blocking.

Every case asserts the exact message and that the inputs are byte-identical afterwards.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.robustness.conftest import N_DEMO, S, small_cfg, snapshot, write_dataset


# ------------------------------------------------------------------------------------------- 3: content keys
def _raw_zip_dataset(path: Path, widths: np.ndarray) -> Path:
    """A ``.zarr.zip`` with uncompressed arrays: editing a value keeps every size (the file's too)."""
    import zarr

    store = zarr.ZipStore(str(path), mode="w")
    root = zarr.group(store)
    root.create_group("data").array("robot0_gripper_width", widths[:, None].astype(np.float32), compressor=None)
    root.create_group("meta").array("episode_ends", np.array([len(widths)]), compressor=None)
    store.close()
    return path


def test_a_same_size_edit_of_the_dataset_changes_the_key_and_reruns_the_stage(session, tmp_path):
    from umi_aug.augment.cache import run_stage
    from umi_aug.augment.sources.session import session_fingerprint

    ds = session / "dataset.zarr.zip"
    w = np.linspace(0.0, 0.08, N_DEMO)
    _raw_zip_dataset(ds, w)
    size, fp1 = ds.stat().st_size, session_fingerprint(session)
    w[3] += 0.01  # the user edits one gripper width in place
    _raw_zip_dataset(ds, w)
    assert ds.stat().st_size == size
    fp2 = session_fingerprint(session)
    assert fp2 != fp1
    runs = []

    def fn(out):
        runs.append(1)
        (out / "o.txt").write_text("x")
        return {"o": "o.txt"}, ["o.txt"], {}

    run_stage("reconstruct", tmp_path / "w", {"a": 1}, {"session": fp1}, fn)
    assert run_stage("reconstruct", tmp_path / "w", {"a": 1}, {"session": fp1}, fn).skipped
    assert not run_stage("reconstruct", tmp_path / "w", {"a": 1}, {"session": fp2}, fn).skipped
    assert len(runs) == 2


def test_a_same_size_edit_of_a_plain_dataset_input_changes_its_fingerprint(tmp_path):
    """Plain-dataset input (``umi-aug augment DATASET.zarr.zip``): the export and scene keys hash content, so an
    in-place edit of the same size within the same second is seen (size + mtime was not)."""
    import os

    from umi_aug.augment.dataset_source import dataset_fingerprint

    ds = tmp_path / "dataset.zarr.zip"
    w = np.linspace(0.0, 0.08, 40)
    _raw_zip_dataset(ds, w)
    st1, fp1 = ds.stat(), dataset_fingerprint(ds)
    w[7] += 0.01
    _raw_zip_dataset(ds, w)
    os.utime(ds, ns=(st1.st_atime_ns, st1.st_mtime_ns))  # same size, same mtime
    assert ds.stat().st_size == st1.st_size
    assert dataset_fingerprint(ds) != fp1


def test_an_edited_intrinsics_file_changes_the_key(session):
    from umi_aug.augment.sources.session import session_fingerprint

    fp1 = session_fingerprint(session)
    p = next((session / "calibration").glob("*.json"))
    d = json.loads(p.read_text())
    d["intrinsics"]["focal_length"] = float(d["intrinsics"]["focal_length"]) * 1.01
    p.write_text(json.dumps(d))
    assert session_fingerprint(session) != fp1


# ------------------------------------------------------------------------------------------- 4: image chunks
@pytest.fixture
def dir_dataset(tmp_path):
    return write_dataset(tmp_path / "ds.zarr", lengths=(5, 3))


def test_validate_reports_a_missing_image_chunk(dir_dataset):
    from umi_aug.data import validate_replay_buffer
    from umi_aug.errors import DatasetError

    (dir_dataset / "data" / "camera0_rgb" / "6.0.0.0").unlink()
    before = snapshot(dir_dataset)
    with pytest.raises(DatasetError) as e:
        validate_replay_buffer(dir_dataset)
    assert str(e.value) == (f"{dir_dataset}: key 'data/camera0_rgb': 1 of 8 chunks missing, first '6.0.0.0' "
                            f"(rows 6..6); they would read as fill value 0 (black frames / zeros). The dataset is "
                            f"truncated or was copied incompletely: re-copy or re-create it")
    assert snapshot(dir_dataset) == before


def test_validate_deep_reports_a_garbage_image_chunk(dir_dataset, capsys):
    from umi_aug.cli import main
    from umi_aug.data import validate_replay_buffer
    from umi_aug.errors import DatasetError

    (dir_dataset / "data" / "camera0_rgb" / "2.0.0.0").write_bytes(b"\x00garbage" * 40)
    before = snapshot(dir_dataset)
    validate_replay_buffer(dir_dataset)  # the listing is complete: plain validate cannot see it
    with pytest.raises(DatasetError, match=r"key 'data/camera0_rgb': chunk 2 \(rows 2..2\) cannot be decoded \("):
        validate_replay_buffer(dir_dataset, deep=True)
    assert main(["validate", "--deep", str(dir_dataset)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    err = [ln for ln in err.splitlines() if ln.startswith("umi-aug")]  # (the rest: the decode progress bar)
    assert len(err) == 1 and err[0].startswith(f"umi-aug validate: error: {dir_dataset}: key 'data/camera0_rgb': "
                                               f"chunk 2 (rows 2..2) cannot be decoded (")
    assert err[0].endswith("the chunk is corrupt: re-copy or re-create the dataset")
    assert snapshot(dir_dataset) == before


def test_validate_deep_passes_a_good_dataset(dir_dataset, capsys):
    from umi_aug.cli import main

    assert main(["validate", "--deep", str(dir_dataset)]) == 0
    assert "every chunk decoded" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------- 6: session inputs
def _check(session):
    from umi_aug.augment.preflight import check_session_inputs
    from umi_aug.errors import AugmentError

    before = snapshot(session)
    with pytest.raises(AugmentError) as e:
        check_session_inputs(session)
    assert snapshot(session) == before
    return str(e.value)


def test_session_truncated_dataset_zip(session):
    ds = session / "dataset.zarr.zip"
    ds.write_bytes(ds.read_bytes()[: ds.stat().st_size // 2])
    assert _check(session) == (f"{ds}: not a readable zip file (File is not a zip file); expected a UMI .zarr.zip")


def test_session_nan_gripper_width(session):
    import zarr

    ds = session / "dataset.zarr.zip"
    tmp = session.parent / "edit.zarr"
    zarr.copy_store(zarr.ZipStore(str(ds), mode="r"), zarr.DirectoryStore(str(tmp)))
    a = zarr.open_group(str(tmp), mode="r+")["data/robot0_gripper_width"]
    a[3] = np.nan
    ds.unlink()
    zs = zarr.ZipStore(str(ds), mode="w")
    zarr.copy_store(zarr.DirectoryStore(str(tmp)), zs)
    zs.close()
    shutil.rmtree(tmp)
    assert _check(session) == f"{ds}: key 'data/robot0_gripper_width' holds NaN/Inf, first at row 3: [nan]"


def test_session_episode_and_demo_count_mismatch(session):
    ds = session / "dataset.zarr.zip"
    ds.unlink()
    write_dataset(ds, lengths=(N_DEMO, N_DEMO))
    # not one episode per video: each must be a tracked segment of a demo video (UMI's episodes), matched by TCP
    msg = _check(session)
    assert msg.startswith(f"{ds}: episode 0 (8 steps) matches no tracked segment of the demo videos (demo_00): "
                          f"robot0_eef_pos must equal the TCP of camera_trajectory.csv"), msg
    assert "within 0.002 m on every frame; nearest tracked start: demo_00 frame 0 at " in msg


def test_session_episode_length_mismatch(session):
    ds = session / "dataset.zarr.zip"
    ds.unlink()
    write_dataset(ds, lengths=(N_DEMO - 1,))
    msg = _check(session)
    assert msg.startswith(f"{ds}: episode 0 ({N_DEMO - 1} steps) matches no tracked segment of the demo videos "
                          f"(demo_00): robot0_eef_pos must equal the TCP"), msg


def test_session_image_size_other_than_the_runs(session, tmp_path, stop_before_stages):
    from umi_aug.errors import AugmentError

    ds = session / "dataset.zarr.zip"
    before = snapshot(session)
    with pytest.raises(AugmentError) as e:  # before: found after the reconstruction, in the gripper_mask stage
        stop_before_stages.export(session, tmp_path / "o.zarr", small_cfg(image_size=2 * S), work_dir=tmp_path / "w",
                                  progress=False)
    assert str(e.value) == (f"{ds}: key 'data/camera0_rgb' has {S}x{S} frames but image_size = {2 * S}; export at "
                            f"the dataset's resolution (--image-size {S})")
    assert snapshot(session) == before


def test_session_missing_image_chunk(session):
    import zipfile

    ds = session / "dataset.zarr.zip"
    with zipfile.ZipFile(ds) as zin:
        items = [(i, zin.read(i)) for i in zin.infolist() if i.filename != "data/camera0_rgb/4.0.0.0"]
    with zipfile.ZipFile(ds, "w") as zout:
        for i, b in items:
            zout.writestr(i, b)
    assert _check(session).startswith(f"{ds}: key 'data/camera0_rgb': 1 of {N_DEMO} chunks missing, first '4.0.0.0'")


def test_session_non_monotonic_csv_timestamps(session):
    csv = session / "demos" / "demo_00" / "camera_trajectory.csv"
    lines = csv.read_text().splitlines()
    f = lines[4].split(",")
    f[1] = "0.01"  # row 3 (line 5) earlier than row 2
    lines[4] = ",".join(f)
    csv.write_text("\n".join(lines) + "\n")
    msg = _check(session)
    assert msg == (f"{csv}: line 5, column 'timestamp' (#2): timestamps must increase: 0.01 s after "
                   f"0.06666666666666667 s (frame_idx 3 after 2)"), msg


def test_session_missing_mapping_csv(session):
    csv = session / "demos" / "mapping" / "mapping_camera_trajectory.csv"
    csv.unlink()
    video = session / "demos" / "mapping" / "raw_video.mp4"
    assert _check(session) == (f"{csv}: missing (the camera trajectory of {video}"
                               f", from UMI's SLAM step); every sequence needs its CSV")


def test_suspicious_intrinsics_warn(session):
    from umi_aug.augment.preflight import check_session_inputs

    p = next((session / "calibration").glob("*.json"))
    d = json.loads(p.read_text())
    d["intrinsics"]["focal_length"] = float(d["intrinsics"]["focal_length"]) * 10  # a wrong focal length
    d["intrinsics"]["principal_pt_x"] = -5.0
    p.write_text(json.dumps(d))
    w = check_session_inputs(session).warnings
    assert any("principal point (cx, cy) = (-5.0," in x and "lies outside the 64x48 image" in x for x in w), w
    assert any("a wrong focal length or a calibration of another resolution?" in x for x in w), w


def test_export_checks_the_session_before_any_stage(session, tmp_path, stop_before_stages):
    from umi_aug.errors import AugmentError

    ds = session / "dataset.zarr.zip"
    ds.write_bytes(ds.read_bytes()[:100])
    before = snapshot(session)
    with pytest.raises(AugmentError, match="not a readable zip file"):
        stop_before_stages.export(session, tmp_path / "o.zarr.zip", small_cfg(), work_dir=tmp_path / "w",
                                  progress=False)
    assert snapshot(session) == before and not (tmp_path / "o.zarr.zip.partial").exists()


# ------------------------------------------------------------------------------------------- 7: interrupted stage
def test_an_interrupted_stage_does_not_block_a_config_change(tmp_path):
    """A stand-in for the 3DGS trainer: it resumes from its checkpoint and refuses one of other settings."""
    from umi_aug.augment.cache import run_stage
    from umi_aug.errors import SplatError

    def trainer(cfg, interrupt=False):
        def fn(out: Path):
            ck = out / "checkpoint.json"
            if ck.exists() and json.loads(ck.read_text())["cfg"] != cfg:
                raise SplatError(f"{ck}: checkpoint was trained with other settings")
            resumed = ck.exists()
            ck.write_text(json.dumps({"cfg": cfg}))
            if interrupt:
                raise KeyboardInterrupt
            (out / "scene.ply").write_text("ply")
            return {"ply": "scene.ply"}, ["scene.ply"], {"resumed": resumed}
        return fn

    work = tmp_path / "w"
    with pytest.raises(KeyboardInterrupt):
        run_stage("splat", work, {"it": 100}, {}, trainer(100, interrupt=True))
    r = run_stage("splat", work, {"it": 200}, {}, trainer(200))  # another config: the partial work is cleared
    assert not r.skipped and r.info == {"resumed": False}
    with pytest.raises(KeyboardInterrupt):
        run_stage("splat", work, {"it": 300}, {}, trainer(300, interrupt=True))
    r = run_stage("splat", work, {"it": 300}, {}, trainer(300))  # the same config resumes
    assert r.info == {"resumed": True}


# ------------------------------------------------------------------------------------------- real data
REAL = (Path(__file__).resolve().parents[2].parent / "shared" / "realdata" / "umi_cup_in_the_wild_ep0"
        / "dataset.zarr.zip")


@pytest.mark.skipif(not REAL.is_file(), reason=f"real UMI dataset not present at {REAL}")
def test_real_umi_dataset_passes_the_chunk_listing_check_and_fingerprints_stably():
    from umi_aug.data import validate_replay_buffer
    from umi_aug.data.fingerprint import content_fingerprint

    r = validate_replay_buffer(REAL)  # no false positive: every one of its 400 image chunks is listed
    assert r.n_steps == 400 and not [w for w in r.warnings if "chunks missing" in w]
    assert content_fingerprint(REAL) == content_fingerprint(REAL)
