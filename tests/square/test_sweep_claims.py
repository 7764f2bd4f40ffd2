"""The paper's cone-angle claim against a study's sweep (issue #29 parts 4–5): the verdict rule, the numbers behind
it, the report's section, and the summary page's rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.square.records import committed_recipe_and_page_section, cpu_recipe, write_success_record
from umi_aug.eval.stats import mcnemar_exact_p
from umi_aug.square import study as st
from umi_aug.square.sweep_claims import (PAPER_SWEEP_CLAIMS, SWEEP_VERDICTS, SweepClaim, sweep_cell_name,
                                         sweep_claim_result, sweep_claims_section, sweep_verdict)


_cfg = cpu_recipe
_write = write_success_record


@pytest.mark.parametrize("expect, lo, hi, wanted", [
    ("up", 0.5, 9.0, "reproduced"), ("up", -3.0, 6.0, "not reproduced"), ("up", 0.0, 4.0, "not reproduced"),
    ("up", -8.0, -0.1, "contradicted"), ("level", -4.0, 4.0, "no difference found"),
    ("level", 0.2, 7.0, "not reproduced: higher"), ("level", -7.0, -0.2, "not reproduced: lower"),
    ("level", 0.0, 0.0, "no difference found"), ("up", float("nan"), float("nan"), "not measured yet")])
def test_sweep_verdict_follows_from_where_zero_lies(expect, lo, hi, wanted):
    assert sweep_verdict(expect, lo, hi) == wanted
    assert wanted in SWEEP_VERDICTS


def test_sweep_verdict_refuses_bad_input():
    with pytest.raises(ValueError, match="swapped"):
        sweep_verdict("up", 3.0, 1.0)
    with pytest.raises(ValueError, match="'up' or 'level'"):
        sweep_verdict("down", -1.0, 1.0)


def test_the_cells_of_the_sweep_are_named_as_the_study_names_them(tmp_path):
    cfg = _cfg(tmp_path)
    names = {c["name"] for c in st.study_cells(cfg)}
    n = cfg.sweep_size
    assert sweep_cell_name(cfg, 50.0) == f"ours_n{n}" and sweep_cell_name(cfg, 20) == f"ours_n{n}_theta20"
    assert {sweep_cell_name(cfg, t) for t in cfg.sweep_thetas} <= names
    assert sweep_cell_name(cfg, 45.0) is None  # not an angle of the sweep
    assert sweep_cell_name(_cfg(tmp_path, "sweep_size=7"), 50.0) is None  # no main-grid cell at 7 demos
    assert sweep_cell_name(_cfg(tmp_path, "variants=[none,spartn]"), 20.0) is None


def test_sweep_numbers_are_the_paired_difference_on_shared_configurations(tmp_path, rng):
    cfg = _cfg(tmp_path)
    n = cfg.sweep_size
    C = 80
    s = {th: rng.random(C) < p for th, p in ((20, 0.15), (50, 0.45), (60, 0.40))}
    _write(cfg, f"ours_n{n}_theta20", s[20])
    _write(cfg, f"ours_n{n}", s[50][3:], configs=range(3, C))  # the pair uses the configurations both evaluated
    rise, plateau = PAPER_SWEEP_CLAIMS
    assert (rise.theta_a, rise.theta_b, rise.expect) == (50.0, 20.0, "up")
    assert (plateau.theta_a, plateau.theta_b, plateau.expect) == (60.0, 50.0, "level")
    r = sweep_claim_result(cfg, rise, n_boot=2000, seed=5)
    x, y = s[50][3:], s[20][3:]
    assert r["cells"] == [f"ours_n{n}", f"ours_n{n}_theta20"] and r["n"] == C - 3
    assert (r["a_successes"], r["b_successes"]) == (int(x.sum()), int(y.sum()))
    assert (r["only_a"], r["only_b"]) == (int((x & ~y).sum()), int((y & ~x).sum()))
    assert r["mcnemar_p"] == mcnemar_exact_p(r["only_a"], r["only_b"])
    assert r["diff_pp"] == pytest.approx(100 * (x.mean() - y.mean()))
    # slow reference: resample the configurations, keep each one's pair of outcomes
    idx = np.random.default_rng(5).integers(0, C - 3, size=(2000, C - 3))
    boot = x[idx].mean(axis=1) - y[idx].mean(axis=1)
    assert r["ci95_pp"] == pytest.approx([100 * np.quantile(boot, 0.025), 100 * np.quantile(boot, 0.975)])
    assert r["verdict"] == sweep_verdict("up", *r["ci95_pp"])
    assert not any(np.isnan(v) for v in (r["diff_pp"], *r["ci95_pp"], r["mcnemar_p"]))
    missing = sweep_claim_result(cfg, plateau, n_boot=200)  # 60° not evaluated yet
    assert missing["verdict"] == "not measured yet" and missing["n"] == 0 and np.isnan(missing["diff_pp"])
    assert sweep_claim_result(cfg, SweepClaim(45.0, 20.0, "up", "test"))["verdict"] == "not in this recipe"


def test_a_clear_rise_is_reproduced_and_an_equal_pair_is_level(tmp_path, rng):
    cfg = _cfg(tmp_path)
    n = cfg.sweep_size
    C = 400
    order = rng.permutation(C)
    low = np.zeros(C, bool)
    low[order[:40]] = True  # 10 %
    high = low.copy()
    high[order[40:200]] = True  # 50 %: +40 pp on random configurations
    _write(cfg, f"ours_n{n}_theta20", low)
    _write(cfg, f"ours_n{n}", high)
    _write(cfg, f"ours_n{n}_theta60", high)
    rise, plateau = (sweep_claim_result(cfg, c, n_boot=1000) for c in PAPER_SWEEP_CLAIMS)
    assert rise["verdict"] == "reproduced" and rise["ci95_pp"][0] > 30
    assert plateau["verdict"] == "no difference found" and plateau["ci95_pp"] == [0.0, 0.0]
    assert plateau["mcnemar_p"] == 1.0
    backwards = sweep_claim_result(cfg, SweepClaim(20.0, 50.0, "up", "test"), n_boot=500)
    assert backwards["verdict"] == "contradicted"
    assert sweep_claim_result(cfg, SweepClaim(60.0, 20.0, "level", "test"), n_boot=500)["verdict"] == \
        "not reproduced: higher"


def test_the_report_has_the_sweep_section_and_json(tmp_path, rng):
    from umi_aug.square.report import write_report

    cfg = _cfg(tmp_path, "variants=[none,ours]")
    n = cfg.sweep_size
    for name in (f"ours_n{n}_theta20", f"ours_n{n}", f"ours_n{n}_theta40"):
        _write(cfg, name, rng.random(50) < 0.3)
    lines, results = sweep_claims_section(cfg, n_boot=300)
    assert lines[1] == "## The paper's cone-angle claim against this study" and len(results) == 2
    assert "30°: not evaluated yet" in lines[3] and "60°: not evaluated yet" in lines[3]
    write_report(cfg, st.study_cells(cfg), {"steps": {}})
    md = Path(cfg.report_md).read_text()
    assert "## The paper's cone-angle claim against this study" in md
    assert "| 50° − 20° | up |" in md and "| 60° − 50° | level |" in md
    rep = json.loads((cfg.out / "report.json").read_text())
    assert [(c["theta_a"], c["theta_b"]) for c in rep["sweep_claims"]] == [(50.0, 20.0), (60.0, 50.0)]
    assert rep["sweep_claims"][1]["verdict"] == "not measured yet" and rep["sweep_claims"][1]["diff_pp"] is None
    assert sweep_claims_section(_cfg(tmp_path, "sweep_thetas=[]"))[0] == []  # no sweep, no section


@pytest.mark.parametrize("recipe", ["cpu_regression", "cpu_abs"])
def test_the_summary_page_states_what_the_sweep_record_says(recipe):
    """docs/square_study.md is written by hand: in each recipe's section, a measured sweep statement's row carries
    the number and the verdict that the committed record gives today; one not measured yet has no row."""
    cfg, section = committed_recipe_and_page_section(recipe)
    for c in PAPER_SWEEP_CLAIMS:
        r = sweep_claim_result(cfg, c)
        rows = [line for line in section if line.startswith(f"| {c.theta_a:g}° - {c.theta_b:g}° `ours`")]
        assert len(rows) <= 1, (recipe, c, rows)
        if r["n"] == 0:
            assert not rows, (recipe, c, "a row for a statement not measured yet")
            continue
        assert rows, (recipe, c, "measured but not on the page")
        assert f"| **{r['verdict']}** |" in rows[0], (r["verdict"], rows[0])
        assert f"{r['diff_pp']:+.1f} [{r['ci95_pp'][0]:+.1f}, {r['ci95_pp'][1]:+.1f}]" in rows[0], rows[0]
        assert f"{r['a_successes']} vs {r['b_successes']}" in rows[0], rows[0]
