"""Numcodecs codecs for UMI replay buffers: a JPEG XL codec whose stored config UMI's reader accepts.

UMI's ``JpegXl`` (codec id ``imagecodecs_jpegxl``) is rebuilt by numcodecs as ``cls(**config)``, so a
``.zarray`` whose compressor config holds any key beyond UMI's eleven makes UMI's reader fail. Modern
``imagecodecs.numcodecs.Jpegxl`` writes extra keys (``bitspersample``, ``squeeze``, ...). :class:`UmiJpegXl`
writes exactly UMI's eleven keys and reads configs with or without the extras.

Nothing is registered at import time: call :func:`register_codecs` (``ReplayBuffer.open``/``create`` do).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numcodecs import Blosc
from numcodecs.abc import Codec
from numcodecs.compat import ensure_contiguous_ndarray, ndarray_copy

from umi_aug.errors import DatasetError

JPEGXL_CODEC_ID = "imagecodecs_jpegxl"

#: UMI's JpegXl constructor parameters, in its order (diffusion_policy/codecs/imagecodecs_numcodecs.py).
UMI_JPEGXL_PARAMS: tuple[str, ...] = (
    "level", "effort", "distance", "lossless", "decodingspeed", "photometric", "planar",
    "usecontainer", "index", "keeporientation", "numthreads",
)

#: JPEG XL quality level UMI's 07_generate_replay_buffer.py uses for camera images.
UMI_JPEGXL_LEVEL = 99


def _squeeze_frames(x: np.ndarray) -> np.ndarray:
    """Reshape ``(1, ..., 1, H, W, C)`` to ``(H, W, C)``; several frames become ``(n, H, W, C)``."""
    if x.ndim <= 3:
        return x
    n = int(np.prod(x.shape[:-3]))
    return x.reshape(x.shape[-3:] if n == 1 else (-1,) + x.shape[-3:])


class UmiJpegXl(Codec):
    """JPEG XL codec with UMI's config schema (codec id ``imagecodecs_jpegxl``).

    Encodes one chunk of images, e.g. ``(1, H, W, 3)`` uint8 RGB, with ``imagecodecs.jpegxl_encode``;
    leading length-1 frame axes are squeezed, as UMI's codec does. ``lossless`` is stored as a bool
    (UMI stores ``bool(lossless)``), so ``UmiJpegXl(level=99, numthreads=1)`` is lossy.
    """

    codec_id = JPEGXL_CODEC_ID

    def __init__(
        self,
        level: int | None = None,
        effort: int | None = None,
        distance: float | None = None,
        lossless: bool | None = False,
        decodingspeed: int | None = None,
        photometric: int | str | None = None,
        planar: bool | None = None,
        usecontainer: bool | None = None,
        index: int | None = None,
        keeporientation: bool | None = None,
        numthreads: int | None = None,
    ) -> None:
        self.level = level
        self.effort = effort
        self.distance = distance
        self.lossless = bool(lossless)
        self.decodingspeed = decodingspeed
        self.photometric = photometric
        self.planar = planar
        self.usecontainer = usecontainer
        self.index = index
        self.keeporientation = keeporientation
        self.numthreads = numthreads

    def get_config(self) -> dict[str, Any]:
        """Return ``{"id": "imagecodecs_jpegxl", <UMI's 11 keys>}`` and nothing else."""
        config: dict[str, Any] = {"id": self.codec_id}
        config.update({k: getattr(self, k) for k in UMI_JPEGXL_PARAMS})
        return config

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> "UmiJpegXl":
        """Build from a stored config, ignoring keys UMI's codec does not know (written by newer
        imagecodecs, e.g. ``bitspersample``, ``squeeze``, ``primaries``, ``transfer``)."""
        return cls(**{k: v for k, v in dict(config).items() if k in UMI_JPEGXL_PARAMS})

    def encode(self, buf: Any) -> bytes:
        """Encode an image chunk (uint8 ``(..., H, W, C)``) to JPEG XL bytes."""
        import imagecodecs  # lazy, start-up: imagecodecs

        arr = _squeeze_frames(np.asarray(buf))
        return imagecodecs.jpegxl_encode(
            arr, level=self.level, effort=self.effort, distance=self.distance, lossless=self.lossless,
            decodingspeed=self.decodingspeed, photometric=self.photometric, planar=self.planar,
            usecontainer=self.usecontainer, numthreads=self.numthreads,
        )

    def decode(self, buf: Any, out: Any = None) -> Any:
        """Decode JPEG XL bytes to an image array; when ``out`` is given its raw bytes are filled."""
        import imagecodecs  # lazy, start-up: imagecodecs

        img = imagecodecs.jpegxl_decode(
            ensure_contiguous_ndarray(buf), index=self.index, keeporientation=self.keeporientation,
            numthreads=self.numthreads,
        )
        if out is None:
            return img
        return ndarray_copy(img, out)


def register_codecs() -> None:
    """Register :class:`UmiJpegXl` with numcodecs under ``imagecodecs_jpegxl`` (idempotent; replaces any
    other class registered for that id, e.g. ``imagecodecs.numcodecs.Jpegxl``)."""
    from numcodecs.registry import codec_registry, register_codec  # lazy, start-up: zarr

    if codec_registry.get(JPEGXL_CODEC_ID) is not UmiJpegXl:
        register_codec(UmiJpegXl, JPEGXL_CODEC_ID)


def umi_image_compressor() -> UmiJpegXl:
    """The compressor UMI uses for ``camera*_rgb``: ``JpegXl(level=99, numthreads=1)`` (lossy)."""
    return UmiJpegXl(level=UMI_JPEGXL_LEVEL, numthreads=1)


def umi_image_codec_from(config: dict[str, Any] | None, effort: int | None = None) -> UmiJpegXl:
    """The codec an export's ``camera*_rgb`` array is written with: UMI's JPEG-XL, whose stored config is exactly
    UMI's 12 keys (``id`` + :data:`UMI_JPEGXL_PARAMS`) whatever ``config`` carried.

    Args:
        config: a source array's stored compressor config (``.zarray`` ``"compressor"``) or None. A JPEG-XL config
            keeps its values for UMI's keys and drops every other key (``bitspersample``, ``squeeze``, ...); any
            other codec (or None) gives :func:`umi_image_compressor`.
        effort: libjxl encoder effort to store (1..9); None keeps the source's (or UMI's default, None).
    """
    if config is not None and config.get("id") == JPEGXL_CODEC_ID:
        codec = UmiJpegXl.from_config(config)
    else:
        codec = umi_image_compressor()
    if effort is not None:
        codec.effort = int(effort)
    return codec


def umi_lowdim_compressor() -> None:
    """The compressor UMI's 07 script uses for low-dimensional arrays: none (stored uncompressed)."""
    return None


def umi_default_compressor() -> Codec:
    """UMI ReplayBuffer's ``'default'`` compressor: Blosc lz4, clevel 5, NOSHUFFLE."""
    return Blosc(cname="lz4", clevel=5, shuffle=Blosc.NOSHUFFLE)


def umi_disk_compressor() -> Codec:
    """UMI ReplayBuffer's ``'disk'`` compressor: Blosc zstd, clevel 5, BITSHUFFLE."""
    return Blosc(cname="zstd", clevel=5, shuffle=Blosc.BITSHUFFLE)


def resolve_compressor(compressor: Codec | str | None) -> Codec | None:
    """Map UMI's compressor names to codecs: ``'default'`` → Blosc lz4, ``'disk'`` → Blosc zstd,
    ``'jpegxl'`` → :func:`umi_image_compressor`, ``None`` → uncompressed; a codec is returned as is."""
    if compressor is None or isinstance(compressor, Codec):
        return compressor
    names = {"default": umi_default_compressor, "disk": umi_disk_compressor, "jpegxl": umi_image_compressor}
    if compressor not in names:
        raise DatasetError(f"unknown compressor name {compressor!r}; use one of {sorted(names)}, None or a codec")
    return names[compressor]()
