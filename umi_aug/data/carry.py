"""A compact, lossless bundle of a UMI replay buffer, to move it to a machine without imagecodecs.

A lent GPU machine (`/work/.library/device`) takes at most 64 MiB of files per call and has no ``imagecodecs``
(the JPEG-XL codec of UMI's ``camera*_rgb`` arrays; its wheel alone is 26 MB). The bundle holds the *decoded*
pixels, so the unpacked buffer trains on exactly the frames the source decodes to:

* every uint8 array of shape ``[N, H, W, C]`` (the frames): per episode, the first frame and then each frame
  minus the one before it (mod 256), zstd level 19 (``numcodecs.Zstd``). Consecutive wrist frames differ
  little; on the 50 square demos at 84² (160 MB decoded, 42 MB as UMI's lossy JPEG XL) the bundle is 36 MB;
* every other array of ``data/`` and ``meta/``: ``arrays.npz`` (compressed);
* ``manifest.json``: shapes, dtypes, chunks, group attributes, and per episode the byte ranges of the frames.

:func:`unpack_bundle` writes a zarr directory store whose frames are stored losslessly (Blosc zstd), arrays
equal to the source's decoded arrays, chunks and attributes as in the source. Only ``numpy``, ``numcodecs`` and
``zarr`` are needed on both sides.

    python -m umi_aug.data.carry pack square_demos/square_expert_fisheye84.zarr.zip .carry/square50
    python -m umi_aug.data.carry unpack .carry/square50 /tmp/square50.zarr          # on the other machine

A single file of float32 tensors (a training checkpoint: weights, EMA weights, Adam moments) travels as
:func:`pack_file` writes it: its bytes regrouped by position in each 4-byte word (all first bytes, then all second
bytes, ...; the sign/exponent bytes of neighbouring floats are alike) and xz-compressed, with its size and SHA-256 in
the header; :func:`unpack_file` gives back the same bytes, checked against that SHA-256. A study checkpoint of the
2 M-parameter square policy after 10,000 steps, 32.4 MB, becomes 23.2 MB (one after 20 steps: 25.6 MB, plain xz
28.9 MB). Only the standard library and numpy.

    python -m umi_aug.data.carry pack-file runs/none_n50/checkpoints/latest.ckpt .carry/none_n50.ckpt.s4xz
    python -m umi_aug.data.carry unpack-file .carry/none_n50.ckpt.s4xz /tmp/none_n50.ckpt   # there
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import DatasetError
from umi_aug.io_utils import atomic_path

__all__ = ["BUNDLE_FORMAT", "pack_bundle", "unpack_bundle", "episode_frames_encode", "episode_frames_decode",
           "pack_file", "unpack_file", "shuffle4", "unshuffle4"]

BUNDLE_FORMAT = "umi_aug.carry/1"
_MANIFEST = "manifest.json"
_ARRAYS = "arrays.npz"
_ZSTD_LEVEL = 19


def _is_frames(arr: Any) -> bool:
    return arr.dtype == np.uint8 and arr.ndim == 4


def episode_frames_encode(frames: np.ndarray, level: int = _ZSTD_LEVEL) -> bytes:
    """One episode's frames ``[T, H, W, C]`` uint8 → zstd bytes of (first frame, successive differences mod 256)."""
    from numcodecs import Zstd  # lazy, start-up: zarr

    delta = frames.copy()
    delta[1:] -= frames[:-1]  # uint8 arithmetic wraps mod 256, which cumsum below undoes exactly
    return bytes(Zstd(level=level).encode(np.ascontiguousarray(delta)))


def episode_frames_decode(blob: bytes, shape: tuple[int, ...]) -> np.ndarray:
    """Inverse of :func:`episode_frames_encode` for an episode of ``shape`` ``[T, H, W, C]``."""
    from numcodecs import Zstd

    raw = np.frombuffer(Zstd().decode(blob), dtype=np.uint8)
    if raw.size != int(np.prod(shape)):
        raise DatasetError(f"bundle frames: {raw.size} bytes decoded, expected {int(np.prod(shape))} for {shape}")
    return np.cumsum(raw.reshape(shape), axis=0, dtype=np.uint8)


def pack_bundle(src: str | os.PathLike, dest: str | os.PathLike, progress: bool = True) -> dict[str, Any]:
    """Write the bundle of the replay buffer ``src`` (zarr directory or ``.zarr.zip``) to the folder ``dest``
    (written beside it, then renamed; an existing ``dest`` is refused). Returns the manifest."""
    from umi_aug.data.replay_buffer import ReplayBuffer

    src, dest = Path(src), Path(dest)
    _refuse_existing(dest)
    with ReplayBuffer.open(src) as buf:
        return _pack_root(buf.root, src, dest, progress)


def _pack_root(root: Any, src: Path, dest: Path, progress: bool) -> dict[str, Any]:
    from tqdm import tqdm

    ends = np.asarray(root["meta/episode_ends"][:], dtype=np.int64)
    if len(ends) == 0:
        raise DatasetError(f"{src}: no episode (meta/episode_ends is empty): nothing to pack")
    starts = np.concatenate([[0], ends[:-1]])
    manifest: dict[str, Any] = {"format": BUNDLE_FORMAT, "source": src.name, "episode_ends": ends.tolist(),
                                "root_attrs": dict(root.attrs), "arrays": {}}
    plain: dict[str, np.ndarray] = {}
    with atomic_path(dest, overwrite=False) as tmp:
        tmp.mkdir(parents=True)
        for group in ("data", "meta"):
            for key, arr in root[group].arrays():
                name = f"{group}/{key}"
                info = {"shape": list(arr.shape), "dtype": str(arr.dtype), "chunks": list(arr.chunks),
                        "attrs": dict(arr.attrs)}
                if group == "data" and _is_frames(arr):
                    if arr.shape[0] != int(ends[-1]):
                        raise DatasetError(f"{src}: {name} has {arr.shape[0]} frames, episode_ends[-1] = {ends[-1]}")
                    offsets, file = [0], f"{key}.frames"
                    with open(tmp / file, "wb") as f:
                        for s, e in tqdm(list(zip(starts, ends)), desc=f"pack {key}", unit="episode",
                                         disable=not progress):
                            blob = episode_frames_encode(arr[int(s):int(e)])
                            f.write(blob)
                            offsets.append(offsets[-1] + len(blob))
                    info.update(kind="frames", file=file, offsets=offsets)
                else:
                    info["kind"] = "array"
                    plain[name] = arr[:]
                manifest["arrays"][name] = info
        with open(tmp / _ARRAYS, "wb") as f:
            np.savez_compressed(f, **{k.replace("/", "__"): v for k, v in plain.items()})
        (tmp / _MANIFEST).write_text(json.dumps(manifest, indent=1))
    return manifest


def _refuse_existing(dest: Path) -> None:
    if dest.exists():
        raise DatasetError(f"{dest} exists; the bundle tools never replace a folder: remove it or pick another path")


def _read_manifest(bundle: Path) -> dict[str, Any]:
    path = bundle / _MANIFEST
    if not path.is_file():
        raise DatasetError(f"{bundle}: no {_MANIFEST}; expected a folder written by "
                           "`python -m umi_aug.data.carry pack`")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not JSON ({exc})") from exc
    if manifest.get("format") != BUNDLE_FORMAT:
        raise DatasetError(f"{path}: format {manifest.get('format')!r} is not {BUNDLE_FORMAT!r}")
    return manifest


def unpack_bundle(bundle: str | os.PathLike, dest: str | os.PathLike, episodes: int | None = None,
                  progress: bool = True) -> Path:
    """Write the replay buffer of ``bundle`` as a zarr directory store at ``dest`` (beside it, then renamed);
    ``episodes``: only the first that many episodes; an existing ``dest`` is refused. Returns ``dest``."""
    import zarr
    from numcodecs import Blosc
    from tqdm import tqdm

    bundle, dest = Path(bundle), Path(dest)
    manifest = _read_manifest(bundle)
    _refuse_existing(dest)
    ends = np.asarray(manifest["episode_ends"], dtype=np.int64)
    n_ep = len(ends) if episodes is None else int(episodes)
    if not 1 <= n_ep <= len(ends):
        raise DatasetError(f"{bundle}: episodes={episodes}: the bundle holds {len(ends)} episodes")
    ends = ends[:n_ep]
    n = int(ends[-1])
    starts = np.concatenate([[0], ends[:-1]])
    with np.load(bundle / _ARRAYS) as z:
        plain = {k.replace("__", "/"): z[k] for k in z.files}
    with atomic_path(dest, overwrite=False) as tmp:
        root = zarr.open_group(zarr.DirectoryStore(str(tmp)), mode="w")
        root.attrs.update(manifest["root_attrs"])
        for name, info in manifest["arrays"].items():
            group, key = name.split("/", 1)
            g = root.require_group(group)
            if name == "meta/episode_ends":
                a = g.array(key, ends, chunks=tuple(info["chunks"]), compressor=None)
            elif info["kind"] == "frames":
                shape = (n, *info["shape"][1:])
                a = g.zeros(key, shape=shape, chunks=tuple(info["chunks"]), dtype=np.uint8,
                            compressor=Blosc("zstd", 3, Blosc.SHUFFLE))
                offsets = info["offsets"]
                with open(bundle / info["file"], "rb") as f:
                    for i in tqdm(range(n_ep), desc=f"unpack {key}", unit="episode", disable=not progress):
                        f.seek(offsets[i])
                        blob = f.read(offsets[i + 1] - offsets[i])
                        s, e = int(starts[i]), int(ends[i])
                        a[s:e] = episode_frames_decode(blob, (e - s, *shape[1:]))
            else:
                values = plain[name]
                if group == "data":
                    values = values[:n]
                a = g.array(key, values, chunks=tuple(info["chunks"]), compressor=Blosc("zstd", 3, Blosc.SHUFFLE))
            a.attrs.update(info.get("attrs", {}))
    return dest


#: Header of a :func:`pack_file` file: magic, then the original size (uint64 LE) and its SHA-256.
_FILE_MAGIC = b"umi_aug.carry.s4xz/1\n"


def shuffle4(data: bytes) -> bytes:
    """``data`` zero-padded to a multiple of 4 bytes, regrouped by byte position within each 4-byte word: bytes
    0, 4, 8, ..., then 1, 5, 9, ..., then 2, ..., then 3, ... (the layout Blosc calls byte shuffle)."""
    pad = (-len(data)) % 4
    words = np.frombuffer(data + b"\0" * pad, dtype=np.uint8).reshape(-1, 4)
    return np.ascontiguousarray(words.T).tobytes()


def unshuffle4(data: bytes, size: int) -> bytes:
    """Inverse of :func:`shuffle4`: the first ``size`` bytes of the regrouped ``data`` back in order."""
    if len(data) % 4 or not 0 <= size <= len(data) < size + 4:
        raise DatasetError(f"packed file: {len(data)} shuffled bytes cannot hold {size} bytes")
    return np.ascontiguousarray(np.frombuffer(data, dtype=np.uint8).reshape(4, -1).T).tobytes()[:size]


def _sha256_bytes(data: bytes) -> bytes:
    import hashlib

    return hashlib.sha256(data).digest()


def pack_file(src: str | os.PathLike, dest: str | os.PathLike, preset: int = 6) -> dict[str, Any]:
    """Write ``src`` byte-shuffled (:func:`shuffle4`) and xz-compressed to the new file ``dest`` (temp path, then
    rename). Returns ``{"bytes", "packed_bytes", "sha256"}``.

    Raises:
        DatasetError: ``src`` missing or empty, or ``dest`` exists.
    """
    import lzma

    src, dest = Path(src), Path(dest)
    if not src.is_file() or src.stat().st_size == 0:
        raise DatasetError(f"{src}: not a file, or empty; nothing to pack")
    _refuse_existing(dest)
    data = src.read_bytes()
    digest = _sha256_bytes(data)
    with atomic_path(dest, overwrite=False) as tmp:
        with open(tmp, "wb") as f:
            f.write(_FILE_MAGIC + len(data).to_bytes(8, "little") + digest)
            f.write(lzma.compress(shuffle4(data), preset=preset))
    return {"bytes": len(data), "packed_bytes": dest.stat().st_size, "sha256": digest.hex()}


def unpack_file(src: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Write the file packed in ``src`` (by :func:`pack_file`) to the new file ``dest``; its SHA-256 is checked
    before anything is written. Returns ``dest``.

    Raises:
        DatasetError: ``src`` is not a packed file, is cut short or corrupt, or ``dest`` exists.
    """
    import lzma

    src, dest = Path(src), Path(dest)
    _refuse_existing(dest)
    try:
        blob = src.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{src}: unreadable ({exc})") from exc
    head = len(_FILE_MAGIC) + 8 + 32
    if not blob.startswith(_FILE_MAGIC) or len(blob) < head:
        raise DatasetError(f"{src}: not a file written by `python -m umi_aug.data.carry pack-file`")
    size = int.from_bytes(blob[len(_FILE_MAGIC):len(_FILE_MAGIC) + 8], "little")
    digest = blob[len(_FILE_MAGIC) + 8:head]
    try:
        data = unshuffle4(lzma.decompress(blob[head:]), size)
    except lzma.LZMAError as exc:
        raise DatasetError(f"{src}: corrupt or cut short ({exc})") from exc
    if _sha256_bytes(data) != digest:
        raise DatasetError(f"{src}: unpacked bytes do not match the SHA-256 {digest.hex()} packed with them")
    with atomic_path(dest, overwrite=False) as tmp:
        tmp.write_bytes(data)
    return dest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m umi_aug.data.carry", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for cmd, help_, src in (("pack", "replay buffer → bundle folder", "src"),
                            ("unpack", "bundle folder → zarr directory store", "bundle"),
                            ("pack-file", "one file (a checkpoint) → byte-shuffled xz file", "src"),
                            ("unpack-file", "byte-shuffled xz file → the original file (SHA-256 checked)", "src")):
        a = sub.add_parser(cmd, help=help_)
        a.add_argument(src)
        a.add_argument("dest")
        if cmd == "unpack":
            a.add_argument("--episodes", type=int, default=None, help="only the first N episodes")
    args = p.parse_args(argv)
    try:
        if args.cmd == "pack-file":
            r = pack_file(args.src, args.dest)
            print(f"{args.dest}: {r['bytes'] / 1e6:.1f} MB → {r['packed_bytes'] / 1e6:.1f} MB, sha256 {r['sha256']}")
        elif args.cmd == "unpack-file":
            print(unpack_file(args.src, args.dest))
        elif args.cmd == "pack":
            m = pack_bundle(args.src, args.dest)
            size = sum(f.stat().st_size for f in Path(args.dest).iterdir())
            print(f"{args.dest}: {len(m['episode_ends'])} episodes, {size / 1e6:.1f} MB")
        else:
            print(unpack_bundle(args.bundle, args.dest, args.episodes))
    except DatasetError as exc:
        print(f"carry: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
