"""NutAssemblySquare (robosuite 1.4.1, Panda, OSC_POSE at 20 Hz) created through robomimic's env utilities,
with a true fisheye wrist observation and UMI-style observation keys.

The environment comes from ``robomimic.utils.env_utils.create_env_from_metadata(env_meta)`` with an ``env_meta``
in robomimic's format (``square_env_meta()``; the same as robomimic's v1.4.1 square datasets plus
``hard_reset=False`` so the MuJoCo model survives resets). robosuite's own cameras are off; the wrist view is
rendered by :class:`~umi_aug.square.camera.WristFisheyeCamera` at the ``robot0_eye_in_hand`` pose.

Observation dict (:meth:`SquareEnv.observation`): robomimic's low-dim keys (``object``, ``robot0_eef_pos``,
``robot0_eef_quat`` (xyzw, robosuite's order), ``robot0_gripper_qpos``, ``robot0_joint_pos`` …) plus

- ``robot0_eye_in_hand_fisheye_image`` and its UMI alias ``camera0_rgb``: uint8 ``[S, S, 3]`` RGB fisheye;
- ``robot0_eef_rot_axis_angle``: rotation vector of the TCP (float64 [3], rad) — the TCP frame has the OpenCV
  wrist-camera axes and sits at robosuite's grip site, so UMI's ``robot0_eef_pos`` equals robomimic's;
- ``robot0_gripper_width``: finger separation in metres ([1]).

Randomness: robosuite 1.4.1 samples object placement and joint noise from numpy's global generator;
:meth:`SquareEnv.reset` seeds it (``np.random.seed(seed)``), so the same seed gives the same initial state.
"""

from __future__ import annotations

import copy
import logging
from typing import Any

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import pose_inverse, so3_log
from umi_aug.square.camera import WRIST_CAMERA, WristFisheyeCamera, camera_pose_cv
from umi_aug.square.compat import import_robomimic_env_utils, import_robosuite, robomimic_quiet

__all__ = [
    "SQUARE_ENV_NAME", "FISHEYE_KEY", "UMI_IMAGE_KEY", "LOW_DIM_KEYS", "CONTROL_FREQ_HZ", "GRIP_SITE",
    "square_env_meta", "init_robomimic_obs_utils", "SquareEnv",
]

log = logging.getLogger(__name__)

SQUARE_ENV_NAME: str = "NutAssemblySquare"
FISHEYE_KEY: str = "robot0_eye_in_hand_fisheye_image"
UMI_IMAGE_KEY: str = "camera0_rgb"
#: robomimic low-dim keys stored in hdf5 ``obs/`` (what robomimic's square low-dim configs use, plus joints).
LOW_DIM_KEYS: tuple[str, ...] = (
    "object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos",
    "robot0_eef_rot_axis_angle", "robot0_gripper_width",
)
CONTROL_FREQ_HZ: int = 20
GRIP_SITE: str = "gripper0_grip_site"
#: Nut / peg names in robosuite's NutAssemblySquare model.
NUT_BODY: str = "SquareNut_main"
NUT_HANDLE_SITE: str = "SquareNut_handle_site"
PEG_BODY: str = "peg1"


def square_env_meta() -> dict[str, Any]:
    """robomimic ``env_meta`` (type 1 = robosuite) of the square task: OSC_POSE delta control at 20 Hz, Panda,
    no robosuite cameras, ``hard_reset=False``. JSON-serialisable; stored as ``data.attrs['env_args']``."""
    rs = import_robosuite()
    from robosuite.controllers import load_controller_config  # lazy, optional dependency: robosuite

    return {
        "env_name": SQUARE_ENV_NAME,
        "env_version": rs.__version__,
        "type": 1,
        "env_kwargs": {
            "has_renderer": False, "has_offscreen_renderer": False, "ignore_done": True, "use_object_obs": True,
            "use_camera_obs": False, "control_freq": CONTROL_FREQ_HZ,
            "controller_configs": load_controller_config(default_controller="OSC_POSE"),
            "robots": ["Panda"], "camera_depths": False, "camera_heights": 84, "camera_widths": 84,
            "reward_shaping": False, "hard_reset": False,
        },
    }


def init_robomimic_obs_utils(image_keys: tuple[str, ...] = (FISHEYE_KEY,)) -> None:
    """Register observation modalities in robomimic's global ObsUtils (its env wrapper and dataset need it):
    :data:`LOW_DIM_KEYS` as ``low_dim``, ``image_keys`` as ``rgb``."""
    import_robomimic_env_utils()
    import robomimic.utils.obs_utils as obs_utils  # lazy, optional dependency: robomimic

    with robomimic_quiet():
        obs_utils.initialize_obs_utils_with_obs_specs(
            {"obs": {"low_dim": list(LOW_DIM_KEYS), "rgb": list(image_keys)}})


class SquareEnv:
    """The square environment with a fisheye wrist camera.

    Args:
        env_meta: robomimic env_meta (default :func:`square_env_meta`); ``env_name`` must be NutAssemblySquare.
            Camera/renderer kwargs are overridden (no robosuite cameras) and ``hard_reset`` forced False.
        image_size: fisheye image size in pixels (224 default, 84 option); ``None`` → no images rendered.
    """

    def __init__(self, env_meta: dict[str, Any] | None = None, image_size: int | None = 224) -> None:
        env_utils = import_robomimic_env_utils()
        meta = copy.deepcopy(env_meta) if env_meta is not None else square_env_meta()
        if meta.get("env_name") != SQUARE_ENV_NAME:
            raise SimError(f"SquareEnv: env_meta['env_name'] is {meta.get('env_name')!r}; expected "
                           f"{SQUARE_ENV_NAME!r}")
        meta.setdefault("env_kwargs", {})["hard_reset"] = False
        init_robomimic_obs_utils()
        self.env_meta = meta
        with robomimic_quiet():
            self.env = env_utils.create_env_from_metadata(
                env_meta=meta, render=False, render_offscreen=False, use_image_obs=False)
        self.rs = self.env.env  # robosuite environment
        self.image_size = image_size
        self._camera: WristFisheyeCamera | None = None
        self._camera_model = None
        # MuJoCo's mj_saveLastXML writes the process-wide last loaded XML, which any other model load (another
        # env, a tabletop scene) replaces: keep the MJCF this env compiled instead
        self._xml: str = self.rs.model.get_xml()
        self._fix_model()

    # ------------------------------------------------------------------ raw MuJoCo access
    @property
    def model(self):
        """Raw ``mujoco.MjModel``."""
        return self.rs.sim.model._model

    @property
    def data(self):
        """Raw ``mujoco.MjData``."""
        return self.rs.sim.data._data

    def _fix_model(self) -> None:
        self.model.mat_reflectance[:] = 0.0  # no planar reflections (halves robosuite render cost)
        # robosuite hides its visualisation sites (grip-site markers) only in reset(); a fresh env or reset_to()
        # would otherwise render red/green markers the recorded demos never show
        self.rs.visualize(vis_settings={v: False for v in self.rs._visualizations})

    @property
    def camera(self) -> WristFisheyeCamera:
        """The fisheye renderer of the current model (rebuilt if the model was replaced)."""
        if self.image_size is None:
            raise SimError("SquareEnv was created with image_size=None: no fisheye camera")
        if self._camera is None or self._camera_model is not self.model:
            if self._camera is not None:
                self._camera.close()
            self._camera = WristFisheyeCamera(self.model, self.image_size)
            self._camera_model = self.model
        return self._camera

    # ------------------------------------------------------------------ episode control
    def reset(self, seed: int | None = None) -> dict[str, np.ndarray]:
        """Reset to a random initial state (numpy's global generator seeded with ``seed`` when given)."""
        if seed is not None:
            np.random.seed(int(seed))
        self.env.reset()
        self._fix_model()
        return self.observation()

    def reset_to(self, states: np.ndarray, model_xml: str | None = None, initial: bool = False
                 ) -> dict[str, np.ndarray]:
        """Set the flattened MuJoCo state (robomimic ``states`` row); with ``model_xml`` load that model first.

        ``initial``: the state STARTS an episode (a start configuration, a demo's first state). robosuite's reset
        sets the OSC controller's null-space posture reference to the arm joints it starts from and its goal to the
        start pose; restoring a state does not, so without this the arm keeps those of the last reset and moves
        differently from an episode started at this state (issue #29: a demo replayed from its first state
        diverged at step 1)."""
        state: dict[str, Any] = {"states": np.asarray(states, dtype=np.float64)}
        if model_xml is not None:
            state["model"] = model_xml
        self.env.reset_to(state)
        if model_xml is not None:
            self._xml = model_xml
        self._fix_model()
        if initial:  # what robosuite's reset leaves in the controller: posture reference and goal = this state
            ctrl = self.rs.robots[0].controller
            ctrl.update_initial_joints(np.array(self.data.qpos[self.rs.robots[0]._ref_joint_pos_indexes]))
            ctrl.update(force=True)
            ctrl.reset_goal()
        return self.observation()

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, dict]:
        """One 20 Hz control step with a 7-D OSC_POSE delta action in [−1, 1] (pos, axis-angle, gripper)."""
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (7,) or not np.all(np.isfinite(a)):
            raise SimError(f"SquareEnv.step: action must be finite [7], got shape {a.shape}")
        _, reward, done, info = self.env.step(a)
        return self.observation(), float(reward), bool(done), info

    def get_state(self) -> np.ndarray:
        """Flattened MuJoCo state (robomimic ``states`` row), float64 [45]."""
        return np.asarray(self.rs.sim.get_state().flatten(), dtype=np.float64)

    def model_xml(self) -> str:
        """The MJCF the current model was compiled from (robomimic stores it per demo as ``model_file``).

        Not ``sim.model.get_xml()``: that is MuJoCo's process-wide last loaded XML, which any later model load in
        the same process (another env, a tabletop scene) replaces.
        """
        return self._xml

    def is_success(self) -> bool:
        """robosuite's task success (nut on the square peg, gripper released)."""
        return bool(self.env.is_success()["task"])

    # ------------------------------------------------------------------ poses
    def site_pose(self, site: str) -> np.ndarray:
        """World pose ``[4, 4]`` of a MuJoCo site."""
        sid = self.rs.sim.model.site_name2id(site)
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[sid].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[sid]
        return T

    def body_pose(self, body: str) -> np.ndarray:
        """World pose ``[4, 4]`` of a MuJoCo body."""
        bid = self.rs.sim.model.body_name2id(body)
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[bid].reshape(3, 3)
        T[:3, 3] = self.data.xpos[bid]
        return T

    def wrist_pose(self) -> np.ndarray:
        """``T_world_cam`` of the wrist camera, OpenCV axes, metres, ``[4, 4]``."""
        return camera_pose_cv(self.model, self.data, WRIST_CAMERA)

    def tcp_pose(self) -> np.ndarray:
        """``T_world_tcp``: position of the grip site, rotation of the wrist camera (OpenCV axes) ``[4, 4]``."""
        T = self.wrist_pose()
        T[:3, 3] = self.data.site_xpos[self.rs.sim.model.site_name2id(GRIP_SITE)]
        return T

    def T_cam_tcp(self) -> np.ndarray:
        """Fixed camera→TCP offset of this robot (translation only, camera axes), ``[4, 4]``."""
        T = pose_inverse(self.wrist_pose()) @ self.tcp_pose()
        T[:3, :3] = np.eye(3)
        return T

    def gripper_width(self) -> float:
        """Finger separation relative to closed, metres (Panda: 0 … 0.08)."""
        q = self.data.qpos[self.rs.robots[0]._ref_gripper_joint_pos_indexes]
        return float(q[0] - q[1])

    # ------------------------------------------------------------------ observations
    def render_wrist(self, T_world_cam: np.ndarray | None = None) -> np.ndarray:
        """Fisheye RGB ``[S, S, 3]`` uint8 of the current state from ``T_world_cam`` (default: the wrist camera).
        This is the GT-rendering hook: any camera pose, current sim state, nothing is changed."""
        T = self.wrist_pose() if T_world_cam is None else np.asarray(T_world_cam, dtype=np.float64)
        return self.camera.render(self.data, T)

    def observation(self) -> dict[str, np.ndarray]:
        """robomimic low-dim observations + fisheye image + UMI keys (see module docstring)."""
        self.rs.sim.forward()  # kinematics of the current state (robosuite observes pre-integration kinematics)
        obs = {k: np.asarray(v).copy() for k, v in self.env.get_observation().items()}
        obs["robot0_eef_rot_axis_angle"] = so3_log(self.tcp_pose()[:3, :3])
        obs["robot0_gripper_width"] = np.array([self.gripper_width()])
        if self.image_size is not None:
            img = self.render_wrist()
            obs[FISHEYE_KEY] = img
            obs[UMI_IMAGE_KEY] = img
        return obs

    def close(self) -> None:
        """Free the renderer and the robosuite environment."""
        if self._camera is not None:
            self._camera.close()
            self._camera = None
        self.rs.close()
