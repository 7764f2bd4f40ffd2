from __future__ import annotations

import time

import numcodecs
import numpy as np
import pytest
from numcodecs.registry import codec_registry

from tests.data.helpers import JXL_MAE_BOUND, JXL_MAX_BOUND, smooth_images
from umi_aug.data import (
    UmiJpegXl, register_codecs, resolve_compressor, umi_default_compressor, umi_image_compressor,
    umi_lowdim_compressor,
)
from umi_aug.errors import DatasetError

UMI_CONFIG = {"id": "imagecodecs_jpegxl", "level": 99, "effort": None, "distance": None, "lossless": False,
              "decodingspeed": None, "photometric": None, "planar": None, "usecontainer": None, "index": None,
              "keeporientation": None, "numthreads": 1}


def test_image_compressor_config_is_exactly_umis():
    assert umi_image_compressor().get_config() == UMI_CONFIG
    assert list(umi_image_compressor().get_config()) == list(UMI_CONFIG)
    assert umi_lowdim_compressor() is None


def test_from_config_ignores_newer_imagecodecs_keys():
    cfg = dict(UMI_CONFIG, bitspersample=None, squeeze=None, primaries=None, transfer=None, lossless=True)
    cfg.pop("id")
    codec = UmiJpegXl.from_config(cfg)
    assert codec.get_config() == dict(UMI_CONFIG, lossless=True)


def test_register_codecs_is_idempotent_and_replaces_imagecodecs():
    from imagecodecs.numcodecs import Jpegxl

    numcodecs.register_codec(Jpegxl)
    register_codecs()
    register_codecs()
    assert codec_registry["imagecodecs_jpegxl"] is UmiJpegXl
    assert isinstance(numcodecs.get_codec(UMI_CONFIG), UmiJpegXl)


def test_blosc_default_and_names():
    cfg = umi_default_compressor().get_config()
    assert (cfg["id"], cfg["cname"], cfg["clevel"], cfg["shuffle"]) == ("blosc", "lz4", 5, 0)
    assert resolve_compressor("default").get_config() == cfg
    assert resolve_compressor("disk").get_config()["cname"] == "zstd"
    assert resolve_compressor(None) is None
    with pytest.raises(DatasetError, match="bogus"):
        resolve_compressor("bogus")


def test_encode_decode_within_tolerance_and_timing(rng):
    imgs = smooth_images(rng, 3, 224, 224)
    codec = umi_image_compressor()
    t0 = time.perf_counter()
    blobs = [codec.encode(imgs[i:i + 1]) for i in range(3)]
    t1 = time.perf_counter()
    out = np.empty((1, 224, 224, 3), np.uint8)
    dec = []
    for b in blobs:
        codec.decode(b, out=out)
        dec.append(out[0].copy())
        np.testing.assert_array_equal(codec.decode(b), out[0])
    t2 = time.perf_counter()
    err = np.abs(np.stack(dec).astype(int) - imgs)
    print(f"jxl 224x224: encode {(t1 - t0) / 3 * 1e3:.1f} ms, decode {(t2 - t1) / 6 * 1e3:.1f} ms, "
          f"{np.mean([len(b) for b in blobs]):.0f} B/frame, MAE {err.mean():.3f}, max {err.max()}")
    assert err.mean() < JXL_MAE_BOUND and err.max() <= JXL_MAX_BOUND
    assert 0 < err.mean()  # level 99 is lossy, as in UMI
