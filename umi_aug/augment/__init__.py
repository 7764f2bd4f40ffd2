"""Augmentation pipeline (issue #9; paper §3, Fig. 2): a UMI session (scan + demos + intrinsics) → many
physically valid, visually consistent demonstrations, offline (:func:`export`) or per episode for an on-the-fly
dataset (:func:`prepare_session` once, then :func:`plan_episode` + :func:`render_episode_frames` anywhere).

Stages (cached on disk, skipped when up to date, only those the mode needs): reconstruct (SfM cloud, SDF) →
fisheye 3DGS → contact split → [obstacle Gaussians] → per episode: cone start (+ obstacle placement) → trajectory
optimisation → 3DGS frames → gripper overlay → UMI episode. Everything is seeded per (demo, aug_id, mode).

Importing this package is cheap (the CLI imports it to build its parser): every name below loads its module on
first access.
"""

from typing import Any

_LAZY = {
    "AugmentConfig": "config", "SplatStageConfig": "config", "ObstacleConfig": "config", "OverlayConfig": "config",
    "SessionAssets": "session_assets", "DemoInfo": "session_assets", "prepare_session": "session_assets",
    "PlannedEpisode": "plan", "ObstacleRecord": "plan", "MODE_CODES": "plan", "episode_seed": "plan",
    "plan_episode": "plan",
    "render_episode_frames": "render",
    "ExportSummary": "exporter", "export": "exporter", "export_jobs": "exporter", "read_episode_records": "exporter",
    "summary_table": "exporter",
    "map_ordered": "executor",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"umi_aug.augment.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted(_LAZY)
