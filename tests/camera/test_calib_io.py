"""Calibration files: OpenICC / UMI GoPro JSON and ORB-SLAM3 KannalaBrandt8 YAML."""

from __future__ import annotations

import copy
import json
import math

import cv2
import numpy as np
import pytest

from tests.camera._kb_helpers import GOPRO_CX, GOPRO_CY, GOPRO_F, GOPRO_K, random_intrinsics
from umi_aug.camera.calib_io import (
    gopro_intrinsics_2_7k,
    load_intrinsics,
    load_orbslam3_yaml,
    load_umi_intrinsics_json,
    orbslam3_gopro_intrinsics_960x720,
    save_umi_intrinsics_json,
)
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import CameraError

# UMI example/calibration/gopro_intrinsics_2_7k.json, as published
UMI_JSON = {
    "final_reproj_error": 0.2916398582648,
    "fps": 59.94005994005994,
    "image_height": 2028,
    "image_width": 2704,
    "intrinsic_type": "FISHEYE",
    "intrinsics": {
        "aspect_ratio": 1.0029788958491257,
        "focal_length": 796.8544625226342,
        "principal_pt_x": 1354.4265245977356,
        "principal_pt_y": 1011.4847310011687,
        "radial_distortion_1": -0.02196117964405394,
        "radial_distortion_2": -0.018959717016668237,
        "radial_distortion_3": 0.001693880829392453,
        "radial_distortion_4": -0.00016807228608000285,
        "skew": 0.0,
    },
    "nr_calib_images": 59,
    "stabelized": False,
}

SLAM_YAML_NEW = """%YAML:1.0

#--------------------------------------------------------------------------------------------
# System config
#--------------------------------------------------------------------------------------------
File.version: "1.0"

#--------------------------------------------------------------------------------------------
# Camera Parameters. Adjust them!
#--------------------------------------------------------------------------------------------
Camera.type: "KannalaBrandt8"

# Camera calibration and distortion parameters (OpenCV)
Camera1.fx: 282.907
Camera1.fy: 282.907
Camera1.cx: 480.0
Camera1.cy: 360.0

# Kannala-Brandt distortion parameters
Camera1.k1: -0.017458
Camera1.k2: -0.028083
Camera1.k3: 0.012833
Camera1.k4: -0.004520

# Camera resolution
Camera.width: 960
Camera.height: 720

# Camera frames per second
Camera.fps: 60

# Color order of the images (0: BGR, 1: RGB. It is ignored if images are grayscale)
Camera.RGB: 1

# Transformation from body-frame (imu) to camera
IMU.T_b_c1: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [0.0, -1.0, 0.0, 0.0,
          -1.0, 0.0, 0.0, 0.0,
          0.0, 0.0, -1.0, 0.0,
          0.0, 0.0, 0.0, 1.0]

IMU.NoiseGyro: 0.0015 # rad/s^0.5
IMU.Frequency: 200.0

ORBextractor.nFeatures: 1250
Viewer.KeyFrameSize: 0.05
"""

SLAM_YAML_OLD = """%YAML:1.0
---
Camera.type: "KannalaBrandt8"
Camera.fx: 190.97847715128717
Camera.fy: 190.9733070521226
Camera.cx: 254.93170605935475
Camera.cy: 256.8974428996504
Camera.k1: 0.0034823894022493434
Camera.k2: 0.0007150348452162257
Camera.k3: -0.0020532361418706202
Camera.k4: 0.00020293673591811182
Camera.width: 512
Camera.height: 512
Camera.fps: 20.0
Camera.RGB: 1
Tbc: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [-0.99952504,  0.00750192, -0.02989013,  0.04557484,
           0.0, 0.0, 0.0, 1.0]
"""


def _write_json(tmp_path, data, name="calib.json"):
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


# ----------------------------------------------------------------------------------------------- JSON
def test_builtin_gopro_matches_published_file(tmp_path):
    g = gopro_intrinsics_2_7k()
    assert (g.width, g.height) == (2704, 2028)
    assert g.fx == g.fy == GOPRO_F  # UMI ignores aspect_ratio
    assert (g.cx, g.cy) == (GOPRO_CX, GOPRO_CY) and g.k == GOPRO_K
    p = _write_json(tmp_path, UMI_JSON)
    assert load_umi_intrinsics_json(p) == g
    # the package-data file has UMI's exact layout and values
    from importlib.resources import files

    shipped = json.loads(files("umi_aug").joinpath("assets/gopro_intrinsics_2_7k.json").read_text())
    assert shipped == UMI_JSON


def test_aspect_ratio_flag(tmp_path):
    p = _write_json(tmp_path, UMI_JSON)
    g = load_umi_intrinsics_json(p, use_aspect_ratio=True)
    assert g.fx == GOPRO_F and g.fy == GOPRO_F * 1.0029788958491257


def test_save_load_round_trip(tmp_path, rng):
    intr = random_intrinsics(rng)
    sq = FisheyeIntrinsics(intr.width, intr.height, intr.fx, intr.fx, intr.cx, intr.cy, intr.k)
    p = save_umi_intrinsics_json(sq, tmp_path / "sub" / "out.json", fps=59.94, final_reproj_error=0.3,
                                 nr_calib_images=12)
    assert load_umi_intrinsics_json(p) == sq
    assert list(tmp_path.joinpath("sub").iterdir()) == [p]  # atomic: no temporaries left
    data = json.loads(p.read_text())
    assert data["intrinsic_type"] == "FISHEYE" and data["fps"] == 59.94 and data["intrinsics"]["skew"] == 0.0
    assert set(data["intrinsics"]) == set(UMI_JSON["intrinsics"])
    # non-square pixels: aspect_ratio = fy/fx, restored with use_aspect_ratio=True
    save_umi_intrinsics_json(intr, p)
    back = load_umi_intrinsics_json(p, use_aspect_ratio=True)
    assert back.fx == intr.fx and back.fy == pytest.approx(intr.fy, rel=1e-15)
    assert load_intrinsics(p) == load_umi_intrinsics_json(p)
    # the GoPro file re-saved equals the published one apart from optional metadata
    save_umi_intrinsics_json(gopro_intrinsics_2_7k(), p, fps=59.94005994005994, final_reproj_error=0.2916398582648,
                             nr_calib_images=59)
    again = json.loads(p.read_text())
    assert again["intrinsics"] == {**UMI_JSON["intrinsics"], "aspect_ratio": 1.0}


def _mutations():
    """(description, mutate(data), key expected in the message)."""
    cases = []
    for key in ("image_width", "image_height", "intrinsic_type", "intrinsics"):
        cases.append((f"missing {key}", lambda d, k=key: d.pop(k), key))
    for key in UMI_JSON["intrinsics"]:
        cases.append((f"missing intrinsics.{key}", lambda d, k=key: d["intrinsics"].pop(k), f"intrinsics.{key}"))
    cases += [
        ("string focal", lambda d: d["intrinsics"].__setitem__("focal_length", "796.8"), "intrinsics.focal_length"),
        ("bool k1", lambda d: d["intrinsics"].__setitem__("radial_distortion_1", True), "radial_distortion_1"),
        ("null cx", lambda d: d["intrinsics"].__setitem__("principal_pt_x", None), "principal_pt_x"),
        ("list k4", lambda d: d["intrinsics"].__setitem__("radial_distortion_4", [0.0]), "radial_distortion_4"),
        ("nan k2", lambda d: d["intrinsics"].__setitem__("radial_distortion_2", float("nan")), "radial_distortion_2"),
        ("inf cy", lambda d: d["intrinsics"].__setitem__("principal_pt_y", float("inf")), "principal_pt_y"),
        ("neg focal", lambda d: d["intrinsics"].__setitem__("focal_length", -5.0), "focal_length"),
        ("zero aspect", lambda d: d["intrinsics"].__setitem__("aspect_ratio", 0.0), "aspect_ratio"),
        ("skew", lambda d: d["intrinsics"].__setitem__("skew", 0.01), "skew"),
        ("pinhole", lambda d: d.__setitem__("intrinsic_type", "PINHOLE"), "intrinsic_type"),
        ("float width", lambda d: d.__setitem__("image_width", 2704.5), "image_width"),
        ("string height", lambda d: d.__setitem__("image_height", "2028"), "image_height"),
        ("zero height", lambda d: d.__setitem__("image_height", 0), "image_height"),
        ("intrinsics not object", lambda d: d.__setitem__("intrinsics", [1, 2]), "intrinsics"),
    ]
    return cases


@pytest.mark.parametrize("desc, mutate, key", _mutations(), ids=[c[0] for c in _mutations()])
def test_malformed_json_raises_naming_file_and_key(tmp_path, desc, mutate, key):
    data = copy.deepcopy(UMI_JSON)
    mutate(data)
    p = _write_json(tmp_path, data, name="bad_calib.json")
    with pytest.raises(CameraError) as exc:
        load_umi_intrinsics_json(p)
    msg = str(exc.value)
    assert "bad_calib.json" in msg and key in msg, msg


@pytest.mark.parametrize("text", ["{not json", "[1, 2, 3]", ""])
def test_unparsable_json(tmp_path, text):
    p = tmp_path / "broken.json"
    p.write_text(text)
    with pytest.raises(CameraError, match="broken.json"):
        load_umi_intrinsics_json(p)


def test_missing_file(tmp_path):
    with pytest.raises(CameraError, match="nope.json"):
        load_umi_intrinsics_json(tmp_path / "nope.json")
    with pytest.raises(CameraError, match="unknown calibration file type"):
        load_intrinsics(tmp_path / "calib.txt")


# ---------------------------------------------------------------------------------------- ORB-SLAM3 YAML
def test_orbslam3_new_style(tmp_path):
    p = tmp_path / "gopro10_maxlens_fisheye_setting_v1_720.yaml"
    p.write_text(SLAM_YAML_NEW)
    intr = load_orbslam3_yaml(p)
    assert intr == orbslam3_gopro_intrinsics_960x720()
    assert load_intrinsics(p) == intr
    # the line parser agrees with OpenCV's own FileStorage reader
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    try:
        assert fs.getNode("Camera1.fx").real() == intr.fx
        assert fs.getNode("Camera1.k4").real() == intr.k[3]
        assert int(fs.getNode("Camera.width").real()) == intr.width
        assert fs.getNode("Camera.type").string() == "KannalaBrandt8"
    finally:
        fs.release()


def test_orbslam3_old_style(tmp_path):
    p = tmp_path / "TUM_VI.yaml"
    p.write_text(SLAM_YAML_OLD)
    intr = load_orbslam3_yaml(p)
    assert (intr.width, intr.height) == (512, 512)
    assert intr.fx == 190.97847715128717 and intr.fy == 190.9733070521226
    assert intr.k == (0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182)


@pytest.mark.parametrize(
    "old, new, key",
    [
        ('Camera.type: "KannalaBrandt8"', 'Camera.type: "PinHole"', "Camera.type"),
        ('Camera.type: "KannalaBrandt8"\n', "", "Camera.type"),
        ("Camera1.k3: 0.012833\n", "", "Camera1.k3"),
        ("Camera.height: 720\n", "", "Camera.height"),
        ("Camera1.fx: 282.907", "Camera1.fx: abc", "Camera1.fx"),
        ("Camera1.cy: 360.0", "Camera1.cy: .nan", "Camera1.cy"),
        ("Camera.width: 960", "Camera.width: 960.5", "Camera.width"),
        ("Camera1.fy: 282.907", "Camera1.fy: -282.907", "fy"),
        ("Camera.fps: 60", "Camera.fps: 60\nCamera.imageScale: 0.5", "Camera.imageScale"),
        ("Camera.fps: 60", "Camera.fps: 60\nCamera.fps: 30", "Camera.fps"),
        ("%YAML:1.0", "camera: {}", "%YAML"),
    ],
)
def test_orbslam3_malformed(tmp_path, old, new, key):
    assert old in SLAM_YAML_NEW
    p = tmp_path / "bad_settings.yaml"
    p.write_text(SLAM_YAML_NEW.replace(old, new, 1))
    with pytest.raises(CameraError) as exc:
        load_orbslam3_yaml(p)
    msg = str(exc.value)
    assert "bad_settings.yaml" in msg and key in msg, msg


def test_orbslam3_intrinsics_geometry():
    s = orbslam3_gopro_intrinsics_960x720()
    # the SLAM calibration folds over earlier (~88 deg) than UMI's JSON calibration (~104 deg)
    assert math.degrees(s.theta_fold) == pytest.approx(88.2, abs=0.1)
    g = gopro_intrinsics_2_7k().scaled(960, 720, pixel_centre="umi")
    assert g.fx == pytest.approx(s.fx, rel=1e-4)  # same lens, two calibrations
    assert np.isfinite(s.theta_d_max)
