"""Policy evaluation in simulation (``eval/eval_sim.py``): the square task from the fixed start configurations.

Sits above ``policy`` and ``sim`` and uses their public APIs only. Modules (nothing heavy imported at package
import):

- :mod:`~umi_aug.eval.config` — :class:`EvalSimConfig` (``configs/eval_sim.yaml``), configuration selection.
- :mod:`~umi_aug.eval.policies` — the eval policy kinds, each a :class:`umi_aug.policy.contract.PolicyLike`
  (``reset()``, ``predict_action(obs_dict) -> {"action": chunk}``, the contract deployment uses too): checkpoint
  adapter (seeded sampling), expert adapter, replay, hold-still and random controls; their ``RolloutSpec`` and the
  documented privileged entry of the controls' obs_dict (``PrivilegedState``).
- :mod:`~umi_aug.eval.rollout` — one rollout and its record (success, sub-goals, collisions, time split); its
  ``PolicyDriver`` builds the obs_dict window, calls ``predict_action`` and executes the chunk (absolute TCP
  target → OSC delta).
- :mod:`~umi_aug.eval.results` — ``run.json`` / append-only ``results.jsonl`` (resume).
- :mod:`~umi_aug.eval.stats` — Wilson interval, summary.
- :mod:`~umi_aug.eval.pictures` — ``init_success.png``.
- :mod:`~umi_aug.eval.runner` — :func:`run_eval`: workers, resume, summary, table, pictures.
"""

from umi_aug.eval.config import EvalSimConfig, parse_config_selection
from umi_aug.eval.stats import wilson_interval

__all__ = ["EvalSimConfig", "parse_config_selection", "wilson_interval"]
