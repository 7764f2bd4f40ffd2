"""Byte-level compatibility with UMI's reader/writer, checked in fresh interpreters (clean codec registry).

``REPLICA`` is a test-only codec with exactly the constructor signature of UMI's ``JpegXl``
(diffusion_policy/codecs/imagecodecs_numcodecs.py): 11 keyword parameters, ``lossless = bool(lossless)``,
config = numcodecs' default ``__dict__`` dump. numcodecs rebuilds it as ``cls(**config)``, so any extra
key in a stored config makes it fail, just as UMI's does.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np

from tests.data.helpers import JXL_MAE_BOUND, random_episode, smooth_images
from tests.data.test_codecs import UMI_CONFIG
from umi_aug.data import ReplayBuffer

REPLICA = textwrap.dedent('''
    import numpy as np, numcodecs, imagecodecs, zarr
    from numcodecs.abc import Codec

    class ReplicaJpegXl(Codec):
        codec_id = "imagecodecs_jpegxl"

        def __init__(self, level=None, effort=None, distance=None, lossless=None, decodingspeed=None,
                     photometric=None, planar=None, usecontainer=None, index=None, keeporientation=None,
                     numthreads=None):
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

        @staticmethod
        def _squeeze(x):
            return x.reshape(x.shape[-3:]) if x.ndim > 3 and int(np.prod(x.shape[:-3])) == 1 else x

        def encode(self, buf):
            return imagecodecs.jpegxl_encode(self._squeeze(np.asarray(buf)), level=self.level,
                effort=self.effort, distance=self.distance, lossless=self.lossless,
                decodingspeed=self.decodingspeed, photometric=self.photometric, planar=self.planar,
                usecontainer=self.usecontainer, numthreads=self.numthreads)

        def decode(self, buf, out=None):
            if out is not None:
                out = self._squeeze(out)
            return imagecodecs.jpegxl_decode(buf, index=self.index, keeporientation=self.keeporientation,
                                             numthreads=self.numthreads, out=out)

    numcodecs.register_codec(ReplicaJpegXl)
''')


def _run(script: str, cwd: Path) -> str:
    res = subprocess.run([sys.executable, "-c", REPLICA + textwrap.dedent(script)], cwd=cwd,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-4000:]
    return res.stdout


def test_on_disk_layout_matches_umi(tmp_path, rng):
    rb = ReplayBuffer.create()
    for n in (3, 2):
        rb.add_episode(random_episode(rng, n, cameras=(0, 1)))
    path = rb.save(tmp_path / "dataset.zarr.zip")
    with zipfile.ZipFile(path) as z:
        meta = {n[:-len("/.zarray")]: json.loads(z.read(n)) for n in z.namelist() if n.endswith(".zarray")}
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())
        assert {".zgroup", "data/.zgroup", "meta/.zgroup"} <= set(z.namelist())
    for cam in ("camera0_rgb", "camera1_rgb"):
        assert meta[f"data/{cam}"]["compressor"] == UMI_CONFIG
        assert meta[f"data/{cam}"]["chunks"] == [1, 64, 64, 3] and meta[f"data/{cam}"]["dtype"] == "|u1"
    for k in ("eef_pos", "eef_rot_axis_angle", "gripper_width"):
        assert meta[f"data/robot0_{k}"]["compressor"] is None and meta[f"data/robot0_{k}"]["dtype"] == "<f4"
        assert meta[f"data/robot0_{k}"]["chunks"][0] == 3
    for k in ("demo_start_pose", "demo_end_pose"):
        assert meta[f"data/robot0_{k}"]["dtype"] == "<f8" and meta[f"data/robot0_{k}"]["compressor"] is None
    assert meta["meta/episode_ends"]["dtype"] == "<i8" and meta["meta/episode_ends"]["compressor"] is None
    assert meta["meta/episode_ends"]["shape"] == [2]


def test_umi_reader_opens_our_zip(tmp_path, rng):
    rb = ReplayBuffer.create()
    for n in (3, 4):
        rb.add_episode(random_episode(rng, n))
    path = rb.save(tmp_path / "dataset.zarr.zip")
    with ReplayBuffer.open(path) as ours:
        expected = {k: ours[k][:] for k in ours.keys()}
    np.savez(tmp_path / "expected.npz", **expected)
    out = _run('''
        import sys
        exp = np.load("expected.npz")
        # like UMI's ReplayBuffer.create_from_path: zarr.open on the .zarr.zip path
        root = zarr.open("dataset.zarr.zip", mode="r")
        assert root["meta"]["episode_ends"][:].tolist() == [3, 7]
        for key in exp.files:
            arr = root["data"][key]
            got = np.stack([arr[i] for i in range(arr.shape[0])])
            assert got.dtype == exp[key].dtype and np.array_equal(got, exp[key]), key
        assert type(root["data"]["camera0_rgb"].compressor).__name__ == "ReplicaJpegXl"
        # like UmiDataset: ZipStore(mode="r") copied into a MemoryStore
        with zarr.ZipStore("dataset.zarr.zip", mode="r") as zs:
            mem = zarr.MemoryStore()
            zarr.copy_store(zs, mem)
        root = zarr.group(mem)
        assert np.array_equal(root["data"]["camera0_rgb"][5], exp["camera0_rgb"][5])
        print("UMI-READ-OK")
    ''', tmp_path)
    assert "UMI-READ-OK" in out


def test_we_open_files_written_by_umi_codec_and_modern_imagecodecs(tmp_path, rng):
    imgs = smooth_images(rng, 5, 64, 64)
    lowdim = rng.normal(size=(5, 3)).astype(np.float32)
    np.savez(tmp_path / "src.npz", imgs=imgs, lowdim=lowdim)
    out = _run('''
        from imagecodecs.numcodecs import Jpegxl
        src = np.load("src.npz")

        def write(out, img_codec, lowdim_codec):
            root = zarr.group(zarr.MemoryStore())       # UMI's 07 script: memory store, then ZipStore copy
            data, meta = root.require_group("data"), root.require_group("meta")
            meta.array("episode_ends", np.array([2, 5], np.int64), compressor=None)
            data.array("camera0_rgb", src["imgs"], chunks=(1, 64, 64, 3), compressor=img_codec)
            data.array("robot0_eef_pos", src["lowdim"], compressor=lowdim_codec)
            with zarr.ZipStore(out, mode="w") as zs:
                zarr.copy_store(root.store, zs)
            np.save(out + ".decoded.npy", data["camera0_rgb"][:])

        write("umi.zarr.zip", ReplicaJpegXl(level=99, numthreads=1), None)
        numcodecs.register_codec(Jpegxl)
        blosc = numcodecs.Blosc(cname="lz4", clevel=5, shuffle=numcodecs.Blosc.NOSHUFFLE)
        write("modern.zarr.zip", Jpegxl(level=99, lossless=False, numthreads=1), blosc)
        numcodecs.register_codec(ReplicaJpegXl)  # negative control: UMI's codec cannot read modern configs
        try:
            zarr.open("modern.zarr.zip", mode="r")["data"]["camera0_rgb"]
        except TypeError:
            print("UMI-REJECTS-MODERN")
    ''', tmp_path)
    assert "UMI-REJECTS-MODERN" in out
    with zipfile.ZipFile(tmp_path / "umi.zarr.zip") as z:
        assert json.loads(z.read("data/camera0_rgb/.zarray"))["compressor"] == UMI_CONFIG
    with zipfile.ZipFile(tmp_path / "modern.zarr.zip") as z:
        cfg = json.loads(z.read("data/camera0_rgb/.zarray"))["compressor"]
        assert set(cfg) - set(UMI_CONFIG)  # really has the keys UMI's codec would choke on
    for name, cpr in (("umi", None), ("modern", "blosc")):
        path = tmp_path / f"{name}.zarr.zip"
        with ReplayBuffer.open(path) as rb:
            assert rb.n_episodes == 2 and rb.report.keys["robot0_eef_pos"].compressor == cpr
            np.testing.assert_array_equal(rb["robot0_eef_pos"][:], lowdim)
            got = rb.get_episode(1)["camera0_rgb"]
            np.testing.assert_array_equal(got, np.load(f"{path}.decoded.npy")[2:])
            assert np.abs(got.astype(int) - imgs[2:]).mean() < JXL_MAE_BOUND
