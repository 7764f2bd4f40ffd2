"""Exact signed distance field of a MuJoCo scene, built from its primitive geoms (ground truth).

The simulator knows its geometry exactly, so until the reconstructed distance field (issue #5) is wired in, and
afterwards as the reference it is measured against, :func:`scene_sdf` turns the solid geoms of a model (at the
poses in ``data``) into a :class:`umi_aug.geometry.sdf.UnionSDF`: planes → half-spaces, boxes, cylinders,
capsules and spheres → their exact fields. World frame, metres, free space positive.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry.sdf import BoxSDF, CapsuleSDF, CylinderSDF, HalfSpaceSDF, SphereSDF, UnionSDF
from umi_aug.sim.gl import import_mujoco

#: Bodies of the built-in scene that move with the camera (never part of the static scene).
GRIPPER_BODIES: tuple[str, ...] = ("umi_gripper", "finger_left", "finger_right")


def scene_sdf(
    model,
    data,
    exclude_bodies: Iterable[str] = GRIPPER_BODIES,
    inflation: float = 0.0,
) -> UnionSDF:
    """Union SDF of every solid geom (``contype`` or ``conaffinity`` non-zero) not on an excluded body.

    Args:
        model: ``mujoco.MjModel``.
        data: ``mujoco.MjData`` whose kinematics are current (``mj_forward`` or ``mj_kinematics`` was run).
        exclude_bodies: body names to leave out (default: the gripper, which moves with the camera).
        inflation: metres added around every solid.

    Raises:
        SimError: a solid geom has a type without an exact field (mesh, height field, ellipsoid), naming it.
    """
    mujoco = import_mujoco()
    gt = mujoco.mjtGeom
    excluded = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in exclude_bodies} - {-1}
    parts = []
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) in excluded or (model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0):
            continue
        typ = int(model.geom_type[g])
        pos = np.array(data.geom_xpos[g], dtype=np.float64)
        R = np.array(data.geom_xmat[g], dtype=np.float64).reshape(3, 3)
        size = np.array(model.geom_size[g], dtype=np.float64)
        if typ == gt.mjGEOM_PLANE:
            parts.append(HalfSpaceSDF(pos, R[:, 2]))
        elif typ == gt.mjGEOM_SPHERE:
            parts.append(SphereSDF(pos, size[0]))
        elif typ == gt.mjGEOM_CAPSULE:
            parts.append(CapsuleSDF(pos, size[0], size[1], R))
        elif typ == gt.mjGEOM_CYLINDER:
            parts.append(CylinderSDF(pos, size[0], size[1], R))
        elif typ == gt.mjGEOM_BOX:
            parts.append(BoxSDF(pos, size[:3], R))
        else:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
            raise SimError(f"scene_sdf: geom {name} has type {typ} (no exact SDF); exclude its body or mark it "
                           "non-colliding")
    if not parts:
        raise SimError("scene_sdf: the model has no solid geoms outside the excluded bodies")
    return UnionSDF(parts, inflation=inflation)
