"""Kinematic state of the built-in tabletop scene: camera/gripper pose, finger opening, mug pose.

Nothing is simulated dynamically: every frame sets the mocap gripper, the finger slide joints and the mug's free
joint, then runs ``mj_forward`` for the geometry. This keeps sessions exactly reproducible.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import matrix_to_quat_wxyz
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.scene import FINGER_JOINTS, GRIPPER_BODY, GRIPPER_GEOM_PREFIX, MUG_BODY

__all__ = ["TabletopState"]


class TabletopState:
    """Holds one ``MjData`` of a compiled tabletop model and sets its kinematic state.

    Args:
        model: ``mujoco.MjModel`` compiled from :func:`umi_aug.sim.scene.build_tabletop_scene`.

    Attributes:
        data: the ``MjData``.
        gripper_geom_ids: ``[G]`` int32 ids of the gripper's geoms (for gripper masks from segmentation).
        mug_geom_ids: ``[M]`` int32 ids of the mug's geoms.
    """

    def __init__(self, model) -> None:
        self._mj = mujoco = import_mujoco()
        self.model = model
        self.data = mujoco.MjData(model)
        obj = mujoco.mjtObj
        body = mujoco.mj_name2id(model, obj.mjOBJ_BODY, GRIPPER_BODY)
        mug = mujoco.mj_name2id(model, obj.mjOBJ_BODY, MUG_BODY)
        if body < 0 or mug < 0:
            raise SimError(f"model is not the built-in tabletop scene (no body {GRIPPER_BODY!r} / {MUG_BODY!r})")
        self._mocap = int(model.body_mocapid[body])
        self._finger_adr = []
        for j in FINGER_JOINTS:
            jid = mujoco.mj_name2id(model, obj.mjOBJ_JOINT, j)
            if jid < 0:
                raise SimError(f"model has no finger joint {j!r}")
            self._finger_adr.append(int(model.jnt_qposadr[jid]))
        mug_joint = int(model.body_jntadr[mug])
        self._mug_adr = int(model.jnt_qposadr[mug_joint])
        names = [mujoco.mj_id2name(model, obj.mjOBJ_GEOM, i) or "" for i in range(model.ngeom)]
        self.gripper_geom_ids = np.array(
            [i for i, n in enumerate(names) if n.startswith(GRIPPER_GEOM_PREFIX)], dtype=np.int32)
        self.mug_geom_ids = np.flatnonzero(model.geom_bodyid == mug).astype(np.int32)
        mujoco.mj_forward(model, self.data)

    def set(self, T_world_cam: np.ndarray, gripper_width: float, T_world_mug: np.ndarray | None = None) -> None:
        """Set the state and update the geometry (``mj_forward``).

        Args:
            T_world_cam: np.ndarray,  # [4, 4] fisheye camera pose, OpenCV axes (= the gripper mocap body frame)
            gripper_width: finger opening (inner faces), metres, >= 0.
            T_world_mug: np.ndarray | None,  # [4, 4] mug pose (bottom centre); None keeps the current one
        """
        T = np.asarray(T_world_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise SimError(f"T_world_cam must be a finite [4, 4] pose, got shape {T.shape}")
        w = float(gripper_width)
        if not np.isfinite(w) or w < 0:
            raise SimError(f"gripper_width must be a finite value >= 0 metres, got {gripper_width!r}")
        d = self.data
        d.mocap_pos[self._mocap] = T[:3, 3]
        d.mocap_quat[self._mocap] = matrix_to_quat_wxyz(T[:3, :3])
        d.qpos[self._finger_adr[0]] = -0.5 * w
        d.qpos[self._finger_adr[1]] = 0.5 * w
        if T_world_mug is not None:
            Tm = np.asarray(T_world_mug, dtype=np.float64)
            d.qpos[self._mug_adr:self._mug_adr + 3] = Tm[:3, 3]
            d.qpos[self._mug_adr + 3:self._mug_adr + 7] = matrix_to_quat_wxyz(Tm[:3, :3])
        d.qvel[:] = 0.0
        self._mj.mj_forward(self.model, d)

    def gripper_mask(self, geom_id: np.ndarray) -> np.ndarray:
        """``[H, W]`` bool: pixels whose segmentation (``FisheyeFrame.geom_id``) is a gripper geom."""
        return np.isin(geom_id, self.gripper_geom_ids)
