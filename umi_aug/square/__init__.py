"""The RoboMimic "square" benchmark (robosuite NutAssemblySquare, Panda, OSC_POSE at 20 Hz) with a true fisheye
wrist camera: simulator, demos, augmentation input, evaluation task and the study — one package on top of the
pipeline (issue #33). ``sim/``, ``augment/`` and ``eval/`` know nothing of it; it plugs into them through their
seams: an input kind for the export (:mod:`~umi_aug.square.source` registers ``square`` with
:func:`umi_aug.augment.sources.register_source`) and a task for the evaluation harness
(:data:`umi_aug.square.eval.SQUARE_TASK`, a :class:`umi_aug.eval.task.SimTask`).

Modules (none imports robosuite/robomimic/MuJoCo at package import; importing the package imports nothing):

Simulator
  - :mod:`~umi_aug.square.compat` — the mujoco_py stand-in robomimic 0.3.0 needs, robosuite/robomimic import.
  - :mod:`~umi_aug.square.env` — :class:`SquareEnv` built from a robomimic ``env_meta``; observations.
  - :mod:`~umi_aug.square.camera` — wrist camera pose (OpenCV axes), GoPro intrinsics, fisheye rendering.
  - :mod:`~umi_aug.square.commands` — commanded TCP targets ↔ OSC_POSE deltas, the gripper command.
  - :mod:`~umi_aug.square.expert` — scripted privileged-state expert, its pre-grasp pose.
  - :mod:`~umi_aug.square.ik` — the Panda's IK (:class:`~umi_aug.square.ik.PandaIK` on :class:`umi_aug.sim.ik.ArmIK`).
  - :mod:`~umi_aug.square.scan` — scans of the static scene and the nut (robot hidden), body poses.
  - :mod:`~umi_aug.square.feasibility` — can the simulated Panda follow a camera path (IK, limits, collisions).
  - :mod:`~umi_aug.square.init_configs` — seeded evaluation start configurations (cone + IK).

Demos
  - :mod:`~umi_aug.square.episode` — one expert episode as arrays (:class:`~umi_aug.square.episode.Episode`).
  - :mod:`~umi_aug.square.writers` — robomimic hdf5 + UMI zarr writers.
  - :mod:`~umi_aug.square.generate` — parallel, resumable expert demo generation.
  - :mod:`~umi_aug.square.convert` — robomimic square hdf5 → fisheye hdf5 + UMI zarr.
  - :mod:`~umi_aug.square.pictures` — contact sheets (docs/square_*.png).
  - :mod:`~umi_aug.square.cli` — ``umi-aug square-demos``, ``square-convert``, ``square-init-configs``.

Augmentation input
  - :mod:`~umi_aug.square.source` — a demo folder as the export's input (checks, stages, per-demo handles) and
    its registration as the input kind ``square``.
  - :mod:`~umi_aug.square.scene` — the scene model: static-scene 3DGS + nut asset, composited per demo.
  - :mod:`~umi_aug.square.variants` — the study's training datasets from one export (``none`` … ``spartn``).

Evaluation and study
  - :mod:`~umi_aug.square.controls` — scripted policies (expert, replay, hold, random) and their privileged state.
  - :mod:`~umi_aug.square.eval` — the task of the harness (``eval/eval_sim.py``): environment, sub-goals, contacts.
  - :mod:`~umi_aug.square.oracle` — the replay oracle of the train/eval contract (``eval/square_oracle.py``).
  - :mod:`~umi_aug.square.study` / :mod:`~umi_aug.square.report` — the study (``eval/square_study.py``) and its
    report; :mod:`~umi_aug.square.claims` — the paper's claims against the study's record, each with a verdict.
  - :mod:`~umi_aug.square.start_angle` — a cell's outcomes by how far its starts are turned from the demos'.
"""
