"""The paper's claims against a study's record (issue #29 part 5): the verdict rule, the numbers behind it, and the
report's section."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.square.records import committed_recipe_and_page_section, cpu_recipe, write_success_record
from umi_aug.square import study as st
from umi_aug.square.claims import PAPER_CLAIMS, VERDICTS, PaperClaim, claim_result, claims_section, verdict


def _cfg(tmp_path: Path, *over: str) -> st.StudyConfig:
    return cpu_recipe(tmp_path, "sweep_thetas=[]", *over)


_write = write_success_record


@pytest.mark.parametrize("paper, lo, hi, expected", [
    (56, 2.1, 5.0, "direction only, smaller"), (56, 50, 60, "reproduced"), (56, 60, 70, "direction only, larger"),
    (8, -1.0, 4.2, "not reproduced"), (8, -1.0, 9.0, "not resolved"), (8, -9.0, -1.0, "contradicted"),
    (8, 8.0, 8.0, "reproduced"), (8, 0.0, 3.0, "not reproduced"),  # 0 inside the closed interval: not excluded
    (-5, -7, -3, "reproduced"), (-5, 1, 3, "contradicted"), (-5, -2, -1, "direction only, smaller"),
    (10, float("nan"), float("nan"), "not measured yet")])
def test_verdict_follows_from_where_zero_and_the_paper_lie(paper, lo, hi, expected):
    assert verdict(paper, lo, hi) == expected
    assert expected in VERDICTS


def test_verdict_refuses_swapped_bounds():
    with pytest.raises(ValueError, match="swapped"):
        verdict(5.0, 3.0, 1.0)


def test_claim_number_is_the_joint_paired_difference_over_data_sizes(tmp_path, rng):
    cfg = _cfg(tmp_path, "variants=[none,ours,gt_render]")
    lo_n, hi_n = cfg.sizes
    C = 60
    p_ours, p_none = {lo_n: 0.5, hi_n: 0.7}, {lo_n: 0.3, hi_n: 0.2}
    s = {(v, n): rng.random(C) < p[n] for v, p in (("ours", p_ours), ("none", p_none)) for n in cfg.sizes}
    for (v, n), x in s.items():
        if (v, n) == ("none", hi_n):  # evaluated on configurations 4..C-1 only: the pair uses the shared ones
            _write(cfg, f"{v}_n{n}", x[4:], configs=range(4, C))
        else:
            _write(cfg, f"{v}_n{n}", x)
    claim = PAPER_CLAIMS[0]
    assert (claim.better, claim.worse, claim.sizes) == ("ours", "none", "mean")
    r = claim_result(cfg, claim, n_boot=2000, seed=3)
    keep = np.arange(4, C)
    x = np.stack([s["ours", n][keep] for n in cfg.sizes]).astype(float)
    y = np.stack([s["none", n][keep] for n in cfg.sizes]).astype(float)
    assert r["sizes_used"] == [lo_n, hi_n] and r["n"] == C - 4 and not r["missing"]
    assert r["better_successes"] == int(x.sum()) and r["worse_successes"] == int(y.sum())
    assert r["diff_pp"] == pytest.approx(100 * np.mean([x[k].mean() - y[k].mean() for k in range(2)]))
    # slow reference: resample configurations once for both sizes, average the per-size rate differences
    idx = np.random.default_rng(3).integers(0, C - 4, size=(2000, C - 4))
    boot = np.mean([x[k][idx].mean(axis=1) - y[k][idx].mean(axis=1) for k in range(2)], axis=0)
    assert r["ci95_pp"] == pytest.approx([100 * np.quantile(boot, 0.025), 100 * np.quantile(boot, 0.975)])
    assert r["verdict"] == verdict(56.0, *r["ci95_pp"]) and not r["cross_machine"]
    # a machine that evaluated one cell of a pair elsewhere marks the claim
    elsewhere = claim_result(cfg, claim, n_boot=200, machine=lambda step: "gpu" if step == f"eval/none_n{lo_n}"
                             else "here")
    assert elsewhere["cross_machine"]
    # the oracle's high-data claim: gt_render_n{hi} missing -> not measured; low-data: only the low size is used
    gt = {c.sizes: c for c in PAPER_CLAIMS if c.better == "gt_render"}
    _write(cfg, f"gt_render_n{lo_n}", s["ours", lo_n])  # the same outcomes as ours: difference exactly 0
    low = claim_result(cfg, gt["low"], n_boot=500)
    assert low["sizes_used"] == [lo_n] and low["diff_pp"] == 0.0 and low["ci95_pp"] == [0.0, 0.0]
    assert low["verdict"] == "not reproduced"
    high = claim_result(cfg, gt["high"], n_boot=500)
    assert high["verdict"] == "not measured yet" and high["missing"] == [f"gt_render_n{hi_n}"]
    assert np.isnan(high["diff_pp"]) and high["sizes_used"] == []
    # a mean claim with one size missing is computed on the size there is, and says it is provisional
    (st.record_eval_dir(cfg, {"name": f"ours_n{hi_n}"}) / "results.jsonl").unlink()
    part = claim_result(cfg, claim, n_boot=500)
    assert part["sizes_used"] == [lo_n] and part["verdict"].startswith("provisional: ")
    assert claim_result(cfg, PAPER_CLAIMS[-1])["verdict"] == "not in this recipe"  # no spartn in this recipe


def test_a_difference_as_large_as_the_paper_says_is_reproduced_and_none_is_not(tmp_path, rng):
    cfg = _cfg(tmp_path, "variants=[none,ours]")
    C = 400
    for n in cfg.sizes:  # exactly +56 pp at each size, on random configurations: the interval holds the paper's value
        order = rng.permutation(C)
        base = np.zeros(C, bool)
        base[order[:80]] = True  # 20 %
        ours = base.copy()
        ours[order[80:80 + 224]] = True  # + 56 % of the configurations
        _write(cfg, f"none_n{n}", base)
        _write(cfg, f"ours_n{n}", ours)
    claim = PaperClaim("ours", "none", 56.0, "mean", "test")
    r = claim_result(cfg, claim, n_boot=2000)
    assert r["ci95_pp"][0] < 56.0 < r["ci95_pp"][1] and r["verdict"] == "reproduced"
    assert claim_result(cfg, PaperClaim("none", "ours", 56.0, "mean", "test"), n_boot=500)["verdict"] == \
        "contradicted"
    assert claim_result(cfg, PaperClaim("none", "none", 5.0, "high", "test"), n_boot=500)["verdict"] == \
        "not reproduced"


def test_the_report_has_the_claims_section_and_json(tmp_path, rng):
    from umi_aug.square.report import write_report

    cfg = _cfg(tmp_path, "variants=[none,ours,gt_render,action_only,spartn]")
    for n in cfg.sizes:
        _write(cfg, f"none_n{n}", rng.random(50) < 0.1)
        _write(cfg, f"ours_n{n}", rng.random(50) < 0.3)
    lines, results = claims_section(cfg, n_boot=300)
    assert len(results) == len(PAPER_CLAIMS) and lines[1] == "## The paper's claims against this study"
    write_report(cfg, st.study_cells(cfg), {"steps": {}})
    md = Path(cfg.report_md).read_text()
    assert "## The paper's claims against this study" in md
    row = next(line for line in md.splitlines() if line.startswith("| §4.1: free-space"))
    assert f"mean of n={cfg.sizes[0]}, n={cfg.sizes[1]}" in row and "‡" not in row
    assert "Verdicts so far — " in md and "not measured yet: 6" in md
    rep = json.loads((cfg.out / "report.json").read_text())
    assert [c["paper_pp"] for c in rep["claims"]] == [c.paper_pp for c in PAPER_CLAIMS]
    assert rep["claims"][0]["better"] == "ours" and rep["claims"][0]["sizes"] == "mean"
    assert rep["claims"][2]["diff_pp"] is None and rep["claims"][2]["ci95_pp"] == [None, None]  # NaN -> null


@pytest.mark.parametrize("recipe", ["cpu_regression", "cpu_abs"])
def test_the_summary_page_states_what_the_record_says(recipe):
    """docs/square_study.md is written by hand: in each recipe's section, each claim's row must carry the number and
    the verdict that the committed record of that study gives today (regenerate the row when a cell lands). A
    running study's section lists every claim it has measured (at least one); a finished one lists all seven."""
    cfg, section = committed_recipe_and_page_section(recipe)
    n_rows = 0
    for c in PAPER_CLAIMS:
        r = claim_result(cfg, c)
        rows = [line for line in section if line.startswith(f"| `{c.better}` - `{c.worse}`")
                and f"| {c.paper_pp:+.0f} |" in line]
        assert len(rows) <= 1, (recipe, c, rows)
        if not rows:
            assert recipe != "cpu_regression" and not r["sizes_used"], (recipe, c, "measured but not on the page")
            continue
        n_rows += 1
        want = r["verdict"]
        assert f"| **{want}** |" in rows[0] or f"| {want} |" in rows[0], (want, rows[0])
        if r["sizes_used"]:
            assert f"{r['diff_pp']:+.1f} [{r['ci95_pp'][0]:+.1f}, {r['ci95_pp'][1]:+.1f}]" in rows[0], rows[0]
            assert f"{r['better_successes']} vs {r['worse_successes']}" in rows[0], rows[0]
    assert n_rows == len(PAPER_CLAIMS) if recipe == "cpu_regression" else n_rows >= 1
