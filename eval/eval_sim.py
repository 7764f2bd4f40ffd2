"""Evaluate a policy in simulation on the fixed square start configurations — a Hydra app.

    python eval/eval_sim.py checkpoint=PATH configs=0:1000 workers=2 out_dir=eval_runs/mine
    python eval/eval_sim.py policy=expert configs=0:1000     # privileged scripted expert (harness check)
    python eval/eval_sim.py policy=hold configs=0:20         # controls that must never succeed (hold | random)
    python eval/eval_sim.py policy=replay replay_dir=square_demos/shards configs=0:5
    python eval/eval_sim.py --cfg job                        # print the composed config

Writes ``out_dir/{run.json, results.jsonl, summary.json, init_success.png, eval_sim.log, videos/}``; rerunning
the same command resumes (finished configurations are skipped), also after Ctrl-C or SIGTERM (``kill``,
``timeout``), which end in one ``eval/eval_sim.py: interrupted (…)`` line (exit 130 / 143). See ``eval/README.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from umi_aug.config_keys import check_known_keys, check_override_keys
from umi_aug.errors import EvalError, UmiAugError
from umi_aug.eval.config import EvalSimConfig

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")

ConfigStore.instance().store(name="eval_sim_schema", node=EvalSimConfig)
#: The results folder of the run (``out``), for the interrupted line.
_RUN: dict[str, Path] = {}


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="eval_sim")
def main(cfg: DictConfig) -> None:
    from umi_aug.eval.runner import default_out_dir, run_eval
    from umi_aug.runtime import configure_threads, log_to_file, make_out_dir

    try:
        check_known_keys(cfg, EvalSimConfig, "eval/eval_sim.py", EvalError)  # Hydra's +key=… included
        typed: EvalSimConfig = OmegaConf.to_object(cfg)
        out_dir = Path(typed.out_dir) if typed.out_dir else default_out_dir(typed)
        make_out_dir(out_dir, "out_dir", EvalError)
        _RUN["out"] = out_dir
        log_to_file(out_dir / "eval_sim.log")
        configure_threads(1)
        from umi_aug.square.eval import SQUARE_TASK  # after configure_threads: the simulator's libraries load here

        summary = run_eval(typed, SQUARE_TASK)
    except UmiAugError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    lo, hi = summary["success_wilson95"]
    print(f"success {summary['successes']}/{summary['n']} = {100 * summary['success_rate']:.1f} % "
          f"(Wilson 95 % [{100 * lo:.1f}, {100 * hi:.1f}]); {out_dir / 'summary.json'}")


def _policy_override(argv: list[str]) -> list[str]:
    """``policy=NAME`` → ``eval_policy=NAME`` (``configs/policy/`` is the training group, so Hydra would read
    ``policy=`` as a choice there)."""
    return ["eval_policy=" + a[len("policy="):] if a.startswith("policy=") else a for a in argv]


if __name__ == "__main__":
    sys.argv[1:] = _policy_override(sys.argv[1:])
    try:  # before Hydra, whose message for an unknown `key=value` advises `+key=value`
        check_override_keys(sys.argv[1:], EvalSimConfig, "eval/eval_sim.py", EvalError, groups=("eval_policy",))
    except EvalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    from umi_aug.runtime import run_interruptible

    def _interrupted(how: str) -> str:
        kept = (f"the finished configurations are kept in {_RUN['out'] / 'results.jsonl'}" if "out" in _RUN
                else "nothing was evaluated")
        return f"eval/eval_sim.py: interrupted ({how}); {kept} — rerun the same command to resume"

    run_interruptible(main, _interrupted)  # SIGTERM (kill, timeout, a scheduler) ends like Ctrl-C: one line
