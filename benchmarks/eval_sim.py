"""Speed of the simulation evaluation loop (umi_aug.eval) and the error bar N configurations give.

Run: ``python benchmarks/eval_sim.py [--steps 24] [--sizes 84 224] [--encoders small clip_vit_b16] [--threads 1]
[--overrides task.img_obs_horizon=1 ...] [--every-step-reference]``

Table 1: per policy × image size, ONE short closed-loop rollout (the harness renders only the frames an inference
looks at; ``--every-step-reference`` adds the same rollout rendering every frame, the old path, for the ratio) of
``--steps`` control steps (20 Hz) from start configuration 0 in this process (1 torch thread = one eval worker), the
per-step time split (simulation / rendering / policy incl. inference every ``n_action_steps`` steps / other) and the
rollouts/hour that gives for a 400-step rollout (the horizon a failing rollout runs to) on 1 worker and on 2 workers
(×2, i.e. assuming the two cores are free). The policies are the training configs ``configs/policy/small.yaml`` and
``clip_vit_b16.yaml`` with RANDOM weights (CLIP weights are not available offline; the speed does not depend on the
values) and an identity normaliser; the scripted expert (no images) is the reference row measured in the same run.
Table 2: Wilson 95 % interval half-width vs N for true success rates 50 / 80 / 95 %.
Timings are wall clock on whatever cores this process gets (project machines: 2 shared cores).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _random_policy(encoder: str, size: int, overrides: tuple[str, ...] = ()):
    """A :class:`umi_aug.policy.Policy` of the training config ``policy=<encoder>`` + ``task=square`` at ``size``²
    (+ Hydra ``overrides``, e.g. ``task.img_obs_horizon=1``), random weights, identity normaliser."""
    from hydra import compose, initialize_config_dir

    from umi_aug.policy import Policy
    from umi_aug.policy.config import shape_meta, structured_config
    from umi_aug.policy.heads import build_policy
    from umi_aug.policy.normalizer import LinearNormalizer, identity_params

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        from hydra.core.config_store import ConfigStore

        from umi_aug.policy.config import TrainConfig

        ConfigStore.instance().store(name="train_schema", node=TrainConfig)
        raw = compose("train", overrides=[f"policy={encoder}", "task=square", f"task.image_size={size}",
                                          "policy.encoder.pretrained_path=null", *overrides])
    cfg = structured_config(raw)
    meta = shape_meta(cfg.task)
    model = build_policy(meta, cfg.policy, warn_random_init=False)
    norm = LinearNormalizer()
    for k, v in meta["obs"].items():
        if v["type"] == "low_dim":
            norm.set(k, *identity_params(v["shape"][0]))
    norm.set("action", *identity_params(meta["action"]["shape"][0]))
    model.set_normalizer(norm)
    n_params = sum(p.numel() for p in model.parameters())
    k = cfg.policy.num_inference_steps if cfg.policy.action_head == "diffusion" else 1  # forward passes
    return Policy(model, cfg, "cpu"), n_params, k


def _measure(env, probe, policy, state, steps: int, camera=None, render_every_step: bool = False) -> dict:
    from umi_aug.eval.rollout import rollout_config

    rec = rollout_config(env, probe, policy, state, 0, 0, horizon=steps, camera=camera, stop_on_success=False,
                         render_every_step=render_every_step)
    n = rec["steps"]
    ms = {k: 1000.0 * v / n for k, v in rec["time_s"].items()}
    return {"ms": ms, "total_ms": sum(ms.values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=24, help="control steps per measured rollout (short)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[84, 224])
    ap.add_argument("--encoders", nargs="+", default=["small", "clip_vit_b16"])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 = one eval worker)")
    ap.add_argument("--overrides", nargs="*", default=[],
                    help="Hydra overrides for every policy, e.g. task.img_obs_horizon=1 (the study's one-frame recipe)")
    ap.add_argument("--every-step-reference", action="store_true",
                    help="also time each policy rendering the wrist frame at every step (before wants_image)")
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    from rich.console import Console
    from rich.table import Table

    from umi_aug.runtime import configure_threads

    configure_threads(args.threads)
    import torch

    torch.set_num_threads(args.threads)
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.eval.stats import wilson_interval
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.controls import ExpertEvalPolicy
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.eval import SceneProbe

    configs = load_eval_configs(ROOT / "eval" / "square_init_configs_1000.npz")
    state = configs["states"][0]
    env = SquareEnv(env_meta=configs["env_args"], image_size=None)
    probe = SceneProbe(env)
    rows = [("expert (no images)", "—", "—", _measure(env, probe, ExpertEvalPolicy(), state, args.steps))]
    for enc in args.encoders:
        for size in args.sizes:
            pol, n_params, k = _random_policy(enc, size, tuple(args.overrides))
            ev = CheckpointEvalPolicy(pol)
            cam = WristFisheyeCamera(env.model, size)
            try:
                _measure(env, probe, ev, state, 2, cam)  # warm-up (first inference, GL context)
                label = (f"{enc} ({n_params / 1e6:.0f} M, {k} forward pass(es), {ev.n_exec}/inference, "
                         f"{pol.task.img_obs_horizon} image frame(s))")
                if args.every_step_reference:
                    rows.append((f"{label}, every frame rendered", f"{size}²", str(ev.n_exec),
                                 _measure(env, probe, ev, state, args.steps, cam, render_every_step=True)))
                rows.append((label, f"{size}²", str(ev.n_exec), _measure(env, probe, ev, state, args.steps, cam)))
            finally:
                cam.close()
    env.close()
    t = Table(title=f"eval_sim: ms per control step ({args.steps}-step rollouts, {args.threads} torch thread(s), "
                    f"shared 2-core machine)")
    for c in ("policy", "image", "sim", "render", "policy+inference", "other", "total", "400-step rollouts/h (1 w)",
              "(2 w)", "× expert"):
        t.add_column(c, justify="right" if c not in ("policy",) else "left")
    ref = rows[0][3]["total_ms"]
    for name, size, _, r in rows:
        ms = r["ms"]
        per_h = 3600.0 / (400 * r["total_ms"] / 1000.0)
        t.add_row(name, size, f"{ms['sim']:.1f}", f"{ms['render']:.1f}", f"{ms['policy']:.1f}", f"{ms['other']:.1f}",
                  f"{r['total_ms']:.1f}", f"{per_h:.0f}", f"{2 * per_h:.0f}", f"{r['total_ms'] / ref:.1f}")
    console = Console(width=max(160, Console().width))
    console.print(t)
    w = Table(title="Wilson 95 % interval vs number of configurations N (half-width, percentage points)")
    w.add_column("N", justify="right")
    for p in (0.5, 0.8, 0.95):
        w.add_column(f"p = {p:.0%}", justify="right")
    for n in (22, 50, 100, 200, 500, 1000):
        cells = []
        for p in (0.5, 0.8, 0.95):
            lo, hi = wilson_interval(round(p * n), n)
            cells.append(f"±{50 * (hi - lo):.1f}  [{100 * lo:.1f}, {100 * hi:.1f}]")
        w.add_row(str(n), *cells)
    console.print(w)


if __name__ == "__main__":
    main()
