"""umi-aug inside UMI's own repository (issue #30): :class:`UmiAugDataset` takes UMI's ``UmiDataset`` arguments, so
one Hydra override makes UMI's unchanged ``train.py`` train on umi-aug's sampler with on-the-fly augmentation::

    task.dataset._target_=umi_aug.umi_compat.UmiAugDataset +task.dataset.aug=freespace

UMI's code is not a dependency: it is imported lazily, when :mod:`umi_aug.umi_compat.dataset` is first imported
(accessing :class:`UmiAugDataset` here does that); with UMI's ``diffusion_policy`` importable the class subclasses
UMI's ``BaseDataset`` and returns UMI's ``LinearNormalizer``, otherwise ``torch.utils.data.Dataset`` and
:class:`~umi_aug.umi_compat.normalizer.UmiLayoutNormalizer` (the same state-dict layout). Importing this package
imports nothing else.
"""

from __future__ import annotations

__all__ = ["UmiAugDataset", "UmiLayoutNormalizer", "umi_importable", "umi_normalizer", "task_from_shape_meta"]

_LAZY = {"UmiAugDataset": "umi_aug.umi_compat.dataset", "task_from_shape_meta": "umi_aug.umi_compat.dataset",
         "UmiLayoutNormalizer": "umi_aug.umi_compat.normalizer", "umi_importable": "umi_aug.umi_compat.normalizer",
         "umi_normalizer": "umi_aug.umi_compat.normalizer"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'umi_aug.umi_compat' has no attribute {name!r}")
