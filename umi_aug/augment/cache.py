"""On-disk stage cache: each stage writes its outputs into ``<work>/<stage>/`` and a ``manifest.json`` LAST.

The manifest holds the stage's key = hash(stage name, version, its config subset, its inputs' keys). A stage is
up to date (skipped, logged) when its manifest exists with the same key and every listed output file exists. A
manifest with another key means stale outputs: the folder is cleared before the stage runs. An interrupted run
(no manifest) keeps the folder only when its ``pending.json`` — written before the stage starts — names the same
key, so a stage that resumes on its own (3DGS training) picks up where it stopped; partial work of another
configuration/input (or of unknown origin) is cleared instead of blocking the run.

Keys are content keys: the stages' ``inputs`` carry the content fingerprints of what they read (the session's
dataset and intrinsics, :func:`umi_aug.data.fingerprint.content_fingerprint`), never sizes alone.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from umi_aug.augment.config import config_hash, jsonable
from umi_aug.errors import AugmentError
from umi_aug.io_utils import atomic_write_text

__all__ = ["StageResult", "run_stage", "read_manifest", "build_lock", "MANIFEST"]

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
#: Key of the run that is (or was, when interrupted) computing the stage; removed with the manifest's write.
PENDING = "pending.json"


@dataclass
class StageResult:
    """Outcome of :func:`run_stage`.

    Attributes:
        name: stage name; dir: its folder; key: its cache key (inputs of later stages hash it);
        outputs: ``{name: path relative to dir, or a small JSON value}``; skipped: True when up to date;
        seconds: wall time of this call (≈0 when skipped); info: what the stage reported (JSON).
    """

    name: str
    dir: Path
    key: str
    outputs: dict[str, Any]
    skipped: bool
    seconds: float
    info: dict[str, Any] = field(default_factory=dict)

    def path(self, name: str) -> Path:
        """Absolute path of output file ``name``."""
        return self.dir / str(self.outputs[name])


@contextmanager
def build_lock(folder: Path, name: str = ".build.lock"):
    """Exclusive, BLOCKING lock (the file ``folder/name``) of a folder of stages, or of one stage in it: executor
    workers that need the same stages while they are being built wait for them, then find them cached (the kernel
    drops the lock if the holder dies)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / name, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def read_manifest(stage_dir: Path) -> dict | None:
    """The stage's manifest dict, or None when missing/unreadable."""
    return _read_json(Path(stage_dir) / MANIFEST)


def _read_json(p: Path) -> dict | None:
    try:
        v = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return v if isinstance(v, dict) else None


def _outputs_exist(stage_dir: Path, files: list[str]) -> bool:
    return all((stage_dir / f).exists() for f in files)


def run_stage(name: str, work_dir: Path, config: Any, inputs: dict[str, str],
              fn: Callable[[Path], tuple[dict[str, Any], list[str], dict[str, Any]]], version: int = 1,
              force: bool = False) -> StageResult:
    """Run ``fn(stage_dir) -> (outputs, files, info)`` unless the stage is up to date.

    Args:
        name: stage name (folder name under ``work_dir``).
        config: the config subset this stage depends on (dataclass/dict/scalars; hashed).
        inputs: ``{input name: key}`` of what it reads (other stages' keys, the session's fingerprint).
        fn: does the work; ``outputs`` is JSON (paths relative to the stage dir, small values), ``files`` the
            output files (relative) that must exist for the cache to count as valid, ``info`` JSON to report.
        version: bump when the stage's code changes its outputs.
        force: run even when up to date.
    Raises:
        AugmentError: ``fn`` did not produce a listed file.
    """
    stage_dir = Path(work_dir) / name
    key = config_hash(name, version, config, dict(sorted(inputs.items())))
    man = read_manifest(stage_dir)
    if man is not None and not force and man.get("key") == key and _outputs_exist(stage_dir, man.get("files", [])):
        log.info("stage %s: up to date (key %s), skipped", name, key)
        return StageResult(name, stage_dir, key, man.get("outputs", {}), True, 0.0, man.get("info", {}))
    if man is not None and stage_dir.exists():
        log.info("stage %s: stale (key %s → %s), clearing %s", name, man.get("key"), key, stage_dir)
        shutil.rmtree(stage_dir)
    elif stage_dir.exists() and any(stage_dir.iterdir()):
        pending = _read_json(stage_dir / PENDING)
        if pending is None or pending.get("key") != key:
            log.warning("stage %s: clearing the partial work of an interrupted run of another configuration/input "
                        "(key %s, this run %s) in %s", name, None if pending is None else pending.get("key"), key,
                        stage_dir)
            shutil.rmtree(stage_dir)
        else:
            log.info("stage %s: resuming the interrupted run in %s", name, stage_dir)
    stage_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(stage_dir / PENDING, json.dumps({"stage": name, "key": key}) + "\n")
    log.info("stage %s: running (key %s)", name, key)
    t0 = time.perf_counter()
    outputs, files, info = fn(stage_dir)
    seconds = time.perf_counter() - t0
    missing = [f for f in files if not (stage_dir / f).exists()]
    if missing:
        raise AugmentError(f"stage {name}: outputs {missing} were not written to {stage_dir}")
    # "settings": the config subset itself (not part of the key), so a later reader can reuse a cached stage's
    # settings (e.g. umi_aug.umi_compat takes the 3DGS iterations / budget of a prepared session from here)
    manifest = {"stage": name, "version": version, "key": key, "inputs": inputs, "config": config_hash(config),
                "settings": jsonable(config),
                "outputs": outputs, "files": list(files), "info": info, "seconds": round(seconds, 3),
                "finished_unix": time.time()}
    atomic_write_text(stage_dir / MANIFEST, json.dumps(manifest, indent=2, default=str) + "\n")
    (stage_dir / PENDING).unlink(missing_ok=True)
    return StageResult(name, stage_dir, key, outputs, False, seconds, info)
