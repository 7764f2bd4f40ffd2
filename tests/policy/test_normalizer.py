import numpy as np
import torch

from umi_aug.policy.normalizer import LinearNormalizer, range_params


def test_range_normalizer_maps_to_unit_interval_and_inverts(rng):
    x = np.concatenate([rng.normal(3, 2, (500, 3)), np.full((500, 1), 0.07)], axis=1)  # last dim constant
    n = LinearNormalizer()
    n.set("a", *range_params(x))
    xt = torch.as_tensor(x, dtype=torch.float32)
    y = n.normalize(xt, "a")
    assert torch.allclose(y[:, :3].min(0).values, torch.tensor(-1.0), atol=1e-5)
    assert torch.allclose(y[:, :3].max(0).values, torch.tensor(1.0), atol=1e-5)
    assert torch.allclose(y[:, 3], torch.tensor(0.0), atol=1e-6)  # constant dim → centred, unit scale
    assert torch.allclose(n.unnormalize(y, "a"), xt, atol=1e-5, rtol=1e-6)
    xd = torch.as_tensor(x)
    assert torch.allclose(n.unnormalize(n.normalize(xd, "a"), "a"), xd, atol=1e-12)


def test_state_dict_round_trip_and_dict_normalize(rng):
    n = LinearNormalizer()
    n.set("action", *range_params(rng.normal(size=(50, 10))))
    n.set("robot0_eef_pos", np.ones(3) * 2, np.zeros(3))
    m = LinearNormalizer()
    m.load_state_dict(n.state_dict())
    assert m.keys() == n.keys()
    obs = {"robot0_eef_pos": torch.ones(2, 3), "camera0_rgb": torch.rand(2, 3, 4, 4)}
    out = m.normalize(obs)
    assert torch.equal(out["robot0_eef_pos"], torch.full((2, 3), 2.0))
    assert out["camera0_rgb"] is obs["camera0_rgb"]  # images pass through (identity, as UMI)
