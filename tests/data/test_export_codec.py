"""Issue #30 item 4: an export's image array always stores UMI's exact 12-key JPEG-XL codec config, whatever the
source dataset carried (newer imagecodecs' ``bitspersample`` / ``squeeze``, another codec), for every
``jpegxl_effort`` — UMI's reader rebuilds the codec as ``JpegXl(**config)`` and refuses any other key."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.data.helpers import JXL_MAE_BOUND, random_episode
from tests.data.test_codecs import UMI_CONFIG
from umi_aug.data import ReplayBuffer

SIZE = 64  # the size JXL_MAE_BOUND was measured at (at 32² effort 4 the error reaches ~1.1)
EXTRA_KEYS = {"bitspersample": None, "squeeze": None}


def _source(tmp_path: Path, rng: np.random.Generator, codec: str) -> tuple[Path, dict[str, np.ndarray]]:
    """A 2-episode zarr directory dataset whose ``camera0_rgb`` codec is UMI's JPEG-XL config plus newer
    imagecodecs' extra keys (``codec="jpegxl+extras"``) or Blosc (``codec="blosc"``); also its decoded frames."""
    rb = ReplayBuffer.create()
    for n in (5, 4):
        ep = random_episode(rng, n, size=SIZE)
        rb.add_episode(ep, compressors={"camera0_rgb": "default"} if codec == "blosc" else None)
    path = rb.save(tmp_path / "src.zarr")
    if codec == "jpegxl+extras":
        zarray = path / "data" / "camera0_rgb" / ".zarray"
        meta = json.loads(zarray.read_text())
        meta["compressor"] = {**meta["compressor"], **EXTRA_KEYS}
        zarray.write_text(json.dumps(meta))
    with ReplayBuffer.open(path) as buf:
        frames = np.asarray(buf["camera0_rgb"][:])
        if codec == "jpegxl+extras":  # the source really carries the extra keys (and still reads)
            raw = json.loads(buf.root.store["data/camera0_rgb/.zarray"])
            assert set(EXTRA_KEYS) <= set(raw["compressor"])
    return path, frames


class _NoJobSource:
    """An export ``source`` (:class:`umi_aug.augment.sources.InputSource`) with no augmentable demo: the export holds
    the originals only, written through every step of :func:`umi_aug.augment.export` (working store, records,
    ``.zip`` copy, summary)."""

    def __init__(self, dataset: Path) -> None:
        self.dataset = str(dataset)

    def reads(self) -> tuple[Path, ...]:
        return (Path(self.dataset),)

    def check(self, image_size: int) -> None:
        assert image_size == SIZE

    def fingerprint(self) -> str:
        return "no-job-source:" + self.dataset

    def n_augment(self, n_episodes: int) -> int:
        return 0

    def prepare(self, work, cfg, *, progress: bool = False, prefit_obstacles=()):
        original = ReplayBuffer.open(self.dataset)
        demos = [SimpleNamespace(index=i, contact_index=None) for i in range(original.n_episodes)]
        return SimpleNamespace(cfg=cfg, paths={"dataset": self.dataset}, original=original, demos=demos,
                               augmentable=[], stages={}, work_dir=Path(work))


def _stored_image_config(path: Path) -> dict:
    if path.name.endswith(".zip"):
        with zipfile.ZipFile(path) as z:
            return json.loads(z.read("data/camera0_rgb/.zarray"))["compressor"]
    return json.loads((path / "data" / "camera0_rgb" / ".zarray").read_text())["compressor"]


@pytest.mark.parametrize("codec", ["jpegxl+extras", "blosc"])
@pytest.mark.parametrize("effort", [None, 4])
@pytest.mark.parametrize("include_original", [True, False])
def test_export_stores_umis_exact_jpegxl_config(tmp_path, rng, codec, effort, include_original):
    from umi_aug.augment import AugmentConfig, export

    src, frames = _source(tmp_path, rng, codec)
    cfg = AugmentConfig(mode="freespace", image_size=SIZE, jpegxl_effort=effort, include_original=include_original)
    out = tmp_path / "out" / "aug.zarr.zip"
    out.parent.mkdir()
    summary = export(tmp_path / "src_folder", out, cfg, work_dir=tmp_path / "work", progress=False, pictures=False,
                     source=_NoJobSource(src))
    stored = _stored_image_config(out)
    want = dict(UMI_CONFIG, effort=effort)
    assert stored == want  # exactly UMI's 12 keys (zarr writes them sorted)
    with ReplayBuffer.open(out) as buf:
        assert buf.n_episodes == (2 if include_original else 0)
        assert summary.n_original == buf.n_episodes
        if include_original:
            got = np.asarray(buf["camera0_rgb"][:])
            assert got.shape == frames.shape and got.dtype == np.uint8
            err = np.abs(got.astype(np.int16) - frames.astype(np.int16))
            if codec == "jpegxl+extras":  # the original chunks are copied as stored
                assert np.array_equal(got, frames)
            else:  # re-encoded with UMI's lossy JPEG-XL level 99
                assert err.mean() < JXL_MAE_BOUND
            assert buf["camera0_rgb"].chunks == (1, SIZE, SIZE, 3)


def test_umis_codec_reads_an_export_of_a_source_with_extra_keys(tmp_path, rng):
    """A replica of UMI's ``JpegXl`` (its exact constructor: 11 keyword parameters) in a fresh interpreter opens
    the export of a source whose codec config carries ``bitspersample``/``squeeze``, with ``jpegxl_effort=None`` —
    the case UMI's reader refused before (issue #30)."""
    from tests.data.test_umi_compat import _run
    from umi_aug.augment import AugmentConfig, export

    src, frames = _source(tmp_path, rng, "jpegxl+extras")
    out = tmp_path / "aug.zarr.zip"
    export(tmp_path / "src_folder", out, AugmentConfig(mode="freespace", image_size=SIZE, jpegxl_effort=None),
           work_dir=tmp_path / "work", progress=False, pictures=False, source=_NoJobSource(src))
    np.save(tmp_path / "expected.npy", frames)
    printed = _run('''
        root = zarr.open("aug.zarr.zip", mode="r")
        arr = root["data"]["camera0_rgb"]
        assert type(arr.compressor).__name__ == "ReplicaJpegXl"
        assert np.array_equal(arr[:], np.load("expected.npy"))
        print("UMI-READ-OK")
    ''', tmp_path)
    assert "UMI-READ-OK" in printed
