"""Can the simulated Panda execute a wrist-camera trajectory? And what would its wrist camera see doing so?

An augmented square episode is a new wrist-camera trajectory ``T_world_cam`` [N, 4, 4] (20 Hz, OpenCV camera
axes, metres): new frames from a start pose into the demo's pre-grasp pose, then, from the splice index ``upto``
on, the demo's own motion. :func:`check_panda_path` restores the demo's initial state (objects, arm), turns every
camera pose into a grip-site target with the state's fixed camera→site transform, and tracks the targets by
damped-least-squares IK (:meth:`~umi_aug.square.ik.PandaIK.refine`), each frame warm-started from the previous
frame's joints after a small bounded null-space step of the elbow towards the Panda's rest posture (robosuite's OSC
controller does the same while recording the demos; without it the IK's elbow drifts and, near the stretched-arm
poses of the insertion, swings faster than the joints may). Frame 0 starts from the state's arm joints, with seeded
restarts, and keeps a solution well inside the joint limits. Per frame it checks

- the IK residual (position / rotation) against :class:`FeasibilityConfig`'s tolerances;
- the joint limits: before ``upto`` with a margin inside them; from ``upto`` on (the demo's replayed motion) the
  slack MuJoCo's soft limits allowed the demo itself (the recorded demos go up to 9 mrad past joint 4's limit);
- the joint step to the previous frame against the Panda's velocity limits × dt (:data:`PANDA_VEL_LIMITS_RAD_S`:
  2.175 rad/s joints 1–4, 2.61 rad/s joints 5–7, Franka datasheet; dt = 1 / 20 s);
- before ``upto`` only: no robot self-collision and no robot contact with the table, pegs or nut deeper than
  ``max_penetration_m`` (after the splice the gripper grasps the nut: contact is expected);

with the fingers at the given widths. Repair: a frame failing from the warm start is retried from the previous
joints without the posture step, with a null-space pull towards mid-range joints, and from seeded perturbations
of the warm start; the first candidate passing every check is kept. Deterministic (restart seeds are derived
from ``cfg.seed`` and the frame index).

:func:`render_gt_frames` renders the simulator's ground-truth wrist images of such a path (the study's
``gt_render`` oracle). Neither function changes ``env``'s simulation state: both work on private ``MjData``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import SimError
from umi_aug.geometry import pose_inverse, so3_log
from umi_aug.sim.gl import import_mujoco
from umi_aug.square.camera import camera_pose_cv
from umi_aug.square.env import CONTROL_FREQ_HZ, GRIP_SITE, SquareEnv
from umi_aug.square.ik import PandaIK

__all__ = ["PANDA_VEL_LIMITS_RAD_S", "FeasibilityConfig", "PathFeasibility", "check_panda_path",
           "render_gt_frames", "state_qpos"]

#: Joint velocity limits of the Franka Emika Panda (datasheet), rad/s, joints 1…7.
PANDA_VEL_LIMITS_RAD_S: np.ndarray = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
PANDA_VEL_LIMITS_RAD_S.setflags(write=False)


@dataclass(frozen=True)
class FeasibilityConfig:
    """Tolerances of :func:`check_panda_path` (metres, radians, seconds).

    Attributes:
        pos_tol_m, rot_tol_rad: largest accepted IK residual (grip-site position; geodesic rotation).
        limit_margin_rad: joints stay this far inside their limits before the splice.
        post_splice_limit_slack_rad: how far past a limit a joint may go from the splice on (the demo's own motion;
            MuJoCo's limits are soft and the recorded demos reach 9 mrad past joint 4's).
        speed_scale: fraction of :data:`PANDA_VEL_LIMITS_RAD_S` allowed before the splice; fps: frame rate (Hz).
        post_splice_speed_scale: the same from the splice on (the demo's replayed motion). The 55 recorded demos
            reach 0.97 of the limit in their own joints and 0.92 re-solved by this IK (with the posture step;
            1.48 without it); arriving at the splice with another elbow position can need more (1.15 seen).
        max_penetration_m: a robot contact deeper than this is a collision; self_collision: check robot–robot too.
        first_restarts, first_restart_std: frame 0's extra IK starts, N(0, std²) rad around the state's arm joints.
        first_frame_margin_rad: frame 0 keeps the first solution this far inside every joint limit, else the
            solution farthest inside (a start pinned at a limit, e.g. a flipped wrist, cannot move on).
        repair_restarts, repair_std: the same for a later frame failing from its warm start.
        null_gain: null-space pull towards mid-range joints of the repair attempt (fraction per iteration).
        posture_gain: per-frame null-space step towards the robot's rest joints (robosuite ``init_qpos``), as a
            fraction of the distance; posture_step_frac: that step's cap as a fraction of a frame's speed limit.
        seed: seed of the restart perturbations.
        stop_at_first_failure: stop at the first infeasible frame (False: go on, for diagnostics).
    """

    pos_tol_m: float = 1e-3
    rot_tol_rad: float = math.radians(0.5)
    limit_margin_rad: float = 0.02
    post_splice_limit_slack_rad: float = 0.015
    speed_scale: float = 1.0
    post_splice_speed_scale: float = 1.0
    fps: float = float(CONTROL_FREQ_HZ)
    max_penetration_m: float = 1e-3
    self_collision: bool = True
    first_restarts: int = 8
    first_restart_std: float = 0.3
    repair_restarts: int = 4
    repair_std: float = 0.05
    null_gain: float = 0.3
    first_frame_margin_rad: float = 0.2
    posture_gain: float = 0.1
    posture_step_frac: float = 0.25
    seed: int = 0
    stop_at_first_failure: bool = True


@dataclass
class PathFeasibility:
    """Result of :func:`check_panda_path` for a path of N frames.

    Attributes:
        ok: every frame passed.
        reason: None, or the first failure naming the frame and the check (``"frame 12: ..."``).
        q: float64 [N, 7] arm joints, rad (NaN where not solved).
        pos_err_m, rot_err_rad: float64 [N] IK residuals, metres / radians (NaN where not solved).
        min_limit_margin_rad: smallest distance of a solved joint to its limit (negative: past it).
        max_joint_speed_rad_s: largest |Δq| · fps between consecutive solved frames.
        max_speed_ratio: the same as a fraction of the joint's velocity limit (above ``speed_scale`` /
            ``post_splice_speed_scale`` fails).
        collision_frames: frames (< upto) whose configuration collides.
        repaired_frames: frames that needed a repair attempt (passed or not).
        upto: the splice index used; seconds: wall time of the check.
    """

    ok: bool
    reason: str | None
    q: np.ndarray
    pos_err_m: np.ndarray
    rot_err_rad: np.ndarray
    min_limit_margin_rad: float
    max_joint_speed_rad_s: float
    max_speed_ratio: float = 0.0
    collision_frames: list[int] = field(default_factory=list)
    repaired_frames: list[int] = field(default_factory=list)
    upto: int = 0
    seconds: float = 0.0


# ---------------------------------------------------------------------------------------------------- helpers
_IK_CACHE: dict[int, tuple[object, PandaIK]] = {}


def _ik(env: SquareEnv) -> PandaIK:
    """One :class:`PandaIK` per MuJoCo model (the entry keeps the model alive, so its id is not reused)."""
    model = env.model
    hit = _IK_CACHE.get(id(model))
    if hit is None or hit[0] is not model:
        hit = _IK_CACHE[id(model)] = (model, PandaIK(model, GRIP_SITE))
    return hit[1]


def state_qpos(env: SquareEnv, state: np.ndarray, who: str = "state0") -> np.ndarray:
    """``qpos`` [nq] of a flattened robosuite state ``[time, qpos (nq), qvel (nv)]`` (robomimic ``states`` row)."""
    m = env.model
    s = np.asarray(state, dtype=np.float64)
    if s.shape != (1 + m.nq + m.nv,) or not np.all(np.isfinite(s)):
        raise SimError(f"{who}: expected a finite flattened state of {1 + m.nq + m.nv} values "
                       f"(time, qpos[{m.nq}], qvel[{m.nv}]), got shape {s.shape}")
    return s[1:1 + m.nq].copy()


class _Fingers:
    """qpos addresses and ranges of the two Panda finger joints; width → ``[w/2, −w/2]``."""

    def __init__(self, env: SquareEnv) -> None:
        m = env.model
        self.adr = np.asarray(env.rs.robots[0]._ref_gripper_joint_pos_indexes, dtype=int)
        jids = [int(np.flatnonzero(m.jnt_qposadr == a)[0]) for a in self.adr]
        self.lo = np.array([m.jnt_range[j][0] for j in jids])
        self.hi = np.array([m.jnt_range[j][1] for j in jids])

    def set(self, data, width: float) -> None:
        data.qpos[self.adr] = np.clip([0.5 * width, -0.5 * width], self.lo, self.hi)


def _scratch(env: SquareEnv, qpos: np.ndarray):
    mj = import_mujoco()
    d = mj.MjData(env.model)
    d.qpos[:] = qpos
    mj.mj_forward(env.model, d)
    return d


def _poses(T_world_cam: np.ndarray, gripper_width: np.ndarray, who: str) -> tuple[np.ndarray, np.ndarray]:
    T = np.asarray(T_world_cam, dtype=np.float64)
    w = np.asarray(gripper_width, dtype=np.float64).reshape(-1)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0 or not np.all(np.isfinite(T)):
        raise SimError(f"{who}: T_world_cam must be a finite [N>=1, 4, 4] array, got shape {T.shape}")
    if w.shape != (len(T),) or not np.all(np.isfinite(w)):
        raise SimError(f"{who}: gripper_width must be finite [N={len(T)}], got shape {np.shape(gripper_width)}")
    return T, w


def _rot_err(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.linalg.norm(so3_log(R_a @ R_b.T)))


# ---------------------------------------------------------------------------------------------------- check
def check_panda_path(env: SquareEnv, state0: np.ndarray, T_world_cam: np.ndarray, gripper_width: np.ndarray, *,
                     upto: int | None = None, cfg: FeasibilityConfig | None = None,
                     scene_state: np.ndarray | None = None) -> PathFeasibility:
    """Check that the simulated Panda can move its wrist camera along ``T_world_cam`` (see the module docstring).

    Args:
        env: a :class:`SquareEnv` (images not needed); its own state is not changed.
        state0: float64 [S] flattened initial state of the demo (objects, arm joints at frame 0's warm start).
        T_world_cam: np.ndarray,  # [N, 4, 4] wrist camera poses, OpenCV axes, metres, at ``cfg.fps``
        gripper_width: np.ndarray,  # [N] finger separation, metres
        upto: splice index: contacts are checked in frames [0, upto) only, the joint-limit margin applies there
            (None: N, the whole path is new).
        cfg: tolerances (default :class:`FeasibilityConfig`).
        scene_state: float64 [S] flattened state whose objects (everything but the arm joints and fingers) the
            contacts are checked against; default ``state0``. A reset drops the nut from 6 cm above the table and
            it settles during the first ~4 frames, so a demo's raw ``states[0]`` has it floating where the approach
            passes: pass the demo's state at the splice frame here (or a ``state0`` with settled objects).
    Returns:
        :class:`PathFeasibility`.
    """
    t_start = time.perf_counter()
    cfg = cfg or FeasibilityConfig()
    T, w = _poses(T_world_cam, gripper_width, "check_panda_path")
    n = len(T)
    upto = n if upto is None else int(upto)
    if not 0 <= upto <= n:
        raise SimError(f"check_panda_path: upto={upto} outside [0, N={n}]")
    m = env.model
    ik, fingers = _ik(env), _Fingers(env)
    qpos0 = state_qpos(env, state0)
    src = _scratch(env, qpos0)
    T_cam_site = pose_inverse(camera_pose_cv(m, src)) @ ik.site_pose(src.qpos[ik.qadr], src)
    q_prev = np.asarray(src.qpos[ik.qadr], dtype=np.float64).copy()
    if scene_state is not None:
        src = _scratch(env, state_qpos(env, scene_state, "scene_state"))
    targets = T @ T_cam_site
    step_pre = cfg.speed_scale * PANDA_VEL_LIMITS_RAD_S / cfg.fps
    step_post = cfg.post_splice_speed_scale * PANDA_VEL_LIMITS_RAD_S / cfg.fps
    mid = 0.5 * (ik.lo + ik.hi)
    posture = np.asarray(env.rs.robots[0].init_qpos, dtype=np.float64)

    q = np.full((n, 7), np.nan)
    pe_all, re_all = np.full(n, np.nan), np.full(n, np.nan)
    collision_frames: list[int] = []
    repaired: list[int] = []
    reason: str | None = None
    have_prev = False  # frame 0 (and frames after an unsolved one) have no speed constraint
    for t in range(n):
        fingers.set(src, w[t])
        pre = t < upto
        if pre:
            lo, hi = ik.lo + cfg.limit_margin_rad, ik.hi - cfg.limit_margin_rad
        else:
            lo, hi = ik.lo - cfg.post_splice_limit_slack_rad, ik.hi + cfg.post_splice_limit_slack_rad
        rng = np.random.default_rng([int(cfg.seed), t])
        restarts, std = (cfg.first_restarts, cfg.first_restart_std) if t == 0 else \
            (cfg.repair_restarts, cfg.repair_std)
        starts = [(q_prev, 0.0), (q_prev, cfg.null_gain)] + \
            [(np.clip(q_prev + rng.normal(0.0, std, 7), lo, hi), 0.0) for _ in range(restarts)]
        if cfg.posture_gain > 0.0 and have_prev:
            starts.insert(0, (ik.posture_step(src, q_prev, posture, cfg.posture_gain,
                                              cfg.posture_step_frac * step_pre), 0.0))
        best, best_key = None, None  # (severity, message, q, pe, re, collided); its ranking
        for k, (start, gain) in enumerate(starts):
            qc, pe, re, _ = ik.refine(src, targets[t], start, lo=lo, hi=hi, q_rest=mid, null_gain=gain)
            sev, msg, collided = _frame_failure(ik, src, qc, pe, re, q_prev if have_prev else None, lo, hi,
                                                step_pre if pre else step_post, cfg, pre)
            margin = float(np.min(np.minimum(qc - ik.lo, ik.hi - qc)))
            key = (sev, -margin if sev < 0 else 0.0)
            if best is None or key < best_key:
                best, best_key = (sev, msg, qc, pe, re, collided), key
            # a start (no previous joints): the first solution well inside the limits, else the one farthest in
            if sev < 0 and (have_prev or margin >= cfg.first_frame_margin_rad):
                break
        if k > 0:
            repaired.append(t)
        sev, msg, qc, pe, re, collided = best
        if collided:
            collision_frames.append(t)
        if sev >= 0 and reason is None:
            reason = f"frame {t}: {msg}"
        if sev < _SEV_IK:  # solved (maybe failing a later check): keep it, track on from it
            q[t], pe_all[t], re_all[t] = qc, pe, re
            q_prev, have_prev = qc, True
        else:
            have_prev = False
        if reason is not None and cfg.stop_at_first_failure:
            break

    solved = ~np.isnan(q[:, 0])
    margins = np.minimum(q[solved] - ik.lo, ik.hi - q[solved])
    both = solved[1:] & solved[:-1]
    steps = np.abs(np.diff(q, axis=0))[both]
    return PathFeasibility(
        ok=reason is None, reason=reason, q=q, pos_err_m=pe_all, rot_err_rad=re_all,
        min_limit_margin_rad=float(margins.min()) if margins.size else float("nan"),
        max_joint_speed_rad_s=float(steps.max() * cfg.fps) if steps.size else 0.0,
        max_speed_ratio=float((steps * cfg.fps / PANDA_VEL_LIMITS_RAD_S).max()) if steps.size else 0.0,
        collision_frames=collision_frames, repaired_frames=repaired, upto=upto,
        seconds=time.perf_counter() - t_start)


#: failure severities of one frame's candidate (lower = closer to feasible; −1 = feasible)
_SEV_COLLISION, _SEV_SPEED, _SEV_LIMIT, _SEV_IK = 0, 1, 2, 3


def _frame_failure(ik: PandaIK, src, q: np.ndarray, pe: float, re: float, q_prev: np.ndarray | None,
                   lo: np.ndarray, hi: np.ndarray, step_max: np.ndarray, cfg: FeasibilityConfig,
                   pre: bool) -> tuple[int, str, bool]:
    """(severity, what failed, collided) of one candidate configuration; severity −1 = it passes."""
    if not (pe <= cfg.pos_tol_m and re <= cfg.rot_tol_rad):
        held = np.flatnonzero((q <= lo + 1e-9) | (q >= hi - 1e-9)) + 1
        why = f"; joint(s) {', '.join(map(str, held))} held at the limit bound" if held.size else ""
        return (_SEV_IK, f"no IK solution: residual {pe * 1e3:.2f} mm / {math.degrees(re):.3f}° > tolerance "
                f"{cfg.pos_tol_m * 1e3:.2f} mm / {math.degrees(cfg.rot_tol_rad):.3f}°{why}", False)
    bad = np.flatnonzero((q < lo - 1e-9) | (q > hi + 1e-9))
    if bad.size:  # refine clips into [lo, hi]; kept as a guard
        j = int(bad[0])
        return _SEV_LIMIT, f"joint {j + 1} = {q[j]:.4f} rad outside [{lo[j]:.4f}, {hi[j]:.4f}]", False
    if q_prev is not None:
        ratio = np.abs(q - q_prev) / step_max
        j = int(np.argmax(ratio))
        if ratio[j] > 1.0:
            return (_SEV_SPEED, f"joint {j + 1} moves {abs(q[j] - q_prev[j]):.4f} rad in one frame "
                    f"({abs(q[j] - q_prev[j]) * cfg.fps:.3f} rad/s > limit "
                    f"{step_max[j] * cfg.fps:.3f} rad/s)", False)
    if pre:
        hits = ik.contacts(src, q, cfg.max_penetration_m, cfg.self_collision)
        if hits:
            g1, g2, dist = min(hits, key=lambda h: h[2])
            return (_SEV_COLLISION, f"collision {g1}/{g2} ({-dist * 1e3:.2f} mm deep; "
                    f"{len(hits)} contact(s) deeper than {cfg.max_penetration_m * 1e3:.2f} mm)", True)
    return -1, "", False


# ---------------------------------------------------------------------------------------------------- render
def render_gt_frames(env: SquareEnv, state0: np.ndarray, q: np.ndarray, gripper_width: np.ndarray,
                     T_world_cam: np.ndarray | None, frame_indices, *,
                     cfg: FeasibilityConfig | None = None) -> np.ndarray:
    """The simulator's ground-truth wrist images of a checked path (the ``gt_render`` oracle).

    For each requested frame the arm is put at ``q[i]``, the fingers at ``gripper_width[i]``, everything else at
    ``state0``, and the scene is rendered by ``env``'s fisheye camera from the camera pose the arm reaches.
    Objects come from ``state0``: pass the demo's state at the splice frame for new frames (a reset drops the nut,
    which settles during the first ~4 frames) and the demo's own states for frames after a grasp (one per frame).
    robosuite's visualisation sites are hidden first, as its ``reset`` does (the recorded demos do not show them).

    Args:
        env: a :class:`SquareEnv` with ``image_size`` set; its own state is not changed.
        state0: float64 [S] flattened state, or [K, S]: one per requested frame.
        q: np.ndarray,  # [N, 7] arm joints, rad (e.g. :attr:`PathFeasibility.q`)
        gripper_width: np.ndarray,  # [N] metres
        T_world_cam: np.ndarray,  # [N, 4, 4] requested camera poses (OpenCV, metres); None: not checked
        frame_indices: the K frames to render (indices into N).
        cfg: tolerances of the camera-pose check (default :class:`FeasibilityConfig`).
    Returns:
        rgb: np.ndarray,  # [K, S, S, 3] uint8, S = env.image_size
    Raises:
        SimError: a frame without a solution (NaN joints), or a reached camera pose off the requested one by more
            than the IK tolerance.
    """
    cfg = cfg or FeasibilityConfig()
    if env.image_size is None:
        raise SimError("render_gt_frames: the SquareEnv was created with image_size=None (no camera)")
    q = np.asarray(q, dtype=np.float64)
    n = len(q)
    if q.ndim != 2 or q.shape[1] != 7:
        raise SimError(f"render_gt_frames: q must be [N, 7], got shape {q.shape}")
    w = np.asarray(gripper_width, dtype=np.float64).reshape(-1)
    if w.shape != (n,):
        raise SimError(f"render_gt_frames: gripper_width must be [N={n}], got shape {np.shape(gripper_width)}")
    if T_world_cam is not None:
        T_req, _ = _poses(T_world_cam, w, "render_gt_frames")
    idx = np.asarray(frame_indices, dtype=int).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise SimError(f"render_gt_frames: frame_indices outside [0, {n - 1}]: {idx.tolist()}")
    s0 = np.asarray(state0, dtype=np.float64)
    rows = [s0] * len(idx) if s0.ndim == 1 else list(s0)
    if len(rows) != len(idx):
        raise SimError(f"render_gt_frames: state0 holds {len(rows)} states for {len(idx)} frames")
    mj, m = import_mujoco(), env.model
    ik, fingers = _ik(env), _Fingers(env)
    # robosuite hides its visualisation sites (grip-site markers …) in reset(); a fresh env still shows them
    env.rs.visualize(vis_settings={v: False for v in env.rs._visualizations})
    d = mj.MjData(m)
    out = np.zeros((len(idx), env.image_size, env.image_size, 3), dtype=np.uint8)
    for k, i in enumerate(idx):
        if not np.all(np.isfinite(q[i])):
            raise SimError(f"render_gt_frames: frame {i} has no joint solution (NaN in q)")
        d.qpos[:] = state_qpos(env, rows[k])
        d.qpos[ik.qadr] = q[i]
        fingers.set(d, w[i])
        mj.mj_forward(m, d)
        T_cam = camera_pose_cv(m, d)
        if T_world_cam is not None:
            dp = float(np.linalg.norm(T_cam[:3, 3] - T_req[i][:3, 3]))
            dr = _rot_err(T_cam[:3, :3], T_req[i][:3, :3])
            if dp > cfg.pos_tol_m or dr > cfg.rot_tol_rad:
                raise SimError(f"render_gt_frames: frame {i}: the arm's camera is {dp * 1e3:.2f} mm / "
                               f"{math.degrees(dr):.3f}° from the requested pose (tolerance "
                               f"{cfg.pos_tol_m * 1e3:.2f} mm / {math.degrees(cfg.rot_tol_rad):.3f}°)")
        out[k] = env.camera.render(d, T_cam)
    return out
