"""The ``umi-aug`` command: the demo runs end to end and writes its artefacts; bad input exits 2 with one
message naming the input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from umi_aug.cli import main


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--episodes", "2", "--frames", "5"]) == 0
    for name in ("dataset.zarr.zip", "camera_trajectory.csv", "intrinsics_224.json", "lens.png", "cone.png", "contact_sheet.png", "summary.json"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset_steps"] == 10
    assert "back" not in summary["cube_faces_rendered"] and len(summary["cube_faces_rendered"]) == 5
    stages = {s["stage"]: s["status"] for s in summary["stages"]}
    assert stages["geometry"] == stages["camera"] == stages["data"] == "ran"
    assert stages["traj"] == "not yet available"
    printed = capsys.readouterr().out
    assert "not yet available" in printed  # honest about missing stages while they are missing

    from umi_aug.data import ReplayBuffer

    buf = ReplayBuffer.open(out / "dataset.zarr.zip")
    ep = buf.get_episode(1)
    assert ep["camera0_rgb"].shape == (5, 224, 224, 3)
    # The generated frames are not blank: the fisheye sees the textured room; the gripper mask is black.
    assert ep["camera0_rgb"].std() > 10
    assert (ep["camera0_rgb"][:, -1, 0] == 0).all()
    assert np.isfinite(ep["robot0_eef_pos"]).all()
    assert main(["validate", str(out / "dataset.zarr.zip")]) == 0


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
