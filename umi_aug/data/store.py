"""Open a UMI zarr store (directory or ``.zarr.zip``) with the zarr-2 API, turning failures into
:class:`~umi_aug.errors.DatasetError` that name the path."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Any

import zarr

from umi_aug.errors import DatasetError


def is_zip_path(path: str | os.PathLike) -> bool:
    """True when ``path`` names a zip store: an existing regular file, or a name ending in ``.zip``."""
    p = Path(path)
    return p.is_file() or p.name.endswith(".zip")


def open_store(path: str | os.PathLike, mode: str = "r") -> tuple[Any, zarr.Group]:
    """Open ``path`` and return ``(store, root_group)``.

    ``mode``: ``"r"`` (read-only; directory or zip) or ``"a"`` (read/write; directory only). The caller
    closes the store (``store.close()`` for a ``zarr.ZipStore``).
    """
    p = Path(path)
    if mode not in ("r", "a"):
        raise DatasetError(f"{p}: mode must be 'r' or 'a', got {mode!r}")
    if not p.exists():
        raise DatasetError(f"{p}: no such file or directory (expected a UMI zarr directory or .zarr.zip)")
    if is_zip_path(p):
        if mode != "r":
            raise DatasetError(
                f"{p}: a .zarr.zip cannot be appended in place; open it with load_to_memory=True, add "
                "episodes, then save() to a new path"
            )
        try:
            store = zarr.ZipStore(str(p), mode="r")
        except (zipfile.BadZipFile, OSError) as exc:
            raise DatasetError(f"{p}: not a readable zip file ({exc}); expected a UMI .zarr.zip") from exc
    elif p.is_dir():
        store = zarr.DirectoryStore(str(p))
    else:
        raise DatasetError(f"{p}: neither a directory nor a zip file")
    try:
        root = zarr.open_group(store, mode="r" if mode == "r" else "r+")  # never create a group here
    except Exception as exc:  # zarr raises GroupNotFoundError, ContainsArrayError, JSON errors...
        hint = _layout_hint(p, store)
        close_store(store)
        raise DatasetError(f"{p}: not a zarr group ({type(exc).__name__}: {exc}); expected a UMI replay "
                           "buffer with data/ and meta/ groups" + (f"; {hint}" if hint else "")) from exc
    return store, root


def _layout_hint(p: Path, store: Any) -> str | None:
    """What the user probably meant when ``p`` is no zarr group: a UMI session folder (its
    ``dataset.zarr.zip``), a folder holding one store, or a zip whose entries sit under a folder prefix
    (``zip -r x.zip dataset.zarr`` instead of zipping the folder's contents)."""
    if p.is_dir():
        for name in ("dataset.zarr.zip", "dataset.zarr"):
            if (p / name).exists():
                return f"did you mean {p / name}? ({p} looks like a UMI session folder)"
        inner = sorted(q for q in p.iterdir() if q.is_dir() and (q / ".zgroup").is_file())
        if len(inner) == 1:
            return f"did you mean {inner[0]}? (it holds a zarr group)"
        return None
    try:
        names = list(store.keys())
    except Exception:  # noqa: BLE001 - only a hint
        return None
    prefixes = sorted({n[: -len(".zgroup")] for n in names if n.endswith("/.zgroup")}, key=len)
    if prefixes and not any(n == ".zgroup" for n in names):
        pre = prefixes[0]
        folder = pre.rstrip("/").split("/")[-1]
        return (f"the entries sit under {pre} (a zip made with `zip -r {p.name} {folder}`), but the store must "
                f"be at the zip's root: unzip it and pass the folder {folder} (zarr directories are read too), or "
                f"zip the folder's contents into a new file: cd {folder} && zip -r -0 ../new.zarr.zip .")
    return None


def close_store(store: Any) -> None:
    """Close ``store`` if it has a ``close`` method (``zarr.ZipStore``); other stores need nothing."""
    close = getattr(store, "close", None)
    if callable(close):
        close()
