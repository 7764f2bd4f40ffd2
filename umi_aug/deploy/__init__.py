"""Real-robot deployment (UR arm via ur-rtde): the policy loop, safety limits, interpolating servo controller.

Stage order: sits above :mod:`umi_aug.policy` and uses only public APIs of lower stages. Modules:

* :mod:`~umi_aug.deploy.clock` — wall/fake clocks (the loop is testable without real time);
* :mod:`~umi_aug.deploy.interpolator` — UMI's pose-trajectory interpolator with speed limits;
* :mod:`~umi_aug.deploy.safety` — workspace box, table-height clamp, step length, NaN, stale observations;
* :mod:`~umi_aug.deploy.shared_state` — a shared-memory ring buffer of timestamped states between processes;
* :mod:`~umi_aug.deploy.runner` — observation alignment, latency-compensated action scheduling;
* :mod:`~umi_aug.deploy.ur_rtde` — the ur-rtde servoL controller (its own process).
"""
