"""Time parameterisation and splicing: augmented pre-contact segment + original post-contact segment.

1. The optimised waypoints become a C² path ``x(s)``, s ∈ [0, 1] the normalised progress (arc length in the metric
   ‖Δt‖ + rot_scale·|Δθ|): cubic spline in position, ``scipy`` ``RotationSpline`` in rotation.
2. Timing follows the demo's speed profile: the demo's pre-contact progress ``P_d(u)`` (u = normalised time,
   speed Gaussian-smoothed) is reused, ``s(t) = P_d(t / D_a)``, with ``D_a = D_d · Λ_a / Λ_d`` (same speeds as the
   demo; the mean progress speed is clamped to [MIN_MEAN_PROGRESS_SPEED, max_speed]), rounded up to whole frames
   of the demo's frame period. If a speed/acceleration bound is exceeded the
   duration is stretched (×``stretch_factor``, bounded number of times).
3. Velocity continuity at the splice: the remaining mismatch between the augmented end velocity and the demo's
   velocity at the contact frame (linear and angular, central difference) is blended out over the last
   ``blend_duration`` seconds with the cubic Hermite ``h(w) = w³ − w²`` (zero offset at both ends, zero velocity at
   the window start, the exact velocity difference at the splice), applied in position and as a world-frame
   rotation vector.
4. Gripper width before the splice follows the demo's pre-contact width at the same normalised time.

Output frames are uniformly spaced at the demo's median frame period; the splice frame is the demo's contact
frame, bit-exact, and every post-contact frame is the original.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, RotationSpline

from umi_aug.errors import TrajError
from umi_aug.geometry import pose_to_pos_rotvec, tcp_poses_from_camera_poses
from umi_aug.geometry.so3 import _so3_exp, _so3_log
from umi_aug.traj.config import TimingConfig
from umi_aug.traj.constants import MIN_MEAN_PROGRESS_SPEED
from umi_aug.traj.problem import Demonstration, path_progress

__all__ = ["AugmentedEpisode", "TimingResult", "time_and_splice", "frame_kinematics"]


@dataclass
class AugmentedEpisode:
    """One augmented demonstration, ready for rendering (camera poses) and for the UMI replay buffer (actions).

    Attributes:
        timestamps: np.ndarray,  # [N] seconds from 0, uniform at the demo's frame period
        T_world_cam: np.ndarray,  # [N, 4, 4] camera poses (render these)
        T_world_tcp: np.ndarray,  # [N, 4, 4] TCP poses (UMI's fixed camera→TCP offset)
        gripper_width: np.ndarray,  # [N] metres
        actions: np.ndarray,  # [N, 7] UMI action: TCP position (3), rotation vector (3), gripper width (1)
        splice_index: int,  # index of the demo's contact frame in this episode (= number of augmented frames)
        progress: np.ndarray,  # [splice_index + 1] path progress s ∈ [0, 1] of the augmented frames
        source_contact_index: int,  # the demo's contact index
    """

    timestamps: np.ndarray
    T_world_cam: np.ndarray
    T_world_tcp: np.ndarray
    gripper_width: np.ndarray
    actions: np.ndarray
    splice_index: int
    progress: np.ndarray
    source_contact_index: int

    def umi_episode(self, robot: int = 0) -> dict[str, np.ndarray]:
        """The UMI replay-buffer keys of this episode (no images; :func:`umi_aug.data.make_umi_episode`)."""
        from umi_aug.data import make_umi_episode  # lazy, start-up: zarr

        return make_umi_episode(self.T_world_tcp, self.gripper_width, robot=robot)


@dataclass
class TimingResult:
    """Kinematics of the retimed augmented segment (frames 0..splice_index, plus the splice transition).

    Attributes:
        duration_s, max_speed, max_accel, max_ang_speed, max_ang_accel, max_jerk, rms_jerk: floats (SI units)
        splice_velocity_jump: float,  # |Δv| m/s between the last augmented and the first post-contact step
        splice_ang_velocity_jump: float,  # rad/s
        blend_max_offset: float,  # largest position offset of the velocity blend (m)
        stretch_steps: int,  # duration stretches needed for the bounds
        within_bounds: bool
    """

    duration_s: float
    max_speed: float
    max_accel: float
    max_ang_speed: float
    max_ang_accel: float
    max_jerk: float
    rms_jerk: float
    splice_velocity_jump: float
    splice_ang_velocity_jump: float
    blend_max_offset: float
    stretch_steps: int
    within_bounds: bool


def frame_kinematics(T_world_cam: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Finite-difference kinematics of frames ``[N, 4, 4]`` at period ``dt``: linear speed/accel/jerk norms and
    world-frame angular speed/accel norms (arrays of length N−1, N−2, N−3)."""
    t = T_world_cam[:, :3, 3]
    R = T_world_cam[:, :3, :3]
    v = np.diff(t, axis=0) / dt
    w = _so3_log(R[1:] @ np.swapaxes(R[:-1], -1, -2)) / dt if len(R) > 1 else np.zeros((0, 3))
    a = np.diff(v, axis=0) / dt
    j = np.diff(a, axis=0) / dt
    al = np.diff(w, axis=0) / dt
    n = lambda x: np.linalg.norm(x, axis=-1)  # noqa: E731
    return {"v": v, "w": w, "speed": n(v), "accel": n(a), "jerk": n(j), "ang_speed": n(w), "ang_accel": n(al)}


def _demo_profile(demo: Demonstration, cfg: TimingConfig) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(u [c+1] normalised demo times, P [c+1] normalised progress (smoothed speed), D_d seconds, Λ_d metres)."""
    c = demo.contact_index
    pre = demo.pre
    tau = demo.timestamps[: c + 1]
    D = float(tau[-1] - tau[0])
    lam = path_progress(pre, cfg.rot_scale)
    L = float(lam[-1])
    u = (tau - tau[0]) / D
    if L <= 1e-12:
        return u, u.copy(), D, L
    dtau = np.diff(tau)
    speed = np.diff(lam) / dtau  # per interval
    sigma = cfg.speed_smoothing / float(np.median(dtau))
    if sigma > 0:
        speed = gaussian_filter1d(speed, sigma, mode="nearest")
    P = np.concatenate([[0.0], np.cumsum(speed * dtau)])
    return u, P / P[-1], D, L


def _demo_velocity_at_contact(demo: Demonstration) -> tuple[np.ndarray, np.ndarray]:
    """Linear and world angular velocity of the demo at the contact frame (central difference when possible)."""
    c = demo.contact_index
    P, ts = demo.T_world_cam, demo.timestamps
    i0, i1 = c - 1, min(c + 1, len(P) - 1)
    dt = ts[i1] - ts[i0]
    v = (P[i1, :3, 3] - P[i0, :3, 3]) / dt
    w = _so3_log(P[i1, :3, :3] @ P[i0, :3, :3].T) / dt
    return v, w


def _demo_accel_near_contact(demo: Demonstration) -> tuple[float, float]:
    """The demo's own largest linear / angular FD acceleration within ±2 frames of the contact frame, × 1.5."""
    c = demo.contact_index
    lo, hi = max(0, c - 3), min(len(demo.T_world_cam), c + 4)
    if hi - lo < 3:
        return 0.0, 0.0
    kin = frame_kinematics(demo.T_world_cam[lo:hi], demo.frame_dt)
    return 1.5 * float(kin["accel"].max()), 1.5 * float(kin["ang_accel"].max())


def _path(X: np.ndarray, rot_scale: float):
    lam = path_progress(X, rot_scale)
    Lam = float(lam[-1])
    T = X.shape[0]
    s = np.linspace(0.0, 1.0, T) if Lam <= 0 else lam / Lam
    s = (1.0 - 1e-6) * s + 1e-6 * np.linspace(0.0, 1.0, T)  # strictly increasing knots
    pos = CubicSpline(s, X[:, :3, 3], axis=0)
    rot = RotationSpline(s, Rotation.from_matrix(X[:, :3, :3]))
    return pos, rot, Lam


def _sample(pos, rot, s: np.ndarray) -> np.ndarray:
    out = np.zeros((s.size, 4, 4))
    out[:, :3, 3] = pos(s)
    out[:, :3, :3] = rot(s).as_matrix()
    out[:, 3, 3] = 1.0
    return out


def time_and_splice(demo: Demonstration, X: np.ndarray, cfg: TimingConfig) -> tuple[AugmentedEpisode, TimingResult]:
    """Retime optimised waypoints ``X`` [T, 4, 4] (x_init → x_goal = demo pre-contact pose) and splice them onto
    the demo's post-contact frames.

    Raises:
        TrajError: ``X`` does not end at the demo's pre-contact pose.
    """
    c = demo.contact_index
    goal = demo.x_goal
    if not np.allclose(X[-1], goal, atol=1e-12, rtol=0):
        raise TrajError("time_and_splice: the trajectory's last waypoint is not the demo's pre-contact pose")
    dt = demo.frame_dt
    u_d, P_d, D_d, L_d = _demo_profile(demo, cfg)
    v_d, w_d = _demo_velocity_at_contact(demo)
    acc_splice, angacc_splice = _demo_accel_near_contact(demo)
    post = demo.T_world_cam[c:]
    post_t = demo.timestamps[c:] - demo.timestamps[c]
    pos, rot, L_a = _path(X, cfg.rot_scale)
    if L_a <= 1e-9:  # start == goal: nothing to add before the contact frame
        frames = goal[None].copy()
        prog = np.ones(1)
        n = 0
        width_pre = demo.gripper_width[c:c + 1]
        timing = TimingResult(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, True)
    else:
        # same mean progress speed as the demo (D_a = D_d · Λ_a / Λ_d), kept within sane limits: a demo whose
        # pre-contact segment barely moves (e.g. contact right after the start) must not make the augmented
        # segment crawl for minutes
        mean_speed = L_d / D_d if D_d > 0 else 0.0
        D_a = L_a / float(np.clip(mean_speed, MIN_MEAN_PROGRESS_SPEED, cfg.max_speed))
        timing = None
        for stretch in range(cfg.max_stretch_steps + 1):
            n = max(2, int(np.ceil(D_a / dt - 1e-9)))
            u = np.arange(n + 1) / n
            prog = np.interp(u, u_d, P_d)
            prog[0], prog[-1] = 0.0, 1.0
            frames = _sample(pos, rot, prog)
            frames[0], frames[-1] = X[0], goal
            Dn = n * dt
            # end velocity of the timed path (one-sided difference of the continuous path)
            eps = 1e-4
            s_eps = float(np.interp(1.0 - eps, u_d, P_d))
            end_prev = _sample(pos, rot, np.array([s_eps]))[0]
            v_a = (goal[:3, 3] - end_prev[:3, 3]) / (eps * Dn)
            w_a = _so3_log(goal[:3, :3] @ end_prev[:3, :3].T) / (eps * Dn)
            tau_b = min(cfg.blend_duration, 0.5 * Dn)
            tf = np.arange(n + 1) * dt
            wgt = np.clip((tf - (Dn - tau_b)) / tau_b, 0.0, 1.0) if tau_b > 0 else np.zeros(n + 1)
            hb = tau_b * (wgt**3 - wgt**2)  # Hermite h11 · window
            dpos = hb[:, None] * (v_d - v_a)
            drot = hb[:, None] * (w_d - w_a)
            frames[:, :3, 3] += dpos
            frames[:, :3, :3] = _so3_exp(drot) @ frames[:, :3, :3]
            frames[-1] = goal
            blend_off = float(np.linalg.norm(dpos, axis=-1).max())
            # kinematics over the augmented frames and the splice transition into the first post frames
            seq = np.concatenate([frames, post[1:3]])
            kin = frame_kinematics(seq, dt)
            # speed[i]: frames i→i+1 (i < n inside the segment); accel[i]: frames i, i+1, i+2 (i < n−1 inside,
            # i = n−1 across the splice, beyond that the demo's own)
            speed, angs = kin["speed"][:n], kin["ang_speed"][:n]
            acc, angacc = kin["accel"][:n], kin["ang_accel"][:n]
            jerk = kin["jerk"][: max(n - 2, 1)]
            jump_v = float(np.linalg.norm(kin["v"][n] - kin["v"][n - 1])) if len(kin["v"]) > n else 0.0
            jump_w = float(np.linalg.norm(kin["w"][n] - kin["w"][n - 1])) if len(kin["w"]) > n else 0.0
            # at the splice frame itself the acceleration also involves the demo's next frame: it only has to be
            # as smooth as the demo is there
            acc_ok = (np.all(acc[: n - 1] <= cfg.max_accel)
                      and acc[n - 1:].max(initial=0.0) <= max(cfg.max_accel, acc_splice))
            angacc_ok = (np.all(angacc[: n - 1] <= cfg.max_ang_accel)
                         and angacc[n - 1:].max(initial=0.0) <= max(cfg.max_ang_accel, angacc_splice))
            ok = speed.max() <= cfg.max_speed and angs.max() <= cfg.max_ang_speed and acc_ok and angacc_ok
            timing = TimingResult(Dn, float(speed.max()), float(acc.max()), float(angs.max()), float(angacc.max()),
                                  float(jerk.max()) if jerk.size else 0.0,
                                  float(np.sqrt(np.mean(jerk**2))) if jerk.size else 0.0,
                                  jump_v, jump_w, blend_off, stretch, ok)
            if ok:
                break
            ratio = max(speed.max() / cfg.max_speed, angs.max() / cfg.max_ang_speed,
                        np.sqrt(acc.max() / cfg.max_accel), np.sqrt(angacc.max() / cfg.max_ang_accel))
            D_a = Dn * min(max(cfg.stretch_factor, ratio), 2.0)
        u = np.arange(n + 1) / n
        width_pre = np.interp(u * D_d + demo.timestamps[0], demo.timestamps[: c + 1], demo.gripper_width[: c + 1])
    T_cam = np.concatenate([frames[:-1], post]) if n > 0 else post.copy()
    width = np.concatenate([width_pre[:-1], demo.gripper_width[c:]]) if n > 0 else demo.gripper_width[c:].copy()
    ts = np.concatenate([np.arange(n) * dt, n * dt + post_t])
    T_tcp = tcp_poses_from_camera_poses(T_cam)
    p6 = pose_to_pos_rotvec(T_tcp)
    actions = np.concatenate([p6, width[:, None]], axis=1)
    ep = AugmentedEpisode(ts, T_cam, T_tcp, width, actions, n, prog if n > 0 else np.ones(1), c)
    return ep, timing
