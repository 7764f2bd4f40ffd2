"""3DGS scenes as PLY files in the standard INRIA layout (what graphdeco-inria/gaussian-splatting writes and the
usual viewers, SuperSplat, gsplat and nerfstudio read).

One ``vertex`` element, binary little-endian float32 properties in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3(K-1)-1)  opacity  scale_0..2  rot_0..3

* ``f_rest`` is channel-major, as INRIA writes it (``features_rest.transpose(1, 2).flatten(1)``):
  ``f_rest_{c*(K-1) + k}`` is SH coefficient ``k+1`` of channel ``c``; 0, 9, 24 or 45 of them (degree 0..3).
* ``opacity`` is the logit, ``scale_*`` are log standard deviations, ``rot_*`` is the quaternion ``(w, x, y, z)``;
  normals are written as zeros and ignored on reading.

The reader also accepts property orders other than INRIA's, extra properties (ignored), ``double`` and integer
properties, big-endian and ASCII files, and other fixed-size elements before ``vertex``; it raises
:class:`~umi_aug.errors.SplatError` naming the file and the property for anything it cannot read.
Writes are atomic (``<path>.tmp-<random>`` then rename).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
import torch

from umi_aug.errors import SplatError
from umi_aug.io_utils import atomic_path
from umi_aug.splat._constants import SH_COEFFS
from umi_aug.splat.gaussians import Gaussians

__all__ = ["read_ply", "write_ply", "ply_header"]

logger = logging.getLogger(__name__)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")
_MAX_HEADER_BYTES = 1 << 20


def _property_names(n_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def ply_header(n: int, sh_degree: int) -> bytes:
    """The INRIA header for ``n`` Gaussians of SH degree ``sh_degree`` (ends with ``end_header\\n``)."""
    n_rest = 3 * (SH_COEFFS[sh_degree] - 1)
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {int(n)}"]
    lines += [f"property float {p}" for p in _property_names(n_rest)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write ``gaussians`` as an INRIA-layout binary PLY (float32; atomic).

    Args:
        path: destination file.
        gaussians: the scene; any dtype (stored as float32, bit-exact for float32 input).

    Returns:
        The path written.
    """
    g = gaussians.detach().to(device="cpu")
    n, deg = g.n, g.sh_degree
    k1 = SH_COEFFS[deg] - 1
    names = _property_names(3 * k1)
    arr = np.empty(n, dtype=np.dtype([(p, "<f4") for p in names]))
    a = g.numpy()
    for i, c in enumerate("xyz"):
        arr[c] = a["means"][:, i]
        arr["n" + c] = 0.0
    for c in range(3):
        arr[f"f_dc_{c}"] = a["sh0"][:, c]
        for k in range(k1):
            arr[f"f_rest_{c * k1 + k}"] = a["sh_rest"][:, k, c]
        arr[f"scale_{c}"] = a["log_scales"][:, c]
    arr["opacity"] = a["logit_opacities"]
    for c in range(4):
        arr[f"rot_{c}"] = a["quats_wxyz"][:, c]
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(ply_header(n, deg))
            f.write(arr.tobytes())
    return path


def _parse_header(path: Path, data: bytes) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], int]:
    end = data.find(b"end_header", 0, _MAX_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise SplatError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the first MiB)")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise SplatError(f"{path}: header ends without a newline after 'end_header'")
    body_start = nl + 1
    try:
        text = data[:end].decode("ascii")
    except UnicodeDecodeError as exc:
        raise SplatError(f"{path}: PLY header is not ASCII") from exc
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for raw in text.splitlines()[1:]:
        line = raw.strip()
        if not line or line.startswith(("comment", "obj_info")):
            continue
        tok = line.split()
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in ("binary_little_endian", "binary_big_endian", "ascii"):
                raise SplatError(f"{path}: unsupported PLY format line {line!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not re.fullmatch(r"\d+", tok[2]):
                raise SplatError(f"{path}: bad element line {line!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise SplatError(f"{path}: property {line!r} before any element")
            if tok[1] == "list":
                elements[-1][2].append((tok[-1], "list"))
                continue
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise SplatError(f"{path}: unsupported property line {line!r}")
            elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        else:
            raise SplatError(f"{path}: unknown PLY header line {line!r}")
    if fmt is None:
        raise SplatError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, body_start


def read_ply(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> Gaussians:
    """Read a 3DGS PLY (INRIA layout; any SH degree 0..3 by the number of ``f_rest_*`` properties).

    Args:
        path: the ``.ply`` file.
        dtype: float dtype of the returned tensors.

    Returns:
        :class:`Gaussians` on the CPU. Zero-norm quaternions (written by some tools) become the identity
        (logged); non-finite values raise.

    Raises:
        SplatError: naming the file and the property (missing property, wrong ``f_rest`` count, list property,
            truncated data, non-finite value, ...).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SplatError(f"{path}: cannot read PLY file: {exc}") from exc
    fmt, elements, offset = _parse_header(path, data)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise SplatError(f"{path}: PLY has no 'vertex' element (elements: {names})")
    vi = names.index("vertex")
    _, n, props = elements[vi]
    for pname, ptype in props:
        if ptype == "list":
            raise SplatError(f"{path}: vertex property {pname!r} is a list; 3DGS PLYs have scalar properties only")
    seen = set()
    for pname, _ in props:
        if pname in seen:
            raise SplatError(f"{path}: duplicate vertex property {pname!r}")
        seen.add(pname)
    missing = [p for p in _REQUIRED if p not in seen]
    if missing:
        raise SplatError(f"{path}: vertex element lacks 3DGS properties {missing} (has {sorted(seen)})")
    rest_idx = sorted(int(p[7:]) for p in seen if re.fullmatch(r"f_rest_\d+", p))
    n_rest = len(rest_idx)
    if rest_idx != list(range(n_rest)) or n_rest % 3 or (n_rest // 3 + 1) not in SH_COEFFS:
        raise SplatError(
            f"{path}: f_rest_* properties must be f_rest_0..f_rest_(M-1) with M in (0, 9, 24, 45) "
            f"(SH degree 0..3), got indices {rest_idx[:5]}{'...' if n_rest > 5 else ''} (M = {n_rest})"
        )

    if fmt == "ascii":
        if vi != 0:
            raise SplatError(f"{path}: ASCII PLY with elements before 'vertex' is not supported")
        try:
            text = data[offset:].decode("ascii").split("\n")
            rows = [r for r in text if r.strip()][:n]
            table = np.array([[float(v) for v in r.split()] for r in rows], dtype=np.float64).reshape(-1, len(props))
        except (UnicodeDecodeError, ValueError) as exc:
            raise SplatError(f"{path}: malformed ASCII vertex data ({exc})") from exc
        if table.shape[0] != n:
            raise SplatError(f"{path}: truncated ASCII PLY: expected {n} vertices, found {table.shape[0]}")
        cols = {pname: table[:, i] for i, (pname, _) in enumerate(props)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        for name, count, eprops in elements[:vi]:
            if any(t == "list" for _, t in eprops):
                raise SplatError(f"{path}: element {name!r} before 'vertex' has list properties; cannot skip it")
            offset += count * sum(np.dtype(t).itemsize for _, t in eprops)
        dt = np.dtype([(pname, endian + ptype) for pname, ptype in props])
        need = offset + n * dt.itemsize
        if len(data) < need:
            raise SplatError(
                f"{path}: truncated PLY: {n} vertices of {dt.itemsize} bytes need {need} bytes, file has {len(data)}"
            )
        arr = np.frombuffer(data, dtype=dt, count=n, offset=offset)
        cols = {pname: arr[pname] for pname, _ in props}

    def stack(keys: list[str]) -> np.ndarray:
        out = np.stack([np.asarray(cols[k]) for k in keys], axis=-1) if keys else np.zeros((n, 0))
        if out.dtype.kind != "f" or out.dtype.itemsize < 4:
            out = out.astype(np.float64)
        bad = ~np.isfinite(out).all(axis=-1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            j = int(np.flatnonzero(~np.isfinite(out[i]))[0])
            raise SplatError(f"{path}: non-finite value {out[i, j]!r} in property {keys[j]!r} of vertex {i}")
        return out

    k1 = n_rest // 3
    rest = stack([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k1).transpose(0, 2, 1)
    quats = stack([f"rot_{i}" for i in range(4)])
    zero_q = ~np.any(quats != 0, axis=-1)
    if zero_q.any():
        logger.warning("%s: %d zero-norm quaternions replaced by the identity", path, int(zero_q.sum()))
        quats = quats.copy()
        quats[zero_q] = (1.0, 0.0, 0.0, 0.0)
    arrays = {
        "means": stack(["x", "y", "z"]),
        "log_scales": stack(["scale_0", "scale_1", "scale_2"]),
        "quats_wxyz": quats,
        "logit_opacities": stack(["opacity"])[:, 0],
        "sh0": stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "sh_rest": np.ascontiguousarray(rest),
    }
    return Gaussians.from_numpy(arrays, dtype=dtype)
