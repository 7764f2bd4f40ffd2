"""The square task's robosuite/robomimic bundle for a lent machine (umi_aug.square.carry_sim): which files go in,
the archive and its wheels, and that the scene rendered from the bundled files is the installed one, pixel for pixel."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from umi_aug.errors import SimError
from umi_aug.square.carry_sim import frame_differences, package_text_files, square_scene_asset_files

ROOT = Path(__file__).resolve().parents[2]


def test_asset_files_are_the_named_files_inside_the_package(tmp_path):
    root = tmp_path / "robosuite"
    (root / "models/assets/meshes").mkdir(parents=True)
    for name in ("a.stl", "b.obj", "unused.stl"):
        (root / "models/assets/meshes" / name).write_bytes(b"x")
    outside = tmp_path / "elsewhere.png"
    outside.write_bytes(b"x")
    xml = (f'<mujoco><asset><mesh file="{root}/models/assets/meshes/b.obj"/><mesh file="{root}/models/assets/'
           f'meshes/a.stl"/><mesh file="{root}/models/assets/meshes/a.stl"/><texture file="{outside}"/></asset>'
           f'</mujoco>')
    assert square_scene_asset_files(xml, root) == [Path("models/assets/meshes/a.stl"),
                                                   Path("models/assets/meshes/b.obj")]
    with pytest.raises(SimError, match="missing.stl, which does not exist"):
        square_scene_asset_files(xml.replace("b.obj", "missing.stl"), root)
    with pytest.raises(SimError, match="names no file under"):
        square_scene_asset_files(f'<mujoco><texture file="{outside}"/></mujoco>', root)


def test_package_text_files_leave_out_caches_and_binaries(tmp_path):
    root = tmp_path / "pkg"
    for rel in ("__init__.py", "sub/m.py", "sub/c.json", "models/x.xml", "sub/__pycache__/m.cpython-311.pyc",
                "__pycache__/y.py", "models/mesh.stl", "data.hdf5"):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("x")
    assert package_text_files(root) == [Path("__init__.py"), Path("models/x.xml"), Path("sub/c.json"),
                                        Path("sub/m.py")]


def test_frame_differences():
    a = np.zeros((2, 4, 4, 3), np.uint8)
    b = a.copy()
    b[1, 0, 0, 2] = 200
    b[1, 1, 1, 0] = 5
    d = frame_differences(a, b)
    assert d[0] == {"mean_abs": 0.0, "max_abs": 0.0, "share_over_8": 0.0}
    assert d[1]["max_abs"] == 200 and d[1]["share_over_8"] == pytest.approx(1 / 16)
    assert d[1]["mean_abs"] == pytest.approx(205 / 48)
    with pytest.raises(SimError, match="differ in shape"):
        frame_differences(a, b[:1])


def _wheel(path: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return path


def test_pack_writes_one_archive_with_packages_and_wheels(tmp_path):
    pytest.importorskip("robosuite")  # the robomimic extra; CI installs it (README)
    from umi_aug.square.carry_sim import pack_sim_bundle, square_bundle_members

    import robosuite

    rs_root = Path(robosuite.__file__).resolve().parent
    mesh = next((rs_root / "models/assets/objects/meshes").rglob("*.stl"))
    xml = f'<mujoco><asset><mesh file="{mesh}"/></asset></mujoco>'
    whl = _wheel(tmp_path / "demo_pkg-1.0-py3-none-any.whl",
                 {"demo_pkg/__init__.py": b"VALUE = 7\n", "demo_pkg/_ext.cpython-312-x86_64-linux-gnu.so": b"\0",
                  "demo_pkg-1.0.dist-info/METADATA": b"Name: demo_pkg\n", "demo_pkg-1.0.data/scripts/run": b"#!"})
    manifest = pack_sim_bundle(tmp_path / "sim", [whl], model_xml=xml)
    members = square_bundle_members(xml)
    with tarfile.open(tmp_path / "sim/site.tar.xz") as tar:
        infos = {i.name: i for i in tar.getmembers()}
        assert f"robosuite/{mesh.relative_to(rs_root).as_posix()}" in infos
        assert not any("__pycache__" in n or n.startswith("demo_pkg-1.0.data") for n in infos)
        assert infos["demo_pkg/_ext.cpython-312-x86_64-linux-gnu.so"].mode == 0o755
        assert infos["demo_pkg/__init__.py"].mode == 0o644 and infos["demo_pkg/__init__.py"].mtime == 0
        n_pkg = sum(len(m) for _, m in members.values())
        assert len(infos) == n_pkg + 3
        site = tmp_path / "site"
        tar.extractall(site, filter="data")
    assert json.loads((tmp_path / "sim/manifest.json").read_text()) == manifest
    assert manifest["wheels"]["demo_pkg-1.0-py3-none-any.whl"]["files"] == 3
    assert manifest["packages"]["robosuite"]["files"] == len(members["robosuite"][1])
    # the unpacked site imports its robosuite and the wheel's package, not the installed ones
    code = "import robosuite, demo_pkg; print(robosuite.__file__); print(demo_pkg.VALUE)"
    env = {**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{ROOT}"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    file, value = out.stdout.split()[-2:]
    assert Path(file).resolve().is_relative_to(site.resolve()) and value == "7"
    with pytest.raises(SimError, match="exists"):
        pack_sim_bundle(tmp_path / "sim", [], model_xml=xml)
    with pytest.raises(SimError, match="already in the bundle"):
        pack_sim_bundle(tmp_path / "sim2", [whl, _wheel(tmp_path / "demo_pkg-2.0-py3-none-any.whl",
                                                       {"demo_pkg/__init__.py": b"VALUE = 8\n"})], model_xml=xml)
    assert not (tmp_path / "sim2").exists()
    (tmp_path / "bad.whl").write_bytes(b"not a zip")
    with pytest.raises(SimError, match="bad.whl: not a readable wheel"):
        pack_sim_bundle(tmp_path / "sim3", [tmp_path / "bad.whl"], model_xml=xml)
    assert not (tmp_path / "sim3").exists()


def test_square_scene_from_the_bundled_files_renders_as_installed(tmp_path, gl):
    """The bundle's file selection (code + the meshes/textures the compiled model names) builds the same scene:
    the wrist frames at the first start states, rendered in a process that imports the copied robosuite, equal the
    installed robosuite's frames exactly."""
    pytest.importorskip("robosuite")
    from umi_aug.square.carry_sim import probe_frames, square_bundle_members

    site = tmp_path / "site"
    for root, members in square_bundle_members().values():
        for rel in members:
            dst = site / root.name / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(root / rel, dst)
    here = probe_frames(ROOT / "eval/square_init_configs_1000.npz", n=2, image_size=64)
    code = ("import sys, numpy as np, robosuite; from umi_aug.square.carry_sim import probe_frames; "
            "assert robosuite.__file__.startswith(sys.argv[1]), robosuite.__file__; "
            "np.save(sys.argv[3], probe_frames(sys.argv[2], n=2, image_size=64))")
    env = {**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{ROOT}"}
    out = subprocess.run([sys.executable, "-c", code, str(site), str(ROOT / "eval/square_init_configs_1000.npz"),
                          str(tmp_path / "there.npy")], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    there = np.load(tmp_path / "there.npy")
    assert there.shape == here.shape == (2, 64, 64, 3) and here.std() > 5  # a scene, not a blank frame
    assert np.array_equal(there, here)
