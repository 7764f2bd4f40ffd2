"""Square demos (``umi-aug square-demos`` output) as export input: the simulator's UMI session.

The square benchmark's code stays together so that it can move as one unit (issue #33 item 2): the source
(:class:`~umi_aug.augment.square_source.SquareSource`, its checks, stages and handles) in
:mod:`umi_aug.augment.square_source`, the scene model in :mod:`umi_aug.augment.square_scene`, the study's
variants in :mod:`umi_aug.augment.square_variants`. This module is its entry among the input sources: the
detector and the factory :mod:`umi_aug.augment.sources` registers.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from umi_aug.augment.square_source import SquareInput, SquareSource, is_square_demos
from umi_aug.errors import AugmentError

__all__ = ["open_square", "is_square_demos"]


def open_square(path: str | os.PathLike, settings: Any = None) -> SquareSource:
    """The :class:`SquareSource` of the demo folder ``path`` with ``settings`` (a :class:`SquareInput`; None: the
    defaults).

    Raises:
        AugmentError: settings of another kind of input.
    """
    if settings is not None and not isinstance(settings, SquareInput):
        raise AugmentError(f"{path}: a square demo folder takes SquareInput settings, not {type(settings).__name__}")
    return SquareSource(Path(path), SquareInput() if settings is None else settings)
