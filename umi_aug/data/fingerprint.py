"""Content fingerprints of input files for the stage caches (cheap, but never "same size = same content").

* a ``.zarr.zip``: the zip's central directory — every entry's name, size and CRC-32 (the CRC covers the entry's
  bytes: a changed low-dim value or image chunk changes it) — read without decompressing anything;
* a zarr directory: the bytes of every file except image chunks (``.zarray``/``.zattrs``, low-dim chunks) and,
  for image chunks (``data/camera*_rgb/*``), name + size + a hash of the chunk's first and last 4 KiB;
* any other file: size + the whole content when small (<= 1 MiB: CSV, JSON, YAML), else size + the first and last
  1 MiB (videos).
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from pathlib import Path

from umi_aug.data import schema
from umi_aug.errors import DatasetError

__all__ = ["content_fingerprint", "file_fingerprint"]

SMALL_FILE = 1 << 20
_EDGE_CHUNK = 4096


def _edges(path: Path, size: int, edge: int) -> bytes:
    with open(path, "rb") as fh:
        head = fh.read(edge)
        if size > 2 * edge:
            fh.seek(size - edge)
        return head + fh.read(edge)


def file_fingerprint(path: str | os.PathLike) -> str:
    """Hash of one (non-zarr) file: its size and content (the first and last MiB of a big file)."""
    p = Path(path)
    size = p.stat().st_size
    h = hashlib.sha256(f"{size};".encode())
    h.update(p.read_bytes() if size <= SMALL_FILE else _edges(p, size, SMALL_FILE))
    return h.hexdigest()[:16]


def _is_image_chunk(rel: str) -> bool:
    parts = rel.split("/")
    return (len(parts) >= 3 and parts[0] == schema.DATA_GROUP and schema.is_image_key(parts[1])
            and not parts[-1].startswith("."))


def content_fingerprint(path: str | os.PathLike) -> str:
    """Content hash of a UMI dataset (``.zarr.zip`` or zarr directory) or of any file (see the module doc).

    Raises:
        DatasetError: a path that does not exist or a ``.zip`` that is not a readable zip (truncated).
    """
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        for dirpath, dirnames, filenames in os.walk(p):
            dirnames.sort()
            for fn in sorted(filenames):
                q = Path(dirpath) / fn
                rel = q.relative_to(p).as_posix()
                size = q.stat().st_size
                h.update(f"{rel}:{size};".encode())
                h.update(_edges(q, size, _EDGE_CHUNK) if _is_image_chunk(rel) else q.read_bytes())
        return h.hexdigest()[:16]
    if not p.is_file():
        raise DatasetError(f"{p}: no such file or directory")
    if p.name.endswith(".zip"):
        try:
            with zipfile.ZipFile(p) as zf:
                for info in sorted(zf.infolist(), key=lambda i: i.filename):
                    h.update(f"{info.filename}:{info.file_size}:{info.CRC};".encode())
        except (zipfile.BadZipFile, OSError) as exc:
            raise DatasetError(f"{p}: not a readable zip file ({exc}); expected a UMI .zarr.zip") from exc
        return h.hexdigest()[:16]
    return file_fingerprint(p)
