"""Small file-system helpers shared by every stage: atomic writes (write to ``<path>.tmp-<random>``, rename).

Nothing is ever left half-written: if the body of :func:`atomic_path` raises, the temporary file or
directory is removed and the destination is untouched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path
from typing import Iterator


def temp_sibling(path: str | os.PathLike) -> Path:
    """Return an unused temporary path next to ``path``: ``<path>.tmp-<random hex>`` (same file system,
    so the final rename is atomic)."""
    path = Path(path)
    return path.with_name(f"{path.name}.tmp-{secrets.token_hex(4)}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Context manager yielding a temporary path to write ``path`` (a file or a directory) into.

    On normal exit the temporary is renamed onto ``path`` (an existing destination is replaced when
    ``overwrite``; a directory destination is moved aside first and deleted after the swap). On an exception
    the temporary is deleted and the exception propagates.

    Example::

        with atomic_path("out/dataset.zarr.zip") as tmp:
            write_zip(tmp)
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists and overwrite=False")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(path)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"atomic write of {path}: nothing was written to the temporary path {tmp}")
        if path.is_dir() and not path.is_symlink():
            old = temp_sibling(path)
            os.replace(path, old)
            os.replace(tmp, path)
            _remove(old)
        else:
            os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)
