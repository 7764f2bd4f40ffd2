"""Contact detection (paper §3.1): split each demo into pre-contact (augmented) and post-contact (replayed).

The gripper is the trajectory stage's collision-sphere model (:func:`umi_aug.geometry.gripper.umi_gripper_spheres`,
camera = TCP axes; fingers placed at each frame's RECORDED width, plus camera body, mount and rail). Per frame the
clearance is ``min_s sdf(c_s) − r_s`` against the scene SDF.

Rules (``rule``):
* ``"proximity"`` (the paper's rule): the contact frame is the first frame whose clearance is below ``threshold``.
* ``"proximity+grasp"`` (default): the proximity frame gates a grasp-onset search: if within ``GRASP_WINDOW_S``
  after it the gripper width drops by more than ``GRASP_CLOSE_DROP_M`` below its running maximum, the contact frame
  is the onset of that closing (walking back while the width still decreases); otherwise (pushing, non-prehensile
  tasks) the proximity frame. Reason: a hand-held approach decelerates smoothly onto the object, so the clearance
  is nearly flat over the last ~10 frames before the fingers close and a pure threshold cannot place the split
  within a couple of frames; the width onset can. Each later approach (the start of a later run of frames below
  ``threshold``) gates the search in turn when an earlier one finds no closing: in a sparse cloud the camera can
  pass a stray point long before it reaches the object (``extra["gating_proximity_index"]`` names the approach
  that found the grasp).
``override`` (a frame index) always wins. Everything is per episode; :func:`detect_contacts` reports all of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal, Sequence

import numpy as np

from umi_aug.errors import ReconError
from umi_aug.geometry.gripper import umi_gripper_spheres
from umi_aug.geometry.sdf import SignedDistanceField, check_sdf_output
from umi_aug.recon import constants as C

__all__ = ["ContactResult", "gripper_clearance", "detect_contact", "detect_contacts"]

ContactRule = Literal["proximity", "proximity+grasp"]


def _default_spheres(width: float):
    return umi_gripper_spheres(float(np.clip(width, 0.0, 0.3)))


@dataclass
class ContactResult:
    """Contact detection of one episode.

    Attributes:
        name: episode name.
        contact_index: int | None, the contact frame: the demo is augmented up to it (it is the pre-contact
            pose the new trajectories funnel into) and replayed from it; None when no contact was found (see
            ``message``).
        proximity_index: int | None, first frame with clearance < threshold.
        grasp_onset_index: int | None, onset of the closing found after proximity.
        clearance: np.ndarray,  # [T] metres, min over spheres of sdf − radius
        closest_sphere: list[str], per frame the name of the sphere of minimum clearance.
        rule: the rule used; overridden: True when ``override`` set the frame.
        message: why no contact was found, or ''.
    """

    name: str
    contact_index: int | None
    proximity_index: int | None
    grasp_onset_index: int | None
    clearance: np.ndarray
    closest_sphere: list[str]
    rule: str
    overridden: bool = False
    message: str = ""
    extra: dict = field(default_factory=dict)


def gripper_clearance(sdf: SignedDistanceField, T_world_cam: np.ndarray, gripper_width: np.ndarray,
                      spheres_fn: Callable[[float], object] | None = None) -> tuple[np.ndarray, list[str]]:
    """Per-frame gripper clearance to the scene.

    Args:
        sdf: scene field (free space positive, metres).
        T_world_cam: np.ndarray,  # [T, 4, 4] camera poses (world, metres)
        gripper_width: np.ndarray,  # [T] finger opening, metres
        spheres_fn: width → sphere set with ``centers_cam [S, 3]``, ``radii [S]``, ``names``; default the
            trajectory stage's UMI gripper model.
    Returns:
        (clearance [T] metres, closest sphere name per frame)
    """
    T = np.asarray(T_world_cam, np.float64)
    w = np.asarray(gripper_width, np.float64).reshape(-1)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(w) != len(T):
        raise ReconError(f"gripper_clearance: T_world_cam {T.shape} and gripper_width {w.shape} must be [T, 4, 4] "
                         f"and [T]")
    if not (np.isfinite(T).all() and np.isfinite(w).all()):
        raise ReconError("gripper_clearance: non-finite poses or widths")
    fn = spheres_fn or _default_spheres
    sets = [fn(x) for x in w]
    S = len(sets[0].radii)
    if any(len(s.radii) != S for s in sets):
        raise ReconError("gripper_clearance: spheres_fn must return the same number of spheres for every width")
    cen = np.stack([s.centers_cam for s in sets])  # [T, S, 3]
    rad = np.stack([s.radii for s in sets])  # [T, S]
    pw = np.einsum("tij,tsj->tsi", T[:, :3, :3], cen) + T[:, None, :3, 3]
    d, g = sdf.distance_and_gradient(pw)
    d, g = np.asarray(d), np.asarray(g)
    check_sdf_output(d, g, pw.shape, "gripper_clearance: scene sdf")
    cl = d - rad
    k = np.argmin(cl, axis=1)
    return cl[np.arange(len(T)), k], [sets[t].names[k[t]] for t in range(len(T))]


def detect_contact(sdf: SignedDistanceField, T_world_cam: np.ndarray, gripper_width: np.ndarray, fps: float,
                   threshold: float = C.CONTACT_THRESHOLD_M, rule: ContactRule = "proximity+grasp",
                   override: int | None = None, name: str = "episode",
                   spheres_fn: Callable[[float], object] | None = None) -> ContactResult:
    """Find the contact frame of one demo (see the module docstring).

    Args:
        sdf: scene field; T_world_cam: [T, 4, 4]; gripper_width: [T] metres; fps: frames per second.
        threshold: clearance below which a sphere touches the scene, metres.
        rule: ``"proximity"`` or ``"proximity+grasp"``.
        override: user-chosen contact frame (validated against the episode length).
    """
    cl, names = gripper_clearance(sdf, T_world_cam, gripper_width, spheres_fn)
    n = len(cl)
    w = np.asarray(gripper_width, np.float64).reshape(-1)
    if rule not in ("proximity", "proximity+grasp"):
        raise ReconError(f"detect_contact: rule must be 'proximity' or 'proximity+grasp', got {rule!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise ReconError(f"detect_contact: fps must be > 0, got {fps!r}")
    below = cl < threshold
    hit = np.flatnonzero(below)
    prox = int(hit[0]) if len(hit) else None
    onset = gate = None
    if prox is not None and rule == "proximity+grasp":
        W = max(1, int(round(C.GRASP_WINDOW_S * fps)))
        # each approach (a run of frames below the threshold) in turn gates the search; the first run may be a pass
        # by (the camera passing a stray point) that ends long before the grasp
        for start in np.flatnonzero(below & ~np.r_[False, below[:-1]]):
            onset = _grasp_onset_after(w, int(start), W)
            if onset is not None:
                gate = int(start)
                break
    res = ContactResult(name, onset if onset is not None else prox, prox, onset, cl, names, rule)
    if gate is not None and gate != prox:
        res.extra["gating_proximity_index"] = gate
    if override is not None:
        o = int(override)
        if not 0 <= o < n:
            raise ReconError(f"detect_contact({name}): override {override} outside the episode's 0..{n - 1}")
        res.contact_index, res.overridden = o, True
    elif prox is None:
        res.message = (f"no frame comes within {threshold * 1000:.0f} mm of the scene (min clearance "
                       f"{cl.min() * 1000:.0f} mm at frame {int(np.argmin(cl))}); raise the threshold, check the "
                       f"reconstruction's alignment, or pass override=<frame>")
    return res


def _grasp_onset_after(w: np.ndarray, prox: int, window: int) -> int | None:
    """Onset of the first closing within ``window`` frames after frame ``prox`` (widths ``w`` [T] metres; the
    running maximum starts ``window`` frames before ``prox``), or None."""
    n = len(w)
    a = max(0, prox - window)
    seg = w[a:min(n, prox + window + 1)]
    run_max = np.maximum.accumulate(seg)
    drop = np.flatnonzero((seg < run_max - C.GRASP_CLOSE_DROP_M) & (np.arange(len(seg)) + a >= prox))
    if not len(drop):
        return None
    g = int(drop[0]) + a
    while g > a and w[g - 1] > w[g] + C.GRASP_ONSET_TOL_M:
        g -= 1
    return min(g + 1, n - 1)  # the first frame whose width is below the one before: closing starts


def detect_contacts(sdf: SignedDistanceField, episodes: Sequence[tuple[str, np.ndarray, np.ndarray, float]],
                    overrides: dict[str, int] | None = None, **kwargs) -> list[ContactResult]:
    """:func:`detect_contact` for every ``(name, T_world_cam, gripper_width, fps)``; ``overrides`` maps episode
    names to user-chosen contact frames."""
    overrides = overrides or {}
    return [detect_contact(sdf, T, w, fps, override=overrides.get(nm), name=nm, **kwargs)
            for nm, T, w, fps in episodes]
