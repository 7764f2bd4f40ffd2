"""Procedural, deterministic PNG textures for the built-in scene (no downloads).

Structure-from-motion needs texture everywhere the camera looks: every surface of the tabletop scene gets a
high-frequency pattern of random dots, blobs and strokes at several scales on a low-frequency base. All
functions are pure: the same generator state gives the same bytes (PNG encoded by OpenCV at a fixed
compression level).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["random_dot_texture", "aruco_texture", "encode_png"]

#: PNG compression level used for every texture (fixed so the bytes are reproducible).
PNG_COMPRESSION: int = 6
#: Spread of feature colours around the base colour: luminance (same for R, G, B) and per-channel chroma, 0..255.
LUMA_SPREAD: float = 95.0
CHROMA_SPREAD: float = 30.0


def encode_png(img_rgb: np.ndarray) -> bytes:
    """Encode an RGB uint8 image ``[H, W, 3]`` (or grey ``[H, W]``) as PNG bytes."""
    img = np.asarray(img_rgb, dtype=np.uint8)
    if img.ndim == 3:
        img = img[..., ::-1]  # OpenCV wants BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:  # pragma: no cover - cv2 only fails on bad input
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def random_dot_texture(
    rng: np.random.Generator,
    size: int = 512,
    base_rgb: tuple[int, int, int] = (150, 120, 90),
    n_dots: int = 900,
    n_strokes: int = 60,
    contrast: float = 1.0,
) -> np.ndarray:
    """A tileable-enough random texture: smooth base + dots/rings/strokes of many sizes and colours.

    Args:
        rng: random generator (the only source of randomness).
        size: texture side, pixels.
        base_rgb: mean background colour, 0..255.
        n_dots: number of filled/ring dots (radius 1.5–3 % of ``size`` and smaller).
        n_strokes: number of line strokes.
        contrast: 0..1 scale of the feature colours' deviation from the base.

    Returns:
        ``[size, size, 3]`` uint8 RGB.
    """
    base = np.asarray(base_rgb, dtype=np.float32)
    # low-frequency base: a few blurred noise octaves
    img = np.empty((size, size, 3), dtype=np.float32)
    img[:] = base
    for octave, amp in ((8, 28.0), (32, 14.0), (128, 8.0)):
        noise = rng.standard_normal((octave, octave, 3)).astype(np.float32)
        img += amp * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    def colour() -> np.ndarray:  # mostly luminance variation, some hue
        lum = rng.uniform(-LUMA_SPREAD, LUMA_SPREAD)
        chroma = rng.uniform(-CHROMA_SPREAD, CHROMA_SPREAD, 3)
        return np.clip(base + contrast * (lum + chroma), 0, 255)

    # strokes
    for _ in range(n_strokes):
        p0 = rng.integers(0, size, 2)
        p1 = np.clip(p0 + rng.integers(-size // 6, size // 6, 2), 0, size - 1)
        col = colour()
        cv2.line(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), col.tolist(),
                 int(rng.integers(1, 4)), lineType=cv2.LINE_AA)
    # dots and rings, log-uniform radii
    radii = np.exp(rng.uniform(np.log(1.5), np.log(0.03 * size), n_dots))
    for r in radii:
        c = rng.integers(0, size, 2)
        col = colour()
        ring = rng.random() < 0.25
        cv2.circle(img, (int(c[0]), int(c[1])), int(round(r)), col.tolist(),
                   2 if ring else -1, lineType=cv2.LINE_AA)
    return np.clip(img, 0, 255).astype(np.uint8)


def aruco_texture(marker_id: int, pixels: int = 240, dictionary: int = cv2.aruco.DICT_4X4_50,
                  white_border_bits: float = 1.0) -> np.ndarray:
    """An ArUco marker image (UMI's table tag is id 13, DICT_4X4_50) with a white quiet zone.

    Args:
        marker_id: marker id.
        pixels: side of the black marker square, pixels (a multiple of 6 keeps the bits crisp).
        dictionary: OpenCV ArUco dictionary id.
        white_border_bits: width of the white margin, in marker bits.

    Returns:
        ``[P, P, 3]`` uint8 RGB with ``P = pixels * (1 + 2 * white_border_bits / 6)`` (rounded): the marker
        occupies the central ``pixels × pixels``.
    """
    d = cv2.aruco.getPredefinedDictionary(dictionary)
    marker = cv2.aruco.generateImageMarker(d, int(marker_id), int(pixels), borderBits=1)
    pad = int(round(pixels * white_border_bits / 6.0))
    img = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    return np.repeat(img[..., None], 3, axis=2)
