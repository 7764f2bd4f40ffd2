"""Real-robot deployment (UR arm via ur-rtde): the policy loop, safety limits, interpolating servo controller.

Stage order: sits above :mod:`umi_aug.policy` and uses only public APIs of lower stages. Modules:

* :mod:`~umi_aug.deploy.clock` — wall/fake clocks (the loop is testable without real time);
* :mod:`~umi_aug.deploy.interpolator` — UMI's pose-trajectory interpolator with speed limits;
* :mod:`~umi_aug.deploy.safety` — workspace box, table-height clamp, step length, NaN, stale observations;
* :mod:`~umi_aug.deploy.shared_state` — a shared-memory ring buffer of timestamped states between processes;
* :mod:`~umi_aug.deploy.runner` — observation alignment, latency-compensated action scheduling;
* :mod:`~umi_aug.deploy.interfaces` — robot / gripper / camera protocols the runner talks to;
* :mod:`~umi_aug.deploy.ur_rtde` — the ur-rtde servoL controller (its own process);
* :mod:`~umi_aug.deploy.wsg50` — WSG-50 binary protocol driver and gripper process (metres);
* :mod:`~umi_aug.deploy.camera` — UVC capture via OpenCV, receive timestamps, UMI's policy-image transform;
* :mod:`~umi_aug.deploy.device_process` — the child-process wrapper shared by robot and gripper (observe-only
  until enabled; every child dies with the runner, ``PR_SET_PDEATHSIG``);
* :mod:`~umi_aug.deploy.arm_process`, :mod:`~umi_aug.deploy.gripper_process` — the host side every arm / gripper
  backend shares (real and simulated alike: state buffer, command queue, heartbeat; the gripper control loop);
* :mod:`~umi_aug.deploy.sim_ur5e` — a simulated UR5e (MuJoCo), gripper and fisheye wrist camera behind the same
  interfaces (``robot=sim_ur5e``, ``backend: sim``);
* :mod:`~umi_aug.deploy.policies` — scripted policies (reach); :mod:`~umi_aug.deploy.recorder` — zarr + mp4 +
  plot + timing; :mod:`~umi_aug.deploy.app` — assembles one episode from the config (``eval/deploy_ur.py``).

``ur-rtde`` is the ``deploy`` extra (``pip install 'umi-aug[deploy]'``); it is imported only inside the controller.
"""
