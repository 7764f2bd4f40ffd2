"""The square study (issue #15): data generation → training → evaluation → report, resumable.

    python eval/square_study.py recipe=cpu                     # configs/square_study/cpu.yaml, every step
    python eval/square_study.py recipe=cpu budget_min=150      # a time slice: no new step after 150 minutes
    python eval/square_study.py recipe=cpu phases=report       # only rewrite docs/square_study.{md,png}
    python eval/square_study.py recipe=paper                   # the paper-scale recipe (GPU machine)

Any recipe field can be overridden as ``key=value`` (``umi_aug.square.study.StudyConfig``); ``phases`` is a
comma list of data, train, eval, report. Rerunning the same command skips finished steps (the record's ``study_state.json``).
Every key is checked before any work — the recipe's and the overrides', ``scene.*`` / ``spartn.*``, and the keys and
values of ``train_overrides`` / ``eval_overrides`` — and a bad one ends in one ``square_study: …`` line (exit 2);
``python eval/square_study.py recipe=cpu --cfg`` prints the composed recipe (every key).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str]) -> int:
    from umi_aug.errors import UmiAugError
    from umi_aug.runtime import configure_threads
    from umi_aug.square.report import report_study
    from umi_aug.square.study import load_recipe, run_study

    recipe, phases, rest, show = "cpu", "data,train,eval,report", [], False
    for a in argv:
        if a.startswith("recipe="):
            recipe = a.split("=", 1)[1]
        elif a.startswith("phases="):
            phases = a.split("=", 1)[1]
        elif a in ("-h", "--help"):
            print(__doc__)
            return 0
        elif a == "--cfg" or (a == "job" and show):
            show = True
        else:
            rest.append(a)
    path = Path(recipe) if recipe.endswith(".yaml") else ROOT / "configs" / "square_study" / f"{recipe}.yaml"
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("umi_aug").setLevel(logging.INFO)
    if not path.is_file():
        known = sorted(p.stem for p in (ROOT / "configs" / "square_study").glob("*.yaml"))
        print(f"square_study: recipe={recipe}: no recipe file {path}; the shipped recipes are {', '.join(known)} "
              f"(or pass a .yaml path)", file=sys.stderr)
        return 2
    try:
        cfg = load_recipe(path, rest)  # every key (and train/eval overrides) checked before any work
        if show:
            from dataclasses import asdict

            from omegaconf import OmegaConf

            print(OmegaConf.to_yaml(OmegaConf.create(asdict(cfg))), end="")
            return 0
        configure_threads(None)
        bad = [p for p in phases.split(",") if p not in ("data", "train", "eval", "report")]
        if bad:
            print(f"square_study: phases {bad} unknown; expected data, train, eval, report", file=sys.stderr)
            return 2
        steps = tuple(p for p in phases.split(",") if p != "report")
        if steps:
            run_study(cfg, steps)
        if "report" in phases.split(","):
            report_study(cfg)
    except UmiAugError as exc:
        print(f"square_study: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
