"""A plain UMI replay buffer (``*.zarr.zip`` / zarr directory, no session folder) as export input.

The scenes are built from the dataset's own frames, per scene group, lazily: a group's stages run when its first
episode is generated (:mod:`umi_aug.augment.dataset_source`, which also holds the checks and the settings,
:class:`~umi_aug.augment.dataset_source.DatasetInput`). Its entry among the input sources: :class:`DatasetSource`,
the factory :func:`open_dataset` and the detector :func:`~umi_aug.augment.dataset_source.is_dataset_path`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from umi_aug.augment.config import AugmentConfig, config_hash
from umi_aug.augment.dataset_source import (DatasetAssets, DatasetCheck, DatasetInput, check_dataset,
                                            dataset_fingerprint, is_dataset_path, prepare_dataset)
from umi_aug.errors import AugmentError

__all__ = ["DatasetSource", "open_dataset", "is_dataset_path"]


@dataclass(frozen=True)
class DatasetSource:
    """A plain UMI dataset as :class:`~umi_aug.augment.sources.base.InputSource`.

    Attributes:
        path: the ``*.zarr.zip`` file or zarr directory; inp: how it becomes scenes (:class:`DatasetInput`).
    """

    path: Path
    inp: DatasetInput = field(default_factory=DatasetInput)

    @property
    def dataset(self) -> Path:
        return self.path

    def reads(self) -> tuple[Path, ...]:
        return (self.path,)

    def check(self, image_size: int) -> DatasetCheck:
        return check_dataset(self.path, image_size, self.inp)  # one error naming the key/episode

    def fingerprint(self) -> str:
        return config_hash(dataset_fingerprint(self.path), self.inp)

    def n_augment(self, n_episodes: int) -> int:
        return len(self.inp.episodes) if self.inp.episodes is not None else n_episodes

    def prepare(self, work: Path, cfg: AugmentConfig, *, progress: bool = True,
                prefit_obstacles: Sequence[str] = ()) -> DatasetAssets:
        """The handle, nothing built yet: a group's scene is built (cached on disk) when its first episode is
        generated, never all up front (``prefit_obstacles`` unused: each asset is fitted on first use)."""
        return prepare_dataset(self.path, work, cfg, self.inp, progress=progress, lazy=True)


def open_dataset(path: str | os.PathLike, settings: Any = None) -> DatasetSource:
    """The :class:`DatasetSource` of ``path`` with ``settings`` (a :class:`DatasetInput`; None: the defaults).

    Raises:
        AugmentError: settings of another kind of input.
    """
    if settings is not None and not isinstance(settings, DatasetInput):
        raise AugmentError(f"{path}: a plain UMI dataset takes DatasetInput settings, not {type(settings).__name__}")
    return DatasetSource(Path(path), DatasetInput() if settings is None else settings)
