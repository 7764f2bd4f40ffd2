"""slim_checkpoint: the inference part of a training checkpoint (what a lent GPU machine can send back)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from tests.policy.helpers import make_dataset, make_tiny_checkpoint, tiny_config
from umi_aug.errors import PolicyError
from umi_aug.policy.checkpoint import load_checkpoint, save_checkpoint, slim_checkpoint
from umi_aug.policy.inference import Policy
from umi_aug.policy.workspace import TrainWorkspace


def _with_ema(tmp_path):
    """The tiny checkpoint plus an EMA model (weights moved by fresh noise) and an optimiser state."""
    src = make_tiny_checkpoint(tmp_path)
    payload = load_checkpoint(src)
    model = payload["state_dicts"]["model"]
    rng = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 31)))
    ema = {k: (v + 0.01 * torch.randn(v.shape, generator=rng) if v.is_floating_point() and "normalizer" not in k
               else v.clone()) for k, v in model.items()}
    payload["state_dicts"].update(ema_model=ema, optimizer={"state": {}, "param_groups": []})
    payload.pop("format")
    return save_checkpoint(tmp_path / "full.ckpt", payload), ema


@pytest.mark.parametrize("half", [False, True])
def test_slim_keeps_the_ema_weights_and_loads(tmp_path, half):
    src, ema = _with_ema(tmp_path)
    dest = slim_checkpoint(src, tmp_path / "slim.ckpt", half=half)
    sd = load_checkpoint(dest)["state_dicts"]
    assert list(sd) == ["ema_model"]
    assert dest.stat().st_size < src.stat().st_size
    policy = Policy.from_checkpoint(dest)
    got = policy.model.state_dict()
    for k, v in ema.items():
        w = got[k]
        if not v.is_floating_point() or "normalizer" in k or not half:
            assert torch.equal(w, v), k
        else:
            assert w.dtype == v.dtype, k  # loaded into the float32 model
            assert torch.allclose(w, v, rtol=1e-3, atol=1e-4), k
            assert torch.isfinite(w).all(), k


def test_bad_weights_and_an_existing_destination_are_refused_and_training_refuses_a_slim_checkpoint(tmp_path):
    src, ema = _with_ema(tmp_path)
    payload = load_checkpoint(src)
    name = next(k for k, v in ema.items() if v.is_floating_point() and "normalizer" not in k)
    payload["state_dicts"]["ema_model"][name] = payload["state_dicts"]["ema_model"][name] * 0 + 1e6
    payload.pop("format")
    big = save_checkpoint(tmp_path / "big.ckpt", payload)
    with pytest.raises(PolicyError, match=f"{name} exceeds float16"):
        slim_checkpoint(big, tmp_path / "x.ckpt", half=True)
    assert not (tmp_path / "x.ckpt").exists()

    payload["state_dicts"]["ema_model"][name] = payload["state_dicts"]["ema_model"][name] * float("nan")
    nan = save_checkpoint(tmp_path / "nan.ckpt", payload)
    for half in (False, True):
        with pytest.raises(PolicyError, match=f"{name} holds NaN"):
            slim_checkpoint(nan, tmp_path / "x.ckpt", half=half)
    assert not (tmp_path / "x.ckpt").exists()
    before = src.read_bytes()
    with pytest.raises(PolicyError, match="exists; it is never replaced"):
        slim_checkpoint(src, src)
    assert src.read_bytes() == before

    ds = make_dataset(tmp_path / "d.zarr.zip", np.random.default_rng(0), n_episodes=2)
    cfg = tiny_config(ds, tmp_path)
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    shutil.copyfile(slim_checkpoint(src, tmp_path / "slim.ckpt"), tmp_path / "run" / "checkpoints" / "latest.ckpt")
    with pytest.raises(PolicyError, match="slim checkpoint"):
        TrainWorkspace(cfg).run()
