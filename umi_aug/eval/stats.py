"""Success-rate statistics of an evaluation: Wilson score interval, per-run summary from rollout records."""

from __future__ import annotations

import math
from typing import Any, Iterable, Sequence

import numpy as np

__all__ = ["wilson_interval", "median_interval", "mcnemar_exact_p", "paired_bootstrap_interval", "summarise"]

#: two-sided 95 % normal quantile
Z95: float = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (``successes`` of ``n``), as fractions in [0, 1].

    ``n == 0`` gives ``(0.0, 1.0)`` (nothing known). Unlike the normal (Wald) interval it never leaves [0, 1] and
    is not degenerate at 0 % or 100 %: 1000/1000 gives (0.9962, 1.0).
    """
    n = int(n)
    k = int(successes)
    if n < 0 or not 0 <= k <= max(n, 0):
        raise ValueError(f"wilson_interval: need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = k / n
    z2 = z * z
    den = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # exact ends (the formula leaves ~1e-19 rounding there)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def median_interval(values: Iterable[float], z: float = Z95) -> tuple[float, float]:
    """Distribution-free 95 % confidence interval of a median: the order statistics ``x(j)``, ``x(k)`` with
    ``j = floor(n/2 - z sqrt(n)/2)``, ``k = ceil(1 + n/2 + z sqrt(n)/2)`` (1-based, clipped to [1, n]) — the normal
    approximation of the binomial(n, 1/2) ranks. Same unit as ``values``; ``(nan, nan)`` for no values.

    Used for the closest approach to the pre-grasp pose and paired per-configuration differences, which separate
    policies that never succeed."""
    x = np.sort(np.asarray(list(values), dtype=np.float64))
    n = len(x)
    if n == 0:
        return float("nan"), float("nan")
    if not np.isfinite(x).all():
        raise ValueError(f"median_interval: {int((~np.isfinite(x)).sum())} of {n} values are not finite")
    half = z * math.sqrt(n) / 2.0
    j = min(max(int(math.floor(n / 2.0 - half)), 1), n)
    k = min(max(int(math.ceil(1.0 + n / 2.0 + half)), 1), n)
    return float(x[j - 1]), float(x[k - 1])


def mcnemar_exact_p(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar test of two policies evaluated on the same configurations: the p-value of the
    discordant counts (``only_a`` configurations where only policy A succeeded, ``only_b`` where only B did) under
    the null hypothesis that both succeed equally often, i.e. ``min(1, 2 · P[X <= min(only_a, only_b)])`` for
    ``X ~ Binomial(only_a + only_b, 1/2)``. Concordant pairs carry no information and are not arguments. 1.0 when
    there is no discordant pair."""
    a, b = int(only_a), int(only_b)
    if a < 0 or b < 0:
        raise ValueError(f"mcnemar_exact_p: discordant counts must be >= 0, got only_a={only_a}, only_b={only_b}")
    n = a + b
    if n == 0:
        return 1.0
    k = min(a, b)
    # log-space binomial terms: exact enough for any n an evaluation has (lgamma), never overflows
    logs = [math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) - n * math.log(2.0)
            for i in range(k + 1)]
    top = max(logs)
    tail = math.exp(top) * sum(math.exp(v - top) for v in logs)
    return min(1.0, 2.0 * tail)


def paired_bootstrap_interval(a: Sequence[bool] | np.ndarray, b: Sequence[bool] | np.ndarray,
                              n_boot: int = 10000, seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval of the difference of two success rates measured on the same configurations
    (``mean(a) - mean(b)``, as fractions): configurations are resampled with replacement, each keeping its pair of
    outcomes, so the interval accounts for what the configurations share. Deterministic for a ``seed``.

    Args:
        a, b: per-configuration outcomes of policy A and B, same length and order (the same configurations).
        n_boot: bootstrap resamples.
        level: coverage of the interval.
    Returns:
        (lo, hi): fractions in [-1, 1]; ``(nan, nan)`` when there is no configuration.
    """
    x = np.asarray(a, dtype=np.float64).reshape(-1)
    y = np.asarray(b, dtype=np.float64).reshape(-1)
    if x.shape != y.shape:
        raise ValueError(f"paired_bootstrap_interval: a and b must pair up, got {x.size} and {y.size} outcomes")
    if not 0.0 < level < 1.0 or int(n_boot) < 1:
        raise ValueError(f"paired_bootstrap_interval: need 0 < level < 1 and n_boot >= 1, got {level}, {n_boot}")
    if x.size == 0:
        return float("nan"), float("nan")
    d = x - y
    rng = np.random.default_rng(seed)
    means = np.empty(int(n_boot))
    chunk = max(1, 2_000_000 // d.size)  # bounded memory: at most ~2M resampled indices at a time
    for s in range(0, int(n_boot), chunk):
        m = min(chunk, int(n_boot) - s)
        means[s:s + m] = d[rng.integers(0, d.size, size=(m, d.size))].mean(axis=1)
    q = (1.0 - level) / 2.0
    return float(np.quantile(means, q)), float(np.quantile(means, 1.0 - q))


def _rate(records: list[dict[str, Any]], key: str) -> dict[str, Any]:
    k = sum(bool(r[key]) for r in records)
    lo, hi = wilson_interval(k, len(records))
    return {"count": k, "rate": k / len(records) if records else float("nan"), "wilson95": [lo, hi]}


def summarise(records: Iterable[dict[str, Any]], wall_seconds: float | None = None, workers: int = 1,
              subgoals: Sequence[str] = (), collisions: Sequence[str] = ()) -> dict[str, Any]:
    """Summary of rollout records (``umi_aug.eval.rollout.rollout_config`` dicts).

    Args:
        records: finished rollouts (order does not matter; the summary is sorted-order independent).
        wall_seconds: wall time of this invocation (used only for the informative ``rollouts_per_hour_wall``).
        workers: parallel workers (for ``rollouts_per_hour`` = workers × 3600 / mean rollout seconds).
        subgoals, collisions: the task's boolean record fields reported as rates
            (:attr:`umi_aug.eval.task.SimTask.subgoals` / ``collisions``).
    Returns:
        JSON-able dict: ``n``, ``success_rate`` + ``success_wilson95``, sub-goal rates, steps, collisions,
        ``time_per_step_ms`` split (sim / render / policy / other), rollouts per hour.
    """
    recs = sorted(records, key=lambda r: r["config"])
    n = len(recs)
    out: dict[str, Any] = {"n": n}
    if n == 0:
        return out | {"success_rate": float("nan"), "success_wilson95": [0.0, 1.0]}
    succ = _rate(recs, "success")
    out["successes"] = succ["count"]
    out["success_rate"] = succ["rate"]
    out["success_wilson95"] = succ["wilson95"]
    out["subgoals"] = {k: _rate(recs, k) for k in subgoals}
    out["collisions"] = {k: _rate(recs, k) for k in collisions}
    s2s = [r["steps_to_success"] for r in recs if r["success"]]
    out["mean_steps_to_success"] = float(np.mean(s2s)) if s2s else None
    out["mean_steps"] = float(np.mean([r["steps"] for r in recs]))
    steps = float(sum(r["steps"] for r in recs))
    t = {k: float(sum(r["time_s"][k] for r in recs)) for k in ("sim", "render", "policy", "other")}
    out["time_per_step_ms"] = {k: 1000.0 * v / max(steps, 1.0) for k, v in t.items()}
    out["time_split"] = {k: v / max(sum(t.values()), 1e-12) for k, v in t.items()}
    mean_wall = float(np.mean([r["wall_s"] for r in recs]))
    out["mean_rollout_s"] = mean_wall
    out["rollouts_per_hour"] = 3600.0 * max(int(workers), 1) / max(mean_wall, 1e-9)
    if wall_seconds:
        out["wall_s_this_run"] = float(wall_seconds)
    out["failures"] = [r["config"] for r in recs if not r["success"]]
    if any("handover_reason" in r for r in recs):  # a second policy finished the rollouts (rollout's Handover)
        out["handover"] = {why or "never": _handover_rate(recs, why) for why in ("subgoal", "step_limit", None)}
    return out


def _handover_rate(recs: list[dict[str, Any]], why: str | None) -> dict[str, Any]:
    """How many rollouts handed over for ``why`` (None: never), and how many of those succeeded."""
    mine = [r for r in recs if r.get("handover_reason") == why]
    ok = sum(bool(r["success"]) for r in mine)
    return {"count": len(mine), "successes": ok, "success_wilson95": list(wilson_interval(ok, len(mine)))}
