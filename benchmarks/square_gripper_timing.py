"""When does a square policy close its gripper? Closed-loop grasp timing of checkpoints against the scripted expert.

Run: ``MUJOCO_GL=egl python benchmarks/square_gripper_timing.py --configs 0:10 CKPT [CKPT ...]``

Each checkpoint (and the expert, the reference) is rolled out through ``eval_sim``'s own path
(:func:`umi_aug.eval.rollout.rollout_config`, :class:`~umi_aug.eval.policies.CheckpointEvalPolicy`) from the
in-distribution resets ``eval/square_init_configs_reset100.npz``. At the first control step whose action closes the
gripper it records the step and where the grip site is relative to the nut's centre (height above it and horizontal
distance, mm). A policy that closes far above the nut, or far to its side, grasps air; once closed it sees a closed
gripper and never re-opens in the demos' data. Prints one row per rollout and medians per policy.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _configs(spec: str) -> list[int]:
    a, _, b = spec.partition(":")
    return list(range(int(a), int(b))) if b else [int(a)]


def grasp_timing(policy, env, probe, state: np.ndarray, config: int, camera=None, horizon: int = 400) -> dict:
    """Roll ``policy`` out from ``state``; the first closing step and the grip site relative to the nut then (m)."""
    from umi_aug.eval.rollout import rollout_config

    first: dict = {}
    step = env.step

    def recording_step(a):  # the executed OSC action, before the state it is applied to changes
        if not first and float(a[-1]) > 0.0:  # OSC gripper command: +1 closes
            d = probe.site_pose()[:3, 3] - probe.nut_pose()[:3, 3]
            first.update(step=probe_step[0], above_m=float(d[2]), side_m=float(np.hypot(d[0], d[1])))
        probe_step[0] += 1
        return step(a)

    probe_step = [0]
    env.step = recording_step
    try:
        rec = rollout_config(env, probe, policy, state, config, 0, horizon=horizon, camera=camera)
    finally:
        del env.step
    return {"config": config, "success": bool(rec["success"]), "lifted": bool(rec["lifted"]),
            "close_step": first.get("step"), "above_mm": 1000 * first["above_m"] if first else None,
            "side_mm": 1000 * first["side_m"] if first else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="*")
    ap.add_argument("--configs", default="0:10")
    ap.add_argument("--configs-file", default="eval/square_init_configs_reset100.npz")
    args = ap.parse_args()
    import torch

    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.runtime import configure_threads
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.controls import ExpertEvalPolicy
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.eval import SceneProbe

    configure_threads()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    states = np.load(args.configs_file)["states"]
    env = SquareEnv(image_size=None)
    probe = SceneProbe(env)
    policies = [("expert", ExpertEvalPolicy(), None)]
    for ck in args.checkpoints:
        pol = CheckpointEvalPolicy.from_checkpoint(ck)
        policies.append((ck, pol, WristFisheyeCamera(env.model, pol.image_size)))
    print(f"{'policy':<60}{'config':>7}{'success':>8}{'lifted':>7}{'close step':>11}{'above nut mm':>13}"
          f"{'to side mm':>11}")
    summary = []
    for name, pol, cam in policies:
        rows = [grasp_timing(pol, env, probe, states[c], c, cam) for c in _configs(args.configs)]
        for r in rows:
            f = (lambda v, fmt: "never" if v is None else format(v, fmt))
            print(f"{name[-60:]:<60}{r['config']:>7}{r['success']!s:>8}{r['lifted']!s:>7}"
                  f"{f(r['close_step'], 'd'):>11}{f(r['above_mm'], '.0f'):>13}{f(r['side_mm'], '.0f'):>11}")
        closed = [r for r in rows if r["close_step"] is not None]
        med = (lambda k: float(np.median([r[k] for r in closed])) if closed else float("nan"))
        summary.append((name, len(rows), sum(r["success"] for r in rows), sum(r["lifted"] for r in rows),
                        len(closed), med("close_step"), med("above_mm"), med("side_mm")))
    print(f"\n{'policy':<60}{'n':>4}{'succ':>6}{'lift':>6}{'closed':>8}{'median step':>13}{'above mm':>10}"
          f"{'side mm':>9}")
    for s in summary:
        print(f"{s[0][-60:]:<60}{s[1]:>4}{s[2]:>6}{s[3]:>6}{s[4]:>8}{s[5]:>13.0f}{s[6]:>10.0f}{s[7]:>9.0f}")
    env.close()


if __name__ == "__main__":
    main()
