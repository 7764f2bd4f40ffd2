"""Feature extraction in blocks of frames (one COLMAP thread each) stores what one thread stores: the same image
ids, keypoints and descriptors (issue #34 item 1: the triangulation's extraction on both cores, still the same
bytes for a Ray worker and the one-process build)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from umi_aug.camera import gopro_intrinsics_2_7k
from umi_aug.errors import ReconError
from umi_aug.recon.colmap_blocks import block_bounds, extract_in_blocks
from umi_aug.recon.sfm import colmap_camera_params

INTR = gopro_intrinsics_2_7k().scaled(320, 240)


def test_block_bounds_cover_the_items_in_order():
    for n in (1, 2, 7, 38, 100):
        for blocks in (1, 2, 3, 8):
            for least in (1, 4):
                b = block_bounds(n, blocks, least)
                assert b[0][0] == 0 and b[-1][1] == n
                assert all(s1 == e0 for (_, e0), (s1, _) in zip(b, b[1:]))
                assert 1 <= len(b) <= blocks
                assert len(b) == 1 or min(e - s for s, e in b) >= least
    assert block_bounds(0, 2) == []
    assert block_bounds(7, 2, 4) == [(0, 7)]  # too few to give two blocks 4 each
    assert block_bounds(38, 2, 4) == [(0, 19), (19, 38)]


def _reader_and_options(pc, mask_dir, threads=1):
    reader = pc.ImageReaderOptions()
    reader.camera_model = "OPENCV_FISHEYE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in colmap_camera_params(INTR))
    reader.mask_path = str(mask_dir)
    ext = pc.FeatureExtractionOptions()
    ext.num_threads = threads
    ext.sift.max_num_features = 400
    return reader, ext


def _contents(pc, db):
    d = pc.Database.open(str(db))
    try:
        images = sorted((im.image_id, im.name) for im in d.read_all_images())
        cams = {c.camera_id: (str(c.model), list(c.params)) for c in d.read_all_cameras()}
        cam_of = {im.image_id: cams[im.camera_id] for im in d.read_all_images()}
        feats = {i: (d.read_keypoints(i).tobytes(), np.asarray(d.read_descriptors(i).data).tobytes())
                 for i, _ in images}
    finally:
        d.close()
    return images, cam_of, feats


def test_blocks_store_the_bytes_of_one_thread(tmp_path):
    pc = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(7)
    img_dir, mask_dir = tmp_path / "images", tmp_path / "masks"
    (img_dir / "s").mkdir(parents=True)
    (mask_dir / "s").mkdir(parents=True)
    base = cv2.GaussianBlur(rng.integers(0, 255, (300, 400, 3), dtype=np.uint8), (5, 5), 0)
    names = []
    for i in range(13):  # a textured plane panned across: every frame has features, frames differ
        names.append(f"s/{i:03d}.png")
        cv2.imwrite(str(img_dir / names[-1]), base[20 + i:260 + i, 3 * i:320 + 3 * i])
        cv2.imwrite(str(mask_dir / f"{names[-1]}.png"), np.full((240, 320), 255, np.uint8))
    reader, ext = _reader_and_options(pc, mask_dir)
    extract_in_blocks(pc, tmp_path / "one.db", img_dir, names, reader, ext, 1)
    extract_in_blocks(pc, tmp_path / "three.db", img_dir, names, reader, ext, 3)  # 3 blocks: two merges
    one, three = _contents(pc, tmp_path / "one.db"), _contents(pc, tmp_path / "three.db")
    assert one[0] == three[0] == [(i + 1, n) for i, n in enumerate(names)]
    assert one[1] == three[1]  # each image's camera has the same model and parameters
    assert all(len(k) > 0 for k, _ in one[2].values())
    assert one[2] == three[2]
    assert sorted(p.name for p in tmp_path.glob("*.db")) == ["one.db", "three.db"]  # block databases removed
    with pytest.raises(ReconError, match="num_threads must be 1"):
        extract_in_blocks(pc, tmp_path / "bad.db", img_dir, names, reader, _reader_and_options(pc, mask_dir, 2)[1],
                          2)
