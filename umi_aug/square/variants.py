"""The square study's training datasets (issue #15), all derived from ONE augmented export so that they share
source demos, trajectories and bytes wherever they are meant to:

* ``none`` — the first ``n`` source demos only (their stored chunks, copied).
* ``ours`` — those demos + their augmented episodes as exported (3DGS frames + gripper overlay; copied).
* ``gt_render`` — the same episodes (same poses, widths, actions, replayed tail), the new pre-splice frames
  rendered by the SIMULATOR with the Panda placed on the trajectory by IK (the oracle upper bound: what a perfect
  scene model would give, with the robot's own fingers in view).
* ``action_only`` — the same episodes, each new pre-splice frame replaced by the ORIGINAL demo frame at the same
  progress towards the splice (new frame ``k`` of ``K`` → original ``round(k · s / K)``, ``s`` the demo's splice
  frame): augmented poses/actions with the demo's images, as Florence et al. 2019 (images not re-rendered).
* ``spartn`` — single-step corrective augmentation (SPARTN-style): the source demos + for every ``stride``-th
  pre-splice step ``t`` of each, ``per_step`` perturbations ``δ`` (translation uniform in a ball of ``trans_m``,
  rotation uniform in angle ≤ ``rot_deg`` about a uniform axis, in the camera frame): a short episode whose
  observed frames ``t−1, t`` are at ``T_world_cam[k] @ δ`` (3DGS render + gripper overlay) and whose later frames
  ``t+1 … t+H−1`` are the ORIGINAL ones. The policy's action window at ``t`` then reads: target 0 = the perturbed
  current pose, targets 1… = the original trajectory — the corrective label back onto the demo. Each short episode
  is ONE training sample, that step (``meta/umi_aug_sample_step``, read by the policy dataset). SPARTN's exact
  magnitudes are not public (``../shared/spec/eval_and_deploy.md`` §5); these are ours and configurable.
* ``ours_rerender`` — not a variant of the paper: ``ours`` (every episode, as exported) + for each source demo one
  more episode, the demo itself with its pre-splice frames ``0..s-1`` RENDERED by the same 3DGS scene model at the
  demo's own poses, with the gripper of the same frames overlaid (``render_new``, as ``spartn``'s), the rest copied
  (records: ``aug_mode`` :data:`RERENDER_MODE_CODE`, ``aug_id`` 0, the demo as ``aug_source_episode``, splice
  ``s``: so ``task.sample_replayed_tails=false`` leaves out its replayed tail as an augmented episode's). Every
  original approach frame then exists twice with the same labels, once as recorded and once as our renders show
  it: paired examples of the two looks (issue #29: ``ours`` fits its renders at the augmented starts and errs twice
  as much on the simulator's frames of the same episodes, and the reverse for ``gt_render``).
* ``ours_spartn`` — not a variant of the paper: ``ours`` (every episode, as exported) + ``spartn``'s perturbed
  samples of the same demos, episode for episode the same bytes as each alone. It tells whether the two add up:
  cone starts that cover where the evaluation begins, and corrections back onto the demo's path near it.

Every output is written to a temporary path and renamed (never half-written); its root attribute
``umi_aug_variant`` records what it is.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from tqdm import tqdm

from umi_aug.augment.export_store import IMAGE_KEY, RECORD_CHUNK, RECORD_KEYS, append_episode, read_episode_records
from umi_aug.augment.plan import MODE_CODES
from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.data.schema import ACTION_KEY, SAMPLE_STEP_KEY
from umi_aug.errors import AugmentError
from umi_aug.geometry import pos_rotvec_to_pose, so3_exp
from umi_aug.geometry.umi import camera_poses_from_tcp_poses, tcp_poses_from_camera_poses

__all__ = ["VARIANTS", "SPARTN_VARIANTS", "SpartnConfig", "write_variant", "subset_variant", "action_only_sources",
           "spartn_perturbation", "VARIANT_ATTR", "RERENDER_MODE_CODE"]

VARIANTS: tuple[str, ...] = ("none", "ours", "gt_render", "action_only", "spartn", "ours_spartn", "ours_rerender")
#: ``meta/aug_mode`` of an ``ours_rerender`` episode: a source demo re-rendered at its own poses, the exporter's
#: ``rerender`` code (:data:`umi_aug.augment.plan.MODE_CODES`; ``umi-aug augment --rerender-originals``).
RERENDER_MODE_CODE: int = MODE_CODES["rerender"]
#: The variants that add SPARTN's perturbed samples.
SPARTN_VARIANTS: tuple[str, ...] = ("spartn", "ours_spartn")
VARIANT_ATTR = "umi_aug_variant"


@dataclass(frozen=True)
class SpartnConfig:
    """SPARTN-style perturbations (metres / degrees; camera frame).

    Attributes:
        stride: every ``stride``-th pre-splice step gets perturbations; per_step: how many per such step.
        trans_m: translation radius (uniform in the ball); rot_deg: largest rotation angle (uniform in angle).
        obs_horizon / action_horizon: the policy's (frames observed, targets predicted) — the episode length is
            ``obs_horizon − 1 + action_horizon``.
        seed: root seed (per demo, step and draw: ``SeedSequence([seed, demo, t, j])``).
    """

    stride: int = 2
    per_step: int = 1
    trans_m: float = 0.03
    rot_deg: float = 15.0
    obs_horizon: int = 2
    action_horizon: int = 16
    seed: int = 0

    def __post_init__(self) -> None:
        for k in ("stride", "per_step", "obs_horizon", "action_horizon"):
            if int(getattr(self, k)) < 1:
                raise AugmentError(f"SpartnConfig.{k} = {getattr(self, k)!r}; expected an int >= 1")
        if not (self.trans_m >= 0 and self.rot_deg >= 0 and math.isfinite(self.trans_m + self.rot_deg)):
            raise AugmentError(f"SpartnConfig: trans_m = {self.trans_m}, rot_deg = {self.rot_deg}; expected >= 0")


def spartn_perturbation(cfg: SpartnConfig, demo: int, t: int, j: int) -> np.ndarray:
    """The camera-frame perturbation ``δ`` [4, 4] of draw ``j`` at step ``t`` of demo ``demo`` (deterministic)."""
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, int(demo), int(t), int(j)]))
    d = rng.normal(size=3)
    d /= max(np.linalg.norm(d), 1e-12)
    trans = d * cfg.trans_m * rng.uniform() ** (1.0 / 3.0)  # uniform in the ball
    axis = rng.normal(size=3)
    axis /= max(np.linalg.norm(axis), 1e-12)
    delta = np.eye(4)
    delta[:3, :3] = so3_exp(axis * math.radians(cfg.rot_deg) * rng.uniform())
    delta[:3, 3] = trans
    return delta


def action_only_sources(n_new: int, source_splice: int) -> np.ndarray:
    """Original frame shown at each of the ``n_new`` new pre-splice frames of an ``action_only`` episode:
    ``round(k · source_splice / n_new)`` (same progress towards the splice)."""
    k = np.arange(int(n_new), dtype=np.float64)
    return np.rint(k * int(source_splice) / max(1, int(n_new))).astype(np.int64)


# ------------------------------------------------------------------------------------------------------ writer
def _empty_like(src):
    """A new in-memory buffer with ``src``'s data keys, chunks and codecs (so stored chunks copy raw)."""
    buf = ReplayBuffer.create()
    for k in src.keys():
        a = src[k]
        buf.data.zeros(k, shape=(0,) + a.shape[1:], chunks=a.chunks, dtype=a.dtype, compressor=a.compressor,
                       filters=a.filters)
    for k in RECORD_KEYS:
        buf.meta.zeros(k, shape=(0,), chunks=(RECORD_CHUNK,), dtype=RECORD_KEYS[k], compressor=None)
    return buf


def _lowdim(src, rows: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.asarray(src[k].get_orthogonal_selection((rows,))) for k in src.keys() if k != IMAGE_KEY}


def _camera_path(src, low: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``T_world_cam`` [N, 4, 4] and ``gripper_width`` [N] of an episode's low-dim rows."""
    T_cam_tcp = np.asarray(src.root.attrs["T_cam_tcp"], dtype=np.float64)
    T_tcp = pos_rotvec_to_pose(np.concatenate([low["robot0_eef_pos"], low["robot0_eef_rot_axis_angle"]],
                                              axis=1).astype(np.float64))
    return {"T_world_cam": camera_poses_from_tcp_poses(T_tcp, T_cam_tcp),
            "gripper_width": np.asarray(low["robot0_gripper_width"], np.float64).reshape(-1)}


def _add(buf, src, lowdim: dict[str, np.ndarray], new_frames: np.ndarray, src_rows: np.ndarray,
         record: dict[str, int]) -> None:
    for k, dt in RECORD_KEYS.items():
        a = buf.meta[k]
        a.resize(a.shape[0] + 1)
        a[-1] = np.asarray(record[k], dtype=dt)
    append_episode(buf, lowdim, new_frames, src[IMAGE_KEY], src_rows)


def write_variant(variant: str, ours_path: str | os.PathLike, out_path: str | os.PathLike, n_demos: int, *,
                  render_new: Callable[[int, dict[str, Any]], np.ndarray] | None = None,
                  spartn: SpartnConfig | None = None, progress: bool = True, label: str | None = None,
                  per_demo: int | None = None) -> dict[str, Any]:
    """Write the ``variant`` dataset of the first ``n_demos`` source demos of the export ``ours_path``.

    Args:
        variant: one of :data:`VARIANTS`.
        ours_path: an ``umi-aug`` export with the originals included (``meta/aug_*`` records).
        out_path: the ``.zarr.zip`` to write (temporary path, then rename).
        render_new: ``gt_render``: ``(episode, info) -> [s, S, S, 3]``, the frames ``0..s-1`` of an augmented
            episode (``info``: its ``T_world_cam`` [N, 4, 4], ``gripper_width`` [N], ``splice`` = ``n_new`` = s,
            ``source`` demo); ``spartn`` / ``ours_spartn``: ``(source episode, info) -> [K, S, S, 3]`` frames at
            ``info["T_world_cam"]`` ([K, 4, 4]) with the gripper of the demo's frames ``info["overlay_rows"]`` [K]
            of source demo ``info["source"]``; ``ours_rerender``: the same, at the demo's own poses ``0..s-1``.
            :func:`square_render_functions` makes both for a square demo folder.
        spartn: :class:`SpartnConfig` (``spartn`` and ``ours_spartn`` only).
        label: the variant name recorded in the output (default ``variant``; :func:`subset_variant`).
        per_demo: keep only each demo's first ``per_demo`` augmented episodes (``meta/aug_id < per_demo``; None:
            all) — fewer augmented episodes per demo from the same export, episode for episode the same bytes.
    Returns:
        summary dict (episodes, frames rendered, per-kind counts) — also stored as the root attribute
        :data:`VARIANT_ATTR`.
    """
    if variant not in VARIANTS:
        raise AugmentError(f"write_variant: variant {variant!r}; expected one of {VARIANTS}")
    if (variant in ("gt_render", "ours_rerender") or variant in SPARTN_VARIANTS) and render_new is None:
        raise AugmentError(f"write_variant({variant}): needs render_new (the frames it renders)")
    if Path(out_path).resolve() == Path(ours_path).resolve():
        raise AugmentError(f"write_variant({variant}): out_path {out_path} is the source export itself; choose "
                           "another path (the export would be replaced)")
    rec = read_episode_records(ours_path)
    src_ep, splice, aug_id = rec["aug_source_episode"], rec["aug_splice_index"], rec["aug_id"]
    n_src = int((aug_id == -1).sum())  # source demos (-2: SPARTN episodes of a spartn variant)
    if n_demos < 1 or n_demos > n_src:
        raise AugmentError(f"{ours_path}: n_demos = {n_demos}; the export holds {n_src} source demos")
    if per_demo is not None and int(per_demo) < 0:
        raise AugmentError(f"write_variant({variant}): per_demo = {per_demo}; expected >= 0 or None")
    out_path = Path(out_path)
    summary: dict[str, Any] = {"variant": label or variant, "n_demos": int(n_demos), "source": str(ours_path),
                               "episodes": 0, "augmented": 0, "frames_new": 0}
    if per_demo is not None:
        summary["per_demo"] = int(per_demo)
    with ReplayBuffer.open(ours_path) as src:
        ends = np.asarray(src.episode_ends)
        starts = np.concatenate([[0], ends[:-1]])
        keep = [e for e in range(len(ends)) if src_ep[e] < n_demos and (aug_id[e] < 0 or variant != "none")
                and (per_demo is None or aug_id[e] < int(per_demo))]
        if variant == "spartn":
            keep = [e for e in keep if aug_id[e] < 0]
        buf = _empty_like(src)
        src_steps = (np.asarray(src.meta[SAMPLE_STEP_KEY][:], dtype=np.int64)
                     if SAMPLE_STEP_KEY in set(src.meta.array_keys()) else np.full(len(ends), -1, np.int64))
        steps: list[int] = []  # meta/umi_aug_sample_step of the output, episode by episode
        for e in tqdm(keep, desc=f"{label or variant} (n={n_demos})", unit="episode", disable=not progress):
            steps.append(int(src_steps[e]))
            rows = np.arange(starts[e], ends[e])
            record = {k: rec[k][e] for k in RECORD_KEYS}
            low = _lowdim(src, rows)
            s = int(splice[e])
            info = {"rows": rows, "splice": s, "source": int(src_ep[e])}
            if aug_id[e] < 0 or variant in ("none", "ours", "ours_spartn", "ours_rerender"):
                _add(buf, src, low, np.zeros((0,) + src[IMAGE_KEY].shape[1:], np.uint8), rows, record)
            elif variant == "action_only":  # the original frames' stored chunks, copied (no re-encode)
                o = int(src_ep[e])
                orig_rows = starts[o] + action_only_sources(s, int(splice[o]))
                _add(buf, src, low, np.zeros((0,) + src[IMAGE_KEY].shape[1:], np.uint8),
                     np.concatenate([orig_rows, rows[s:]]), record)
            else:  # gt_render
                info.update(_camera_path(src, low), n_new=s)
                new = np.asarray(render_new(e, info))
                if new.shape[0] != s:
                    raise AugmentError(f"write_variant(gt_render): render_new gave {new.shape[0]} frames for "
                                       f"episode {e}'s {s} new frames")
                _add(buf, src, low, new, rows[s:], record)
                summary["frames_new"] += s
            summary["episodes"] += 1
            summary["augmented"] += int(aug_id[e] >= 0)
            if variant == "ours_rerender" and aug_id[e] == -1:  # a source demo: it again, as our renders show it
                summary["frames_new"] += _rerendered_episode(buf, src, low, rows, s, int(src_ep[e]), render_new)
                steps.append(-1)
                summary["episodes"] += 1
                summary["augmented"] += 1
            if variant in SPARTN_VARIANTS and aug_id[e] == -1:  # a source demo: its perturbed samples
                summary["frames_new"] += _spartn_episodes(buf, src, e, rows, s, spartn or SpartnConfig(),
                                                          render_new, summary, steps)
        buf.root.attrs[VARIANT_ATTR] = summary | {"spartn": asdict(spartn) if variant in SPARTN_VARIANTS and spartn
                                                  else None}
        if "T_cam_tcp" in src.root.attrs:
            buf.root.attrs["T_cam_tcp"] = src.root.attrs["T_cam_tcp"]
        if any(k >= 0 for k in steps):
            buf.meta.array(SAMPLE_STEP_KEY, np.asarray(steps, dtype=np.int64), chunks=(RECORD_CHUNK,),
                           compressor=None)
        buf.save(out_path)  # atomic (temporary path, then rename)
    return summary


def subset_variant(variant_path: str | os.PathLike, out_path: str | os.PathLike, n_demos: int, *,
                   progress: bool = True) -> dict[str, Any]:
    """The same variant for the first ``n_demos`` source demos only, from a variant dataset of more demos: every
    episode of those demos copied as stored (no rendering again: a smaller data size shares the larger one's
    episodes, as the study's data sizes do)."""
    with ReplayBuffer.open(variant_path) as b:
        attrs = dict(b.root.attrs.get(VARIANT_ATTR, {}))
    if "variant" not in attrs:
        raise AugmentError(f"{variant_path}: no root attribute '{VARIANT_ATTR}' (not written by write_variant)")
    summary = write_variant("ours", variant_path, out_path, n_demos, progress=progress, label=attrs["variant"])
    return summary | {"subset_of": str(variant_path)}


def _rerendered_episode(buf, src, low: dict[str, np.ndarray], rows: np.ndarray, splice: int, source: int,
                        render_new) -> int:
    """Append source demo ``source`` (export rows ``rows``, low-dim ``low``) again with its frames ``0..splice-1``
    from ``render_new`` at its own camera poses and the gripper of the same frames; returns the frames rendered."""
    path = _camera_path(src, low)
    k = np.arange(splice)
    frames = np.asarray(render_new(source, {"T_world_cam": path["T_world_cam"][k], "overlay_rows": k,
                                            "source": source, "rows": rows, "splice": splice}))
    if frames.shape[0] != splice:
        raise AugmentError(f"write_variant(ours_rerender): render_new gave {frames.shape[0]} frames for demo "
                           f"{source}'s {splice} pre-splice frames")
    record = {"aug_source_episode": source, "aug_mode": RERENDER_MODE_CODE, "aug_id": 0, "aug_seed": 0,
              "aug_attempts": 1, "aug_splice_index": splice, "aug_job": -1}
    _add(buf, src, low, frames, rows[splice:], record)
    return splice


def _spartn_episodes(buf, src, e: int, rows: np.ndarray, splice: int, cfg: SpartnConfig, render_new,
                     summary: dict, steps: list[int]) -> int:
    """Append the SPARTN episodes of source demo ``e`` (rows ``rows`` of ``src``); returns frames rendered. Each is
    ONE training sample, its perturbed step ``To−1`` (appended to ``steps``, ``meta/umi_aug_sample_step``): the
    windows at its other frames would pair unperturbed or mixed observations with a padded, stopping tail."""
    T_cam_tcp = np.asarray(src.root.attrs["T_cam_tcp"], dtype=np.float64)
    low = _lowdim(src, rows)
    path = _camera_path(src, low)
    T_cam, width = path["T_world_cam"], path["gripper_width"]
    To, L = cfg.obs_horizon, cfg.obs_horizon - 1 + cfg.action_horizon
    n_new = 0
    for t in range(To - 1, splice, cfg.stride):
        if t - (To - 1) + L > len(rows):
            break
        for j in range(cfg.per_step):
            delta = spartn_perturbation(cfg, e, t, j)
            k = np.arange(t - (To - 1), t - (To - 1) + L)  # frames of the short episode (demo indices)
            Tp = T_cam[k].copy()
            Tp[:To] = T_cam[k[:To]] @ delta
            ep = make_umi_episode(tcp_poses_from_camera_poses(Tp, T_cam_tcp), width[k])
            ep = {kk: np.asarray(v, dtype=src[kk].dtype).reshape((len(k),) + src[kk].shape[1:])
                  for kk, v in ep.items() if kk != IMAGE_KEY}
            for kk in ("robot0_demo_start_pose", "robot0_demo_end_pose"):  # a piece of the source demo
                if kk in low:
                    ep[kk] = low[kk][k]
            if ACTION_KEY in low:  # commanded targets: the original ones, the perturbed frames' = their poses
                act = low[ACTION_KEY][k].copy()
                act[:To, :3] = ep["robot0_eef_pos"][:To]
                act[:To, 3:6] = ep["robot0_eef_rot_axis_angle"][:To]
                ep[ACTION_KEY] = act
            frames = np.asarray(render_new(e, {"T_world_cam": Tp[:To], "overlay_rows": k[:To], "source": e,
                                               "rows": rows, "splice": splice}))
            record = {"aug_source_episode": e, "aug_mode": 0, "aug_id": -2, "aug_seed": cfg.seed,
                      "aug_attempts": 1, "aug_splice_index": To, "aug_job": -1}
            _add(buf, src, ep, frames, rows[k[To:]], record)
            steps.append(To - 1)
            n_new += To
            summary["episodes"] += 1
            summary["augmented"] += 1
    return n_new
