"""Policy evaluation in simulation (``eval/eval_sim.py``): the harness that rolls policies out from fixed start
configurations of a simulated benchmark and scores them.

Sits above ``policy`` and ``sim`` and uses their public APIs only; it knows no benchmark: a task brings its
environment, its record fields and its scripted controls through :mod:`~umi_aug.eval.task` (the square task:
:data:`umi_aug.square.eval.SQUARE_TASK`, in the package above). Modules (nothing heavy imported at package import):

- :mod:`~umi_aug.eval.task` — the protocols a benchmark implements: ``SimEnv``, ``TaskProbe``, ``SimTask``.
- :mod:`~umi_aug.eval.config` — :class:`EvalSimConfig` (``configs/eval_sim.yaml``), configuration selection.
- :mod:`~umi_aug.eval.policies` — how a policy is run (``RolloutSpec``, ``CONTROL_SPEC`` of scripted controls,
  the privileged obs_dict entry) and the checkpoint adapter (seeded sampling), each policy a
  :class:`umi_aug.policy.contract.PolicyLike` (``reset()``, ``predict_action(obs_dict) -> {"action": chunk}``,
  the contract deployment uses too).
- :mod:`~umi_aug.eval.rollout` — one rollout and its record (success, the task's fields, time split); its
  ``PolicyDriver`` builds the obs_dict window, calls ``predict_action`` and executes the chunk (absolute TCP
  target → the environment's action through the task's probe).
- :mod:`~umi_aug.eval.results` — ``run.json`` / append-only ``results.jsonl`` (resume).
- :mod:`~umi_aug.eval.stats` — Wilson interval, summary.
- :mod:`~umi_aug.eval.pictures` — ``init_success.png``.
- :mod:`~umi_aug.eval.runner` — :func:`run_eval` (config + task): workers, resume, summary, table, pictures.
"""

from umi_aug.eval.config import EvalSimConfig, parse_config_selection
from umi_aug.eval.stats import wilson_interval

__all__ = ["EvalSimConfig", "parse_config_selection", "wilson_interval"]
