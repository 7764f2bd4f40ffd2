"""Task functions the executor tests run on spawned workers (importable by the children)."""

from __future__ import annotations

import os
import time
from pathlib import Path


def sleep_and_report(folder: str) -> int:
    """Write ``<folder>/<pid>.pid``, then sleep 60 s (a long task a killed parent leaves behind)."""
    Path(folder, f"{os.getpid()}.pid").write_text("")
    time.sleep(60)
    return os.getpid()
