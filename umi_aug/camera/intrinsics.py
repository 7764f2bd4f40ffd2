"""Fisheye (Kannala–Brandt / OpenCV ``cv2.fisheye``) intrinsics that carry their own image size.

Pixel convention: ``(u, v)`` = (column, row), pixel centres at integer coordinates (OpenCV). Resizing or cropping
returns a new object (:meth:`FisheyeIntrinsics.scaled`, :meth:`FisheyeIntrinsics.umi_policy`); distortion
coefficients never change with scaling.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal, Mapping

import numpy as np

from umi_aug.camera.kb_poly import THETA_PI_MARGIN, kb_theta_d, theta_fold as _theta_fold
from umi_aug.config_check import is_positive
from umi_aug.errors import CameraError

__all__ = ["FisheyeIntrinsics", "PixelCentre"]

PixelCentre = Literal["exact", "umi"]

_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "k", "theta_limit")


def _as_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        if isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value).is_integer():
            value = int(value)
        else:
            raise CameraError(f"FisheyeIntrinsics.{name} must be a positive integer, got {value!r}")
    value = int(value)
    if value <= 0:
        raise CameraError(f"FisheyeIntrinsics.{name} must be a positive integer, got {value!r}")
    return value


def _as_float(name: str, value: Any, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise CameraError(f"FisheyeIntrinsics.{name} must be a real number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise CameraError(f"FisheyeIntrinsics.{name} must be finite, got {value!r}")
    if positive and not is_positive(v):
        raise CameraError(f"FisheyeIntrinsics.{name} must be > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class FisheyeIntrinsics:
    """Kannala–Brandt fisheye intrinsics at a given image resolution.

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels per radian of ``theta_d``.
        cx, cy: principal point in pixels (pixel centres at integer coordinates).
        k: ``(k1, k2, k3, k4)`` of ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``
            (OpenCV ``D``); all zero = equidistant.
        theta_limit: optional physical lens limit on the ray angle from the optical axis, radians in (0, pi].
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    theta_limit: float | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "width", _as_int("width", self.width))
        object.__setattr__(self, "height", _as_int("height", self.height))
        object.__setattr__(self, "fx", _as_float("fx", self.fx, positive=True))
        object.__setattr__(self, "fy", _as_float("fy", self.fy, positive=True))
        object.__setattr__(self, "cx", _as_float("cx", self.cx))
        object.__setattr__(self, "cy", _as_float("cy", self.cy))
        try:
            kk = tuple(np.asarray(self.k, dtype=np.float64).reshape(-1).tolist())
        except (TypeError, ValueError) as exc:
            raise CameraError(f"FisheyeIntrinsics.k must be 4 real numbers, got {self.k!r}") from exc
        if len(kk) != 4:
            raise CameraError(f"FisheyeIntrinsics.k must have 4 coefficients (k1..k4), got {self.k!r}")
        for i, c in enumerate(kk):
            if not math.isfinite(c):
                raise CameraError(f"FisheyeIntrinsics.k[{i}] (k{i + 1}) must be finite, got {c!r}")
        object.__setattr__(self, "k", kk)
        if self.theta_limit is not None:
            t = _as_float("theta_limit", self.theta_limit, positive=True)
            if t > math.pi:
                raise CameraError(f"FisheyeIntrinsics.theta_limit must be in (0, pi] radians, got {t!r}")
            object.__setattr__(self, "theta_limit", t)

    # ------------------------------------------------------------------------------------------------ matrices
    @property
    def K(self) -> np.ndarray:
        """Camera matrix ``[3, 3]`` float64 (OpenCV layout, zero skew)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64)

    @property
    def D(self) -> np.ndarray:
        """Distortion coefficients ``[4]`` float64 ``(k1, k2, k3, k4)`` (reshape to (4, 1) for cv2.fisheye)."""
        return np.array(self.k, dtype=np.float64)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels (OpenCV ``dsize`` order)."""
        return (self.width, self.height)

    # ----------------------------------------------------------------------------------------------- geometry
    @cached_property
    def theta_fold(self) -> float:
        """Fold-over angle (radians): smallest ``theta > 0`` with ``d theta_d / d theta = 0``; ``inf`` when
        ``theta_d`` is strictly increasing on ``(0, pi]`` (e.g. equidistant). UMI GoPro: 1.815 rad (104 deg)."""
        return _theta_fold(self.k)

    @cached_property
    def theta_max(self) -> float:
        """Largest valid ray angle from the optical axis (radians): ``min(theta_fold, theta_limit, pi(1-tiny))``.
        Rays beyond 90 deg (``z < 0``) are valid up to this."""
        cap = math.pi * (1.0 - THETA_PI_MARGIN)
        lim = self.theta_limit if self.theta_limit is not None else cap
        return float(min(self.theta_fold, lim, cap))

    @cached_property
    def theta_d_max(self) -> float:
        """``theta_d(theta_max)``: radius of the image circle in normalised fisheye units."""
        return float(kb_theta_d(self.theta_max, self.k))

    @property
    def image_circle_radius_px(self) -> tuple[float, float]:
        """Image-circle semi-axes ``(fx * theta_d_max, fy * theta_d_max)`` in pixels, centred at ``(cx, cy)``."""
        return (self.fx * self.theta_d_max, self.fy * self.theta_d_max)

    @property
    def fov_deg(self) -> float:
        """Full field of view of the valid image circle, ``2 * theta_max`` in degrees."""
        return math.degrees(2.0 * self.theta_max)

    def check_image_shape(self, shape: tuple[int, ...]) -> None:
        """Raise :class:`CameraError` unless ``shape[:2] == (height, width)`` (an image ``(H, W[, C])``)."""
        if tuple(shape[:2]) != (self.height, self.width):
            raise CameraError(
                f"image of shape {tuple(shape)} does not match intrinsics {self.width}x{self.height} "
                f"(expected (H, W) = ({self.height}, {self.width})); rescale the intrinsics, never the frame"
            )

    # --------------------------------------------------------------------------------------------- factories
    @classmethod
    def equidistant(
        cls, width: int, height: int, f: float, cx: float | None = None, cy: float | None = None,
        theta_limit: float | None = None,
    ) -> "FisheyeIntrinsics":
        """Equidistant fisheye (``r = f theta``, ``k = 0``); the principal point defaults to the image centre
        ``((W - 1)/2, (H - 1)/2)`` (pixel centres at integers)."""
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        return cls(width, height, f, f, cx, cy, (0.0, 0.0, 0.0, 0.0), theta_limit)

    def crop_geometry(self, out_width: int, out_height: int) -> tuple[int, int, int, int]:
        """The full-height, horizontally centred crop (or pad) that has the aspect ratio of the output.

        Returns ``(x0, y0, crop_w, crop_h)``: the crop is ``image[y0:y0+crop_h, x0:x0+crop_w]`` with
        ``crop_h = height``, ``crop_w = round(height * out_width / out_height)``, ``x0 = (width - crop_w) // 2``
        (negative ``x0``: that many pixels of padding on the left), ``y0 = 0``.
        """
        out_width = _as_int("out_width", out_width)
        out_height = _as_int("out_height", out_height)
        crop_h = self.height
        crop_w = int(round(self.height * out_width / out_height))
        x0 = (self.width - crop_w) // 2
        return x0, 0, crop_w, crop_h

    def scaled(self, out_width: int, out_height: int, pixel_centre: PixelCentre = "exact") -> "FisheyeIntrinsics":
        """Intrinsics after scaling to ``out_height`` with a symmetric horizontal crop/pad to ``out_width``
        (UMI ``convert_fisheye_intrinsics_resolution``).

        ``pixel_centre="umi"`` reproduces UMI exactly: ``s = out_h/h``, ``f' = f s``,
        ``cx' = (cx - w/2) s + out_w/2``, ``cy' = cy s`` (treats pixel corners as integers; off by
        ``(1 - s)/2`` px for a downscale).

        ``pixel_centre="exact"`` (default) is exact for pixel centres at integer coordinates and the actual image
        operation "crop ``image[:, x0:x0+crop_w]`` (see :meth:`crop_geometry`), then ``cv2.resize`` to
        ``(out_w, out_h)``" (any area-preserving resampling, e.g. INTER_AREA): with
        ``sx = out_w/crop_w``, ``sy = out_h/h``: ``fx' = fx sx``, ``fy' = fy sy``,
        ``cx' = (cx - x0 + 0.5) sx - 0.5``, ``cy' = (cy + 0.5) sy - 0.5``.

        Distortion ``k`` and ``theta_limit`` are unchanged.
        """
        out_width = _as_int("out_width", out_width)
        out_height = _as_int("out_height", out_height)
        if pixel_centre == "umi":
            s = out_height / self.height
            fx, fy = self.fx * s, self.fy * s
            cx = (self.cx - self.width / 2.0) * s + out_width / 2.0
            cy = self.cy * s
        elif pixel_centre == "exact":
            x0, _, crop_w, crop_h = self.crop_geometry(out_width, out_height)
            sx, sy = out_width / crop_w, out_height / crop_h
            fx, fy = self.fx * sx, self.fy * sy
            cx = (self.cx - x0 + 0.5) * sx - 0.5
            cy = (self.cy + 0.5) * sy - 0.5
        else:
            raise CameraError(f"pixel_centre must be 'exact' or 'umi', got {pixel_centre!r}")
        return FisheyeIntrinsics(out_width, out_height, fx, fy, cx, cy, self.k, self.theta_limit)

    def umi_policy(self, size: int = 224, pixel_centre: PixelCentre = "exact") -> "FisheyeIntrinsics":
        """Intrinsics of UMI's policy observation: full-height centre square crop, then resize to
        ``size x size`` (UMI ``07_generate_replay_buffer``). Same as ``scaled(size, size, pixel_centre)``."""
        return self.scaled(size, size, pixel_centre)

    # ------------------------------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dict ``{width, height, fx, fy, cx, cy, k: [4], theta_limit}``."""
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "k": list(self.k),
            "theta_limit": self.theta_limit,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "FisheyeIntrinsics":
        """Inverse of :meth:`to_dict` (``k`` and ``theta_limit`` optional); unknown or missing keys raise
        :class:`CameraError`."""
        if not isinstance(d, Mapping):
            raise CameraError(f"FisheyeIntrinsics.from_dict expects a mapping, got {type(d).__name__}")
        unknown = sorted(set(d) - set(_FIELDS))
        if unknown:
            raise CameraError(f"FisheyeIntrinsics.from_dict: unknown keys {unknown}; expected {list(_FIELDS)}")
        missing = [key for key in _FIELDS[:6] if key not in d]
        if missing:
            raise CameraError(f"FisheyeIntrinsics.from_dict: missing keys {missing}")
        return cls(
            d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"],
            d.get("k", (0.0, 0.0, 0.0, 0.0)), d.get("theta_limit"),
        )
