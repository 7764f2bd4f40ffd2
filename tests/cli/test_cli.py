"""The ``umi-aug`` command: the demo runs end to end and writes its artefacts; bad input exits 2 with one
message naming the input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from umi_aug.cli import main


@pytest.mark.slow
def test_demo_runs_end_to_end(demo_run):
    """The run itself is the session fixture ``demo_run`` (tests/conftest.py): CI-sized, 1 augmented episode and
    60 3DGS steps (held-out PSNR ~17 dB; 40 steps gave 15.4 dB, 150 gave 22.6 dB — the thresholds below are sanity
    bounds; 3DGS quality itself is tested in tests/splat)."""
    out, args = demo_run.out, demo_run.args
    assert demo_run.rc == 0
    for name in ("dataset.zarr.zip", "dataset.zarr.zip.summary.json", "render_vs_gt.png", "lens.png",
                 "summary.json", "session/session.json", "session/dataset.zarr.zip", "session/contact_sheet.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset_episodes"] == 2  # the original + 1 augmented
    for pic in summary["export"]["pictures"].values():
        assert Path(pic).is_file(), pic
    stages = {s["stage"]: s["status"] for s in summary["stages"]}
    for name in ("geometry", "camera", "data", "sim", "recon", "splat", "traj", "augment"):
        assert stages[name] == "ran", name
    assert summary["splat"]["trained"] and summary["splat"]["heldout_psnr"] > 11.0  # 60 steps only
    gt = summary["ground_truth_check"]
    assert gt["frames"] > 0 and np.isfinite(gt["psnr_db_median"]) and gt["psnr_db_median"] > 12.0
    printed = demo_run.printed
    assert "augmented vs ground truth" in printed and "umi-aug augment" in printed

    from umi_aug.augment import read_episode_records
    from umi_aug.data import ReplayBuffer

    rec = read_episode_records(out / "dataset.zarr.zip")
    assert rec["aug_mode"].tolist() == [0, 1]
    buf = ReplayBuffer.open(out / "dataset.zarr.zip")
    orig, new = buf.get_episode(0), buf.get_episode(1)
    n_new = int(rec["aug_splice_index"][1])  # frames before the splice
    c = len(orig["robot0_eef_pos"]) - (len(new["robot0_eef_pos"]) - n_new)  # the demo's splice frame
    assert new["camera0_rgb"].shape[1:] == (224, 224, 3)
    # after the splice the new episode replays the original motion and frames exactly
    np.testing.assert_array_equal(new["robot0_eef_pos"][n_new:], orig["robot0_eef_pos"][c:])
    np.testing.assert_array_equal(new["camera0_rgb"][n_new:], orig["camera0_rgb"][c:])
    # before it the approach is new: a different start pose and different (not blank) images
    assert np.linalg.norm(new["robot0_eef_pos"][0] - orig["robot0_eef_pos"][0]) > 0.01
    assert new["camera0_rgb"][0].std() > 10
    buf.close()
    assert main(["validate", str(out / "dataset.zarr.zip")]) == 0
    # a second run reuses the session and every cached stage
    assert main(args) == 0
    again = json.loads((out / "summary.json").read_text())
    assert again["session_info"]["reused"] and all(v["skipped"] for v in again["export"]["stages"].values())


def test_validate_bad_path_exits_2_naming_it(tmp_path, capsys):
    bad = tmp_path / "nope.zarr.zip"
    bad.write_bytes(b"not a zip")
    assert main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "nope.zarr.zip" in err and err.count("\n") == 1


def test_intrinsics_command_on_shipped_calibration(capsys):
    from importlib.resources import files

    path = files("umi_aug") / "assets" / "gopro_intrinsics_2_7k.json"
    assert main(["intrinsics", str(path)]) == 0
    out = capsys.readouterr().out
    assert "2704×2028" in out and "224×224" in out
