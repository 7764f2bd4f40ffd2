"""A fixed-layout ring buffer of timestamped float64 records in shared memory, written by one controller process
and read by the runner (UMI's ``SharedMemoryRingBuffer``, reduced to what the runner needs)."""

from __future__ import annotations

import multiprocessing as mp
from typing import Mapping

import numpy as np

from umi_aug.errors import DeployError

__all__ = ["SharedStateBuffer"]


class SharedStateBuffer:
    """Ring buffer of records ``{name: [width] float64}``; picklable into ``multiprocessing`` children.

    Args:
        fields: record layout, name → number of float64 values (e.g. ``{"timestamp": 1, "tcp_pose": 6}``).
        capacity: number of records kept.
        ctx: multiprocessing context (default: the default one).
    """

    def __init__(self, fields: Mapping[str, int], capacity: int = 1024, ctx=None) -> None:
        ctx = ctx or mp.get_context()
        if capacity < 2 or not fields or any(int(w) < 1 for w in fields.values()):
            raise DeployError(f"SharedStateBuffer: need capacity >= 2 and field widths >= 1, got {capacity}, {fields}")
        self.fields = {k: int(w) for k, w in fields.items()}
        self.width = sum(self.fields.values())
        self.capacity = int(capacity)
        self._arr = ctx.Array("d", self.capacity * self.width, lock=True)
        self._count = ctx.Value("q", 0, lock=False)  # guarded by self._arr's lock

    def _view(self) -> np.ndarray:
        return np.frombuffer(self._arr.get_obj(), dtype=np.float64).reshape(self.capacity, self.width)

    @property
    def count(self) -> int:
        """Records written so far (including overwritten ones)."""
        with self._arr.get_lock():
            return int(self._count.value)

    def put(self, record: Mapping[str, np.ndarray | float]) -> None:
        """Append one record (every field required)."""
        row = np.empty(self.width)
        o = 0
        for k, w in self.fields.items():
            if k not in record:
                raise DeployError(f"SharedStateBuffer.put: field {k!r} missing")
            row[o:o + w] = np.asarray(record[k], np.float64).reshape(w)
            o += w
        with self._arr.get_lock():
            self._view()[self._count.value % self.capacity] = row
            self._count.value += 1

    def latest(self, n: int = 1) -> dict[str, np.ndarray]:
        """The last ``min(n, available)`` records, oldest first: ``{name: [k, width]}`` (``[k]`` for width 1).

        Raises:
            DeployError: nothing written yet.
        """
        with self._arr.get_lock():
            c = int(self._count.value)
            if c == 0:
                raise DeployError("SharedStateBuffer: no state received yet")
            k = min(int(n), c, self.capacity)
            idx = np.arange(c - k, c) % self.capacity
            rows = self._view()[idx].copy()
        out, o = {}, 0
        for name, w in self.fields.items():
            out[name] = rows[:, o] if w == 1 else rows[:, o:o + w]
            o += w
        return out
