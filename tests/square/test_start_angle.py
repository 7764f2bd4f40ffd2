"""The square report's outcomes by the start's angle (umi_aug/square/start_angle.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from umi_aug.square.start_angle import outcomes_by_start_angle, start_angle_section, start_angles_deg


def _starts(angles_deg, n_azimuth: int, R_world_ref: np.ndarray, rng) -> np.ndarray:
    """Camera poses whose optical axes make ``angles_deg`` with the reference axis ``R_world_ref[:, 2]``, each angle
    at ``n_azimuth`` evenly spread azimuths (so the mean axis is the reference axis), random positions."""
    T = []
    for a in angles_deg:
        for k in range(n_azimuth):
            phi = 2 * np.pi * k / n_azimuth
            tilt = Rotation.from_rotvec(np.radians(a) * np.array([np.cos(phi), np.sin(phi), 0.0]))
            spin = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])  # about the optical axis
            M = np.eye(4)
            M[:3, :3] = R_world_ref @ (tilt * spin).as_matrix()
            M[:3, 3] = rng.normal(size=3)
            T.append(M)
    return np.array(T)


def test_angles_are_measured_from_the_mean_optical_axis_in_any_world_frame():
    rng = np.random.default_rng(7)
    angles = [0.0, 1e-4, 10.0, 50.0, 100.0, 119.0]  # past 90° too; the mean axis stays the reference
    R0 = Rotation.random(random_state=3).as_matrix()
    got = start_angles_deg(_starts(angles, 4, R0, rng))
    np.testing.assert_allclose(got, np.repeat(angles, 4), atol=1e-6)
    assert np.isfinite(got).all()


def test_bad_poses_are_refused_with_a_reason():
    with pytest.raises(ValueError, match="shape"):
        start_angles_deg(np.zeros((3, 3, 3)))
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, :3, 2] = [np.nan, 0, 1]
    with pytest.raises(ValueError, match="non-finite"):
        start_angles_deg(T)
    T[1, :3, :3] = np.diag([1.0, -1.0, -1.0])  # the second camera looks the opposite way
    with pytest.raises(ValueError, match="cancel out"):
        start_angles_deg(T)


def test_outcomes_are_counted_per_bin_with_half_open_bins_and_an_open_last_one():
    angles = np.array([5.0, 19.999, 20.0, 35.0, 40.0, 80.0])
    rows = {0: {"success": True, "pregrasp_reached": True}, 1: {"success": False, "pregrasp_reached": True},
            2: {"success": True, "pregrasp_reached": False}, 4: {"success": False, "pregrasp_reached": False},
            5: {"success": True, "pregrasp_reached": True}}  # config 3 not evaluated
    got = outcomes_by_start_angle(rows, angles, (0.0, 20.0, 30.0, 40.0))
    assert [b["bin"] for b in got] == ["0°–20°", "20°–30°", "30°–40°", "≥ 40°"]
    assert [(b["n"], b["success"], b["pregrasp_reached"]) for b in got] == [(2, 1, 2), (1, 1, 0), (0, 0, 0),
                                                                             (2, 1, 1)]
    with pytest.raises(ValueError, match="configuration 6"):
        outcomes_by_start_angle({6: {"success": True}}, angles)


def test_the_report_section_has_a_row_per_evaluated_cell(tmp_path):
    rng = np.random.default_rng(0)
    T = _starts([10.0, 45.0], 4, np.eye(3), rng)  # configs 0-3 at 10°, 4-7 at 45°
    path = tmp_path / "configs.npz"
    np.savez(path, T_world_cam=T, states=np.zeros((len(T), 3)))
    rows = {"a": {i: {"success": i < 2, "pregrasp_reached": i in (0, 5)} for i in range(8)}, "b": {}}
    cells = [{"name": "a"}, {"name": "b"}]
    lines = start_angle_section(cells, lambda c: rows[c["name"]], path, (0.0, 30.0))
    table = [ln for ln in lines if ln.startswith("| `")]
    assert table == ["| `a` | 4 / 2 / 1 | 4 / 0 / 1 |"]  # b has no evaluation: no row
    assert start_angle_section([{"name": "b"}], lambda c: rows[c["name"]], path) == []
    missing = start_angle_section(cells, lambda c: rows[c["name"]], tmp_path / "nope.npz")
    assert any("not on this machine" in ln for ln in missing)
    np.savez(path, states=np.zeros((8, 3)))  # no poses: one error naming the file and the key
    with pytest.raises(Exception, match=r"configs\.npz.*T_world_cam"):
        start_angle_section(cells, lambda c: rows[c["name"]], path)
