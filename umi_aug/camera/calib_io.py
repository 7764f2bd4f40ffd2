"""Fisheye calibration files: UMI / OpenICC GoPro JSON and ORB-SLAM3 ``KannalaBrandt8`` settings YAML.

Both describe the same Kannala–Brandt model as :class:`~umi_aug.camera.intrinsics.FisheyeIntrinsics`
(OpenCV ``cv2.fisheye``). Every reader validates and raises :class:`~umi_aug.errors.CameraError` naming the file,
the key and the offending value; every writer is atomic.

* OpenICC JSON (UMI ``example/calibration/gopro_intrinsics_2_7k.json``)::

      {"final_reproj_error", "fps", "image_height", "image_width", "intrinsic_type": "FISHEYE",
       "intrinsics": {"aspect_ratio", "focal_length", "principal_pt_x", "principal_pt_y",
                      "radial_distortion_1".."radial_distortion_4", "skew"},
       "nr_calib_images", "stabelized"}

  UMI's ``parse_fisheye_intrinsics`` uses ``fx = fy = focal_length`` and ignores ``aspect_ratio``; so do we by
  default (``use_aspect_ratio=True`` gives ``fy = focal_length * aspect_ratio``, the OpenICC/Theia meaning).
* ORB-SLAM3 settings (``%YAML:1.0``, which PyYAML rejects): old keys ``Camera.fx .. Camera.k4`` or new
  (v1.0) keys ``Camera1.fx .. Camera1.k4``, plus ``Camera.width``, ``Camera.height`` and
  ``Camera.type: "KannalaBrandt8"``. Parsed by a small line parser (top-level ``key: value`` scalars only;
  matrices such as ``Tbc`` are skipped).
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import math
import os
import re
from pathlib import Path
from typing import Any

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.config_check import is_positive
from umi_aug.errors import CameraError
from umi_aug.io_utils import atomic_write_text

__all__ = [
    "load_umi_intrinsics_json",
    "save_umi_intrinsics_json",
    "load_orbslam3_yaml",
    "load_intrinsics",
    "gopro_intrinsics_2_7k",
    "orbslam3_gopro_intrinsics_960x720",
    "GOPRO_JSON_ASSET",
]

#: Package-data file (OpenICC layout) with UMI's published GoPro 10 + Max Lens Mod calibration at 2704x2028.
GOPRO_JSON_ASSET = "assets/gopro_intrinsics_2_7k.json"

_UMI_INTRINSIC_KEYS = (
    "focal_length",
    "aspect_ratio",
    "principal_pt_x",
    "principal_pt_y",
    "radial_distortion_1",
    "radial_distortion_2",
    "radial_distortion_3",
    "radial_distortion_4",
    "skew",
)


# ------------------------------------------------------------------------------------------------ helpers
def _real(path: Path, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CameraError(f"{path}: key {key!r} must be a number, got {value!r} ({type(value).__name__})")
    v = float(value)
    if not math.isfinite(v):
        raise CameraError(f"{path}: key {key!r} must be finite, got {value!r}")
    return v


def _posint(path: Path, key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
        raise CameraError(f"{path}: key {key!r} must be a positive integer, got {value!r}")
    if not is_positive(value):
        raise CameraError(f"{path}: key {key!r} must be a positive integer, got {value!r}")
    return int(value)


def _build(path: Path, **kw: Any) -> FisheyeIntrinsics:
    try:
        return FisheyeIntrinsics(**kw)
    except CameraError as exc:
        raise CameraError(f"{path}: invalid intrinsics: {exc}") from exc


# ----------------------------------------------------------------------------------------- OpenICC JSON
def load_umi_intrinsics_json(path: str | os.PathLike, use_aspect_ratio: bool = False) -> FisheyeIntrinsics:
    """Read an OpenICC fisheye calibration JSON as UMI does (``parse_fisheye_intrinsics``).

    Args:
        path: the ``.json`` file.
        use_aspect_ratio: ``False`` (UMI behaviour): ``fx = fy = focal_length``; ``True``:
            ``fy = focal_length * aspect_ratio``.

    Returns:
        intrinsics at ``image_width x image_height`` pixels.

    Raises:
        CameraError: unreadable file, invalid JSON, missing key, wrong type, ``intrinsic_type != "FISHEYE"``,
            nonzero ``skew`` or non-finite value (the message names the file and the key).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CameraError(f"{path}: cannot read calibration file: {exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CameraError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise CameraError(f"{path}: top level must be a JSON object, got {type(data).__name__}")
    for key in ("image_width", "image_height", "intrinsic_type", "intrinsics"):
        if key not in data:
            raise CameraError(f"{path}: missing key {key!r} (OpenICC fisheye calibration layout)")
    if data["intrinsic_type"] != "FISHEYE":
        raise CameraError(
            f"{path}: key 'intrinsic_type' must be 'FISHEYE' (Kannala-Brandt), got {data['intrinsic_type']!r}"
        )
    width = _posint(path, "image_width", data["image_width"])
    height = _posint(path, "image_height", data["image_height"])
    intr = data["intrinsics"]
    if not isinstance(intr, dict):
        raise CameraError(f"{path}: key 'intrinsics' must be an object, got {intr!r}")
    vals: dict[str, float] = {}
    for key in _UMI_INTRINSIC_KEYS:
        if key not in intr:
            raise CameraError(f"{path}: missing key 'intrinsics.{key}'")
        vals[key] = _real(path, f"intrinsics.{key}", intr[key])
    if vals["skew"] != 0.0:
        raise CameraError(f"{path}: key 'intrinsics.skew' must be 0 (no skew in the KB model), got {vals['skew']!r}")
    if vals["aspect_ratio"] <= 0.0:
        raise CameraError(f"{path}: key 'intrinsics.aspect_ratio' must be > 0, got {vals['aspect_ratio']!r}")
    if vals["focal_length"] <= 0.0:
        raise CameraError(f"{path}: key 'intrinsics.focal_length' must be > 0, got {vals['focal_length']!r}")
    f = vals["focal_length"]
    fy = f * vals["aspect_ratio"] if use_aspect_ratio else f
    k = tuple(vals[f"radial_distortion_{i}"] for i in range(1, 5))
    return _build(path, width=width, height=height, fx=f, fy=fy, cx=vals["principal_pt_x"],
                  cy=vals["principal_pt_y"], k=k)


def save_umi_intrinsics_json(
    intr: FisheyeIntrinsics,
    path: str | os.PathLike,
    fps: float = 59.94,
    final_reproj_error: float | None = None,
    nr_calib_images: int | None = None,
    stabelized: bool = False,
) -> Path:
    """Write ``intr`` as an OpenICC fisheye JSON (UMI's layout), atomically.

    ``focal_length = fx`` and ``aspect_ratio = fy / fx`` (so ``load_umi_intrinsics_json(path,
    use_aspect_ratio=True)`` restores ``fy``; with ``fx == fy`` both loaders round-trip exactly).
    ``theta_limit`` is not part of the format and is dropped. Optional metadata keys are written when given.

    Returns:
        the path written.
    """
    if not isinstance(intr, FisheyeIntrinsics):
        raise CameraError(f"save_umi_intrinsics_json expects FisheyeIntrinsics, got {type(intr).__name__}")
    data: dict[str, Any] = {}
    if final_reproj_error is not None:
        data["final_reproj_error"] = float(final_reproj_error)
    data["fps"] = float(fps)
    data["image_height"] = intr.height
    data["image_width"] = intr.width
    data["intrinsic_type"] = "FISHEYE"
    data["intrinsics"] = {
        "aspect_ratio": 1.0 if intr.fy == intr.fx else intr.fy / intr.fx,
        "focal_length": intr.fx,
        "principal_pt_x": intr.cx,
        "principal_pt_y": intr.cy,
        "radial_distortion_1": intr.k[0],
        "radial_distortion_2": intr.k[1],
        "radial_distortion_3": intr.k[2],
        "radial_distortion_4": intr.k[3],
        "skew": 0.0,
    }
    if nr_calib_images is not None:
        data["nr_calib_images"] = int(nr_calib_images)
    data["stabelized"] = bool(stabelized)
    return atomic_write_text(path, json.dumps(data, indent=4) + "\n")


# ------------------------------------------------------------------------------------ ORB-SLAM3 YAML
_YAML_LINE = re.compile(r"^([A-Za-z_][\w.\-]*)\s*:\s*(.*?)\s*$")


def _strip_comment(value: str) -> str:
    out, quote = [], None
    for ch in value:
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            break
        out.append(ch)
    return "".join(out).strip()


def _parse_orbslam_yaml(path: Path, text: str) -> dict[str, str]:
    """Top-level ``key: scalar`` pairs of an OpenCV-FileStorage YAML (values as raw strings, quotes removed)."""
    lines = text.splitlines()
    if not lines or not lines[0].startswith("%YAML"):
        raise CameraError(f"{path}: not an OpenCV/ORB-SLAM3 settings file (first line must be '%YAML:1.0')")
    out: dict[str, str] = {}
    for lineno, raw in enumerate(lines[1:], start=2):
        if not raw.strip() or raw.lstrip().startswith("#") or raw.startswith("---") or raw.startswith("%"):
            continue
        if raw[0] in " \t":  # nested block content (matrix rows, ...)
            continue
        m = _YAML_LINE.match(raw)
        if m is None:
            raise CameraError(f"{path}:{lineno}: cannot parse line {raw!r}")
        key, value = m.group(1), _strip_comment(m.group(2))
        if value.startswith("!!") or value == "" or value.startswith("[") or value.startswith("{"):
            continue  # a matrix / sequence / mapping, not a scalar
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "\"'":
            value = value[1:-1]
        if key in out:
            raise CameraError(f"{path}:{lineno}: duplicate key {key!r}")
        out[key] = value
    return out


def _yaml_number(path: Path, key: str, raw: dict[str, str]) -> float:
    if key not in raw:
        raise CameraError(f"{path}: missing key {key!r}")
    try:
        v = float(raw[key])
    except ValueError as exc:
        raise CameraError(f"{path}: key {key!r} must be a number, got {raw[key]!r}") from exc
    if not math.isfinite(v):
        raise CameraError(f"{path}: key {key!r} must be finite, got {raw[key]!r}")
    return v


def load_orbslam3_yaml(path: str | os.PathLike) -> FisheyeIntrinsics:
    """Read the fisheye camera of an ORB-SLAM3 settings file (``Camera.type: "KannalaBrandt8"``).

    Supports the old key style (``Camera.fx, Camera.fy, Camera.cx, Camera.cy, Camera.k1..k4``) and the v1.0
    style (``Camera1.fx .. Camera1.k4``), both with ``Camera.width`` and ``Camera.height``. Only
    ``Camera.imageScale`` = 1 (or absent) is supported.

    Raises:
        CameraError: unreadable/unparsable file, another camera type, missing or non-numeric key.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraError(f"{path}: cannot read ORB-SLAM3 settings file: {exc}") from exc
    raw = _parse_orbslam_yaml(path, text)
    if "Camera.type" not in raw:
        raise CameraError(f"{path}: missing key 'Camera.type' (expected \"KannalaBrandt8\")")
    if raw["Camera.type"] != "KannalaBrandt8":
        raise CameraError(
            f"{path}: key 'Camera.type' is {raw['Camera.type']!r}; only \"KannalaBrandt8\" (fisheye) is supported"
        )
    prefix = "Camera1." if "Camera1.fx" in raw else "Camera."
    vals = {name: _yaml_number(path, prefix + name, raw) for name in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")}
    w = _yaml_number(path, "Camera.width", raw)
    h = _yaml_number(path, "Camera.height", raw)
    for key, v in (("Camera.width", w), ("Camera.height", h)):
        if v <= 0 or not v.is_integer():
            raise CameraError(f"{path}: key {key!r} must be a positive integer, got {raw[key]!r}")
    if "Camera.imageScale" in raw and _yaml_number(path, "Camera.imageScale", raw) != 1.0:
        raise CameraError(f"{path}: key 'Camera.imageScale' = {raw['Camera.imageScale']!r} is not supported (use 1.0)")
    return _build(path, width=int(w), height=int(h), fx=vals["fx"], fy=vals["fy"], cx=vals["cx"], cy=vals["cy"],
                  k=(vals["k1"], vals["k2"], vals["k3"], vals["k4"]))


def load_intrinsics(path: str | os.PathLike, **kwargs: Any) -> FisheyeIntrinsics:
    """Load a calibration by extension: ``.json`` -> :func:`load_umi_intrinsics_json`, ``.yaml``/``.yml`` ->
    :func:`load_orbslam3_yaml`."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return load_umi_intrinsics_json(path, **kwargs)
    if suffix in (".yaml", ".yml"):
        return load_orbslam3_yaml(path, **kwargs)
    raise CameraError(f"{path}: unknown calibration file type {suffix!r} (expected .json or .yaml)")


# ------------------------------------------------------------------------------------------ built-ins
@functools.lru_cache(maxsize=None)
def gopro_intrinsics_2_7k() -> FisheyeIntrinsics:
    """UMI's published GoPro 10 + Max Lens Mod calibration at 2704x2028 (package data, OpenICC layout):
    ``f = 796.854, (cx, cy) = (1354.427, 1011.485)``, ``k = (-0.021961, -0.018960, 0.0016939, -0.00016807)``,
    read like UMI (``fx = fy``, aspect ratio ignored). Fold-over at 104 deg, image circle 1103 px."""
    res = importlib.resources.files("umi_aug").joinpath(GOPRO_JSON_ASSET)
    with importlib.resources.as_file(res) as p:
        return load_umi_intrinsics_json(p)


def orbslam3_gopro_intrinsics_960x720() -> FisheyeIntrinsics:
    """The KB8 camera of UMI's ORB-SLAM3 settings (its own calibration at 960x720): ``fx = fy = 282.907``,
    ``(cx, cy) = (480, 360)``, ``k = (-0.017458, -0.028083, 0.012833, -0.004520)``."""
    return FisheyeIntrinsics(960, 720, 282.907, 282.907, 480.0, 360.0, (-0.017458, -0.028083, 0.012833, -0.004520))
