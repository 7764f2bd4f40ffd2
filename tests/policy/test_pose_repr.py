import numpy as np
import pytest

from umi_aug.errors import PolicyError
from umi_aug.geometry import pos_rotvec_to_pose, pose_to_pos_rotvec, relative_pose
from umi_aug.policy.pose_repr import (
    abs_actions_to_model, model_actions_to_abs, obs_pose_to_model, wrt_start_rot6d,
)


def _actions(rng, *lead):
    return np.concatenate([rng.normal(0, 0.4, lead + (3,)), rng.normal(0, 1.0, lead + (3,)),
                           rng.uniform(0, 0.09, lead + (1,))], axis=-1)


@pytest.mark.parametrize("rep", ["relative", "abs"])
def test_action_round_trip_exact(rng, rep):
    """absolute [pos, rotvec, g] → relative 10-D → absolute: same poses to 1e-9 (float64)."""
    a = _actions(rng, 6, 16)
    cur = _actions(rng, 6)[:, :6]
    m = abs_actions_to_model(a, cur, rep)
    assert m.shape == (6, 16, 10)
    back = model_actions_to_abs(m, cur, rep)
    assert back.shape == a.shape
    np.testing.assert_allclose(pos_rotvec_to_pose(back[..., :6]), pos_rotvec_to_pose(a[..., :6]), atol=1e-9, rtol=0)
    np.testing.assert_array_equal(back[..., 6], a[..., 6])


def test_relative_action_is_inv_cur_times_t(rng):
    a = _actions(rng, 16)
    cur = pos_rotvec_to_pose(_actions(rng)[:6])
    m = abs_actions_to_model(a, cur)
    T_rel = relative_pose(cur, pos_rotvec_to_pose(a[:, :6]))
    np.testing.assert_allclose(m[:, :3], T_rel[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(m[:, 3:9], T_rel[:, :2, :3].reshape(16, 6), atol=1e-12)  # first two ROWS
    # the current pose itself maps to the identity
    m0 = abs_actions_to_model(np.concatenate([pose_to_pos_rotvec(cur), [0.05]])[None], cur)
    np.testing.assert_allclose(m0[0, :9], [0, 0, 0, 1, 0, 0, 0, 1, 0], atol=1e-12)


def test_two_arm_round_trip(rng):
    a = np.concatenate([_actions(rng, 3, 16), _actions(rng, 3, 16)], axis=-1)
    cur = np.stack([_actions(rng, 3)[:, :6], _actions(rng, 3)[:, :6]], axis=1)  # [B, R, 6]
    m = abs_actions_to_model(a, cur)
    assert m.shape == (3, 16, 20)
    back = model_actions_to_abs(m, cur)
    np.testing.assert_allclose(pos_rotvec_to_pose(back[..., 7:13]), pos_rotvec_to_pose(a[..., 7:13]), atol=1e-9)
    with pytest.raises(PolicyError):
        model_actions_to_abs(m, cur[:, 0])


def test_obs_relative_and_wrt_start(rng):
    p = _actions(rng, 2)
    pos, rot = obs_pose_to_model(p[:, :3], p[:, 3:6])
    np.testing.assert_allclose(pos[-1], 0, atol=1e-12)
    np.testing.assert_allclose(rot[-1], [1, 0, 0, 0, 1, 0], atol=1e-12)
    w = wrt_start_rot6d(p[:, :3], p[:, 3:6], p[0, :6])
    np.testing.assert_allclose(w[0], [1, 0, 0, 0, 1, 0], atol=1e-12)
