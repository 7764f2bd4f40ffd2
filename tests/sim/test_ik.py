"""The simulator arms' DLS IK (umi_aug.sim.ik) on a small 6-joint MJCF arm: both callers' parameter sets reach
poses of the arm, joint bounds hold, the model's missing names are one SimError."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.errors import SimError
from umi_aug.geometry import rotation_geodesic_distance, so3_log
from umi_aug.sim.ik import ArmIK, DLSParams, rodrigues_log

_AXES = ["0 0 1", "0 1 0", "0 1 0", "1 0 0", "0 1 0", "1 0 0"]
_ARM = "".join(f'<body pos="0 0 {0.0 if i == 0 else 0.15}"><joint name="j{i}" axis="{a}" range="-2.5 2.5"/>'
               f'<geom type="capsule" size="0.02" fromto="0 0 0 0 0 0.15"/>' for i, a in enumerate(_AXES))
_XML = (f'<mujoco><compiler angle="radian"/><worldbody>{_ARM}<site name="tip" pos="0 0 0.2"/>'
        + "</body>" * len(_AXES) + "</worldbody></mujoco>")
_JOINTS = [f"j{i}" for i in range(6)]


@pytest.fixture(scope="module")
def model():
    from umi_aug.sim.gl import import_mujoco

    return import_mujoco().MjModel.from_xml_string(_XML)


def _regular_joints(ik: ArmIK, rng: np.random.Generator) -> np.ndarray:
    """Random joints [6] (rad) away from the arm's singularities (smallest singular value of J above 0.05): from
    0.1 rad off, both parameter sets then converge in < 30 iterations (6000 seeded trials)."""
    while True:
        q = rng.uniform(-1.2, 1.2, 6)
        ik.load(q)
        if np.linalg.svd(ik.jacobian(), compute_uv=False).min() > 0.05:
            return q


@pytest.mark.parametrize("params", [DLSParams(max_step=0.2, step_norm="l2", rot_log=so3_log),
                                    DLSParams(max_step=0.05, step_norm="max", rot_log=rodrigues_log)],
                         ids=["panda_l2_so3log", "ur5e_max_rodrigues"])
def test_dls_reaches_poses_of_the_arm(model, params, rng):
    ik = ArmIK(model, "tip", _JOINTS)
    for _ in range(5):
        q_goal = _regular_joints(ik, rng)
        T_goal = ik.fk(q_goal)
        q0 = q_goal + rng.normal(0.0, 0.1, 6)
        q, pe, re, it = ik.solve_dls(T_goal, q0, params, max_iters=300)
        assert pe < 1e-6 and re < 1e-5 and 0 < it < 300
        T = ik.fk(q)
        assert np.linalg.norm(T[:3, 3] - T_goal[:3, 3]) == pytest.approx(pe, abs=1e-12)
        assert rotation_geodesic_distance(T[:3, :3], T_goal[:3, :3]) < 1e-5


def test_bounds_hold_and_release_bounds_uses_the_other_joints(model):
    ik = ArmIK(model, "tip", _JOINTS)
    params = DLSParams(max_step=0.2)
    lo, hi = ik.lo.copy(), ik.hi.copy()
    hi[1] = 0.3  # the shoulder may not lean further than 0.3 rad
    q_goal = np.array([0.2, 0.29, 0.5, 0.1, 0.3, -0.2])
    T_goal = ik.fk(q_goal)
    for release in (False, True):
        q, pe, _, _ = ik.solve_dls(T_goal, np.zeros(6), params, max_iters=300, lo=lo, hi=hi, release_bounds=release)
        assert np.all(q >= lo) and np.all(q <= hi)
        assert pe < 1e-4


def test_missing_site_or_joint_is_one_sim_error(model):
    with pytest.raises(SimError, match="TestArm: no site 'nope' in the model"):
        ArmIK(model, "nope", _JOINTS, owner="TestArm")
    with pytest.raises(SimError, match=r"TestArm: joints j0..j6 not all found"):
        ArmIK(model, "tip", _JOINTS + ["j6"], owner="TestArm", joints_label="j0..j6")
