"""robosuite and robomimic packed small, to run the square task on a machine that cannot install them.

A lent GPU machine (``/work/.library/device``; 16 CPU cores) has torch, numba, scipy, h5py and OpenCV but neither
robosuite nor robomimic, and takes at most 64 MiB of files per call. robosuite 1.4.1's wheel is 193 MB, almost all
of it meshes of robots the square task never loads. The bundle keeps:

* robosuite: every ``.py``, ``.json`` and ``.xml`` file (code, controller configs, every model's XML) and, of the
  meshes and textures, only the files the square scene's compiled MuJoCo model names (``file="…"``): 77 files,
  47.7 MB, of 586 MB of assets. The scene built from the bundle is the installed one, file for file
  (``tests/square/test_carry_sim.py`` renders both and compares);
* robomimic: its ``.py`` and ``.json`` files;
* the wheels given (for the other machine's Python: mujoco, PyOpenGL for MuJoCo's EGL backend, numcodecs, zarr,
  hydra-core, ...; ``eval/lent_gpu_eval.sh`` lists them), unzipped as pip would install them, ``*.data/`` left out.

All of it goes into one ``site.tar.xz`` whose members are site-packages paths, so ``tar -xJf site.tar.xz -C SITE``
and ``PYTHONPATH=SITE`` make the packages importable there: 19.3 MB with the ten wheels ``eval/lent_gpu_eval.sh``
lists (20.3 MB as wheels), where robosuite's wheel alone is 193 MB. ``manifest.json`` lists what went in (versions, file counts, sizes, SHA-256).

    python -m umi_aug.square.carry_sim pack .carry/sim --wheels .whl/*.whl     # here (robosuite + robomimic installed)

``probe`` renders the fisheye wrist frames at the first start configurations, so that frames rendered there (GPU
EGL) can be compared with frames rendered here (Mesa's software EGL): same scene, same state, another rasteriser.

    python -m umi_aug.square.carry_sim probe there.npz                        # there
    python -m umi_aug.square.carry_sim probe here.npz --compare there.npz     # here: per-frame differences
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tarfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import SimError
from umi_aug.io_utils import atomic_path

__all__ = ["SIM_BUNDLE_FORMAT", "square_scene_asset_files", "package_text_files", "square_bundle_members",
           "pack_sim_bundle", "probe_frames", "frame_differences"]

SIM_BUNDLE_FORMAT = "umi_aug.carry_sim/1"
#: Source and data files every robosuite / robomimic module may read (code, configs, model XML).
_TEXT_SUFFIXES = (".py", ".json", ".xml")


def _package_root(name: str) -> Path:
    import importlib.util

    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise SimError(f"carry_sim: package {name!r} is not installed here; install the robomimic extra "
                       f"(pip install -c constraints.txt -e '.[robomimic]')")
    return Path(list(spec.submodule_search_locations)[0]).resolve()


def package_text_files(root: Path) -> list[Path]:
    """Every ``.py`` / ``.json`` / ``.xml`` file under ``root`` (a package folder), ``__pycache__`` left out;
    paths relative to ``root``, sorted."""
    return sorted(p.relative_to(root) for p in root.rglob("*")
                  if p.is_file() and p.suffix in _TEXT_SUFFIXES and "__pycache__" not in p.parts)


def square_scene_asset_files(model_xml: str, robosuite_root: Path) -> list[Path]:
    """The files (meshes, textures) a compiled square model names with ``file="…"`` inside ``robosuite_root``,
    relative to it, sorted.

    Raises:
        SimError: a named file is missing, or the model names no file inside robosuite (not robosuite's model).
    """
    root = Path(robosuite_root).resolve()
    out: set[Path] = set()
    for name in re.findall(r'\bfile="([^"]+)"', model_xml):
        p = Path(name).resolve()
        if not p.is_relative_to(root):
            continue
        if not p.is_file():
            raise SimError(f"carry_sim: the square model names {p}, which does not exist")
        out.add(p.relative_to(root))
    if not out:
        raise SimError(f"carry_sim: the square model names no file under {root}; is it robosuite's model?")
    return sorted(out)


def _square_model_xml() -> str:
    """The compiled square scene's XML (robosuite builds it with absolute asset paths)."""
    from umi_aug.square.env import SquareEnv  # lazy: robosuite, MuJoCo

    env = SquareEnv(image_size=None)
    try:
        return env.model_xml()
    finally:
        env.close()


def _clean(info: tarfile.TarInfo) -> tarfile.TarInfo:
    """No owner, mtime 0; files 0644 (shared libraries 0755), folders 0755: the archive depends on content only."""
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    info.mtime = 0
    info.mode = 0o755 if (not info.isfile() or ".so" in Path(info.name).suffixes) else 0o644
    return info


def _add_package(tar: tarfile.TarFile, root: Path, members: list[Path]) -> int:
    """``root.name/<member>`` for each member; returns the raw bytes added."""
    for rel in members:
        tar.add(root / rel, arcname=f"{root.name}/{rel.as_posix()}", recursive=False, filter=_clean)
    return sum((root / m).stat().st_size for m in members)


def _add_wheel(tar: tarfile.TarFile, wheel: Path, seen: set[str]) -> tuple[int, int]:
    """The wheel's files at their site-packages paths (``*.data/`` left out); returns (files, raw bytes).

    Raises:
        SimError: not a readable wheel, or a path another wheel or package already put in the archive.
    """
    import io

    try:
        zf = zipfile.ZipFile(wheel)
    except (OSError, zipfile.BadZipFile) as exc:
        raise SimError(f"carry_sim: wheel {wheel}: not a readable wheel ({exc})") from exc
    n = size = 0
    with zf:
        for zi in zf.infolist():
            top = zi.filename.split("/", 1)[0]
            if zi.is_dir() or top.endswith(".data"):
                continue
            if zi.filename in seen:
                raise SimError(f"carry_sim: wheel {wheel}: {zi.filename} is already in the bundle (two versions "
                               f"of one package?)")
            seen.add(zi.filename)
            data = zf.read(zi)
            info = _clean(tarfile.TarInfo(zi.filename))
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
            n, size = n + 1, size + len(data)
    return n, size


def square_bundle_members(model_xml: str | None = None) -> dict[str, tuple[Path, list[Path]]]:
    """What the bundle takes of each package: ``{"robosuite": (root, files), "robomimic": (root, files)}``, files
    relative to the package folder ``root``: every code/config/XML file, and of robosuite's meshes and textures those
    the compiled square model names.

    Args:
        model_xml: the compiled square scene's XML; None builds the scene here (robosuite, MuJoCo).
    """
    rs_root, rm_root = _package_root("robosuite"), _package_root("robomimic")
    xml = _square_model_xml() if model_xml is None else model_xml
    assets = square_scene_asset_files(xml, rs_root)
    return {"robosuite": (rs_root, sorted(set(package_text_files(rs_root)) | set(assets))),
            "robomimic": (rm_root, package_text_files(rm_root))}


def pack_sim_bundle(dest: str | os.PathLike, wheels: list[str | os.PathLike] = (),
                    model_xml: str | None = None) -> dict[str, Any]:
    """Write ``dest/{site.tar.xz, manifest.json}`` (a new folder; temp path, then rename).

    Args:
        dest: the bundle folder; must not exist.
        wheels: wheels to unpack into the archive too (for the other machine's Python and platform).
        model_xml: the compiled square scene's XML; None builds the scene here (robosuite, MuJoCo).

    Returns:
        The manifest: format, per package its version / files / raw bytes (per wheel its name), the archive's bytes
        and SHA-256.

    Raises:
        SimError: ``dest`` exists, robosuite/robomimic not installed, the model names a missing file, a wheel is
        unreadable or repeats a path.
    """
    dest = Path(dest)
    if dest.exists():
        raise SimError(f"carry_sim: {dest} exists; choose a new folder (a bundle is never overwritten)")
    parts = square_bundle_members(model_xml)
    from importlib.metadata import version

    from umi_aug.eval.results import file_sha256

    manifest: dict[str, Any] = {"format": SIM_BUNDLE_FORMAT, "packages": {}, "wheels": {}}
    with atomic_path(dest, overwrite=False) as tmp:
        tmp.mkdir(parents=True)
        archive = tmp / "site.tar.xz"
        seen: set[str] = set()
        with tarfile.open(archive, "w:xz", preset=9) as tar:
            for name, (root, members) in parts.items():
                seen.update(f"{root.name}/{m.as_posix()}" for m in members)
                manifest["packages"][name] = {"version": version(name), "files": len(members),
                                              "raw_bytes": _add_package(tar, root, members)}
            for w in sorted(Path(w) for w in wheels):
                n, size = _add_wheel(tar, w, seen)
                manifest["wheels"][w.name] = {"files": n, "raw_bytes": size}
        manifest["archive"] = {"name": archive.name, "bytes": archive.stat().st_size, "sha256": file_sha256(archive)}
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def probe_frames(configs_file: str | os.PathLike, n: int = 4, image_size: int = 84) -> np.ndarray:
    """The fisheye wrist frames ``[n, S, S, 3]`` uint8 at the start states of the first ``n`` configurations of
    ``configs_file`` (``umi-aug square-init-configs``), rendered as an evaluation renders them."""
    from umi_aug.eval.runner import load_eval_configs  # lazy: the simulator
    from umi_aug.square.eval import SQUARE_TASK

    states = load_eval_configs(configs_file)["states"]
    if not 1 <= n <= len(states):
        raise SimError(f"carry_sim probe: n={n}: {configs_file} has {len(states)} configurations")
    env = SQUARE_TASK.make_env(None)
    camera = SQUARE_TASK.camera(env, int(image_size))
    try:
        frames = []
        for state in states[:n]:
            env.reset_to(state, initial=True)
            frames.append(camera.render(env.data, env.wrist_pose()))
        return np.stack(frames)
    finally:  # the GL context goes before the interpreter's exit tears EGL down
        camera.close()
        env.close()


def frame_differences(a: np.ndarray, b: np.ndarray) -> list[dict[str, float]]:
    """Per frame of two ``[n, H, W, 3]`` uint8 stacks: mean and max absolute difference (grey levels) and the
    share of pixels whose largest channel difference exceeds 8 grey levels.

    Raises:
        SimError: the stacks differ in shape.
    """
    if a.shape != b.shape:
        raise SimError(f"carry_sim probe: frames {a.shape} and {b.shape} differ in shape")
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return [{"mean_abs": float(f.mean()), "max_abs": float(f.max()), "share_over_8": float((f.max(-1) > 8).mean())}
            for f in d]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m umi_aug.square.carry_sim", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack", help="robosuite + robomimic as the square scene needs them, into a new folder")
    p.add_argument("dest")
    p.add_argument("--wheels", nargs="*", default=[], help="wheels for the other machine, unpacked into the archive")
    q = sub.add_parser("probe", help="wrist frames at the first start configurations, saved (and compared)")
    q.add_argument("out", help=".npz to write (frames)")
    q.add_argument("--configs-file", default="eval/square_init_configs_1000.npz")
    q.add_argument("--n", type=int, default=4)
    q.add_argument("--size", type=int, default=84)
    q.add_argument("--compare", default=None, help="an .npz another machine's probe wrote")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "probe":
            return _probe_main(args)
        manifest = pack_sim_bundle(args.dest, args.wheels)
    except SimError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for name, pk in manifest["packages"].items():
        print(f"{name} {pk['version']}: {pk['files']} files, {pk['raw_bytes'] / 1e6:.1f} MB")
    for name, wh in manifest["wheels"].items():
        print(f"{name}: {wh['files']} files, {wh['raw_bytes'] / 1e6:.1f} MB")
    a = manifest["archive"]
    print(f"{args.dest}/{a['name']}: {a['bytes'] / 1e6:.1f} MB")
    return 0


def _probe_main(args: argparse.Namespace) -> int:
    from umi_aug.io_utils import atomic_path as _atomic

    frames = probe_frames(args.configs_file, args.n, args.size)
    with _atomic(args.out) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, frames=frames)
    print(f"{args.out}: {len(frames)} frames {frames.shape[1]}x{frames.shape[2]}")
    if args.compare:
        try:
            other = np.load(args.compare)["frames"]
        except (OSError, KeyError, ValueError) as exc:
            raise SimError(f"carry_sim probe: --compare {args.compare}: no 'frames' array ({exc})") from exc
        for i, d in enumerate(frame_differences(frames, other)):
            print(f"config {i}: mean |diff| {d['mean_abs']:.3f}, max {d['max_abs']:.0f} grey levels, "
                  f"{100 * d['share_over_8']:.2f} % of pixels over 8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
