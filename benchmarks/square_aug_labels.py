"""Do an augmented square episode's action labels drive the simulated Panda through the task? (issue #29 part 4's
check before the study's numbers are read: the augmented analogue of the replay oracle, eval/README (e).)

Run: ``MUJOCO_GL=egl python benchmarks/square_aug_labels.py --export AUG.zarr.zip --demos square_demos``
(``AUG`` from ``umi-aug augment square_demos -n 1 --episodes 0:20 --out AUG.zarr.zip``).

Every augmented episode of the export (``meta/aug_id >= 0``) starts where it was planned: the source demo's first
simulator state (nut, pegs, fingers), the arm placed by IK (:class:`umi_aug.square.ik.PandaIK`) so that the grip
site is at the episode's first TCP pose. Its ``action`` rows — the commanded targets the policy learns
(:func:`umi_aug.square.source.square_umi_episode`: on the new frames the planned path's targets 3 control steps
ahead, after the splice the source demo's own commands) — are then executed exactly as ``eval_sim`` executes a
policy's targets (:meth:`umi_aug.square.eval.SceneProbe.env_action`: the OSC_POSE delta from the current TCP pose;
row ``t + 1`` at control step ``t``), and ``--extra-steps`` more steps hold the last row. Recorded per episode:
how far the placed arm's TCP is from the planned start (mm / degrees: ~0 when the placement is right), the tracking
error against the planned TCP positions over the new frames and at the splice frame, the pre-grasp /
lift / insertion sub-goals of eval's probe, and success. The same is done for each source demo's own labels from its
own first state (the control: the replay oracle, 20/20 in eval/README).

A label set that a perfect imitator cannot execute is one a policy cannot learn to succeed from; this measures how
far the planned frames' lead-3 approximation is from that.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def load_augmented(export: Path) -> list[dict]:
    """The export's augmented episodes: ``source``, ``splice``, ``pos`` [T, 3] and ``rotvec`` [T, 3] of the planned
    TCP, ``action`` [T, 7] (position, rotation vector, width target)."""
    from umi_aug.data.store import open_store

    _, g = open_store(export)
    meta, data = g["meta"], g["data"]
    ends = np.asarray(meta["episode_ends"][:])
    aug_id = np.asarray(meta["aug_id"][:])
    source = np.asarray(meta["aug_source_episode"][:])
    splice = np.asarray(meta["aug_splice_index"][:])
    pos, rot, act = (np.asarray(data[k][:]) for k in ("robot0_eef_pos", "robot0_eef_rot_axis_angle", "action"))
    starts = np.concatenate([[0], ends[:-1]])
    out = []
    for e in np.flatnonzero(aug_id >= 0):
        sl = slice(int(starts[e]), int(ends[e]))
        out.append({"episode": int(e), "source": int(source[e]), "splice": int(splice[e]), "pos": pos[sl],
                    "rotvec": rot[sl], "action": act[sl]})
    return out


def load_sources(export: Path, sources: set[int]) -> dict[int, dict]:
    """The original episodes ``sources`` of the export (the source demos, copied first), in the same layout."""
    from umi_aug.data.store import open_store

    _, g = open_store(export)
    meta, data = g["meta"], g["data"]
    ends = np.asarray(meta["episode_ends"][:])
    aug_id = np.asarray(meta["aug_id"][:])
    starts = np.concatenate([[0], ends[:-1]])
    originals = np.flatnonzero(aug_id < 0)
    out = {}
    for s in sorted(sources):
        e = int(originals[s])
        sl = slice(int(starts[e]), int(ends[e]))
        out[s] = {"episode": e, "source": s, "splice": -1, "pos": np.asarray(data["robot0_eef_pos"][sl]),
                  "rotvec": np.asarray(data["robot0_eef_rot_axis_angle"][sl]),
                  "action": np.asarray(data["action"][sl])}
    return out


def replay(env, state0: np.ndarray, ep: dict, extra_steps: int, place_by_ik: bool, seed: int) -> dict:
    """Execute ``ep``'s labels from ``state0`` (arm moved by IK to the episode's first TCP pose when
    ``place_by_ik``); the record of eval's probe plus tracking errors (mm, degrees)."""
    from umi_aug.geometry import pos_rotvec_to_pose, so3_log
    from umi_aug.square.env import GRIP_SITE
    from umi_aug.square.eval import SceneProbe
    from umi_aug.square.ik import PandaIK

    env.reset(seed=0)
    env.reset_to(state0, initial=True)
    rec: dict = {"episode": ep["episode"], "source": ep["source"], "splice": ep["splice"], "steps": len(ep["pos"])}
    T_tcp0 = pos_rotvec_to_pose(np.r_[ep["pos"][0], ep["rotvec"][0]])
    if place_by_ik:
        from umi_aug.square.oracle import episode_start_state

        state, res = episode_start_state(env, PandaIK(env.model, GRIP_SITE), env.get_state(), T_tcp0, seed)
        rec.update(ik_reachable=bool(res.reachable), ik_pos_err_mm=1e3 * res.pos_err,
                   ik_collisions=list(res.collisions))
        if state is None:
            return rec
        env.reset_to(state, initial=True)
    T = env.tcp_pose()
    rec.update(start_pos_err_mm=1e3 * float(np.linalg.norm(T[:3, 3] - T_tcp0[:3, 3])),
               start_rot_err_deg=math.degrees(float(np.linalg.norm(so3_log(T[:3, :3] @ T_tcp0[:3, :3].T)))))
    probe = SceneProbe(env)
    rec.update(probe.start())
    n = len(ep["action"])
    s = ep["splice"] if ep["splice"] >= 0 else None
    dev, success_step = [], None
    for t in range(n - 1 + extra_steps):
        env.step(probe.env_action(ep["action"][min(t + 1, n - 1)], None))
        probe.observe(rec, t + 1)
        if t + 1 < n:
            dev.append(float(np.linalg.norm(env.tcp_pose()[:3, 3] - ep["pos"][t + 1])))
        if s is not None and t + 1 == s:
            T_plan = pos_rotvec_to_pose(np.r_[ep["pos"][s], ep["rotvec"][s]])
            T_now = env.tcp_pose()
            rec["splice_pos_err_mm"] = 1e3 * float(np.linalg.norm(T_now[:3, 3] - T_plan[:3, 3]))
            rec["splice_rot_err_deg"] = math.degrees(float(np.linalg.norm(so3_log(T_now[:3, :3] @ T_plan[:3, :3].T))))
        if success_step is None and env.is_success():
            success_step = t + 1
    probe.finish(rec)
    new = np.asarray(dev[: s] if s is not None else dev) * 1e3
    rec.update(success=success_step is not None, success_step=success_step,
               track_median_mm=float(np.median(new)) if len(new) else None,
               track_max_mm=float(np.max(new)) if len(new) else None)
    return rec


def _row(r: dict) -> list[str]:
    f = (lambda v, p=1: "-" if v is None else f"{v:.{p}f}")  # noqa: E731
    return [str(r["episode"]), str(r["source"]), str(r["splice"]),
            f"{f(r.get('start_pos_err_mm'), 2)} / {f(r.get('start_rot_err_deg'), 2)}",
            f(r.get("track_median_mm")), f(r.get("track_max_mm")), f(r.get("splice_pos_err_mm")),
            f(r.get("splice_rot_err_deg")), "yes" if r.get("pregrasp_reached") else "no",
            "yes" if r.get("lifted") else "no", "yes" if r.get("success") else "no", str(r.get("success_step") or "-")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--export", required=True, help="augmented square export (umi-aug augment square_demos ...)")
    ap.add_argument("--demos", default="square_demos", help="the square demo folder the export was made from")
    ap.add_argument("--max-episodes", type=int, default=None)
    ap.add_argument("--extra-steps", type=int, default=40, help="steps holding the last label after the episode")
    ap.add_argument("--seed", type=int, default=0, help="IK restarts")
    ap.add_argument("--out", default=None, help="JSON of every record")
    args = ap.parse_args()
    from umi_aug.runtime import configure_threads

    configure_threads(1)
    from rich.console import Console
    from rich.table import Table

    from umi_aug.io_utils import atomic_write_text
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.init_configs import source_states_from_hdf5

    export, demos = Path(args.export), Path(args.demos)
    hdf5 = sorted(demos.glob("*.hdf5"))
    if not export.exists() or not hdf5:
        print(f"error: need --export (an augmented square export) and --demos with the demos' hdf5; got {export}, "
              f"{demos}", file=sys.stderr)
        return 2
    episodes = load_augmented(export)[: args.max_episodes]
    if not episodes:
        print(f"error: {export}: no augmented episode (meta/aug_id >= 0)", file=sys.stderr)
        return 2
    states0, _ = source_states_from_hdf5(hdf5[0])
    sources = load_sources(export, {e["source"] for e in episodes})
    env = SquareEnv(image_size=None)
    recs = {"augmented": [replay(env, states0[e["source"]], e, args.extra_steps, True, args.seed) for e in episodes],
            "source demos": [replay(env, states0[s], ep, args.extra_steps, False, args.seed)
                             for s, ep in sources.items()]}
    env.close()
    console = Console(width=160)
    for name, rows in recs.items():
        t = Table(title=f"{name}: labels executed through eval's controller ({export.name})")
        for c in ("episode", "source", "splice", "start mm / °", "track median mm", "track max mm", "splice mm",
                  "splice °", "pre-grasp", "lifted", "success", "at step"):
            t.add_column(c, justify="right")
        for r in rows:
            t.add_row(*_row(r))
        console.print(t)
        ok = sum(bool(r.get("success")) for r in rows)
        pre = sum(bool(r.get("pregrasp_reached")) for r in rows)
        console.print(f"{name}: {ok}/{len(rows)} succeed, pre-grasp {pre}"
                      f", lifted {sum(bool(r.get('lifted')) for r in rows)}")
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(recs, indent=1, default=float) + "\n")
        console.print(f"records: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
