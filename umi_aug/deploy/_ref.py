"""Slow references of the deploy stage (gsplat ``_torch_impl`` style: private, for tests only).

* :func:`_interpolator_reference` mirrors :meth:`umi_aug.deploy.interpolator.PoseTrajectoryInterpolator.__call__`
  (the servo loop's pose query) through :func:`umi_aug.geometry.interp.interpolate_pose`.
"""

from __future__ import annotations

import numpy as np

from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator
from umi_aug.geometry.interp import interpolate_pose
from umi_aug.geometry.se3 import pose_to_pos_rotvec


def _interpolator_reference(interp: PoseTrajectoryInterpolator, t: float | np.ndarray) -> np.ndarray:
    """Reference of ``interp(t)``: pose(s) at time(s) ``t`` ([6] for a scalar, [M, 6] for an array), by the slow
    :func:`umi_aug.geometry.interp.interpolate_pose` between the segment's end poses."""
    ts = np.atleast_1d(np.asarray(t, np.float64))
    if len(interp.times) == 1:
        out = np.repeat(interp.poses, len(ts), axis=0)
    else:
        i, s = interp._segment(ts)
        out = pose_to_pos_rotvec(interpolate_pose(interp._T[i], interp._T[i + 1], s))
    return out[0] if np.ndim(t) == 0 else out
