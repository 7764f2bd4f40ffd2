"""One exception type per stage, all deriving from :class:`UmiAugError`.

Messages name the input that is wrong: the file, the key and the offending value, and say what to do.
Each stage error also derives from ``ValueError`` so callers that catch bad-input errors generically work.
"""

from __future__ import annotations


class UmiAugError(Exception):
    """Base class of every error raised on purpose by umi-aug."""


class GeometryError(UmiAugError, ValueError):
    """Bad pose/rotation input (wrong shape, non-finite values, not a rotation)."""


class CameraError(UmiAugError, ValueError):
    """Bad camera intrinsics, calibration file or image size."""


class DatasetError(UmiAugError, ValueError):
    """Malformed UMI replay buffer, camera-trajectory CSV or other dataset file."""


class SimError(UmiAugError, RuntimeError):
    """Simulation / offscreen rendering failure."""


class ReconError(UmiAugError, RuntimeError):
    """Structure-from-motion, alignment or distance-field failure."""


class SplatError(UmiAugError, ValueError):
    """Bad Gaussian scene, PLY file or rasteriser input."""


class TrajError(UmiAugError, ValueError):
    """Trajectory problem or optimisation failure."""


class AugmentError(UmiAugError, RuntimeError):
    """Augmentation pipeline failure."""


class PolicyError(UmiAugError, ValueError):
    """Policy / training configuration or checkpoint problem."""


class EvalError(UmiAugError, ValueError):
    """Policy evaluation problem (configuration file, selection, results folder of another run)."""


class DeployError(UmiAugError, RuntimeError):
    """Robot deployment problem: bad robot config, lost connection, safety stop (the message says which)."""
