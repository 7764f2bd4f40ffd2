"""The square study's report: ``docs/square_study_<recipe>.md`` (tables) and ``docs/square_study_<recipe>.png``
(figure).

Everything is read from the study's record (``record_dir``: evaluation ``summary.json`` / ``results.jsonl``, export
summaries, ``study_state.json`` wall times, rendering fidelity); cells not evaluated yet are listed as such, never
filled in. The paper's claims and their verdicts: :mod:`umi_aug.square.claims` (its cone-angle claim:
:mod:`umi_aug.square.sweep_claims`).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.eval.results import ResultsLog
from umi_aug.eval.stats import mcnemar_exact_p, median_interval, paired_bootstrap_interval, wilson_interval
from umi_aug.io_utils import atomic_path, atomic_write_text
from umi_aug.square.claims import claims_section
from umi_aug.square.start_angle import start_angle_section
from umi_aug.square.study import (StudyError, eval_command, export_path, handover_configs, load_state,
                                  record_eval_dir, record_export_summary, study_cells, train_command, variant_path)
from umi_aug.square.sweep_claims import sweep_claims_section

__all__ = ["cell_metrics", "paired_vs", "paired_outcomes", "fidelity", "report_study", "write_report",
           "write_frames_sheet", "frames_sheet_panels", "frames_sheet_path"]

METRICS: tuple[str, ...] = ("success", "pregrasp_reached", "lifted", "inserted", "collision_table", "collision_peg")


def _cell_rows(eval_dir: Path) -> dict[int, dict[str, Any]]:
    """A cell's rollout records by configuration (empty when it has none)."""
    p = Path(eval_dir) / "results.jsonl"
    return ResultsLog(p).read() if p.exists() else {}


def cell_metrics(eval_dir: Path) -> dict[str, Any] | None:
    """Counts, rates and Wilson 95 % intervals of every metric ``eval_sim`` records, plus the median closest
    approach to the pre-grasp pose (mm / degrees; distribution-free 95 % interval of the median in mm), from a
    cell's ``results.jsonl`` (None when there is none)."""
    rows = list(_cell_rows(eval_dir).values())
    if not rows:
        return None
    n = len(rows)
    out: dict[str, Any] = {"n": n}
    for m in METRICS:
        k = int(sum(bool(r.get(m)) for r in rows))
        out[m] = {"count": k, "rate": k / n, "wilson95": list(wilson_interval(k, n))}
    pos = [1000.0 * r["pregrasp_min_pos_err_m"] for r in rows if r.get("pregrasp_min_pos_err_m") is not None]
    rot = [r["pregrasp_min_rot_err_deg"] for r in rows if r.get("pregrasp_min_rot_err_deg") is not None]
    out["closest_pregrasp_mm_median"] = float(np.median(pos)) if pos else None
    out["closest_pregrasp_mm_ci95"] = list(median_interval(pos)) if pos else None
    out["closest_pregrasp_deg_median"] = float(np.median(rot)) if rot else None
    out["nut_moved"] = int(sum((r.get("max_nut_rise_m") or 0.0) >= 0.005 for r in rows))
    out["ends"] = rollout_ends(rows)
    return out


#: :func:`rollout_ends`' classes, in the order the report shows them (they partition a cell's rollouts).
ENDS: tuple[str, ...] = ("success", "lifted_touched_peg", "lifted_no_peg_contact", "pregrasp_not_lifted",
                         "no_pregrasp_not_lifted")


def rollout_ends(rows: list[dict[str, Any]]) -> dict[str, int]:
    """Where each rollout ended, from ``eval_sim``'s records: a partition of the rollouts into :data:`ENDS` —
    succeeded; lifted the nut but did not insert it, with a gripper geom touching either peg at some step
    (``collision_peg``) or never;
    never lifted it, having reached the scripted expert's pre-grasp pose or not — plus ``lifted_without_pregrasp``
    (across classes: lifts, successful or not, that never reached the pre-grasp pose first)."""
    ends = dict.fromkeys(ENDS, 0)
    for r in rows:
        if r.get("success"):
            k = "success"
        elif r.get("lifted"):
            k = "lifted_touched_peg" if r.get("collision_peg") else "lifted_no_peg_contact"
        else:
            k = "pregrasp_not_lifted" if r.get("pregrasp_reached") else "no_pregrasp_not_lifted"
        ends[k] += 1
    ends["lifted_without_pregrasp"] = int(sum(bool(r.get("lifted") or r.get("success"))
                                              and not r.get("pregrasp_reached") for r in rows))
    return ends


def paired_vs(eval_dir: Path, baseline_dir: Path) -> dict[str, Any] | None:
    """A cell against a baseline cell on the configurations both evaluated (the study evaluates every cell on the
    same ones): the per-configuration differences of the closest approach to the pre-grasp pose (cell − baseline;
    position in mm and orientation in degrees, each the smallest error over the rollout; median and its
    distribution-free 95 % interval), in how many configurations the cell came closer, and both success counts.
    None when they share no configuration."""
    a, b = _cell_rows(eval_dir), _cell_rows(baseline_dir)
    key, rkey = "pregrasp_min_pos_err_m", "pregrasp_min_rot_err_deg"
    both = sorted(c for c in set(a) & set(b)
                  if all(r[c].get(k) is not None for r in (a, b) for k in (key, rkey)))
    if not both:
        return None
    d = np.array([1000.0 * (a[c][key] - b[c][key]) for c in both])
    dr = np.array([a[c][rkey] - b[c][rkey] for c in both])
    return {"n": len(both), "closest_mm_diff_median": float(np.median(d)),
            "closest_mm_diff_ci95": list(median_interval(d)), "closer": int((d < 0).sum()),
            "closest_deg_diff_median": float(np.median(dr)), "closest_deg_diff_ci95": list(median_interval(dr)),
            "closer_deg": int((dr < 0).sum()),
            "successes": int(sum(bool(a[c].get("success")) for c in both)),
            "baseline_successes": int(sum(bool(b[c].get("success")) for c in both))}


def paired_outcomes(eval_dir: Path, other_dir: Path, key: str = "success", n_boot: int = 10000,
                    seed: int = 0) -> dict[str, Any] | None:
    """A cell against another on the configurations both evaluated, for one boolean outcome ``key`` of the rollout
    records (``success``, ``pregrasp_reached``, ...): both counts, the discordant pairs (``only_cell``: the cell
    succeeded and the other did not; ``only_other``), the exact McNemar p-value, and the difference of the two
    rates (cell − other, fractions) with its paired percentile-bootstrap 95 % interval (configurations
    resampled; ``seed`` fixed so the report is reproducible). None when they share no configuration."""
    a, b = _cell_rows(eval_dir), _cell_rows(other_dir)
    both = sorted(set(a) & set(b))
    if not both:
        return None
    x = np.array([bool(a[c].get(key)) for c in both])
    y = np.array([bool(b[c].get(key)) for c in both])
    only_a, only_b = int((x & ~y).sum()), int((~x & y).sum())
    lo, hi = paired_bootstrap_interval(x, y, n_boot=n_boot, seed=seed)
    return {"n": len(both), "key": key, "cell": int(x.sum()), "other": int(y.sum()), "only_cell": only_a,
            "only_other": only_b, "mcnemar_p": mcnemar_exact_p(only_a, only_b),
            "diff": float(x.mean() - y.mean()), "diff_ci95": [lo, hi]}


#: the outcomes :func:`_ours_rows` pairs: (where the records are, record key, label)
PAIRED_OUTCOMES: tuple[tuple[bool, str, str], ...] = ((False, "success", "(a) success"),
                                                      (False, "pregrasp_reached", "(b) pre-grasp reached"),
                                                      (True, "success", "(c) learned approach + scripted grasp"))


def _machine(lent: dict[str, dict[str, Any]], step: str) -> str:
    """Where a step ran: the lent machine's name, or ``"here"`` (the study's own machine)."""
    return lent[step]["machine"] if step in lent else "here"


def _ours_rows(cfg, cells, lent: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Markdown rows: ``ours`` against every other variant of the main grid at the same data size, for each
    outcome of :data:`PAIRED_OUTCOMES` both cells have; a pair evaluated on two different machines is marked ‡."""
    lent = lent or {}
    rows = []
    for n in cfg.sizes:
        ours = {"name": f"ours_n{n}"}
        for c in cells:
            if c["theta"] is not None or c["variant"] == "ours" or c["n"] != n:
                continue
            for handover, key, label in PAIRED_OUTCOMES:
                if handover and not cfg.eval_handover:
                    continue
                p = paired_outcomes(record_eval_dir(cfg, ours, handover), record_eval_dir(cfg, c, handover), key)
                if p is None:
                    continue
                lo, hi = p["diff_ci95"]
                step = "eval_handover/" if handover else "eval/"
                mark = " ‡" if _machine(lent, step + ours["name"]) != _machine(lent, step + c["name"]) else ""
                rows.append(f"| {c['variant']}{mark} | {n} | {label} | {p['n']} | {p['cell']} vs {p['other']} | "
                            f"{p['only_cell']} / {p['only_other']} | {p['mcnemar_p']:.3g} | {100 * p['diff']:+.1f} "
                            f"[{100 * lo:+.1f}, {100 * hi:+.1f}] |")
    return rows


def _pct(m: dict[str, Any], key: str) -> str:
    v = m[key]
    lo, hi = v["wilson95"]
    return f"{100 * v['rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def _closest(m: dict[str, Any]) -> str:
    if m["closest_pregrasp_mm_median"] is None:
        return "—"
    lo, hi = m["closest_pregrasp_mm_ci95"]
    return f"{m['closest_pregrasp_mm_median']:.0f} [{lo:.0f}, {hi:.0f}] / {m['closest_pregrasp_deg_median']:.1f}"


def _paired_rows(cfg, cells, lent: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Markdown rows: every evaluated cell of the main grid against ``none`` at the same data size (‡: the two were
    evaluated on different machines)."""
    lent = lent or {}
    rows = []
    for c in cells:
        if c["theta"] is not None or c["variant"] == "none":
            continue
        p = paired_vs(record_eval_dir(cfg, c), record_eval_dir(cfg, {"name": f"none_n{c['n']}"}))
        if p is None:
            continue
        lo, hi = p["closest_mm_diff_ci95"]
        rlo, rhi = p["closest_deg_diff_ci95"]
        mark = " ‡" if _machine(lent, f"eval/{c['name']}") != _machine(lent, f"eval/none_n{c['n']}") else ""
        rows.append(f"| {c['variant']}{mark} | {c['n']} | {p['n']} | {p['closest_mm_diff_median']:+.0f} [{lo:+.0f}, "
                    f"{hi:+.0f}] | {p['closer']} / {p['n']} | {p['closest_deg_diff_median']:+.1f} [{rlo:+.1f}, "
                    f"{rhi:+.1f}] | {p['closer_deg']} / {p['n']} | {p['successes']} vs {p['baseline_successes']} |")
    return rows


#: In the record: steps whose work ran on another machine (a lent GPU machine's evaluation, eval/lent_gpu_eval.sh),
#: ``{"<step>": {"seconds": wall time there, "machine": "...", "workers": N}}``, and the folder's README beside it.
LENT_STEPS = "lent_machine/steps.json"


def lent_steps(cfg) -> dict[str, dict[str, Any]]:
    """The record's :data:`LENT_STEPS` (empty when there is none).

    Raises:
        StudyError: the file is not a JSON object of step → {"seconds": number ≥ 0, "machine": str, ...}.
    """
    path = cfg.record / LENT_STEPS
    if not path.exists():
        return {}
    try:
        steps = json.loads(path.read_text())
    except ValueError as exc:
        raise StudyError(f"{path}: not JSON ({exc})") from exc
    bad = [k for k, v in (steps.items() if isinstance(steps, dict) else [("(file)", None)])
           if not isinstance(v, dict) or not isinstance(v.get("machine"), str)
           or not isinstance(v.get("seconds"), (int, float)) or not v["seconds"] >= 0]
    if bad:
        raise StudyError(f"{path}: steps {bad} need {{\"seconds\": wall time ≥ 0, \"machine\": \"...\"}}")
    return steps


def _minutes(state: dict[str, Any], step: str, lent: dict[str, dict[str, Any]] | None = None) -> str:
    """A step's wall minutes: the record's, or, for a step that ran on a lent machine, the time there (marked †)."""
    if lent and step in lent:
        return f"{lent[step]['seconds'] / 60.0:.1f} †"
    row = state.get("steps", {}).get(step)
    return "—" if row is None else f"{row['seconds'] / 60.0:.1f}" + ("" if row.get("done") else " (partial)")


def _cross_machine_note(cfg, rows: list[str]) -> list[str]:
    if not any(" ‡ |" in r for r in rows):
        return []
    readme = cfg.record / Path(LENT_STEPS).parent / "README.md"
    return ["", "‡ the two cells were evaluated on different machines (one on a lent GPU machine, whose renderer "
                "draws the wrist frames a little differently): a machine effect is part of this difference; how "
                f"large it can be: [{Path(LENT_STEPS).parent}/README.md]"
                f"({os.path.relpath(readme, Path(cfg.report_md).parent)})."]


def _lent_note(cfg, lent: dict[str, dict[str, Any]]) -> list[str]:
    if not lent:
        return []
    where = "; ".join(f"`{k}`: {v['machine']}" + (f", {v['workers']} workers" if v.get("workers") else "")
                      for k, v in lent.items())
    readme = cfg.record / Path(LENT_STEPS).parent / "README.md"
    return ["", f"† ran on another machine, and its minutes are the wall time there ({where}); how, and whether the "
                f"machine changes outcomes: [{Path(LENT_STEPS).parent}/README.md]"
                f"({os.path.relpath(readme, Path(cfg.report_md).parent)})."]


def report_study(cfg) -> dict[str, Any]:
    """The report of a study recipe from its record: :func:`write_report` over every cell of the recipe."""
    return write_report(cfg, study_cells(cfg), load_state(cfg))


def write_report(cfg, cells: list[dict[str, Any]], state: dict[str, Any]) -> dict[str, Any]:
    """Write ``cfg.report_md`` and ``cfg.report_png`` (and ``<record>/report.json``); returns the JSON.

    Metrics come from the record (``record_eval_dir``), export summaries from the record's copies; the rendering
    fidelity is computed when both datasets it compares are on this machine (and kept in ``<record>/fidelity.json``),
    otherwise read from there."""
    metrics = {c["name"]: cell_metrics(record_eval_dir(cfg, c)) for c in cells}
    handover = {c["name"]: cell_metrics(record_eval_dir(cfg, c, True)) for c in cells} if cfg.eval_handover else {}
    big = max(cfg.sizes)
    ours_p = variant_path(cfg, {"name": f"ours_n{big}"})
    gt_p = variant_path(cfg, {"name": f"gt_render_n{big}"})
    fid_p = cfg.record / "fidelity.json"
    fid = None
    if ours_p.exists() and gt_p.exists():
        fid = fidelity(ours_p, gt_p)
        atomic_write_text(fid_p, json.dumps(fid, indent=1) + "\n")
    elif fid_p.exists():
        fid = json.loads(fid_p.read_text())
    exports = {}
    for th in [None, *sorted({c["theta"] for c in cells if c["theta"] is not None})]:
        for sp in (record_export_summary(cfg, th), Path(str(export_path(cfg, th)) + ".summary.json")):
            if sp.exists():
                exports["main" if th is None else f"theta{th:g}"] = json.loads(sp.read_text())
                break
    report = {"recipe": _recipe_dict(cfg), "metrics": metrics, "handover_metrics": handover, "fidelity": fid,
              "exports": {k: {kk: v.get(kk) for kk in ("n_augmented", "n_failed", "n_resampled", "n_jobs",
                                                      "status_counts", "timings_s")} for k, v in exports.items()},
              "steps": state.get("steps", {})}
    cfg.record.mkdir(parents=True, exist_ok=True)
    sheet = write_frames_sheet(cfg)
    if sheet is None and frames_sheet_path(cfg).exists():
        sheet = str(frames_sheet_path(cfg))  # made on a machine that had the datasets
    report["frames_sheet"] = sheet
    lent = lent_steps(cfg)
    claims_lines, claims = claims_section(cfg, machine=lambda step: _machine(lent, step))
    report["claims"] = [{**asdict(r["claim"]), **{k: _finite_or_none(v) for k, v in r.items() if k != "claim"}}
                        for r in claims]
    sweep_lines, sweep_claims = sweep_claims_section(cfg)
    report["sweep_claims"] = [{**asdict(r["claim"]), **{k: _finite_or_none(v) for k, v in r.items() if k != "claim"}}
                              for r in sweep_claims]
    atomic_write_text(cfg.record / "report.json", json.dumps(report, indent=1) + "\n")
    _write_md(cfg, cells, metrics, fid, report["exports"], state, report["frames_sheet"], handover, lent,
              claims_lines + sweep_lines)
    _write_png(cfg, cells, metrics, handover)
    return report


def _finite_or_none(v: Any) -> Any:
    """JSON has no NaN: a float (or a list of floats) that is not finite becomes null."""
    if isinstance(v, list):
        return [_finite_or_none(x) for x in v]
    return None if isinstance(v, float) and not np.isfinite(v) else v


def _recipe_dict(cfg) -> dict[str, Any]:
    d = asdict(cfg)
    d.pop("python", None)
    return d


def _ends_section(cells, metrics) -> list[str]:
    """The table of :func:`rollout_ends` for every evaluated cell (nothing when none is evaluated)."""
    rows = []
    for c in cells:
        m = metrics[c["name"]]
        if m is None:
            continue
        e = m["ends"]
        rows.append(f"| `{c['name']}` | {m['n']} | " + " | ".join(str(e[k]) for k in ENDS)
                    + f" | {e['lifted_without_pregrasp']} |")
    if not rows:
        return []
    return ["", "## Where the rollouts end", "",
            "Each cell's rollouts by how far they got (counts; the five columns after n add up to n). Lifted = the "
            "nut rose off the table held by a finger; a peg touched = a gripper geom (hand or finger) touched either "
            "peg. The last column counts the lifts (successful or not) that never reached the scripted expert's "
            "pre-grasp pose (2 cm / 15°) first: grasps from elsewhere on the handle.", "",
            "| cell | n | success | lifted, not inserted: gripper touched a peg | lifted, not inserted: gripper never "
            "touched a peg | not lifted: pre-grasp reached | not lifted: pre-grasp never reached | lifts without "
            "pre-grasp |",
            "|---|---:|---:|---:|---:|---:|---:|---:|", *rows]


def _handover_cell(cfg, m: dict[str, Any] | None) -> str:
    """The main table's metric (c) cell: success of the learned approach + scripted grasp, or why it is empty."""
    if not cfg.eval_handover:
        return ""
    return " not evaluated yet |" if m is None else f" {_pct(m, 'success')} |"


def _write_md(cfg, cells, metrics, fid, exports, state, sheet: str | None = None,
              handover: dict[str, Any] | None = None, lent: dict[str, dict[str, Any]] | None = None,
              claims_lines: list[str] | None = None) -> None:
    handover, lent = handover or {}, lent or {}
    hcol = " (c) learned approach + scripted grasp |" if cfg.eval_handover else ""
    L = [f"# Square study — recipe `{cfg.name}`", "",
         "Generated by `eval/square_study.py` from the study's record (`" + str(cfg.record) + "`); a cell "
         "without an evaluation is marked as such. Success and sub-goals: rate in % with the Wilson 95 % "
         f"interval over the evaluated configurations (`{cfg.eval_configs_file}`, `configs={cfg.eval_configs}`).",
         "", f"![success, pre-grasp, closest approach and its paired orientation difference vs none per data size; "
         f"the cone sweep]({os.path.relpath(cfg.report_png, Path(cfg.report_md).parent)})",
         "", "## Success and sub-goals", "",
         "| variant | demos | n | success | pre-grasp reached | lifted | inserted | gripper–table | gripper–peg | "
         "closest approach to pre-grasp: median mm [95 %] / ° | train min | eval min |" + hcol,
         "|---|---:|---:|---|---|---|---|---|---|---|---:|---:|" + ("---|" if hcol else "")]
    for c in cells:
        if c["theta"] is not None:
            continue
        m = metrics[c["name"]]
        tm, em = _minutes(state, f"train/{c['name']}", lent), _minutes(state, f"eval/{c['name']}", lent)
        hc = _handover_cell(cfg, handover.get(c["name"]))
        if m is None:
            L.append(f"| {c['variant']} | {c['n']} | 0 | not evaluated yet | | | | | | | {tm} | {em} |" + hc)
            continue
        ca = _closest(m)
        L.append(f"| {c['variant']} | {c['n']} | {m['n']} | {_pct(m, 'success')} | {_pct(m, 'pregrasp_reached')} | "
                 f"{_pct(m, 'lifted')} | {_pct(m, 'inserted')} | {_pct(m, 'collision_table')} | "
                 f"{_pct(m, 'collision_peg')} | {ca} | {tm} | {em} |" + hc)
    if cfg.eval_handover:
        L += ["", "(c): the learned policy drives until it reaches the scripted expert's pre-grasp pose (2 cm / 15°) "
              "or for `handover_step_limit` control steps, then the scripted expert finishes from the state it "
              f"left (`eval_sim.py handover=expert`; configurations `{handover_configs(cfg)}`): labelled as such, "
              "never counted as the policy's own success."]
    L += _lent_note(cfg, lent)
    ours_rows = _ours_rows(cfg, cells, lent) if "ours" in cfg.variants else []
    if ours_rows:
        L += ["", "## `ours` against every other variant, configuration by configuration", "",
              "On the configurations both cells evaluated: both counts, the discordant pairs (only `ours` / only the "
              "other succeeded), the exact McNemar p-value on them (two-sided), and the difference of the rates "
              "(`ours` − other, percentage points) with its paired bootstrap 95 % interval (configurations "
              "resampled, 10,000 times, seed 0).", "",
              "| other variant | demos | outcome | paired configurations | ours vs other | only ours / only other | "
              "McNemar p | Δ rate, pp [95 %] |", "|---|---:|---|---:|---|---|---:|---|", *ours_rows,
              *_cross_machine_note(cfg, ours_rows)]
    L += claims_lines or []
    paired = _paired_rows(cfg, cells, lent)
    if paired:
        L += ["", "## Against `none`, configuration by configuration", "",
              "Every cell is evaluated on the same configurations, so each can be paired with `none` at the same "
              "data size: the differences of the closest approach to the pre-grasp pose, in position and in "
              "orientation (each the smallest error over the rollout; negative = closer than `none`; median and its "
              "distribution-free 95 % interval), in how many configurations it came closer, and the successes of "
              "both.", "",
              "| variant | demos | paired configurations | Δ closest position, median mm [95 %] | closer | "
              "Δ closest orientation, median ° [95 %] | closer | successes (cell vs none) |",
              "|---|---:|---:|---|---:|---|---:|---|", *paired, *_cross_machine_note(cfg, paired)]
    sweep = [c for c in cells if c["theta"] is not None or (c["variant"] == "ours" and c["n"] == cfg.sweep_size)]
    if any(c["theta"] is not None for c in cells):
        L += ["", f"## Cone-angle sweep (`ours`, {cfg.sweep_size} demos, r = {cfg.radius_m} m)", "",
              "| θ (°) | n | success | pre-grasp reached | lifted | closest approach: median mm [95 %] / ° | "
              f"paired vs `none_n{cfg.sweep_size}`: Δ mm [95 %] / Δ ° [95 %] |" + hcol,
              "|---:|---:|---|---|---|---|---|" + ("---|" if hcol else "")]

        for c in sorted(sweep, key=lambda c: cfg.theta_deg if c["theta"] is None else c["theta"]):
            m = metrics[c["name"]]
            th = cfg.theta_deg if c["theta"] is None else c["theta"]
            hc = _handover_cell(cfg, handover.get(c["name"]))
            if m is None:
                L.append(f"| {th:g} | 0 | not evaluated yet | | | | |" + hc)
                continue
            p = paired_vs(record_eval_dir(cfg, c), record_eval_dir(cfg, {"name": f"none_n{cfg.sweep_size}"}))
            pv = "—" if p is None else (
                f"{p['closest_mm_diff_median']:+.0f} [{p['closest_mm_diff_ci95'][0]:+.0f}, "
                f"{p['closest_mm_diff_ci95'][1]:+.0f}] / {p['closest_deg_diff_median']:+.1f} "
                f"[{p['closest_deg_diff_ci95'][0]:+.1f}, {p['closest_deg_diff_ci95'][1]:+.1f}]")
            L.append(f"| {th:g} | {m['n']} | {_pct(m, 'success')} | {_pct(m, 'pregrasp_reached')} | "
                     f"{_pct(m, 'lifted')} | {_closest(m)} | {pv} |" + hc)
    L += _ends_section(cells, metrics)
    L += start_angle_section([c for c in cells if c["theta"] is None],
                             lambda c: _cell_rows(record_eval_dir(cfg, c)), cfg.eval_configs_file)
    L += ["", "## Rendering fidelity of `ours` against `gt_render` at the augmented poses", ""]
    if fid is None:
        L.append("Not computed yet (needs both datasets of the largest data size).")
    else:
        L += ["New (pre-splice) frames of the same augmented episodes, inside the fisheye image circle; `ours` = "
              "3DGS (static scene + nut) + gripper overlay, `gt_render` = the simulator with the Panda placed by "
              "IK.", "", "| frames | PSNR median dB | PSNR 5th pct dB | SSIM median | SSIM 5th pct |",
              "|---:|---:|---:|---:|---:|",
              f"| {fid['frames']} | {fid['psnr_median']:.2f} | {fid['psnr_p5']:.2f} | {fid['ssim_median']:.3f} | "
              f"{fid['ssim_p5']:.3f} |"]
    if sheet is not None:
        rel = os.path.relpath(sheet, Path(cfg.report_md).parent)
        L += ["", f"![the same augmented episodes in ours, gt_render (|difference| x3) and action_only; SPARTN's "
                  f"perturbed frames beside the originals]({rel})"]
    L += ["", "## Data generation", "", "| export | episodes | failed jobs | resampled attempts | attempt failures "
          "by reason | plan s | render s | total s |", "|---|---:|---:|---:|---|---:|---:|---:|"]
    for k, e in exports.items():
        t = e.get("timings_s") or {}
        reasons = ", ".join(f"{r}: {n}" for r, n in sorted((e.get("status_counts") or {}).items())) or "none"
        L.append(f"| {k} | {e.get('n_augmented')} | {e.get('n_failed')} | {e.get('n_resampled')} | {reasons} | "
                 f"{t.get('plan_s', 0):.0f} | {t.get('render_s', 0):.0f} | {t.get('total_s', 0):.0f} |")
    L += ["", "## Wall time per step (minutes)", "", "| step | minutes |", "|---|---:|"]
    for name in state.get("steps", {}):
        L.append(f"| {name} | {_minutes(state, name, lent)} |")
    L += _lent_note(cfg, lent)
    ex = cells[0]
    L += ["", "## Commands", "", "```", f"python eval/square_study.py recipe={cfg.name}   # all steps, resumable", "",
          "# the source demos (the study makes them when demos_dir lacks them):",
          f"umi-aug square-demos --n {max(cfg.sizes)} --image-size {cfg.image_size} --workers {cfg.augment_workers} "
          f"--out {cfg.demos_dir}", "",
          "# what one cell runs (here " + ex["name"] + "):", " ".join(train_command(cfg, ex)[1:]),
          " ".join(eval_command(cfg, ex)[1:]),
          *([" ".join(eval_command(cfg, ex, handover=True)[1:])] if cfg.eval_handover else []), "```", ""]
    p = Path(cfg.report_md)
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(p, "\n".join(L))


def _legend(ax, **kw) -> None:
    """A legend only where something was drawn (matplotlib warns otherwise)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kw)


def _paired_deg(cfg, cell: dict[str, Any], n_none: int) -> tuple[float, float, float] | None:
    """``cell`` against ``none_n{n_none}``: the median per-configuration difference of the closest orientation to
    the pre-grasp pose (degrees, negative = closer) and its 95 % interval, or None (nothing paired)."""
    p = paired_vs(record_eval_dir(cfg, cell), record_eval_dir(cfg, {"name": f"none_n{n_none}"}))
    if p is None:
        return None
    return p["closest_deg_diff_median"], *p["closest_deg_diff_ci95"]


def _errorbar_median(ax, xs, meds_cis, **kw) -> None:
    """Medians with their asymmetric 95 % intervals: ``meds_cis`` = ``[(median, lo, hi), ...]``."""
    a = np.array(meds_cis, dtype=float).reshape(-1, 3)
    ax.errorbar(xs, a[:, 0], yerr=[a[:, 0] - a[:, 1], a[:, 2] - a[:, 0]], capsize=3, **kw)


def _write_png(cfg, cells, metrics, handover: dict[str, Any] | None = None) -> None:
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    # 2 x 3: (a) success | (c) learned approach + scripted grasp | (b) pre-grasp reached; closest approach |
    # paired orientation difference | cone sweep. (c) has its own panel: at ~60 % it would flatten (a)'s few %.
    fig, grid = plt.subplots(2, 3, figsize=(18, 9.5))
    ax_success, ax_handover, ax_pregrasp, ax_mm, ax_deg, ax_sweep = grid.ravel()
    colour = {v: f"C{i}" for i, v in enumerate(cfg.variants)}  # one colour per variant in every panel
    for v in cfg.variants:  # the metric that separates policies that never succeed
        pts = sorted((c["n"], metrics[c["name"]]) for c in cells if c["variant"] == v and c["theta"] is None
                     and metrics[c["name"]] is not None and metrics[c["name"]]["closest_pregrasp_mm_median"] is not None)
        if pts:
            med = np.array([m["closest_pregrasp_mm_median"] for _, m in pts])
            ci = np.array([m["closest_pregrasp_mm_ci95"] for _, m in pts])
            ax_mm.errorbar([n for n, _ in pts], med, yerr=[med - ci[:, 0], ci[:, 1] - med], marker="o", capsize=3,
                           label=v, color=colour[v])
    ax_mm.set_xlabel("source demos")
    ax_mm.set_ylabel("mm")
    ax_mm.set_title("closest approach to pre-grasp (median, 95 %)")
    _legend(ax_mm, fontsize=8)
    for v in cfg.variants:  # what separates the cells: the paired orientation difference against none
        pts = [(c["n"], _paired_deg(cfg, c, c["n"])) for c in cells
               if c["variant"] == v and v != "none" and c["theta"] is None]
        pts = sorted((n, p) for n, p in pts if p is not None)
        if pts:
            _errorbar_median(ax_deg, [n for n, _ in pts], [p for _, p in pts], marker="o", label=v, color=colour[v])
    ax_deg.axhline(0.0, color="0.5", linewidth=0.8)
    ax_deg.set_xlabel("source demos")
    ax_deg.set_ylabel("°")
    ax_deg.set_title("Δ closest orientation vs none (paired, median, 95 %)")
    _legend(ax_deg, fontsize=8)
    panels = [(ax_success, "success", "(a) task success", metrics),
              (ax_pregrasp, "pregrasp_reached", "(b) pre-grasp reached", metrics)]
    if handover:
        panels.insert(1, (ax_handover, "success", "(c) learned approach + scripted grasp", handover))
    else:
        ax_handover.set_axis_off()
        ax_handover.set_title("(c) learned approach + scripted grasp: not evaluated")
    for ax, key, title, source in panels:
        for v in cfg.variants:
            xs, ys, lo, hi = [], [], [], []
            for c in cells:
                m = source.get(c["name"])
                if c["variant"] != v or c["theta"] is not None or m is None:
                    continue
                r = m[key]
                xs.append(c["n"])
                ys.append(100 * r["rate"])
                lo.append(100 * (r["rate"] - r["wilson95"][0]))
                hi.append(100 * (r["wilson95"][1] - r["rate"]))
            if xs:
                ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=3, label=v, color=colour[v])
        ax.set_xlabel("source demos")
        ax.set_ylabel("%")
        ax.set_title(f"{title} (Wilson 95 %)")
        _legend(ax, fontsize=8)
    ax = ax_sweep
    pts = []
    for c in cells:
        th = cfg.theta_deg if c["theta"] is None else c["theta"]
        if c["variant"] == "ours" and c["n"] == cfg.sweep_size and metrics[c["name"]] is not None:
            pts.append((th, metrics[c["name"]]))
    for key in ("success", "pregrasp_reached"):
        pts.sort(key=lambda t: t[0])
        if pts:
            ax.errorbar([p[0] for p in pts], [100 * p[1][key]["rate"] for p in pts],
                        yerr=[[100 * (p[1][key]["rate"] - p[1][key]["wilson95"][0]) for p in pts],
                              [100 * (p[1][key]["wilson95"][1] - p[1][key]["rate"]) for p in pts]],
                        marker="o", capsize=3, label=key)
    ax.set_xlabel("cone half-angle θ (°)")
    ax.set_ylabel("%")
    ax.set_title(f"cone sweep, ours, {cfg.sweep_size} demos")
    handles, labels = ax.get_legend_handles_labels()
    sweep = [(cfg.theta_deg if c["theta"] is None else c["theta"], _paired_deg(cfg, c, cfg.sweep_size))
             for c in cells if c["variant"] == "ours" and c["n"] == cfg.sweep_size]
    sweep = sorted((th, p) for th, p in sweep if p is not None)
    if sweep:
        ax2 = ax.twinx()
        _errorbar_median(ax2, [th for th, _ in sweep], [p for _, p in sweep], color="k", linestyle="--", marker="s",
                         label="Δ closest orientation vs none (°, paired, 95 %)")
        ax2.axhline(0.0, color="0.5", linewidth=0.8)
        ax2.set_ylabel("Δ closest orientation vs none (°)")
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    if handles:  # below the panel: the lines span its whole height
        ax.legend(handles, labels, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
    for a in (ax_success, ax_handover, ax_pregrasp, ax_mm, ax_deg):
        a.set_xticks(sorted(cfg.sizes))
    ax_sweep.set_xticks(sorted({float(t) for t in [*cfg.sweep_thetas, cfg.theta_deg]}))
    fig.suptitle(f"square study — {cfg.name}")
    fig.tight_layout()
    p = Path(cfg.report_png)
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(p) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def frames_sheet_path(cfg) -> Path:
    """``<report_png stem>_frames.jpg`` beside the figure."""
    p = Path(cfg.report_png)
    return p.with_name(p.stem + "_frames.jpg")


def _episode_rows(buf, rec) -> dict[tuple[int, int], np.ndarray]:
    ends = np.asarray(buf.episode_ends)
    out = {}
    for e in range(len(ends)):
        out.setdefault((int(rec["aug_source_episode"][e]), int(rec["aug_id"][e])), np.arange(ends[e - 1] if e else 0,
                                                                                             ends[e]))
    return out


def frames_sheet_panels(cfg, n_episodes: int = 4) -> list[list[dict[str, Any]]] | None:
    """The frames of :func:`write_frames_sheet`, row by row: each panel ``{"image", "title", ...}``. Augmented rows
    carry ``key`` (source demo, aug id) and ``t``; the SPARTN row pairs each perturbed frame (``kind`` "perturbed",
    with ``demo``, ``t``, ``episode``) with the source demo's frame ``t`` it perturbs (``kind`` "original"). None
    when the largest data size's ours or gt_render dataset is not there; the action_only panels and the SPARTN row
    are left out while their datasets are not there yet (a study makes the variants one after another)."""
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.data import ReplayBuffer
    from umi_aug.square.variants import VARIANT_ATTR

    big = max(cfg.sizes)
    paths = {v: variant_path(cfg, {"name": f"{v}_n{big}"}) for v in ("ours", "gt_render", "action_only", "spartn")}
    if not (paths["ours"].exists() and paths["gt_render"].exists()):
        return None
    paths = {v: p for v, p in paths.items() if p.exists()}
    recs = {v: read_episode_records(p) for v, p in paths.items()}
    bufs = {v: ReplayBuffer.open(p) for v, p in paths.items()}
    try:
        rows = {v: _episode_rows(bufs[v], recs[v]) for v in paths}
        img = lambda v, r: np.asarray(bufs[v]["camera0_rgb"][int(r)])  # noqa: E731
        gt = recs["gt_render"]
        splice = {(int(gt["aug_source_episode"][e]), int(gt["aug_id"][e])): int(gt["aug_splice_index"][e])
                  for e in range(len(gt["aug_id"]))}
        shown = [v for v in ("ours", "gt_render", "action_only") if v in paths]
        shared = sorted(k for k in rows["gt_render"] if k[1] >= 0 and all(k in rows[v] for v in shown))
        by_demo: dict[int, tuple[int, int]] = {}
        for k in shared:
            by_demo.setdefault(k[0], k)
        picks = list(by_demo.values())[:: max(1, len(by_demo) // n_episodes)][:n_episodes]
        panels: list[list[dict[str, Any]]] = []
        for k in picks:
            row = []
            for t in (0, max(1, splice[k] // 2)):
                im = {v: img(v, rows[v][k][t]) for v in shown}
                a, g = im["ours"].astype(np.float32), im["gt_render"].astype(np.float32)
                im["|ours-gt| x3"] = np.clip(3.0 * np.abs(a - g), 0, 255).astype(np.uint8)
                for name in ("ours", "gt_render", "|ours-gt| x3", "action_only"):
                    if name in im:
                        row.append({"image": im[name], "title": f"demo {k[0]} aug {k[1]} t={t}: {name}", "key": k,
                                    "t": t})
            panels.append(row)
        if "spartn" not in paths:
            return panels
        # SPARTN: short episode i of a demo perturbs demo frame t = To-1 + (i // per_step)*stride (its frame To-1)
        sp = dict(bufs["spartn"].root.attrs.get(VARIANT_ATTR, {})).get("spartn") or {}
        To, stride, per = int(sp.get("obs_horizon", 2)), int(sp.get("stride", 2)), int(sp.get("per_step", 1))
        rs = recs["spartn"]
        short = [e for e in range(len(rs["aug_id"])) if int(rs["aug_id"][e]) == -2]
        ends = np.asarray(bufs["spartn"].episode_ends)
        row = []
        for e in short[:: max(1, len(short) // n_episodes)][:n_episodes]:
            d = int(rs["aug_source_episode"][e])
            before = sum(1 for f in short if f < e and int(rs["aug_source_episode"][f]) == d)
            t = To - 1 + stride * (before // per)
            start = int(ends[e - 1]) if e else 0
            row.append({"image": img("spartn", rows["spartn"][(d, -1)][t]), "title": f"demo {d} t={t}: original",
                        "kind": "original", "demo": d, "t": t, "episode": e, "j": before % per})
            row.append({"image": img("spartn", start + To - 1), "title": "spartn perturbed", "kind": "perturbed",
                        "demo": d, "t": t, "episode": e, "j": before % per})
        panels.append(row)
        return panels
    finally:
        for b in bufs.values():
            b.close()


def write_frames_sheet(cfg, n_episodes: int = 4) -> str | None:
    """What the policies see: the same augmented episodes' frames in ``ours`` (3DGS + overlay), ``gt_render`` (the
    simulator) and ``action_only`` (the original demo's frame), with |ours − gt| ×3, at the episode's first frame
    and half-way to the splice; plus SPARTN's perturbed frames beside the original frames they perturb
    (:func:`frames_sheet_panels`). Written to :func:`frames_sheet_path`; None when the datasets are not there."""
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    panels = frames_sheet_panels(cfg, n_episodes)
    if panels is None:
        return None
    n_cols = max(len(r) for r in panels)
    fig, axes = plt.subplots(len(panels), n_cols, figsize=(2 * n_cols, 2.1 * len(panels)), squeeze=False)
    for i, row in enumerate(panels):
        for j, p in enumerate(row):
            axes[i, j].imshow(p["image"])
            axes[i, j].set_title(p["title"], fontsize=7)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"square study {cfg.name}: what each variant trains on ({max(cfg.sizes)} demos)", fontsize=10)
    fig.tight_layout()
    out = frames_sheet_path(cfg)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=100, format="jpg", pil_kwargs={"quality": 88})
    plt.close(fig)
    return str(out)


def fidelity(ours: Path, gt: Path, max_frames: int = 2000, seed: int = 0) -> dict[str, Any]:
    """PSNR / SSIM of ``ours`` vs ``gt_render`` on the new frames of the augmented episodes they share (inside the
    fisheye image circle): median and 5th percentile."""
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.data import ReplayBuffer

    ra, rb = read_episode_records(ours), read_episode_records(gt)
    with ReplayBuffer.open(ours) as A, ReplayBuffer.open(gt) as B:
        ea, eb = np.asarray(A.episode_ends), np.asarray(B.episode_ends)
        key = lambda r, e: (int(r["aug_source_episode"][e]), int(r["aug_id"][e]))  # noqa: E731
        ia = {key(ra, e): e for e in range(len(ea)) if ra["aug_id"][e] >= 0}
        rows_a, rows_b = [], []
        for e in range(len(eb)):
            if rb["aug_id"][e] < 0 or key(rb, e) not in ia:
                continue
            a = ia[key(rb, e)]
            s = int(rb["aug_splice_index"][e])
            sa, sb = (int(ea[a - 1]) if a else 0), (int(eb[e - 1]) if e else 0)
            rows_a += list(range(sa, sa + s))
            rows_b += list(range(sb, sb + s))
        rng = np.random.default_rng(seed)
        pick = np.sort(rng.choice(len(rows_a), size=min(max_frames, len(rows_a)), replace=False)) if rows_a else []
        import torch  # lazy, start-up: torch

        # lazy, start-up: cv2, torch
        from umi_aug.camera.kb import unproject
        from umi_aug.splat.losses import masked_psnr, masked_ssim
        from umi_aug.square.camera import wrist_intrinsics

        intr = wrist_intrinsics(int(A["camera0_rgb"].shape[1]))
        vv, uu = np.mgrid[0:intr.height, 0:intr.width]
        circle = torch.as_tensor(unproject(np.stack([uu, vv], axis=-1).astype(np.float64), intr)[1])
        psnr, ssim = [], []
        for i in pick:
            x = torch.as_tensor(np.asarray(A["camera0_rgb"][rows_a[i]]), dtype=torch.float64) / 255.0
            y = torch.as_tensor(np.asarray(B["camera0_rgb"][rows_b[i]]), dtype=torch.float64) / 255.0
            psnr.append(masked_psnr(x, y, circle))
            ssim.append(float(masked_ssim(x, y, circle)))
    p, s = np.asarray(psnr), np.asarray(ssim)
    # identical frames have PSNR = inf: no interpolation between ranks then (inf - inf would give NaN)
    method = "linear" if np.isfinite(p).all() else "lower"
    return {"frames": int(len(p)), "psnr_median": float(np.percentile(p, 50, method=method)) if len(p) else None,
            "psnr_p5": float(np.percentile(p, 5, method=method)) if len(p) else None,
            "ssim_median": float(np.median(s)) if len(s) else None,
            "ssim_p5": float(np.percentile(s, 5)) if len(s) else None}
