"""UMI's predefined gripper / mirror / finger masks (umi_stack.md §3), reimplemented from the published facts.

UMI describes every mask polygon in *canonical coordinates*::

    c = (pixel_xy - (W/2, H/2)) / H          # pixel_xy = (u, v) = (column, row)

i.e. origin at the image centre, unit = image height. Because the unit is the image height and the origin the
centre, the same polygons apply to the raw GoPro frame (2704×2028), the capture-card frame (1920×1080, a
symmetric horizontal crop of the same optics after scaling) and the 224×224 policy image (full-height centre
square). Note UMI uses ``W/2`` (not ``(W-1)/2``) as the centre; we keep that for bit-compatibility with UMI's
masks, so masks drawn here match the masks baked into UMI datasets.

Polygons are given for the LEFT side in pixels at the reference resolution; the right polygon is the left one
with canonical x negated. The finger mask is one centred trapezoid.

All functions are pure: arrays in, new arrays out. Raise :class:`umi_aug.errors.CameraError` for bad input.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from umi_aug.errors import CameraError

# ---------------------------------------------------------------------------------------------------------------
# Named constants (umi_stack.md §3)
# ---------------------------------------------------------------------------------------------------------------
#: Reference resolution of UMI's pixel lists (raw GoPro 2.7K frame).
REFERENCE_HEIGHT: int = 2028
REFERENCE_WIDTH: int = 2704

#: Left side-mirror polygon, pixels (x, y) at 2704×2028.
MIRROR_LEFT_PX: tuple[tuple[int, int], ...] = (
    (540, 1700),
    (680, 1450),
    (590, 1070),
    (290, 1130),
    (290, 1770),
    (550, 1770),
)

#: Left gripper polygon, pixels (x, y) at 2704×2028. The last point lies below the image on purpose.
GRIPPER_LEFT_PX: tuple[tuple[int, int], ...] = (
    (1352, 1730),
    (1100, 1700),
    (650, 1500),
    (0, 1350),
    (0, 2028),
    (1352, 2704),
)

#: Left mirror crop box corners, pixels (x, y) at 2704×2028: (x0, y0), (x1, y1).
MIRROR_CROP_LEFT_PX: tuple[tuple[int, int], ...] = ((290, 1120), (650, 1480))

#: Finger trapezoid, in units of image height: height from the bottom edge, top width, bottom width (centred).
FINGER_HEIGHT: float = 0.37
FINGER_TOP_WIDTH: float = 0.25
FINGER_BOTTOM_WIDTH: float = 1.4


# ---------------------------------------------------------------------------------------------------------------
# Coordinates
# ---------------------------------------------------------------------------------------------------------------
def _check_size(height: int, width: int) -> tuple[int, int]:
    """Validate an image size; return it as python ints."""
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) <= 0:
            raise CameraError(f"image {name} must be a positive int, got {v!r}")
    return int(height), int(width)


def pixel_to_canonical(xy: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixel coordinates → UMI canonical coordinates.

    Args:
        xy: ``[..., 2]`` pixel coordinates ``(u, v)`` = (column, row) of an image of size ``height × width``.
        height, width: image size in pixels.

    Returns:
        ``[..., 2]`` float64 canonical coordinates ``(xy - (W/2, H/2)) / H`` (origin at the image centre,
        unit = image height, x right, y down).
    """
    h, w = _check_size(height, width)
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim == 0 or xy.shape[-1] != 2:
        raise CameraError(f"pixel coordinates must have shape [..., 2], got {xy.shape}")
    return (xy - np.array([w * 0.5, h * 0.5])) / h


def canonical_to_pixel(c: np.ndarray, height: int, width: int) -> np.ndarray:
    """UMI canonical coordinates → pixel coordinates (inverse of :func:`pixel_to_canonical`).

    Args:
        c: ``[..., 2]`` canonical coordinates (unit = image height, origin at the image centre).
        height, width: target image size in pixels.

    Returns:
        ``[..., 2]`` float64 pixel coordinates ``(u, v) = c * H + (W/2, H/2)``.
    """
    h, w = _check_size(height, width)
    c = np.asarray(c, dtype=np.float64)
    if c.ndim == 0 or c.shape[-1] != 2:
        raise CameraError(f"canonical coordinates must have shape [..., 2], got {c.shape}")
    return c * h + np.array([w * 0.5, h * 0.5])


def _left_right(left_px: Sequence[Sequence[int]]) -> np.ndarray:
    """Left polygon in reference pixels → ``[2, N, 2]`` canonical (left, right = x negated)."""
    left = pixel_to_canonical(np.asarray(left_px, dtype=np.float64), REFERENCE_HEIGHT, REFERENCE_WIDTH)
    right = left.copy()
    right[:, 0] *= -1.0
    return np.stack([left, right])


# ---------------------------------------------------------------------------------------------------------------
# Polygons (canonical coordinates)
# ---------------------------------------------------------------------------------------------------------------
def mirror_polygons() -> np.ndarray:
    """The two side-mirror polygons.

    Returns:
        ``[2, 6, 2]`` float64 canonical coordinates; index 0 = left mirror, 1 = right mirror.
    """
    return _left_right(MIRROR_LEFT_PX)


def gripper_polygons() -> np.ndarray:
    """The two gripper-jaw polygons (they cover the bottom corners of the image).

    Returns:
        ``[2, 6, 2]`` float64 canonical coordinates; index 0 = left, 1 = right.
    """
    return _left_right(GRIPPER_LEFT_PX)


def finger_polygon() -> np.ndarray:
    """The centred finger trapezoid: height 0.37·H from the bottom edge, top width 0.25·H, bottom width 1.4·H.

    Returns:
        ``[1, 4, 2]`` float64 canonical coordinates, vertices bottom-left, top-left, top-right, bottom-right.
    """
    bottom_y = 0.5
    top_y = bottom_y - FINGER_HEIGHT
    tw, bw = FINGER_TOP_WIDTH / 2.0, FINGER_BOTTOM_WIDTH / 2.0
    pts = np.array([[-bw, bottom_y], [-tw, top_y], [tw, top_y], [bw, bottom_y]], dtype=np.float64)
    return pts[None]


def _selected_polygons(mirror: bool, gripper: bool, finger: bool) -> list[np.ndarray]:
    polys: list[np.ndarray] = []
    if mirror:
        polys.extend(mirror_polygons())
    if gripper:
        polys.extend(gripper_polygons())
    if finger:
        polys.extend(finger_polygon())
    return polys


# ---------------------------------------------------------------------------------------------------------------
# Drawing
# ---------------------------------------------------------------------------------------------------------------
def draw_predefined_mask(
    img: np.ndarray,  # [H, W, C] or [H, W]
    color: tuple[int, ...] | int | float = (0, 0, 0),
    mirror: bool = True,
    gripper: bool = True,
    finger: bool = False,
    use_aa: bool = False,
) -> np.ndarray:
    """Paint UMI's predefined mask polygons onto a copy of ``img`` (the input is not modified).

    Each polygon is mapped from canonical coordinates to the image's own resolution, rounded to integer pixels
    and filled with ``cv2.fillPoly`` (``cv2.LINE_AA`` when ``use_aa`` else ``cv2.LINE_8``), as UMI does.

    Args:
        img: ``[H, W, C]`` or ``[H, W]`` image (uint8 RGB by convention; any dtype cv2.fillPoly accepts).
        color: fill colour, one value per channel (or a scalar).
        mirror, gripper, finger: which polygons to paint.
        use_aa: anti-aliased polygon edges (UMI uses this at eval time after resizing to 224²).

    Returns:
        New array, same shape and dtype as ``img``.
    """
    img = np.asarray(img)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise CameraError(f"image must have shape [H, W] or [H, W, C] with C in (1, 3, 4), got {img.shape}")
    h, w = _check_size(img.shape[0], img.shape[1])
    if np.isscalar(color):
        color_t: tuple[float, ...] = (float(color),)  # type: ignore[arg-type]
    else:
        color_t = tuple(float(c) for c in color)  # type: ignore[union-attr]
        n_ch = 1 if img.ndim == 2 else img.shape[2]
        if len(color_t) not in (1, n_ch):
            raise CameraError(f"color has {len(color_t)} values but the image has {n_ch} channels")
    out = np.ascontiguousarray(img.copy())
    line = cv2.LINE_AA if use_aa else cv2.LINE_8
    for poly in _selected_polygons(mirror, gripper, finger):
        pts = np.round(canonical_to_pixel(poly, h, w)).astype(np.int32)
        cv2.fillPoly(out, [pts], color=color_t, lineType=line)
    return out


def predefined_mask(
    height: int, width: int, mirror: bool = True, gripper: bool = True, finger: bool = False
) -> np.ndarray:
    """Boolean mask of the selected predefined polygons at ``height × width``.

    Returns:
        ``[H, W]`` bool, True where a polygon covers the pixel (drawn without anti-aliasing).
    """
    h, w = _check_size(height, width)
    canvas = np.zeros((h, w), dtype=np.uint8)
    return draw_predefined_mask(canvas, color=255, mirror=mirror, gripper=gripper, finger=finger) > 0


def mirror_crop_slices(height: int, width: int, left: bool = True) -> tuple[slice, slice]:
    """Bounding box of one side mirror as array slices.

    UMI's left box is (290, 1120)–(650, 1480) (x, y) at 2704×2028; it is mapped canonically to the target size
    (right box: canonical x negated), rounded to integer pixels and clipped to the image (UMI does not clip; on
    224×224 its box would start at column −5, which numpy would read as an empty slice).

    Args:
        height, width: target image size.
        left: left mirror (True) or right mirror (False).

    Returns:
        ``(row_slice, col_slice)`` for ``img[row_slice, col_slice]``.
    """
    h, w = _check_size(height, width)
    c = pixel_to_canonical(np.asarray(MIRROR_CROP_LEFT_PX, dtype=np.float64), REFERENCE_HEIGHT, REFERENCE_WIDTH)
    if not left:
        c[:, 0] *= -1.0
    px = np.round(canonical_to_pixel(c, h, w)).astype(np.int64)
    px[:, 0] = np.clip(px[:, 0], 0, w)
    px[:, 1] = np.clip(px[:, 1], 0, h)
    return (
        slice(int(px[:, 1].min()), int(px[:, 1].max())),
        slice(int(px[:, 0].min()), int(px[:, 0].max())),
    )
