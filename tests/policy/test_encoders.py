import logging

import numpy as np
import pytest
import torch

from tests.policy.helpers import SIZE
from umi_aug.errors import PolicyError
from umi_aug.policy.config import EncoderConfig, TaskConfig, shape_meta
from umi_aug.policy.encoders import ObsEncoder, timm_clip_to_hf
from umi_aug.policy.image_aug import (CLIP_MEAN, CLIP_STD, center_crop_resize, color_jitter, crop_side,
                                      random_crop_resize, hsv_to_rgb, normalize_image, rgb_to_hsv)

TINY_VIT = dict(name="clip_vit", vit_hidden_size=64, vit_layers=2, vit_heads=2, vit_mlp_size=128, vit_patch_size=8)


def _meta(size=SIZE, **kw):
    return shape_meta(TaskConfig(dataset_path="x", image_size=size, **kw))


def _obs(B=2, size=SIZE, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"camera0_rgb": torch.rand(B, 2, 3, size, size, generator=g),
            "robot0_eef_pos": torch.randn(B, 2, 3, generator=g),
            "robot0_eef_rot_axis_angle": torch.randn(B, 2, 6, generator=g),
            "robot0_gripper_width": torch.rand(B, 2, 1, generator=g),
            "robot0_eef_rot_axis_angle_wrt_start": torch.randn(B, 2, 6, generator=g)}


def _hf_to_timm(sd):
    """Inverse of timm_clip_to_hf (test helper): CLIPVisionModel keys → timm vit_*_clip keys."""
    out = {}
    vm = "vision_model."
    sd = {(k if k.startswith(vm) else vm + k): v for k, v in sd.items()}  # transformers 5 drops the prefix
    out["cls_token"] = sd[vm + "embeddings.class_embedding"].reshape(1, 1, -1)
    out["pos_embed"] = sd[vm + "embeddings.position_embedding.weight"][None]
    out["patch_embed.proj.weight"] = sd[vm + "embeddings.patch_embedding.weight"]
    for a, b in (("pre_layrnorm", "norm_pre"), ("post_layernorm", "norm")):
        for p in ("weight", "bias"):
            out[f"{b}.{p}"] = sd[f"{vm}{a}.{p}"]
    i = 0
    while f"{vm}encoder.layers.{i}.layer_norm1.weight" in sd:
        L = f"{vm}encoder.layers.{i}."
        for p in ("weight", "bias"):
            out[f"blocks.{i}.attn.qkv.{p}"] = torch.cat([sd[L + f"self_attn.{x}_proj.{p}"] for x in "qkv"])
            for a, b in (("self_attn.out_proj", "attn.proj"), ("layer_norm1", "norm1"), ("layer_norm2", "norm2"),
                         ("mlp.fc1", "mlp.fc1"), ("mlp.fc2", "mlp.fc2")):
                out[f"blocks.{i}.{b}.{p}"] = sd[L + f"{a}.{p}"]
        i += 1
    return out


def test_vit_encoder_shapes_and_train_only_augmentation(caplog):
    torch.manual_seed(0)
    with caplog.at_level(logging.WARNING):
        enc = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT))
    assert "RANDOM weights" in caplog.text
    assert enc.output_dim == 2 * 64 + 2 * (3 + 6 + 1 + 6)
    obs = _obs()
    enc.eval()
    with torch.no_grad():
        a, b = enc(obs), enc(obs)
    assert a.shape == (2, enc.output_dim) and torch.equal(a, b)  # eval: deterministic (centre crop, no jitter)
    # eval pre-processing is exactly the centre crop (same scale as training) + the CLIP normalisation
    pre = enc.preprocess(obs["camera0_rgb"])
    m, s = torch.tensor(CLIP_MEAN)[:, None, None], torch.tensor(CLIP_STD)[:, None, None]
    assert torch.allclose(pre, (center_crop_resize(obs["camera0_rgb"], enc.cfg.crop_ratio) - m) / s)
    enc.train()
    with torch.no_grad():
        c = enc(obs)
    assert not torch.allclose(a[:, :128], c[:, :128])  # training: augmented images
    assert torch.equal(a[:, 128:], c[:, 128:])  # low-dim part untouched, sorted keys flattened
    assert torch.equal(a[:, 128:131], obs["robot0_eef_pos"][:, 0])


@pytest.mark.parametrize("size,ratio", [(84, 0.95), (224, 0.95), (85, 0.9), (16, 0.5), (84, 1.0)])
def test_eval_images_have_the_training_scale(size, ratio):
    """B1: the image evaluation sees is one of the crops training draws (the centred one), so an object has the same
    apparent size (the distance cue of a wrist camera) in training and evaluation — not the uncropped image, which
    is 1/ratio smaller than anything the policy was trained on."""
    g = torch.Generator().manual_seed(size)
    img = torch.rand(2, 2, 3, size, size, generator=g)
    ev = center_crop_resize(img, ratio)
    side = crop_side(size, ratio)
    off = (size - side) // 2
    # the same crop drawn by training: a generator whose draws land on the centre offset
    assert 0 <= off <= size - side
    found = any(torch.equal(random_crop_resize(img[:1], ratio, torch.Generator().manual_seed(seed)), ev[:1])
                for seed in range(2000))
    assert found, "the evaluation crop is not one of the crops training draws"
    ref = torch.nn.functional.interpolate(img[:, :, :, off: off + side, off: off + side].reshape(-1, 3, side, side),
                                          size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    assert torch.equal(ev, ref.reshape(img.shape))
    assert torch.isfinite(ev).all()
    if side < size:  # the scale: a centred square of half the image grows by size / side in both
        sq = torch.zeros(1, 1, 3, size, size)
        q = size // 4
        sq[..., q: size - q, q: size - q] = 1.0
        frac = lambda x: float((x[0, 0, 0] > 0.5).float().mean())  # noqa: E731
        assert frac(center_crop_resize(sq, ratio)) == pytest.approx(frac(sq) * (size / side) ** 2, rel=0.15)


def _spatial_softmax_reference(feat, weight, bias):
    """Keypoints the slow way: per sample and keypoint, loop over the cells, softmax weights in float64."""
    n, c, h, w = feat.shape
    k = weight.shape[0]
    out = torch.zeros(n, 2 * k, dtype=torch.float64)
    f, wt, b = feat.double(), weight.double().reshape(k, c), bias.double()
    for i in range(n):
        for j in range(k):
            logits = [(wt[j] * f[i, :, r, q]).sum() + b[j] for r in range(h) for q in range(w)]
            m = max(float(v) for v in logits)
            e = [torch.exp(v - m) for v in logits]
            z = sum(e)
            for idx, ev in enumerate(e):
                r, q = divmod(idx, w)
                x = -1.0 + 2.0 * q / (w - 1) if w > 1 else -1.0
                y = -1.0 + 2.0 * r / (h - 1) if h > 1 else -1.0
                out[i, 2 * j] += ev / z * x
                out[i, 2 * j + 1] += ev / z * y
    return out


@pytest.mark.parametrize("shape", [(3, 5, 3, 3), (2, 4, 6, 4), (2, 3, 1, 5)])
def test_spatial_softmax_matches_the_reference(rng, shape):
    """The batched keypoints equal a per-cell loop on random maps, moderate and extreme logits (a near one-hot
    softmax must not overflow to NaN); a single peak lands on its cell's centre, x along the width."""
    from umi_aug.policy.encoders import SpatialSoftmax

    n, c, h, w = shape
    torch.manual_seed(int(rng.integers(1 << 30)))
    ss = SpatialSoftmax(c, 4)
    for scale in (1.0, 300.0):
        feat = torch.from_numpy(rng.normal(0.0, scale, shape)).float()
        got = ss(feat)
        want = _spatial_softmax_reference(feat, ss.keypoint_maps.weight.detach(), ss.keypoint_maps.bias.detach())
        assert got.shape == (n, 8) and torch.isfinite(got).all()
        assert torch.allclose(got.double(), want, atol=1e-5), (scale, (got.double() - want).abs().max())
        assert got.abs().max() <= 1.0 + 1e-6
    one = SpatialSoftmax(1, 1)
    with torch.no_grad():
        one.keypoint_maps.weight.fill_(1.0)
        one.keypoint_maps.bias.zero_()
    peak = torch.zeros(1, 1, 3, 5)
    peak[0, 0, 2, 1] = 1e4  # bottom row, second column
    assert torch.allclose(one(peak), torch.tensor([[-0.5, 1.0]]), atol=1e-6)


@pytest.mark.parametrize("pool", ["avg", "spatial_softmax"])
def test_channels_last_resnet_matches_the_nchw_reference(rng, pool, monkeypatch):
    """The ResNet backbone runs channels-last; the same weights in NCHW give the same features and gradients.

    The gradients are compared with the kinks smoothed out (ReLU → softplus, max-pool → average pool in both nets):
    a float32 rounding difference of 1e-7 can put a pre-activation on the other side of a ReLU's or a max-pool's
    kink, and that one element then routes its whole gradient elsewhere (CI seed 1537110821: one ReLU input at
    −8e-7 in float64, +1e-7 channels-last, 4 % off in every gradient below it) — correct arithmetic either way."""
    from torch import nn

    from umi_aug.policy.encoders import ResNetBackbone

    torch.manual_seed(int(rng.integers(1 << 30)))
    kw = dict(name="resnet", resnet_width=8, resnet_blocks=[1, 1, 1, 1], resnet_pool=pool, spatial_softmax_keypoints=6)
    net = ResNetBackbone(EncoderConfig(**kw))
    assert net.feature_dim == (12 if pool == "spatial_softmax" else 64)
    assert net.stem[0].weight.is_contiguous(memory_format=torch.channels_last)
    ref = ResNetBackbone(EncoderConfig(**kw, channels_last=False))
    ref.load_state_dict(net.state_dict())
    assert ref.stem[0].weight.is_contiguous() and not ref.stem[0].weight.is_contiguous(
        memory_format=torch.channels_last)
    x = torch.from_numpy(rng.uniform(0.0, 1.0, (5, 3, 40, 40))).float()
    x[0] = 0.0  # a black frame
    y, y_ref = net(x), ref(x)
    assert y.shape == (5, net.feature_dim)
    assert torch.isfinite(y).all() and torch.allclose(y, y_ref, atol=1e-5)

    monkeypatch.setattr(torch, "relu", lambda t: nn.functional.softplus(t, beta=10.0))
    for m in (net, ref):
        m.stem[2], m.stem[3] = nn.Softplus(beta=10.0), nn.AvgPool2d(3, 2, 1)
    net(x).square().sum().backward()
    ref(x).square().sum().backward()
    for (name, p), p_ref in zip(net.named_parameters(), ref.parameters()):
        assert torch.isfinite(p.grad).all() and p.grad.abs().max() > 0, name
        assert torch.allclose(p.grad, p_ref.grad, atol=1e-4, rtol=1e-4), name


@pytest.mark.parametrize("c_in", [3, 8, 16])
def test_strided_pointwise_conv_matches_the_einsum_reference(rng, c_in):
    """The ResNet's 1×1 stride-2 shortcut (a stride-1 convolution of every 2nd pixel) gives a strided 1×1
    convolution's output and gradients, channels-last included, with fewer input channels than oneDNN's block (the
    case whose strided backward-weights kernel corrupts memory with torch 2.13.0) and on odd and even sizes."""
    from umi_aug.policy.encoders import _StridedPointwiseConv

    torch.manual_seed(int(rng.integers(1 << 30)))
    conv = _StridedPointwiseConv(c_in, 16, 2)
    for size, batch in [(10, 5), (11, 3), (1, 2), (21, 64)]:
        for fmt in (torch.contiguous_format, torch.channels_last):
            x = torch.from_numpy(rng.normal(size=(batch, c_in, size, size))).float()
            x = x.contiguous(memory_format=fmt).requires_grad_(True)
            conv.to(memory_format=fmt).weight.grad = None
            y = conv(x)
            x_ref = x.detach().contiguous().requires_grad_(True)
            w_ref = conv.weight.detach().contiguous().requires_grad_(True)
            # the obvious reference: every 2nd pixel's channels times the weight matrix (torch's own strided 1×1
            # convolution cannot be the reference: its backward is the kernel that crashes, NCHW too)
            y_ref = torch.einsum("oc,bchw->bohw", w_ref[:, :, 0, 0], x_ref[:, :, ::2, ::2])
            assert y.shape == y_ref.shape == (batch, 16, (size + 1) // 2, (size + 1) // 2)
            assert torch.allclose(y, y_ref, atol=1e-5)
            g = torch.from_numpy(rng.normal(size=tuple(y.shape))).float()
            y.backward(g)
            y_ref.backward(g)
            assert torch.allclose(x.grad, x_ref.grad, atol=1e-5)
            assert torch.isfinite(conv.weight.grad).all()  # a weight gradient sums batch·H·W products: float32
            assert torch.allclose(conv.weight.grad, w_ref.grad, rtol=1e-5, atol=1e-5 * float(w_ref.grad.abs().max()))
    if c_in == 8:  # the checkpoint keys and shapes of the nn.Conv2d it replaces
        assert {k: v.shape for k, v in conv.state_dict().items()} == {
            k: v.shape for k, v in torch.nn.Conv2d(8, 16, 1, 2, bias=False).state_dict().items()}


def test_resnet_encoder_and_frozen():
    enc = ObsEncoder(_meta(), EncoderConfig(name="resnet", resnet_width=8, resnet_blocks=[1, 1, 1, 1], frozen=True))
    assert enc.feature_dim == 64 and enc.output_dim == 2 * 64 + 32
    assert not any(p.requires_grad for p in enc.backbone_parameters())
    assert enc.eval()(_obs()).shape == (2, enc.output_dim)
    with pytest.raises(PolicyError, match="camera0_rgb"):
        enc({k: v for k, v in _obs().items() if k != "camera0_rgb"})
    with pytest.raises(PolicyError, match="must be"):
        enc({**_obs(), "robot0_eef_pos": torch.zeros(2, 3, 3)})


def test_clip_weights_from_hf_folder_and_timm_file(tmp_path):
    torch.manual_seed(1)
    src = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT)).eval()
    hf_model = src.backbones["camera0_rgb"].model
    hf_model.save_pretrained(tmp_path / "clip")
    obs = _obs()
    with torch.no_grad():
        ref = src(obs)
    from_dir = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, pretrained_path=str(tmp_path / "clip"))).eval()
    assert from_dir.pretrained
    with torch.no_grad():
        assert torch.allclose(from_dir(obs), ref, atol=1e-6)
    # a UMI-style checkpoint: timm keys under obs_encoder.key_model_map.<camera>.
    sd = _hf_to_timm(hf_model.state_dict())
    own = {k.replace("vision_model.", "") for k in hf_model.state_dict() if not k.endswith("position_ids")}
    assert {k.replace("vision_model.", "") for k in timm_clip_to_hf(sd)} == own
    payload = {"state_dicts": {"model": {f"obs_encoder.key_model_map.camera0_rgb.{k}": v for k, v in sd.items()}}}
    torch.save(payload, tmp_path / "umi.ckpt")
    from_timm = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, pretrained_path=str(tmp_path / "umi.ckpt"))).eval()
    with torch.no_grad():
        assert torch.allclose(from_timm(obs), ref, atol=1e-6)
    # wrong architecture / not weights → clear errors naming the file
    torch.save({"foo": torch.zeros(3)}, tmp_path / "bad.pt")
    with pytest.raises(PolicyError, match="bad.pt"):
        ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, pretrained_path=str(tmp_path / "bad.pt")))
    wide = dict(TINY_VIT, vit_hidden_size=32, vit_mlp_size=64)
    with pytest.raises(PolicyError, match="does not fit"):
        ObsEncoder(_meta(), EncoderConfig(**wide, pretrained_path=str(tmp_path / "umi.ckpt")))
    with pytest.raises(PolicyError, match="not a file"):
        ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, pretrained_path=str(tmp_path / "missing.bin")))


def test_clip_weights_from_full_clip_model(tmp_path):
    """OpenAI's HF checkpoints are full CLIPModel folders (vision_model.* + text_model.*): folder and file load."""
    from transformers import CLIPConfig, CLIPModel

    torch.manual_seed(2)
    conf = CLIPConfig(
        text_config=dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                         vocab_size=64, max_position_embeddings=16),
        vision_config=dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=2,
                           image_size=SIZE, patch_size=8, hidden_act="quick_gelu"), projection_dim=16)
    clip = CLIPModel(conf).eval()
    clip.save_pretrained(tmp_path / "clip_full")
    x = torch.rand(2, 2, 3, SIZE, SIZE)
    ref = clip.vision_model(pixel_values=normalize_image(x.reshape(4, 3, SIZE, SIZE), CLIP_MEAN, CLIP_STD))
    for p in (tmp_path / "clip_full", tmp_path / "clip_full" / "model.safetensors"):
        enc = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, crop_ratio=1.0, pretrained_path=str(p))).eval()
        with torch.no_grad():
            out = enc({**_obs(), "camera0_rgb": x})
        assert torch.allclose(out[:, :128], ref.pooler_output.reshape(2, 128), atol=1e-5), p


def test_color_jitter_and_hsv():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 2, 3, 8, 8, generator=g)
    assert torch.allclose(hsv_to_rgb(rgb_to_hsv(img)), img, atol=1e-5)
    assert torch.allclose(color_jitter(img, 0, 0, 0, 0), img)
    out = color_jitter(img, 0.3, 0.4, 0.5, 0.08, generator=g)
    assert out.shape == img.shape and float(out.min()) >= 0 and float(out.max()) <= 1
    assert not torch.allclose(out, img)
    assert not torch.allclose(out[0] - img[0], out[1] - img[1])  # per-sample factors
    assert torch.allclose(normalize_image(torch.ones(3, 1, 1), (0.5,) * 3, (0.25,) * 3), torch.full((3, 1, 1), 2.0))


def test_fast_hsv_to_rgb_matches_the_reference(rng):
    """The sector-free hsv_to_rgb against the sector-by-sector reference on fresh random HSV values, with the
    extremes: grey (s = 0), black (v = 0), hues on the sector borders and just below 1 turn."""
    from umi_aug.policy.image_aug import _hsv_to_rgb_reference

    n = 4096
    h = torch.from_numpy(rng.uniform(0.0, 1.0, n)).float()
    h[:12] = torch.tensor([0.0, 1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6, 1 - 1e-7, 0.5, 1e-8, 0.25, 0.75, 0.999999])
    s = torch.from_numpy(rng.uniform(0.0, 1.0, n)).float()
    v = torch.from_numpy(rng.uniform(0.0, 1.0, n)).float()
    s[12:40], v[40:60], s[60:70], v[60:70] = 0.0, 0.0, 1.0, 1.0
    hsv = torch.stack([h, s, v]).reshape(3, 64, 64)[None, None]
    fast, ref = hsv_to_rgb(hsv), _hsv_to_rgb_reference(hsv)
    assert torch.isfinite(fast).all() and fast.shape == ref.shape
    assert torch.allclose(fast, ref, atol=2e-6)
    img = torch.from_numpy(rng.uniform(0.0, 1.0, (2, 3, 3, 16, 16))).float()
    img[0, 0, :, :4] = 0.5  # grey pixels
    assert torch.allclose(hsv_to_rgb(rgb_to_hsv(img)), img, atol=2e-6)


@pytest.mark.slow
def test_vit_b16_output_matches_umi():
    """The paper's encoder: ViT-B/16 at 224², CLS 768-d per frame → 2·768 + 2·16 = 1568 (UMI's global cond)."""
    torch.manual_seed(0)
    enc = ObsEncoder(_meta(224), EncoderConfig()).eval()
    n = sum(p.numel() for p in enc.backbone_parameters())
    assert 85e6 < n < 87e6
    assert enc.output_dim == 1568
    with torch.no_grad():
        assert enc(_obs(1, 224)).shape == (1, 1568)


@pytest.mark.parametrize("sigma_max", [0.4, 1.0, 2.5])
def test_random_blur_matches_the_reference(rng, sigma_max):
    """The separable blur equals the per-pixel 2-D reference on fresh random images, for per-sample sigmas
    including 0 (the identity), the largest one and tiny ones; the T frames of a sample share it; NaN never
    passes; it keeps an image's mean away from the border; a kernel wider than the image is refused."""
    from umi_aug.policy.image_aug import _random_gaussian_blur_reference, blur_sigmas, random_gaussian_blur

    B, T, S = 5, 2, 11
    img = torch.from_numpy(rng.uniform(0, 1, (B, T, 3, S, S))).to(torch.float32)
    sig = torch.tensor([0.0, 1e-4, sigma_max / 3, sigma_max, float(rng.uniform(0, sigma_max))])
    radius = max(1, int(np.ceil(3 * sigma_max)))
    got = random_gaussian_blur(img, sigma_max, sigmas=sig)
    want = _random_gaussian_blur_reference(img, sig, radius)
    assert torch.isfinite(got).all() and got.shape == img.shape and got.dtype == img.dtype
    assert torch.allclose(got.to(torch.float64), want, atol=2e-6)
    assert torch.allclose(got[:2], img[:2], atol=1e-6)  # sigma 0 (and ~0): the image itself
    assert not torch.allclose(got[3], img[3], atol=1e-2)
    flat = torch.full((1, 1, 3, S, S), 0.3)
    assert torch.allclose(random_gaussian_blur(flat, sigma_max, sigmas=torch.tensor([sigma_max])), flat, atol=1e-6)
    g = torch.Generator().manual_seed(3)
    s = blur_sigmas(1000, sigma_max, g)
    assert float(s.min()) >= 0 and float(s.max()) <= sigma_max and abs(float(s.mean()) - sigma_max / 2) < 0.05
    same = torch.cat([img[:1, :1], img[:1, :1]], dim=1)  # two equal frames stay equal
    out = random_gaussian_blur(same, sigma_max, generator=torch.Generator().manual_seed(1))
    assert torch.equal(out[:, 0], out[:, 1])
    with pytest.raises(PolicyError, match="needs a"):
        random_gaussian_blur(img[:, :, :, :4, :4], 2.0)


def test_encoder_blurs_in_training_only():
    torch.manual_seed(0)
    enc = ObsEncoder(_meta(), EncoderConfig(**TINY_VIT, crop_ratio=1.0, color_jitter=[], blur_sigma_max=1.5))
    obs = _obs()
    enc.eval()
    m, s = torch.tensor(CLIP_MEAN)[:, None, None], torch.tensor(CLIP_STD)[:, None, None]
    assert torch.allclose(enc.preprocess(obs["camera0_rgb"]), (obs["camera0_rgb"] - m) / s)
    enc.train()
    enc.generator = torch.Generator().manual_seed(0)
    pre = enc.preprocess(obs["camera0_rgb"])
    assert not torch.allclose(pre, (obs["camera0_rgb"] - m) / s, atol=1e-3)
