"""Augmentation pipeline (issue #9; paper §3, Fig. 2): an input (a UMI session, a plain UMI dataset, or a kind
registered from above, e.g. the square benchmark's demos) → many physically valid, visually consistent
demonstrations, offline (:func:`export`) or per episode for an on-the-fly dataset (:func:`prepare_session` once,
then :func:`plan_episode` + :func:`render_episode_frames` anywhere).

How it is built (issue #33):

- ``sources/`` — one :class:`~umi_aug.augment.sources.InputSource` per kind of input (built in: ``session``,
  ``dataset``; :func:`open_source` picks one per path, :func:`register_source` adds a kind — ``umi_aug.square``
  adds ``square``): check → fingerprint → prepare its stages → the :class:`SessionAssets` handle the episode loop
  consumes;
- ``stages.py`` — the stages the sources share (contact/splice frame, gripper overlay mask, untrained scene);
  ``cache.py`` runs every stage (cached on disk, skipped when up to date, only those the mode needs);
  ``obstacle_stage.py`` the obstacle Gaussians;
- ``plan.py`` (cone start + obstacle placement → trajectory optimisation) and ``render.py`` (3DGS frames →
  gripper overlay, ``overlay.py``) — one episode, seeded per (demo, aug_id, mode);
- ``exporter.py`` — the episode loop over any source: jobs in order, resumable (``encode.py``, ``executor.py``),
  appended to the output store of ``export_store.py`` (a UMI replay buffer + per-episode records), reported by
  ``export_report.py`` (summary, table, pictures); ``cli.py`` the ``umi-aug augment`` command.

Importing this package is cheap (the CLI imports it to build its parser): every name below loads its module on
first access.
"""

from typing import Any

_LAZY = {
    "AugmentConfig": "config", "SplatStageConfig": "config", "ObstacleConfig": "config", "OverlayConfig": "config",
    "SessionAssets": "session_assets", "DemoInfo": "session_assets", "prepare_session": "sources.session",
    "InputSource": "sources", "open_source": "sources", "register_source": "sources",
    "PlannedEpisode": "plan", "ObstacleRecord": "plan", "MODE_CODES": "plan", "episode_seed": "plan",
    "plan_episode": "plan", "rerender_episode": "plan", "RERENDER_MODE": "plan",
    "render_episode_frames": "render",
    "export": "exporter", "export_jobs": "exporter", "ExportSummary": "export_report", "summary_table": "export_report",
    "read_episode_records": "export_store",
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
