"""INRIA-layout PLY: bit-exact round trips, a hand-built INRIA file, fewer SH bands, other encodings, errors."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat import Gaussians, read_ply, write_ply
from umi_aug.splat.ply import ply_header
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import gopro_small

INRIA_NAMES = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
               + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _random_float32(rng, n: int, degree: int) -> Gaussians:
    g = random_gaussians(n, rng, gopro_small(), sh_degree=degree, dtype=torch.float32)
    # awkward float32 values: subnormals, negative zero, extremes (still finite)
    g.sh0.view(-1)[:3] = torch.tensor([1e-42, -0.0, 3.0e38])
    return g


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_bit_exact(rng, tmp_path, degree):
    g = _random_float32(rng, 57, degree)
    path = write_ply(tmp_path / "scene.ply", g)
    h = read_ply(path)
    assert h.sh_degree == degree and h.n == g.n and h.dtype == torch.float32
    for name in g.tensors():
        a, b = getattr(g, name).numpy(), getattr(h, name).numpy()
        assert a.shape == b.shape
        assert np.array_equal(a.view(np.uint32), b.view(np.uint32)), name
    # a second write gives identical bytes (deterministic, atomic: no temporaries left)
    path2 = write_ply(tmp_path / "again.ply", h)
    assert path.read_bytes() == path2.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.ply", "scene.ply"]


def test_header_is_inria_layout(tmp_path, rng):
    g = _random_float32(rng, 3, 3)
    data = write_ply(tmp_path / "s.ply", g).read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    lines = header.splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 3"]
    assert lines[3:-1] == [f"property float {n}" for n in INRIA_NAMES]
    assert len(data) == len(header) + 3 * 62 * 4
    assert ply_header(3, 3).decode() == header


def test_reads_hand_built_inria_file(tmp_path, rng):
    """A file written the way graphdeco-inria's ``save_ply`` does (numpy structured array, channel-major
    f_rest), built here by hand with struct: values land in the right fields."""
    n, k1 = 4, 15
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    dc = rng.normal(size=(n, 3)).astype(np.float32)
    rest = rng.normal(size=(n, k1, 3)).astype(np.float32)  # [N, K-1, 3] as the model stores it
    op = rng.normal(size=n).astype(np.float32)
    sc = rng.normal(size=(n, 3)).astype(np.float32)
    rot = rng.normal(size=(n, 4)).astype(np.float32)
    f_rest_inria = rest.transpose(0, 2, 1).reshape(n, -1)  # features_rest.transpose(1, 2).flatten(1)
    body = b"".join(
        struct.pack("<62f", *xyz[i], 0, 0, 0, *dc[i], *f_rest_inria[i], op[i], *sc[i], *rot[i]) for i in range(n)
    )
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 4\n" + "".join(
        f"property float {p}\n" for p in INRIA_NAMES) + "end_header\n"
    path = tmp_path / "inria.ply"
    path.write_bytes(header.encode() + body)
    g = read_ply(path)
    assert g.sh_degree == 3
    np.testing.assert_array_equal(g.means.numpy(), xyz)
    np.testing.assert_array_equal(g.sh0.numpy(), dc)
    np.testing.assert_array_equal(g.sh_rest.numpy(), rest)
    np.testing.assert_array_equal(g.logit_opacities.numpy(), op)
    np.testing.assert_array_equal(g.log_scales.numpy(), sc)
    np.testing.assert_array_equal(g.quats_wxyz.numpy(), rot)


def _write_custom(path, props: list[tuple[str, str]], rows: np.ndarray, fmt="binary_little_endian",
                  extra_elements: str = "", prefix: bytes = b""):
    header = f"ply\nformat {fmt} 1.0\ncomment made by a test\n{extra_elements}element vertex {rows.shape[0]}\n"
    header += "".join(f"property {t} {p}\n" for p, t in props) + "end_header\n"
    if fmt == "ascii":
        body = "\n".join(" ".join(repr(float(v)) for v in r) for r in rows).encode() + b"\n"
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        tmap = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4"}
        dt = np.dtype([(p, end + tmap[t]) for p, t in props])
        arr = np.zeros(rows.shape[0], dtype=dt)
        for j, (p, _) in enumerate(props):
            arr[p] = rows[:, j]
        body = arr.tobytes()
    path.write_bytes(header.encode() + prefix + body)
    return path


def _minimal_props(n_rest: int = 0, t: str = "float") -> list[tuple[str, str]]:
    names = ["rot_3", "rot_2", "rot_1", "rot_0", "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "red"] + [f"f_rest_{i}" for i in range(n_rest)]
    return [(p, "uchar" if p == "red" else t) for p in names]


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("n_rest", [0, 9, 24])
def test_reads_other_orders_encodings_and_fewer_bands(tmp_path, rng, fmt, n_rest):
    props = _minimal_props(n_rest, "double")
    rows = rng.normal(size=(5, len(props)))
    rows[:, 14] = rng.integers(0, 255, 5)
    g = read_ply(_write_custom(tmp_path / "x.ply", props, rows, fmt), dtype=torch.float64)
    col = {p: rows[:, j] for j, (p, _) in enumerate(props)}
    assert g.sh_degree == {0: 0, 9: 1, 24: 2}[n_rest]
    np.testing.assert_allclose(g.quats_wxyz.numpy(), np.stack([col[f"rot_{i}"] for i in range(4)], 1), rtol=1e-15)
    np.testing.assert_allclose(g.means.numpy(), np.stack([col[c] for c in "xyz"], 1), rtol=1e-15)
    k1 = n_rest // 3
    for c in range(3):
        for k in range(k1):
            np.testing.assert_allclose(g.sh_rest.numpy()[:, k, c], col[f"f_rest_{c * k1 + k}"], rtol=1e-15)


def test_skips_fixed_size_elements_before_vertex(tmp_path, rng):
    props = _minimal_props()
    rows = rng.normal(size=(3, len(props)))
    rows[:, 14] = 7
    prefix = np.arange(2 * 3, dtype="<f4").tobytes()  # element camera 2 x (3 float)
    path = _write_custom(tmp_path / "x.ply", props, rows, extra_elements=(
        "element camera 2\nproperty float a\nproperty float b\nproperty float c\n"), prefix=prefix)
    g = read_ply(path, dtype=torch.float64)
    np.testing.assert_allclose(g.means.numpy()[:, 0], rows[:, 4].astype(np.float32), rtol=1e-7)


def test_zero_quaternion_becomes_identity(tmp_path, rng, caplog):
    g = _random_float32(rng, 4, 0)
    g.quats_wxyz[1] = 0.0
    h = read_ply(write_ply(tmp_path / "q.ply", g))
    assert h.quats_wxyz[1].tolist() == [1.0, 0.0, 0.0, 0.0]
    assert "zero-norm" in caplog.text


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda p, r: ([x for x in p if x[0] != "opacity"], None), "lacks 3DGS properties.*opacity"),
        (lambda p, r: (p + [("f_rest_0", "float"), ("f_rest_1", "float"), ("f_rest_3", "float")], None),
         r"f_rest_0..f_rest_\(M-1\).*indices \[0, 1, 3\]"),
        (lambda p, r: (p + [(f"f_rest_{i}", "float") for i in range(6)], None), r"M = 6"),
    ],
)
def test_bad_properties_raise(tmp_path, rng, mutate, match):
    props, _ = mutate(_minimal_props(), None)
    rows = rng.normal(size=(2, len(props)))
    path = _write_custom(tmp_path / "bad.ply", props, rows)
    with pytest.raises(SplatError, match=match) as exc:
        read_ply(path)
    assert "bad.ply" in str(exc.value)


def test_errors_name_file_and_property(tmp_path, rng):
    props = _minimal_props()
    rows = rng.normal(size=(4, len(props)))
    rows[2, 5] = np.nan  # y of vertex 2
    with pytest.raises(SplatError, match=r"nan.*'y'.*vertex 2"):
        read_ply(_write_custom(tmp_path / "nan.ply", props, rows))
    good = _write_custom(tmp_path / "t.ply", props, rng.normal(size=(4, len(props))))
    (tmp_path / "trunc.ply").write_bytes(good.read_bytes()[:-5])
    with pytest.raises(SplatError, match="truncated"):
        read_ply(tmp_path / "trunc.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(SplatError, match="not a PLY"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(SplatError, match="cannot read"):
        read_ply(tmp_path / "missing.ply")
    listy = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n"
    (tmp_path / "list.ply").write_bytes(listy.encode())
    with pytest.raises(SplatError, match="list"):
        read_ply(tmp_path / "list.ply")


def test_failed_write_leaves_destination_untouched(tmp_path, rng, monkeypatch):
    g = _random_float32(rng, 5, 1)
    path = write_ply(tmp_path / "s.ply", g)
    before = path.read_bytes()

    def boom(self):
        raise RuntimeError("disk full")

    monkeypatch.setattr(Gaussians, "numpy", boom)
    with pytest.raises(RuntimeError):
        write_ply(path, g)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.ply"]
