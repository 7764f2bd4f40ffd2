"""Which episodes of a plain UMI dataset were recorded in one place, from the data alone (issue #34 item 2).

UMI's camera poses are in each session's table-tag frame, so episodes of one session share a frame, but a dataset
merged from several sessions (several places) holds no session id, and every session's tag frame looks alike
(the tag lies on the table beside the objects, so the demos' poses overlap whichever place they come from).
Evidence that two episodes are of one place must therefore combine both: frames of the two episodes taken from
nearby poses (in the tag frame) are compared, and their SIFT matches are kept only where they agree with the
relative pose the two frames have *if both poses are in one frame*: the matched rays must lie on a common
epipolar plane (within ``EPIPOLAR_TOL_DEG``). Episodes of one place give tens of such matches per frame pair;
for episodes of different places, the few SIFT matches there are (repeated texture) are placed at random relative
to the wrong epipolar geometry and almost none survive. No frame pair at nearby poses: no evidence, so separate
scenes (today's per-episode default).

Grouping (:func:`group_by_place`) walks the episodes in order (UMI stores a session's episodes together) and
puts each into the most recent of the last ``window`` groups whose last episode it matches, up to ``max_group``
episodes per scene (a pooled scene's triangulation and 3DGS grow with its frames), else starts a group.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import cv2
import numpy as np

from umi_aug.camera.kb import unproject
from umi_aug.errors import AugmentError
from umi_aug.geometry.so3 import so3_log

__all__ = ["PlaceEvidence", "nearby_frame_pairs", "epipolar_inliers", "compare_episodes", "group_by_place"]

#: frame pairs compared per episode pair (evenly spaced over the first episode's pre-grasp frames)
FRAME_PAIRS = 6
#: a frame pair's poses: at most this far apart (m, degrees) and at least this baseline (m; the epipolar test needs
#: one)
MAX_PAIR_DISTANCE_M, MAX_PAIR_ANGLE_DEG, MIN_PAIR_BASELINE_M = 0.15, 25.0, 0.01
#: angle of a matched ray to the epipolar plane of the known relative pose (degrees) for an inlier
EPIPOLAR_TOL_DEG = 1.0
#: SIFT features per frame and Lowe's ratio
SIFT_FEATURES, RATIO = 600, 0.8
#: one place: the median frame pair has at least this many epipolar inliers, and this fraction of its matches
#: (texture alike but geometry not, e.g. the same room under another tag frame, gives many matches but few inliers)
MIN_INLIERS, MIN_INLIER_FRACTION = 15, 0.5


@dataclass(frozen=True)
class PlaceEvidence:
    """The comparison of two episodes.

    Attributes:
        episode_a, episode_b: the episodes (dataset indices).
        frame_pairs: ``(frame of a, frame of b)`` compared (poses nearby in the shared tag frame).
        matches: SIFT matches (ratio test) per frame pair.
        inliers: of those, the ones on the epipolar plane of the two poses, per frame pair.
        same_place: at least two frame pairs, and the median inlier count and fraction reach ``MIN_INLIERS``
            and ``MIN_INLIER_FRACTION``.
    """

    episode_a: int
    episode_b: int
    frame_pairs: tuple[tuple[int, int], ...]
    matches: tuple[int, ...]
    inliers: tuple[int, ...]
    same_place: bool

    @property
    def median_inliers(self) -> float:
        return float(np.median(self.inliers)) if self.inliers else 0.0

    @property
    def median_inlier_fraction(self) -> float:
        f = [i / m for i, m in zip(self.inliers, self.matches) if m > 0]
        return float(np.median(f)) if f else 0.0


def nearby_frame_pairs(T_a: np.ndarray, T_b: np.ndarray, n: int = FRAME_PAIRS,
                       max_distance_m: float = MAX_PAIR_DISTANCE_M, max_angle_deg: float = MAX_PAIR_ANGLE_DEG,
                       min_baseline_m: float = MIN_PAIR_BASELINE_M) -> list[tuple[int, int]]:
    """Up to ``n`` frame pairs ``(i, j)``: ``i`` evenly spaced over ``T_a`` ``[N, 4, 4]``, ``j`` the frame of
    ``T_b`` ``[M, 4, 4]`` nearest to it among those within the distance/angle limits and beyond the baseline
    (camera poses, world = tag frame, metres)."""
    out = []
    if len(T_a) == 0 or len(T_b) == 0:
        return out
    for i in np.unique(np.linspace(0, len(T_a) - 1, n).round().astype(int)):
        d = np.linalg.norm(T_b[:, :3, 3] - T_a[i, :3, 3], axis=1)
        ang = np.degrees(np.linalg.norm(so3_log(np.swapaxes(T_b[:, :3, :3], 1, 2) @ T_a[i, :3, :3]), axis=-1))
        ok = np.flatnonzero((d <= max_distance_m) & (d >= min_baseline_m) & (ang <= max_angle_deg))
        if len(ok):
            out.append((int(i), int(ok[np.argmin(d[ok])])))
    return out


def epipolar_inliers(rays_a: np.ndarray, rays_b: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray,
                     tol_deg: float = EPIPOLAR_TOL_DEG) -> np.ndarray:
    """``[K]`` bool: matched unit rays (camera frames, ``[K, 3]`` each) that lie within ``tol_deg`` of the
    epipolar plane spanned by the baseline and ray a, given both camera poses in one frame."""
    T_ab = np.linalg.inv(T_world_a) @ T_world_b
    t = T_ab[:3, 3]
    rb = rays_b @ T_ab[:3, :3].T  # ray b in camera a
    n = np.cross(t, rb)  # normal of the plane through both centres and ray b
    norm = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.abs(np.einsum("ij,ij->i", rays_a, n)) / norm
    return (norm > 1e-12) & (s <= math.sin(math.radians(tol_deg)))


def _epipolar_inliers_reference(rays_a: np.ndarray, rays_b: np.ndarray, T_world_a: np.ndarray,
                                T_world_b: np.ndarray, tol_deg: float = EPIPOLAR_TOL_DEG) -> np.ndarray:
    """Slow reference of :func:`epipolar_inliers`, one match at a time in the world frame: the angle between ray a
    and the plane through both camera centres that contains ray b."""
    out = np.zeros(len(rays_a), bool)
    ca, cb = T_world_a[:3, 3], T_world_b[:3, 3]
    for k, (ra, rb) in enumerate(zip(rays_a, rays_b)):
        da, db = T_world_a[:3, :3] @ ra, T_world_b[:3, :3] @ rb
        normal = np.cross(cb - ca, db)
        if np.linalg.norm(normal) <= 1e-12:
            continue
        normal = normal / np.linalg.norm(normal)
        angle = math.degrees(math.asin(min(1.0, abs(float(normal @ da)) / np.linalg.norm(da))))
        out[k] = angle <= tol_deg
    return out


class _Features:
    """SIFT keypoints (as unit rays) and descriptors of dataset frames, computed once per frame."""

    def __init__(self, read_frame: Callable[[int, int], np.ndarray], intr, mask: np.ndarray):
        self.read_frame, self.intr, self.mask = read_frame, intr, mask
        self.sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES)
        self.cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}

    def __call__(self, episode: int, frame: int):
        key = (int(episode), int(frame))
        if key not in self.cache:
            gray = cv2.cvtColor(self.read_frame(*key), cv2.COLOR_RGB2GRAY)
            kps, desc = self.sift.detectAndCompute(gray, self.mask)
            uv = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
            rays, ok = unproject(uv, self.intr) if len(uv) else (np.zeros((0, 3)), np.zeros(0, bool))
            self.cache[key] = (rays[ok], None if desc is None else desc[ok])
        return self.cache[key]


def compare_episodes(a: int, b: int, T_a: np.ndarray, T_b: np.ndarray, features: Callable) -> PlaceEvidence:
    """:class:`PlaceEvidence` of episodes ``a`` and ``b`` from their pre-grasp camera poses ``T_a``/``T_b``
    ``[N, 4, 4]`` and ``features(episode, frame) -> (rays [K, 3], descriptors [K, 128])``."""
    pairs = nearby_frame_pairs(T_a, T_b)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    matches, inliers = [], []
    for i, j in pairs:
        ra, da = features(a, i)
        rb, db = features(b, j)
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            matches.append(0)
            inliers.append(0)
            continue
        good = [m[0] for m in matcher.knnMatch(da, db, k=2) if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
        ia = np.array([m.queryIdx for m in good], int)
        ib = np.array([m.trainIdx for m in good], int)
        matches.append(len(good))
        inliers.append(int(epipolar_inliers(ra[ia], rb[ib], T_a[i], T_b[j]).sum()) if len(good) else 0)
    ev = PlaceEvidence(int(a), int(b), tuple(pairs), tuple(matches), tuple(inliers), False)
    same = len(pairs) >= 2 and ev.median_inliers >= MIN_INLIERS and ev.median_inlier_fraction >= MIN_INLIER_FRACTION
    return dataclasses.replace(ev, same_place=bool(same))


def group_by_place(episodes: Sequence[int], T_world_cam: Mapping[int, np.ndarray],
                   read_frame: Callable[[int, int], np.ndarray], intr, mask: np.ndarray, max_group: int = 4,
                   window: int = 3, progress: bool = False) -> tuple[dict[str, list[int]], list[PlaceEvidence]]:
    """Scene groups ``{"place<first episode>": [episode, ...]}`` of ``episodes`` (see the module docstring) and the
    evidence of every comparison made.

    Args:
        episodes: dataset episode indices, in dataset order.
        T_world_cam: per episode its pre-grasp camera poses ``[N, 4, 4]`` (tag frame, metres).
        read_frame: ``(episode, frame) -> [S, S, 3] uint8`` RGB policy frame.
        intr: the frames' fisheye intrinsics; mask: ``[S, S]`` uint8 feature mask (255 = use).
        max_group: at most this many episodes per scene (>= 1); window: groups to try per episode (>= 1).
    """
    from tqdm import tqdm  # lazy, start-up: tqdm

    if max_group < 1 or window < 1:
        raise AugmentError(f"group_by_place: max_group {max_group} and window {window} must be >= 1")
    features = _Features(read_frame, intr, mask)
    groups: list[list[int]] = []
    evidence: list[PlaceEvidence] = []
    for e in tqdm(list(episodes), desc="grouping episodes by place", unit="episode", disable=not progress):
        home = None
        for g in reversed(groups[-window:]):
            if len(g) >= max_group:
                continue
            ev = compare_episodes(g[-1], e, T_world_cam[g[-1]], T_world_cam[e], features)
            evidence.append(ev)
            if ev.same_place:
                home = g
                break
        if home is None:
            groups.append([int(e)])
        else:
            home.append(int(e))
    return {f"place{g[0]:06d}": g for g in groups}, evidence

