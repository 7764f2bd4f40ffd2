"""Inputs of the export behind one seam (issue #33): :class:`InputSource` (check → fingerprint → prepare → the
episode loop's :class:`~umi_aug.augment.session_assets.SessionAssets`) and a registry that picks one per path.

Built-in kinds, asked in this order: ``dataset`` — a plain UMI replay buffer (:mod:`.dataset`); ``session`` — a UMI
session folder, the default (:mod:`.session`). A new kind is one file here with a class that has the methods of
:class:`InputSource` and a factory, registered below (or, from a package above augment, with
:func:`register_source`: the square benchmark's demo folders, kind ``square``, are registered when
``umi_aug.square.source`` is imported — after ``dataset``, so asked after it).
"""

from umi_aug.augment.sources.base import (InputSource, open_source, register_source, settings_from_cli, source_kind,
                                          source_kinds)
from umi_aug.augment.sources.dataset import is_dataset_path, open_dataset
from umi_aug.augment.sources.session import open_session

__all__ = ["InputSource", "open_source", "register_source", "settings_from_cli", "source_kind", "source_kinds"]

register_source("dataset", is_dataset_path, open_dataset)
register_source("session", None, open_session)  # the default: any path no other kind claims
