"""The paper's square-study claims set against a study's record, each with a verdict that follows from the numbers.

The paper (``../shared/paper/1001_demos.tex`` §4.1–4.2, Fig. 3b) states its simulation results as differences of
task success "in %" between variants, averaged over its data sizes or for its low- / high-data regime. They are
read here as **percentage points of the success rate** (the paper does not say whether they are absolute or
relative; the absolute reading is the one a reader of a success-rate bar chart takes, and the one tested here).

For each claim the study's number is the same difference of success rates on the configurations both cells
evaluated (every cell of a study is evaluated on the same ones), with a paired percentile-bootstrap 95 % interval:
for a claim averaged over the data sizes, each configuration carries its mean difference over the sizes, so the
configurations are resampled jointly across sizes. The verdict (:func:`verdict`) depends only on where 0 and the
paper's value lie relative to that interval.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from umi_aug.eval.results import ResultsLog
from umi_aug.eval.stats import paired_bootstrap_interval
from umi_aug.square.study import record_eval_dir

__all__ = ["PaperClaim", "PAPER_CLAIMS", "VERDICTS", "verdict", "claim_result", "claims_section",
           "success_by_config"]


@dataclass(frozen=True)
class PaperClaim:
    """One difference of task success the paper reports.

    Attributes:
        better: the variant the paper finds better (``ours``, ``gt_render``, ...).
        worse: the variant it is compared with.
        paper_pp: the paper's difference, percentage points of success (``better`` − ``worse``).
        sizes: ``"mean"`` (averaged over the study's data sizes), ``"low"`` (the smallest) or ``"high"`` (the
            largest).
        where: the paper's words and section.
    """

    better: str
    worse: str
    paper_pp: float
    sizes: str
    where: str


#: The simulation claims of the paper's §4.1–4.2 (Fig. 3b), in its order.
PAPER_CLAIMS: tuple[PaperClaim, ...] = (
    PaperClaim("ours", "none", 56.0, "mean", "§4.1: free-space augmentation gives \"an average of 56 % task success "
               "rate improvement\" over no augmentation"),
    PaperClaim("gt_render", "ours", 8.0, "low", "§4.1: the ground-truth-rendering oracle is above ours by 8 % in "
               "the low-data regime"),
    PaperClaim("gt_render", "ours", 11.0, "high", "§4.1: … and by 11 % in the high-data regime"),
    PaperClaim("action_only", "none", 29.0, "mean", "§4.2: action-only augmentation \"boosts the average success "
               "rate by 29 %\" over no augmentation"),
    PaperClaim("ours", "action_only", 35.0, "high", "§4.2: ours outperforms action-only \"by up to 35 %, "
               "especially in high-data regimes\" (read: at the largest data size)"),
    PaperClaim("spartn", "none", 41.0, "mean", "§4.2: SPARTN has \"a performance gain of 41 %\" over no "
               "augmentation (read: averaged over the data sizes)"),
    PaperClaim("ours", "spartn", 15.0, "mean", "§4.2: ours outperforms SPARTN, \"boosting the average success rate "
               "by 15 %\""),
)

#: Every verdict :func:`verdict` gives, in the order the report counts them.
VERDICTS: tuple[str, ...] = ("reproduced", "direction only, smaller", "direction only, larger", "not resolved",
                             "not reproduced", "contradicted", "not measured yet")


def verdict(paper_pp: float, lo_pp: float, hi_pp: float) -> str:
    """The verdict on a claimed difference ``paper_pp`` (> 0: the claimed better variant is better) from the study's
    95 % interval ``[lo_pp, hi_pp]`` of the same difference (percentage points):

    - ``reproduced``: the interval excludes 0 on the paper's side and contains the paper's value;
    - ``direction only, smaller`` / ``larger``: it excludes 0 on the paper's side but lies below / above the
      paper's value;
    - ``not resolved``: it contains both 0 and the paper's value (too few configurations to tell);
    - ``not reproduced``: it contains 0 but not the paper's value;
    - ``contradicted``: it excludes 0 on the other side;
    - ``not measured yet``: no interval (NaN bounds).
    """
    if not (np.isfinite(lo_pp) and np.isfinite(hi_pp)):
        return "not measured yet"
    if lo_pp > hi_pp:
        raise ValueError(f"verdict: interval [{lo_pp}, {hi_pp}] has its bounds swapped")
    sign = 1.0 if paper_pp >= 0 else -1.0
    lo, hi = sorted((sign * lo_pp, sign * hi_pp))  # the paper's direction is positive from here on
    claim = abs(paper_pp)
    if lo > 0:
        if claim > hi:
            return "direction only, smaller"
        return "direction only, larger" if claim < lo else "reproduced"
    if hi < 0:
        return "contradicted"
    return "not resolved" if lo <= claim <= hi else "not reproduced"


def success_by_config(eval_dir: Path) -> dict[int, bool]:
    """``{configuration: success}`` of an evaluation directory's ``results.jsonl`` (empty when it has none)."""
    p = Path(eval_dir) / "results.jsonl"
    return {c: bool(r.get("success")) for c, r in ResultsLog(p).read().items()} if p.exists() else {}


def claim_result(cfg, claim: PaperClaim, n_boot: int = 10000, seed: int = 0,
                 machine: Callable[[str], str] | None = None) -> dict[str, Any]:
    """The study's number for one claim, from the record's evaluations (``success`` of each rollout).

    Returns a dict with ``sizes_used`` (the data sizes used: every size of the claim where both cells are evaluated),
    ``missing`` (cells of the claim's sizes not evaluated yet), ``n`` (configurations evaluated by every cell used),
    ``better_successes`` / ``worse_successes`` (success counts summed over the sizes used), ``diff_pp`` and
    ``ci95_pp`` (mean over the sizes used of ``better`` − ``worse``, percentage points; NaN when nothing is
    measured), ``verdict`` (:func:`verdict`; prefixed ``provisional:`` when a size is missing) and
    ``cross_machine`` (a pair was evaluated on two different machines: ``machine(step)`` names where
    ``eval/<cell>`` ran).
    """
    wanted = {"mean": list(cfg.sizes), "low": [min(cfg.sizes)], "high": [max(cfg.sizes)]}[claim.sizes]
    if claim.better not in cfg.variants or claim.worse not in cfg.variants:
        return {"claim": claim, "sizes_used": [], "missing": [], "n": 0, "better_successes": 0, "worse_successes": 0,
                "diff_pp": float("nan"), "ci95_pp": [float("nan"), float("nan")], "verdict": "not in this recipe",
                "cross_machine": False}
    pairs, missing = [], []
    for n in wanted:
        a, b = (success_by_config(record_eval_dir(cfg, {"name": f"{v}_n{n}"})) for v in (claim.better, claim.worse))
        missing += [f"{v}_n{n}" for v, rows in ((claim.better, a), (claim.worse, b)) if not rows]
        if a and b:
            pairs.append((n, a, b))
    configs = sorted(set.intersection(*(set(a) & set(b) for _, a, b in pairs))) if pairs else []
    pairs = pairs if configs else []
    sizes = [n for n, _, _ in pairs]
    x = np.array([[a[c] for c in configs] for _, a, _ in pairs], dtype=np.float64).reshape(len(sizes), len(configs))
    y = np.array([[b[c] for c in configs] for _, _, b in pairs], dtype=np.float64).reshape(len(sizes), len(configs))
    if configs:
        lo, hi = paired_bootstrap_interval(x.mean(axis=0), y.mean(axis=0), n_boot=n_boot, seed=seed)
        diff = float(x.mean() - y.mean())
    else:
        lo = hi = diff = float("nan")
    v = verdict(claim.paper_pp, 100.0 * lo, 100.0 * hi)
    if missing and v != "not measured yet":
        v = "provisional: " + v
    machine = machine or (lambda step: "here")
    cross = any(machine(f"eval/{claim.better}_n{n}") != machine(f"eval/{claim.worse}_n{n}") for n in sizes)
    return {"claim": claim, "sizes_used": sizes, "missing": missing, "n": len(configs),
            "better_successes": int(x.sum()), "worse_successes": int(y.sum()), "diff_pp": 100.0 * diff,
            "ci95_pp": [100.0 * lo, 100.0 * hi], "verdict": v, "cross_machine": cross}


def _sizes_text(claim: PaperClaim, r: dict[str, Any]) -> str:
    if not r["sizes_used"]:
        return "—"
    used = ", ".join(f"n={n}" for n in r["sizes_used"])
    return f"mean of {used}" if claim.sizes == "mean" and len(r["sizes_used"]) > 1 else used


def claims_section(cfg, machine: Callable[[str], str] | None = None, n_boot: int = 10000,
                   seed: int = 0) -> tuple[list[str], list[dict[str, Any]]]:
    """Markdown lines of the report's section "The paper's claims against this study" (a table, the verdict rule,
    and one sentence counting the verdicts), and the per-claim results of :func:`claim_result`."""
    results = [claim_result(cfg, c, n_boot=n_boot, seed=seed, machine=machine) for c in PAPER_CLAIMS]
    rows = []
    for r in results:
        c = r["claim"]
        mark = " ‡" if r["cross_machine"] else ""
        here = "—" if not r["sizes_used"] else (f"{r['diff_pp']:+.1f} [{r['ci95_pp'][0]:+.1f}, {r['ci95_pp'][1]:+.1f}]")
        counts = ("—" if not r["sizes_used"] else
                  f"{r['better_successes']} vs {r['worse_successes']} of {r['n'] * len(r['sizes_used'])}")
        todo = f" (no evaluation yet: {', '.join('`' + m + '`' for m in r['missing'])})" if r["missing"] else ""
        rows.append(f"| {c.where} | `{c.better}` − `{c.worse}` | {c.paper_pp:+.0f} | {_sizes_text(c, r)}{mark} | "
                    f"{counts} | {here} | **{r['verdict']}**{todo} |")
    tally = {}
    for r in results:
        key = r["verdict"].removeprefix("provisional: ")
        tally[key] = tally.get(key, 0) + 1
    said = "; ".join(f"{k}: {tally[k]}" for k in (*VERDICTS, "not in this recipe") if k in tally)
    lines = ["", "## The paper's claims against this study", "",
             "Each simulation claim of the paper (§4.1–4.2, Fig. 3b), read as a difference of full-task success in "
             "percentage points, against the same difference here: on the configurations both cells evaluated, "
             "summed success counts, the difference of the rates (averaged over the data sizes where the paper "
             "says \"average\") and its paired bootstrap 95 % interval (configurations resampled jointly across the "
             f"data sizes, {n_boot:,} times, seed {seed}). Low / high data regime = the smallest / largest data size "
             "of this recipe.", "",
             "Verdict: **reproduced** = the interval excludes 0 on the paper's side and contains the paper's value; "
             "**direction only** = it excludes 0 on the paper's side but not the paper's value (smaller or larger); "
             "**not resolved** = it contains both 0 and the paper's value; **not reproduced** = it contains 0 and "
             "not the paper's value; **contradicted** = it excludes 0 on the other side; **provisional** = a data "
             "size of the claim has no evaluation yet.", "",
             "| the paper | difference | paper, pp | data sizes here | successes here | here, pp [95 %] | verdict |",
             "|---|---|---:|---|---|---|---|", *rows, "", f"Verdicts so far — {said}."]
    if any(r["cross_machine"] for r in results):
        lines += ["", "‡ a pair of cells in this claim was evaluated on two different machines (see the note under "
                      "the paired table)."]
    return lines, results
