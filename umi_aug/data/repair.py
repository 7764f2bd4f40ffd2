"""``umi-aug repair IN --out NEW``: a repaired COPY of a replay buffer left by an interrupted append.

An append writes the data rows first and ``meta/episode_ends`` last, so a kill leaves rows beyond
``episode_ends[-1]`` (and possibly a half-written last episode end). :meth:`ReplayBuffer.open` with
``repair=True`` cuts them off IN PLACE; done on a buffer whose ``episode_ends`` is the damaged part, that
truncated every row. This command never opens its input for writing: it copies the store (chunks as stored,
nothing re-encoded) to a new path, repairs the copy, validates it and renames it into place, so the original
is untouched whatever the repair drops, and a failure leaves nothing at ``--out``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import zarr

from umi_aug.data.codecs import register_codecs
from umi_aug.data.replay_buffer import ReplayBuffer
from umi_aug.data.store import close_store, open_store
from umi_aug.data.validate import open_array
from umi_aug.errors import DatasetError
from umi_aug.io_utils import atomic_path, is_inside, remove_tree_atomically, temp_sibling

__all__ = ["RepairResult", "repair_copy"]


@dataclass
class RepairResult:
    """What :func:`repair_copy` wrote: the copy's episodes/steps, the input's rows, and what was cut."""

    out: Path
    n_episodes: int
    n_steps: int
    input_rows: dict[str, int]
    notes: list[str] = field(default_factory=list)


def repair_copy(src: str | os.PathLike, dst: str | os.PathLike) -> RepairResult:
    """Write a repaired copy of the replay buffer ``src`` to the new path ``dst`` (``*.zip``: a ``.zarr.zip``,
    else a zarr directory); ``src`` is only read.

    Raises:
        DatasetError: ``dst`` exists, is ``src`` or lies inside it (or ``src`` inside it); ``src`` is not a
            readable store; the repaired copy would hold no step (``episode_ends`` is the damaged part: cutting the
            data to it would drop every row) or is still invalid.
    """
    src, dst = Path(src), Path(dst)
    if os.path.lexists(dst):
        raise DatasetError(f"--out {dst}: exists; repair writes a new copy and never replaces anything: choose a "
                           "path that does not exist")
    if is_inside(dst, src) or is_inside(src, dst):
        raise DatasetError(f"--out {dst}: is, contains or lies inside the input {src}; the repaired copy goes "
                           "next to it: choose another --out")
    register_codecs()
    store, root = open_store(src, mode="r")  # never writable: the input is not changed, whatever happens below
    try:
        data = root["data"] if "data" in root else None
        rows = ({k: int(open_array(data, k, str(src)).shape[0]) for k in sorted(data.array_keys())}
                if data is not None else {})
        work = temp_sibling(dst)
        try:
            zarr.copy_store(store, zarr.DirectoryStore(str(work)))
        except BaseException:
            if work.exists():
                remove_tree_atomically(work)
            raise
    finally:
        close_store(store)
    try:
        quiet = logging.getLogger("umi_aug.data.replay_buffer")  # its notes are returned (named by the copy)
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            buf = ReplayBuffer.open(work, mode="a", repair=True)  # repairs the COPY, then validates it
        except DatasetError as exc:  # still invalid: name the input, not the temporary copy
            raise DatasetError(str(exc).replace(str(work), str(src)) + " (a repair cannot fix this; nothing was "
                               "written)") from exc
        finally:
            quiet.setLevel(level)
        with buf:
            notes = [n.replace(str(work), str(dst)) for n in buf.report.warnings if "repair" in n]
            n_eps, n_steps = buf.n_episodes, int(buf.report.n_steps)
            if n_steps == 0 and any(rows.values()):
                raise DatasetError(f"{src}: the repaired copy would hold no step: meta/episode_ends ends at 0 after "
                                   f"the repair, and cutting the data to it drops every row ({max(rows.values())} "
                                   "rows per key); episode_ends is the damaged part, not the data: re-create the "
                                   "dataset (nothing was written)")
            if dst.name.endswith(".zip"):
                buf.save(dst)  # atomic: <dst>.tmp-* renamed when complete
        if not dst.name.endswith(".zip"):
            with atomic_path(dst, overwrite=False) as tmp:
                os.replace(work, tmp)
    finally:
        if work.exists():
            remove_tree_atomically(work)
    return RepairResult(dst, n_eps, n_steps, rows, notes)
