"""UMI's side mirrors in augmented frames (#34 item 6): the convention of a dataset's frames, and the overlay mask."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from umi_aug.augment.cache import StageResult
from umi_aug.augment.config import AugmentConfig, OverlayConfig
from umi_aug.augment.mirrors import detect_mirror_convention, mirror_mask, mirror_pixels_from_source
from umi_aug.augment.stages import gripper_mask_stage
from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.errors import AugmentError
from umi_aug.geometry import pos_rotvec_to_pose

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"
S = 96


def _scene(rng: np.random.Generator, n: int, size: int = S) -> np.ndarray:
    """[n, S, S, 3] uint8: a smooth textured scene panning across the frame (what a rig without mirrors sees)."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    ph = rng.uniform(0, 2 * np.pi, 3)
    f = [np.stack([128 + 80 * np.sin(2 * np.pi * (2.0 * xx + 1.3 * c * yy) + ph[c] + 0.4 * k) for c in range(3)], -1)
         for k in range(n)]
    return np.clip(np.round(f), 0, 255).astype(np.uint8)


def _with_mirrors(frames: np.ndarray, content: np.ndarray) -> np.ndarray:
    out = frames.copy()
    m = mirror_mask(frames.shape[1])
    out[:, m] = content[:, m]
    return out


def _below_circle(frames: np.ndarray) -> np.ndarray:
    """Black below a disc, as UMI's frames are outside the lens circle (part of each mirror polygon lies there)."""
    out = frames.copy()
    s = frames.shape[1]
    yy, xx = np.mgrid[0:s, 0:s]
    out[:, (yy - 0.42 * s) ** 2 + (xx - s / 2) ** 2 > (0.62 * s) ** 2] = 0
    return out


def test_the_three_conventions_are_told_apart():
    rng = np.random.default_rng(3)
    scene = _below_circle(_scene(rng, 24))
    # a rig without mirrors: the scene continues through the polygons
    assert detect_mirror_convention(scene)[0] == "none"
    # a mirror: other content inside the polygons (a reflection of somewhere else), or UMI's swap of it
    other = _scene(np.random.default_rng(4), 24)[:, :, ::-1]
    conv, ev = detect_mirror_convention(_below_circle(_with_mirrors(scene, other)))
    assert conv == "reflection" and ev["edge_ratio"] >= ev["mirror_edge_ratio"], ev
    # UMI's --no_mirror: painted black
    conv, ev = detect_mirror_convention(_with_mirrors(scene, np.zeros_like(scene)))
    assert conv == "masked" and ev["black_fraction"] == 1.0, ev
    for bad in (scene[0], scene[:1], scene.astype(np.float32), scene[:, :, :-1]):
        with pytest.raises(AugmentError, match="detect_mirror_convention"):
            detect_mirror_convention(bad)


def test_the_real_episode_has_reflections():
    if not REAL.is_file():
        pytest.fail(f"{REAL}: the real UMI demonstration lives in ../shared/realdata next to the repository")
    with ReplayBuffer.open(REAL) as buf:
        n = buf["camera0_rgb"].shape[0]
        f = np.asarray(buf["camera0_rgb"].get_orthogonal_selection((np.linspace(0, n - 1, 32).round().astype(int),)))
    conv, ev = detect_mirror_convention(f)
    assert conv == "reflection", ev
    assert 0.3 < ev["black_fraction"] < 0.5  # the polygons' part outside the lens circle
    masked = f.copy()
    masked[:, mirror_mask(f.shape[1])] = 0
    assert detect_mirror_convention(masked)[0] == "masked"


@pytest.mark.parametrize("mode, convention, copied", [
    ("auto", "reflection", True), ("auto", "masked", True), ("auto", "none", False),
    ("source", "none", True), ("scene", "reflection", False), ("scene", "masked", False),
])
def test_mode_and_convention_decide_the_copy(mode, convention, copied):
    assert mirror_pixels_from_source(mode, convention) is copied


def test_a_bad_mode_is_named():
    with pytest.raises(AugmentError, match=r"overlay.mirrors='mirror'"):
        mirror_pixels_from_source("mirror", "none")
    with pytest.raises(AugmentError, match=r"OverlayConfig.mirrors = 'mirror'"):
        AugmentConfig(overlay=OverlayConfig(mirrors="mirror"))


class _Demo:
    def __init__(self, index: int, n: int) -> None:
        self.index, self.contact_index, self.gripper_width = index, n - 1, np.full(n, 0.08)


def _dataset(path: Path, frames: np.ndarray) -> Path:
    buf = ReplayBuffer.create()
    n = len(frames)
    T = pos_rotvec_to_pose(np.concatenate([np.linspace([0, 0, 0.3], [0.1, 0, 0.3], n), np.zeros((n, 3))], 1))
    buf.add_episode(make_umi_episode(T, np.full(n, 0.08), {0: frames}))
    buf.save(path)
    return path


@pytest.mark.parametrize("content, mode, expect_mirrors", [
    ("reflection", "auto", True), ("none", "auto", False), ("none", "source", True), ("reflection", "scene", False),
])
def test_the_overlay_mask_takes_the_mirrors_as_decided(tmp_path, content, mode, expect_mirrors):
    rng = np.random.default_rng(5)
    frames = _below_circle(_scene(rng, 20))
    if content == "reflection":
        frames = _below_circle(_with_mirrors(frames, _scene(np.random.default_rng(6), 20)[:, :, ::-1]))
    ds = _dataset(tmp_path / "d.zarr.zip", frames)
    cfg = AugmentConfig(image_size=S, overlay=OverlayConfig(mask="predefined", mirrors=mode))
    contact = StageResult("contact", tmp_path, "k", {}, False, 0.0)
    gm = gripper_mask_stage(tmp_path / "work", cfg, "fp", ds, [_Demo(0, 20)], contact)
    mask = np.load(gm.dir / gm.outputs["mask"])
    # a camera without UMI's rig (the square's Panda) never takes them: the gripper mask alone
    gm2 = gripper_mask_stage(tmp_path / "work2", cfg, "fp", ds, [_Demo(0, 20)], contact, umi_mirrors=False)
    base = np.load(gm2.dir / gm2.outputs["mask"])
    mirrors = mirror_mask(S)
    assert "mirrors" not in gm2.info and (mirrors & ~base).sum() > 100  # most of the mirrors lie outside it
    np.testing.assert_array_equal(mask, base | mirrors if expect_mirrors else base)
    assert gm.info["mirrors"]["convention"] == content and gm.info["mirrors"]["from_source"] is expect_mirrors
