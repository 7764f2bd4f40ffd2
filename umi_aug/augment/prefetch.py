"""Modules a later stage needs, imported on a thread while a stage leaves a core idle.

A dataset scene's known-pose triangulation runs on one thread with the GIL released (COLMAP's
``triangulate_points``, ~3 s of the real episode's scene on 2 cores), and the stages after it start with imports that
take seconds on their own: open3d for the cloud clean-up, torch and the 3DGS trainer for the splat stage. Importing
them on a thread while the triangulation runs moves that time onto the idle core. Nothing but import time changes:
a module's code runs once whichever thread imports it, and a stage importing a module the thread is still
importing waits for it (Python's per-module import lock). An import that fails here is left to fail, with its own
message, where the stage imports it.
"""

from __future__ import annotations

import importlib
import threading
from typing import Sequence

__all__ = ["import_in_background"]


def import_in_background(modules: Sequence[str]) -> threading.Thread:
    """Start a daemon thread importing ``modules`` in order; returns it (join it before forking workers: a fork
    while a module is half-imported would leave that module's lock held in the child)."""
    names = [str(m) for m in modules]

    def run() -> None:
        for name in names:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the stage that needs it imports it again and reports the error
                return

    th = threading.Thread(target=run, name="umi-aug-import", daemon=True)
    th.start()
    return th
