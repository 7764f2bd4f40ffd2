"""The stages every input source shares, each cached on disk by :func:`umi_aug.augment.cache.run_stage`.

A source (:mod:`umi_aug.augment.sources`) builds its own scene first — a UMI session reconstructs its scan, a plain
dataset triangulates its episodes' frames, square demos take the simulator's scene — then calls these on what it
built:

- :func:`contact_stage` — per demo the splice frame: the last frame at or before its contact frame whose gripper
  keeps ``pregrasp_m`` clearance to the scene SDF (the pre-contact pose the new trajectories funnel into; the demo
  is replayed from it on);
- :func:`gripper_mask_stage` — the gripper overlay mask at policy resolution (:mod:`umi_aug.augment.overlay`),
  chosen from the demos' pre-contact frames;
- :func:`init_only_gaussians` — the untrained scene of ``splat.iterations = 0`` (smoke runs): isotropic Gaussians
  at the cloud's points.

Cache keys are those the stages always had (stage name, version, config subset, inputs' keys), so work folders
written before this module existed stay valid.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from scipy.spatial import cKDTree

from umi_aug.augment.cache import StageResult, run_stage
from umi_aug.augment.config import AugmentConfig
from umi_aug.augment.mirrors import detect_mirror_convention, mirror_mask, mirror_pixels_from_source
from umi_aug.augment.overlay import choose_overlay_mask
from umi_aug.data import ReplayBuffer
from umi_aug.data.rows import read_rows, shared_decoded_chunks
from umi_aug.errors import AugmentError
from umi_aug.io_utils import atomic_write_text
from umi_aug.recon.cloud import read_ply as read_cloud
from umi_aug.recon.contact import gripper_clearance
from umi_aug.recon.pipeline import first_close_index
from umi_aug.recon.sdf_grid import VoxelSDF

__all__ = ["OVERLAY_MASK_RULE", "DemoPath", "MaskDemo", "contact_stage", "gripper_mask_stage", "init_only_gaussians"]

log = logging.getLogger(__name__)

#: Version of the overlay-mask rule (3: "auto" = UMI's jaw polygons + the static finger pixels of the trapezoid).
#: Part of the gripper-mask stage's key and of the export's run key: bump it when the rule changes.
OVERLAY_MASK_RULE = 3


class DemoPath(Protocol):
    """What :func:`contact_stage` reads of a demo."""

    name: str
    T_world_cam: np.ndarray  # [H, 4, 4] camera poses (world, OpenCV camera), metres
    gripper_width: np.ndarray  # [H] metres


class MaskDemo(Protocol):
    """What :func:`gripper_mask_stage` reads of a demo (:class:`~umi_aug.augment.session_assets.DemoInfo`)."""

    index: int  # its episode in the dataset
    gripper_width: np.ndarray  # [H] metres
    contact_index: int | None  # splice frame (None: the frames before the gripper first closes are used)


def contact_stage(work: Path, recon: StageResult, demos: Sequence[DemoPath], overrides: Mapping[str, int],
                  pregrasp_m: float) -> StageResult:
    """Per demo: the detected contact frame (the ``report`` of ``recon``, or an override by demo name) and the splice
    frame — the last frame at or before it whose gripper clearance to ``recon``'s ``sdf`` is at least ``pregrasp_m``
    (metres). Writes ``contacts.json``: one row per demo, in order (``index``, ``name``, ``contact_index``,
    ``splice_index`` — None: not augmented —, ``overridden``)."""

    def fn(out: Path):
        report = json.loads(recon.path("report").read_text())
        found = {c["episode"]: c for c in report.get("contacts", [])}
        sdf = VoxelSDF.load(recon.path("sdf"))
        rows = []
        for i, d in enumerate(demos):
            c = found.get(d.name, {})
            idx = overrides.get(d.name, c.get("contact_index"))
            splice = None
            if idx is None:
                log.warning("contact: demo %s has no contact frame (%s); it is not augmented", d.name,
                            c.get("message", "not in the reconstruction report"))
            else:
                clr, _ = gripper_clearance(sdf, d.T_world_cam[: int(idx) + 1], d.gripper_width[: int(idx) + 1])
                ok = np.flatnonzero(clr[1:] >= pregrasp_m) + 1
                splice = int(ok[-1]) if len(ok) else None
                if splice is None:
                    log.warning("contact: demo %s: no frame before contact %d keeps %.3f m clearance; not augmented",
                                d.name, idx, pregrasp_m)
            rows.append({"index": i, "name": d.name, "contact_index": None if idx is None else int(idx),
                         "splice_index": splice, "overridden": d.name in overrides})
        atomic_write_text(out / "contacts.json", json.dumps(rows, indent=2) + "\n")
        return {"contacts": "contacts.json"}, ["contacts.json"], {"demos": rows}

    return run_stage("contact", work, {"overrides": dict(sorted(overrides.items())), "pregrasp_m": pregrasp_m},
                     {"reconstruct": recon.key}, fn)


def gripper_mask_stage(work: Path, cfg: AugmentConfig, fp: str, dataset: Path, demos: Sequence[MaskDemo],
                       contact: StageResult, umi_mirrors: bool = True) -> StageResult:
    """The gripper overlay mask (``mask.npy``: [S, S] bool, ``mask.png``) chosen by
    :func:`~umi_aug.augment.overlay.choose_overlay_mask` from up to 48 frames per demo before its splice frame (or
    before the gripper first closes), read from ``dataset``'s ``camera0_rgb`` (which must hold ``S x S`` frames,
    ``S = cfg.image_size``). ``fp``: the input's fingerprint (part of the key). ``umi_mirrors``: the camera is
    UMI's GoPro rig: the mirror convention of the frames is detected (stage info ``mirrors``) and, as
    ``cfg.overlay.mirrors`` says, UMI's mirror polygons join the mask (:mod:`umi_aug.augment.mirrors`)."""
    S = cfg.image_size

    def fn(out: Path):
        frames = []
        with ReplayBuffer.open(dataset) as buf:
            if "camera0_rgb" not in buf:
                raise AugmentError(f"{dataset}: no key 'data/camera0_rgb'; the gripper overlay needs the originals")
            shape = tuple(buf["camera0_rgb"].shape[1:])
            if shape != (S, S, 3):
                raise AugmentError(f"{dataset}: key 'data/camera0_rgb' has frames {shape}, but image_size = {S}; "
                                   f"export at the dataset's resolution (--image-size {shape[0]})")
            for d in demos:
                end = d.contact_index if d.contact_index is not None else first_close_index(d.gripper_width)
                end = len(d.gripper_width) if end is None else int(end)
                sl = buf.get_episode_slice(d.index)
                idx = np.linspace(0, max(0, end - 1), min(end, 48)).round().astype(int)
                # only these frames are decoded (one chunk per frame, on the cores), not the whole episode
                frames.append(read_rows(buf["camera0_rgb"], idx + sl.start, cache=shared_decoded_chunks()))
        frames = np.concatenate(frames)
        mask, info = choose_overlay_mask(frames, S, cfg.overlay.mask, cfg.overlay.std_threshold,
                                         cfg.overlay.min_coverage)
        if umi_mirrors:
            convention, evidence = detect_mirror_convention(frames)
            copied = mirror_pixels_from_source(cfg.overlay.mirrors, convention)
            if copied:
                mask = mask | mirror_mask(S)
            info = {**info, "mirrors": {"convention": convention, "from_source": copied, **evidence}}
            log.info("gripper overlay: mirrors look %s (black %.0f %%, edge ratio %.2f): %s", convention,
                     100 * evidence["black_fraction"], evidence["edge_ratio"],
                     "copied from the source frame" if copied else "rendered from the scene")
        np.save(out / "mask.npy", mask)
        cv2.imwrite(str(out / "mask.png"), mask.astype(np.uint8) * 255)
        return {"mask": "mask.npy", "png": "mask.png"}, ["mask.npy", "mask.png"], info

    # "rule": bump when choose_overlay_mask's rule changes, so cached masks of the old rule are rebuilt
    return run_stage("gripper_mask", work, {"overlay": cfg.overlay, "image_size": S, "rule": OVERLAY_MASK_RULE,
                                            "umi_mirrors": umi_mirrors},
                     {"session": fp, "contact": contact.key}, fn)


def init_only_gaussians(cloud_path: Path, sh_degree: int):
    """Isotropic Gaussians at the points of the PLY cloud ``cloud_path`` (world frame, metres; σ = mean distance to
    the 3 nearest neighbours, clipped to 1..50 mm; opacity 0.8), no optimisation: the scene of
    ``splat.iterations = 0``. Returns :class:`umi_aug.splat.Gaussians`."""
    from umi_aug.splat import Gaussians  # lazy: torch takes seconds to import; only untrained scenes need it here

    cloud = read_cloud(cloud_path)
    if len(cloud) < 4:
        raise AugmentError(f"{cloud_path}: {len(cloud)} points; too few to initialise Gaussians")
    d, _ = cKDTree(cloud.points).query(cloud.points, k=4)
    sigma = np.clip(d[:, 1:].mean(axis=1), 1e-3, 0.05)
    return Gaussians.from_points(cloud.points, cloud.colors / 255.0, sigma, opacity=0.8, sh_degree=sh_degree)
