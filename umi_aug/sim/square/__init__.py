"""RoboMimic "square" (robosuite NutAssemblySquare, Panda, OSC_POSE at 20 Hz) with a true fisheye wrist camera.

Modules (none imports robosuite/robomimic/MuJoCo at package import):

- :mod:`~umi_aug.sim.square.compat` — the mujoco_py stand-in robomimic 0.3.0 needs, robosuite/robomimic import.
- :mod:`~umi_aug.sim.square.env` — :class:`SquareEnv` built from a robomimic ``env_meta``; observations.
- :mod:`~umi_aug.sim.square.camera` — wrist camera pose (OpenCV axes), GoPro intrinsics, fisheye rendering.
- :mod:`~umi_aug.sim.square.expert` — scripted privileged-state expert.
- :mod:`~umi_aug.sim.square.rollout` — one expert episode as arrays (:class:`Episode`).
- :mod:`~umi_aug.sim.square.ik` — damped-least-squares IK of the Panda arm.
- :mod:`~umi_aug.sim.square.writers` — robomimic hdf5 + UMI zarr writers.
- :mod:`~umi_aug.sim.square.generate` — parallel, resumable expert demo generation.
- :mod:`~umi_aug.sim.square.convert` — robomimic square hdf5 → fisheye hdf5 + UMI zarr.
- :mod:`~umi_aug.sim.square.init_configs` — seeded evaluation start configurations (cone + IK).
- :mod:`~umi_aug.sim.square.pictures` — contact sheets (docs/square_*.png).
- :mod:`~umi_aug.sim.square.cli` — ``square-demos``, ``square-convert``, ``square-init-configs``.
"""
