"""The square study driver (issue #15): recipes, cells, step order, resume, time slices, failures, the report.

The steps themselves (export, variants, train.py, eval_sim.py) are tested where they live; here they are replaced by
recorders so the driver's bookkeeping is checked in well under a second per test.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from umi_aug.square import study as st

ROOT = Path(__file__).resolve().parents[2]


def _cfg(tmp_path: Path, *over: str) -> st.StudyConfig:
    return st.load_recipe(ROOT / "configs" / "square_study" / "cpu.yaml",
                          [f"out_dir={tmp_path / 'out'}", "record_dir=''", f"report_md={tmp_path / 'r.md'}",
                           f"report_png={tmp_path / 'r.png'}", *over])


def test_recipes_load_and_bad_keys_are_named(tmp_path):
    cpu = _cfg(tmp_path)
    assert cpu.sizes == [10, 25] and cpu.n_per_demo == 20 and cpu.theta_deg == 50.0
    assert st.expected_rollouts(cpu) == 200  # the issue's >= 200 configurations
    paper = st.load_recipe(ROOT / "configs" / "square_study" / "paper.yaml")
    assert paper.sizes == [30, 50, 100, 150, 200] and st.expected_rollouts(paper) == 1000
    reg = st.load_recipe(ROOT / "configs" / "square_study" / "cpu_regression.yaml")  # issue #29 part 4
    assert st.expected_rollouts(reg) == 500 and st.expected_rollouts(reg, handover=True) == 100
    assert reg.eval_handover and not cpu.eval_handover and not paper.eval_handover
    # cpu_abs (session 29) is cpu_regression with absolute actions and, since session 30, without re-sampling the
    # augmented episodes' replayed tails (a no-op for none and spartn), and nothing else
    ab = st.load_recipe(ROOT / "configs" / "square_study" / "cpu_abs.yaml")
    differ = {k for k in vars(reg) if getattr(reg, k) != getattr(ab, k)}
    assert differ == {"name", "out_dir", "record_dir", "report_md", "report_png", "train_overrides"}, differ
    assert [a for a in ab.train_overrides if a not in reg.train_overrides] == ["task.action_pose_repr=abs",
                                                                                "task.sample_replayed_tails=false"]
    assert [a for a in reg.train_overrides if a not in ab.train_overrides] == ["task.action_pose_repr=relative"]
    # every recipe writes its own report; docs/square_study.md is the hand-written overview no recipe overwrites
    shipped = [st.load_recipe(p) for p in sorted((ROOT / "configs" / "square_study").glob("*.yaml"))]
    assert len({r.report_md for r in shipped}) == len(shipped) >= 3
    assert all(r.report_md == f"docs/square_study_{r.name}.md" for r in shipped)
    assert all(r.report_png == f"docs/square_study_{r.name}.png" for r in shipped)
    unset = st.load_recipe(ROOT / "configs" / "square_study" / "cpu.yaml", ["name=abc", "report_md=''",
                                                                            "report_png=''"])
    assert (unset.report_md, unset.report_png) == ("docs/square_study_abc.md", "docs/square_study_abc.png")
    assert st.StudyConfig(name="x").report_md == "docs/square_study_x.md"
    with pytest.raises(st.StudyError, match="no_such_key"):
        _cfg(tmp_path, "no_such_key=3")
    with pytest.raises(st.StudyError, match="'magic'"):
        _cfg(tmp_path, "variants=[none,magic]")
    with pytest.raises(st.StudyError, match="sizes"):
        _cfg(tmp_path, "sizes=[0]")
    assert st.expected_rollouts(_cfg(tmp_path, "eval_configs='3,7,9'")) == 3
    bad = tmp_path / "demos"
    bad.mkdir()
    (bad / "report.json").write_text("{not json")
    with pytest.raises(st.StudyError, match="report.json: unreadable square-demos report"):
        st.demos_ready(_cfg(tmp_path, f"demos_dir={bad}"))


def test_the_study_trains_on_every_demo(tmp_path):
    """B3: the study's training command (task=square + the recipe's overrides) holds no episode out — validation
    never runs in the recipe, and UMI's 5 % hold-out would train `none_n10` on 9 demos."""
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from tests.policy.helpers import make_dataset, with_commanded_targets
    from umi_aug.policy.config import TrainConfig, structured_config
    from umi_aug.policy.dataset import UmiPolicyDataset

    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
    ds = make_dataset(tmp_path / "d.zarr.zip", np.random.default_rng(0), n_episodes=10, length=30, size=84)
    ds = with_commanded_targets(ds, tmp_path / "a.zarr.zip", np.random.default_rng(1))[0]  # task=square labels
    for recipe in ("cpu", "paper", "cpu_regression", "cpu_abs"):
        cfg = st.load_recipe(ROOT / "configs" / "square_study" / f"{recipe}.yaml")
        cmd = st.train_command(cfg, {"name": "none_n10", "variant": "none", "n": 10})
        over = [a for a in cmd[2:] if not a.startswith(("hydra.", "task.dataset_path="))]
        with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
            typed = structured_config(compose("train", overrides=over))
        assert typed.task.val_ratio == 0.0, recipe
        train = UmiPolicyDataset(ds, typed.task, "train")
        assert not train.val_mask.any() and len(train.get_validation_dataset()) == 0, recipe


def test_cells_main_grid_then_sweep(tmp_path):
    cells = st.study_cells(_cfg(tmp_path))
    names = [c["name"] for c in cells]
    assert names[:10] == [f"{v}_n{n}" for v in ("none", "ours", "gt_render", "action_only", "spartn")
                          for n in (10, 25)]
    # the sweep: every θ but the main one (its cell is ours_n10 of the grid), at the sweep size
    assert names[10:] == ["ours_n10_theta20", "ours_n10_theta30", "ours_n10_theta40", "ours_n10_theta60"]
    assert len(set(names)) == len(names)
    assert st.study_cells(_cfg(tmp_path, "variants=[none,spartn]"))[-1]["name"] == "spartn_n25"  # no ours: no sweep


def _fake_steps(monkeypatch, calls: list[str], fail: str | None = None, unfinished_eval: str | None = None):
    """Every step replaced by a recorder that writes the output the driver checks; train.py / eval_sim.py are faked
    at the subprocess, so the driver's own train / eval bookkeeping (record copies) runs for real."""
    def demos(cfg):
        calls.append("demos")
        d = Path(cfg.demos_dir)
        d.mkdir(parents=True, exist_ok=True)
        (d / "report.json").write_text(json.dumps({"successes": max(cfg.sizes),
                                                   "config": {"image_size": cfg.image_size}}))
        return {}

    def export(cfg, theta):
        calls.append(f"export_theta{theta:g}" if theta is not None else "export")
        st.export_path(cfg, theta).parent.mkdir(parents=True, exist_ok=True)
        st.export_path(cfg, theta).write_text("x")
        return {"n_augmented": 3}

    def variant(cfg, cell):
        calls.append(f"variant/{cell['name']}")
        if cell["name"] == fail:
            raise st.StudyError("boom")
        st.variant_path(cfg, cell).write_text("x")
        return {}

    def run(cmd, log_path):
        arg = dict(a.split("=", 1) for a in cmd[2:] if "=" in a)
        if cmd[1] == "train/train.py":
            name = Path(arg["hydra.run.dir"]).name
            calls.append(f"train/{name}")
            ck = Path(arg["hydra.run.dir"]) / "checkpoints" / "latest.ckpt"
            ck.parent.mkdir(parents=True, exist_ok=True)
            ck.write_text("x")
        else:
            out = Path(arg["out_dir"])
            calls.append(("eval_handover/" if arg.get("handover") == "expert" else "eval/") + out.name)
            out.mkdir(parents=True, exist_ok=True)
            n = 5 if out.name == unfinished_eval else 200
            (out / "results.jsonl").write_text("".join(json.dumps({"config": i, "success": i % 2 == 0}) + "\n"
                                                       for i in range(n)))
            (out / "summary.json").write_text(json.dumps({"n": n, "success_rate": 0.5}))
        return 0

    monkeypatch.setattr(st, "_step_demos", demos)
    monkeypatch.setattr(st, "_step_export", export)
    monkeypatch.setattr(st, "_step_variant", variant)
    monkeypatch.setattr(st, "_run", run)


def _cell(name: str) -> list[str]:
    return [f"train/{name}", f"eval/{name}"]


def test_step_order_resume_and_unfinished_eval(tmp_path, monkeypatch):
    cfg = _cfg(tmp_path, "variants=[none,ours]", "sweep_thetas=[30,50]", f"record_dir={tmp_path / 'record'}",
               f"demos_dir={tmp_path / 'demos'}")
    calls: list[str] = []
    _fake_steps(monkeypatch, calls, unfinished_eval="ours_n25")
    state = st.run_study(cfg, ("data", "train", "eval"))
    # cell by cell, each with the data it needs first; a smaller size is cut from the largest one's dataset
    assert calls == ["demos", "export", "variant/none_n25", "variant/none_n10", *_cell("none_n10"),
                     *_cell("none_n25"), "variant/ours_n25", "variant/ours_n10", *_cell("ours_n10"),
                     *_cell("ours_n25"), "export_theta30", "variant/ours_n10_theta30", *_cell("ours_n10_theta30")]
    assert state["steps"]["export"]["n_augmented"] == 3 and state["steps"]["export"]["seconds"] >= 0
    assert not state["steps"]["eval/ours_n25"]["done"]  # fewer rollouts than the subset: not done
    saved = json.loads((tmp_path / "record" / "study_state.json").read_text())
    assert saved["steps"].keys() == state["steps"].keys()
    # finished cells are in the record; the unfinished one is not
    rec = tmp_path / "record" / "evals"
    assert sorted(p.name for p in rec.iterdir()) == ["none_n10", "none_n25", "ours_n10", "ours_n10_theta30"]
    assert (rec / "none_n10" / "results.jsonl").read_text() == \
        (st.eval_dir(cfg, {"name": "none_n10"}) / "results.jsonl").read_text()
    calls.clear()
    st.run_study(cfg, ("data", "train", "eval"))
    assert calls == ["eval/ours_n25"]  # a rerun does only what is not done (eval_sim resumes its own results)


def test_a_second_concurrent_run_is_refused_before_touching_anything(tmp_path, monkeypatch):
    """Two runs on the same outputs or record would interleave steps and overwrite each other's state."""
    from umi_aug.io_utils import exclusive_run_lock

    cfg = _cfg(tmp_path, "variants=[none]", "sweep_thetas=[]", f"record_dir={tmp_path / 'record'}",
               f"demos_dir={tmp_path / 'demos'}")
    calls: list[str] = []
    _fake_steps(monkeypatch, calls)
    for held in (cfg.out / st.STUDY_LOCK, cfg.record / st.STUDY_LOCK):
        with exclusive_run_lock(held, "square study"):
            with pytest.raises(st.StudyError, match="another square study .* is running"):
                st.run_study(cfg, ("data", "train", "eval"))
        assert calls == [] and not (cfg.record / "study_state.json").exists()
    st.run_study(cfg, ("data", "train", "eval"))  # free again
    assert calls and (cfg.record / "study_state.json").exists()


def test_a_fresh_machine_continues_from_the_record(tmp_path, monkeypatch):
    import shutil

    cfg = _cfg(tmp_path, "variants=[none,ours]", "sweep_thetas=[]", f"record_dir={tmp_path / 'record'}",
               f"demos_dir={tmp_path / 'demos'}")
    calls: list[str] = []
    _fake_steps(monkeypatch, calls, unfinished_eval="ours_n25")
    st.run_study(cfg, ("data", "train", "eval"))
    shutil.rmtree(cfg.out)  # the machine is gone: datasets, checkpoints, partial evaluations with it
    shutil.rmtree(tmp_path / "demos")
    calls.clear()
    _fake_steps(monkeypatch, calls)
    st.run_study(cfg, ("data", "train"))  # without the eval phase too, a finished cell is not trained again
    assert calls == ["demos", "export", "variant/ours_n25", "train/ours_n25"]
    shutil.rmtree(cfg.out)
    shutil.rmtree(tmp_path / "demos")
    calls.clear()
    state = st.run_study(cfg, ("data", "train", "eval"))
    # only the unfinished cell, and only what it needs
    assert calls == ["demos", "export", "variant/ours_n25", *_cell("ours_n25")]
    assert state["steps"]["export"]["reruns"] == 2 and state["steps"]["train/ours_n25"]["reruns"] == 2
    assert "reruns" not in state["steps"]["train/none_n10"]
    assert state["steps"]["eval/ours_n25"]["done"]
    assert json.loads((tmp_path / "record" / "evals" / "ours_n25" / "summary.json").read_text())["n"] == 200
    # the report needs only the record
    from umi_aug.square.report import report_study

    shutil.rmtree(cfg.out)
    rep = report_study(cfg)
    assert all(rep["metrics"][c]["n"] == 200 for c in ("none_n10", "none_n25", "ours_n10", "ours_n25"))
    assert "not evaluated yet" not in Path(cfg.report_md).read_text()
    assert (tmp_path / "record" / "report.json").exists()


def test_a_training_stopped_before_its_first_checkpoint_is_set_aside_and_trained_again(tmp_path, monkeypatch):
    """A slice killed between train.py's first log row and its first checkpoint leaves logs.jsonl without
    latest.ckpt; train.py refuses that folder (nothing to resume), so the study sets it aside and starts over."""
    import torch

    from umi_aug.policy.train_checks import prepare_run_folder

    cfg = _cfg(tmp_path, "variants=[none]", "sweep_thetas=[]")
    cell = {"name": "none_n10"}
    run_dir = cfg.out / "runs" / "none_n10"
    run_dir.mkdir(parents=True)
    (run_dir / "logs.jsonl").write_text("".join(json.dumps({"step": i, "loss": 1.0}) + "\n" for i in range(1, 9)))
    with pytest.raises(Exception, match="left no checkpoint"):  # what train.py says of it
        prepare_run_folder(run_dir, st.checkpoint_path(cfg, cell), resume=True)
    seen: list[bool] = []

    def run(cmd, log_path):
        prepare_run_folder(run_dir, st.checkpoint_path(cfg, cell), resume=True)  # train.py's own check, for real
        seen.append((run_dir / "logs.jsonl").exists())
        st.checkpoint_path(cfg, cell).parent.mkdir(parents=True, exist_ok=True)
        torch.save({"pickles": {"global_step": 1}}, st.checkpoint_path(cfg, cell))
        (run_dir / "logs.jsonl").write_text(json.dumps({"step": 1}) + "\n")
        return 0

    monkeypatch.setattr(st, "_run", run)
    st._step_train(cfg, cell)
    assert seen == [False]
    aside = [p for p in (cfg.out / "runs").iterdir() if p.name.startswith("none_n10.before-")]
    assert len(aside) == 1 and len((aside[0] / "logs.jsonl").read_text().splitlines()) == 8  # kept, not deleted
    # with a checkpoint, the folder is the run to resume: left where it is
    st._step_train(cfg, cell)
    assert seen == [False, True] and len([p for p in (cfg.out / "runs").iterdir() if p.is_dir()]) == 2


def test_a_step_that_succeeds_after_a_failure_keeps_no_error(tmp_path):
    state = st._State(tmp_path / "study_state.json")
    state.record("train/none_n25", 2.0, False, error="train none_n25: exit status 2")
    state.record("train/none_n25", 60.0, True, checkpoint="c.ckpt")
    row = json.loads((tmp_path / "study_state.json").read_text())["steps"]["train/none_n25"]
    assert row["done"] and "error" not in row and row["seconds"] == 62.0 and row["checkpoint"] == "c.ckpt"
    state.record("eval/none_n25", 5.0, False, error="boom")
    assert st._State(tmp_path / "study_state.json").data["steps"]["eval/none_n25"]["error"] == "boom"


def test_budget_stops_before_the_next_step_and_failures_are_recorded(tmp_path, monkeypatch):
    import types

    calls: list[str] = []
    _fake_steps(monkeypatch, calls)
    clock = [0.0]  # a fake clock: the export step takes 2 minutes, a cell's train + eval 30 minutes
    monkeypatch.setattr(st, "time", types.SimpleNamespace(perf_counter=lambda: clock[0], time=lambda: 0.0,
                                                          strftime=lambda f: "t"))
    real_export, real_run = st._step_export, st._run

    def slow_export(cfg, theta):
        clock[0] += 120.0
        return real_export(cfg, theta)

    def slow_run(cmd, log_path):
        clock[0] += 900.0
        return real_run(cmd, log_path)

    monkeypatch.setattr(st, "_step_export", slow_export)
    monkeypatch.setattr(st, "_run", slow_run)
    over = ("variants=[none]", "sweep_thetas=[]", f"demos_dir={tmp_path / 'demos'}")
    cfg = _cfg(tmp_path, *over, "budget_min=1")
    st.run_study(cfg, ("data", "train"))
    assert calls == ["demos", "export"]  # the first steps run, none starts after the 1-minute budget
    # a cell is not started when the cells recorded so far took longer than what is left
    calls.clear()
    st.run_study(_cfg(tmp_path, *over, "budget_min=45"), ("data", "train", "eval"))
    assert calls == ["variant/none_n25", "variant/none_n10", *_cell("none_n10")]  # 30 min done, 30 needed, 15 left
    assert st.cell_minutes_estimate(cfg, json.loads((cfg.out / "study_state.json").read_text())) == 30.0
    monkeypatch.undo()
    calls.clear()
    _fake_steps(monkeypatch, calls, fail="none_n25")
    with pytest.raises(st.StudyError, match="variant/none_n25.*boom"):
        st.run_study(_cfg(tmp_path, "variants=[none]", "sweep_thetas=[]", "sizes=[25]",
                          f"demos_dir={tmp_path / 'demos'}", f"out_dir={tmp_path / 'out2'}"), ("data",))
    row = json.loads((tmp_path / "out2" / "study_state.json").read_text())["steps"]["variant/none_n25"]
    assert row["done"] is False and row["error"] == "boom"


def _write_results(d: Path, rows: list[dict]) -> None:
    d.mkdir(parents=True)
    (d / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_report_marks_unevaluated_cells_and_counts_what_was_recorded(tmp_path, rng):
    from umi_aug.eval.stats import wilson_interval
    from umi_aug.square.report import cell_metrics, write_report

    cfg = _cfg(tmp_path, "variants=[none,ours]", "sweep_thetas=[40,50]")
    cells = st.study_cells(cfg)
    n = 20
    succ = rng.random(n) < 0.3
    rows = [{"config": i, "success": bool(s), "pregrasp_reached": bool(s or i % 2), "lifted": bool(s),
             "inserted": bool(s), "collision_table": i % 3 == 0, "collision_peg": False,
             "pregrasp_min_pos_err_m": 0.01 * (i + 1), "pregrasp_min_rot_err_deg": float(i),
             "max_nut_rise_m": 0.01 if s else 0.0} for i, s in enumerate(succ)]
    _write_results(st.eval_dir(cfg, cells[0]), rows)
    _write_results(st.eval_dir(cfg, {"name": "ours_n10_theta40"}), rows[:5])
    m = cell_metrics(st.eval_dir(cfg, cells[0]))
    k = int(succ.sum())
    assert m["n"] == n and m["success"]["count"] == k
    assert m["success"]["wilson95"] == pytest.approx(list(wilson_interval(k, n)))
    assert m["closest_pregrasp_mm_median"] == pytest.approx(1000 * np.median(0.01 * np.arange(1, n + 1)))
    assert m["nut_moved"] == k
    assert cell_metrics(st.eval_dir(cfg, cells[1])) is None
    rep = write_report(cfg, cells, {"steps": {"train/none_n10": {"seconds": 120.0, "done": True}}})
    md = Path(cfg.report_md).read_text()
    assert f"| none | 10 | {n} | {100 * k / n:.1f} [" in md
    # none_n25, ours_n10, ours_n25; sweep θ = 50 (ours_n10) in the sweep's table and in its claim's sentence
    assert md.count("not evaluated yet") == 3 + 1 + 1
    assert "40°: " in md and "50°: not evaluated yet" in md
    assert "| 40 | 5 |" in md and "| train/none_n10 | 2.0 |" in md
    assert "†" not in md  # no step ran elsewhere
    # an evaluation made on a lent machine: its minutes there, marked, with a note naming the machine
    lent = cfg.record / "lent_machine" / "steps.json"
    lent.parent.mkdir(parents=True)
    lent.write_text(json.dumps({"eval/none_n10": {"seconds": 273.0, "machine": "lent H200 machine", "workers": 16}}))
    write_report(cfg, cells, {"steps": {"train/none_n10": {"seconds": 120.0, "done": True},
                                        "eval/none_n10": {"seconds": 2.5, "done": True}}})
    md_lent = Path(cfg.report_md).read_text()
    assert "| eval/none_n10 | 4.5 † |" in md_lent and f"| none | 10 | {n} |" in md_lent
    assert "| 2.0 | 4.5 † |" in md_lent  # train min, eval min of the cell's row
    assert "`eval/none_n10`: lent H200 machine, 16 workers" in md_lent and "lent_machine/README.md" in md_lent
    assert "‡" not in md_lent  # no ours cell evaluated: nothing paired across machines
    lent.write_text(json.dumps({"eval/none_n10": {"seconds": -1, "machine": "x"}}))
    with pytest.raises(st.StudyError, match=r"steps \['eval/none_n10'\] need"):
        write_report(cfg, cells, {"steps": {}})
    lent.unlink()
    row40 = next(line for line in md.splitlines() if line.startswith("| 40 | 5 |")).split("|")
    assert row40[7].strip().startswith("+0 [") and "/ +0.0 [" in row40[7]  # paired vs none_n10: the same rows
    assert Path(cfg.report_png).stat().st_size > 10_000
    assert f"]({os.path.relpath(cfg.report_png, Path(cfg.report_md).parent)})" in md  # the figure is shown
    from umi_aug.square.report import _paired_deg  # the figure's orientation panels: same rows, no difference

    assert _paired_deg(cfg, {"name": "ours_n10_theta40"}, 10) == (0.0, 0.0, 0.0)
    assert _paired_deg(cfg, {"name": "ours_n25"}, 25) is None
    rows_b = [dict(r, pregrasp_min_rot_err_deg=r["pregrasp_min_rot_err_deg"] - 2.0) for r in rows[:5]]
    _write_results(st.eval_dir(cfg, {"name": "ours_n10_theta50"}), rows_b)
    assert _paired_deg(cfg, {"name": "ours_n10_theta50"}, 10) == pytest.approx((-2.0, -2.0, -2.0))
    assert rep["metrics"]["ours_n25"] is None and rep["fidelity"] is None
    assert json.loads((cfg.out / "report.json").read_text())["metrics"]["none_n10"]["n"] == n


def test_paired_comparison_with_none_on_shared_configurations(tmp_path, rng):
    """The per-configuration comparison that separates policies that never succeed: differences are taken on the
    configurations both cells evaluated, signs and counts are the cell's minus the baseline's."""
    from umi_aug.square.report import cell_metrics, paired_vs, write_report

    cfg = _cfg(tmp_path, "variants=[none,ours]", "sweep_thetas=[]")
    base = rng.uniform(0.05, 0.2, 40)
    closer = rng.random(40) < 0.7
    delta = np.where(closer, -0.02, 0.01)  # metres: ours 20 mm closer on ~70 %, 10 mm farther elsewhere
    row = lambda i, d, s: {"config": i, "success": s, "pregrasp_min_pos_err_m": d,  # noqa: E731
                           "pregrasp_min_rot_err_deg": 10.0 + (i % 7) + 1000 * d}
    _write_results(st.eval_dir(cfg, {"name": "none_n10"}), [row(i, base[i], False) for i in range(40)])
    # ours evaluated configs 5..44: 35 shared with none; 44 > 39 has no partner
    _write_results(st.eval_dir(cfg, {"name": "ours_n10"}),
                   [row(i, base[i] + delta[i] if i < 40 else 0.0, i == 7) for i in range(5, 45)])
    p = paired_vs(st.eval_dir(cfg, {"name": "ours_n10"}), st.eval_dir(cfg, {"name": "none_n10"}))
    d = 1000 * delta[5:40]
    assert p["n"] == 35 and p["closer"] == int((d < 0).sum())
    assert p["closest_mm_diff_median"] == pytest.approx(np.median(d))
    lo, hi = p["closest_mm_diff_ci95"]
    assert lo <= p["closest_mm_diff_median"] <= hi
    assert all(min(abs(v + 20.0), abs(v - 10.0)) < 1e-9 for v in (lo, hi))  # order statistics of the differences
    assert p["closest_deg_diff_median"] == pytest.approx(np.median(d)) and p["closer_deg"] == p["closer"]
    assert p["successes"] == 1 and p["baseline_successes"] == 0
    assert paired_vs(st.eval_dir(cfg, {"name": "ours_n10"}), tmp_path / "nothing") is None
    m = cell_metrics(st.eval_dir(cfg, {"name": "none_n10"}))
    assert m["closest_pregrasp_mm_ci95"][0] <= m["closest_pregrasp_mm_median"] <= m["closest_pregrasp_mm_ci95"][1]
    write_report(cfg, st.study_cells(cfg), {"steps": {}})
    md = Path(cfg.report_md).read_text()
    assert f"| ours | 10 | 35 | {np.median(d):+.0f} [" in md and f"| {p['closer']} / 35 | {np.median(d):+.1f} [" in md and "| 1 vs 0 |" in md


def test_handover_evaluation_is_a_step_of_its_own_and_the_report_pairs_ours_with_every_variant(tmp_path, monkeypatch,
                                                                                              rng):
    """Part 4's metric (c) — learned approach + scripted grasp — runs after a cell's own evaluation on its own
    configurations and is recorded apart; a recipe without it is unchanged; `ours` is paired with every variant."""
    from umi_aug.square.report import paired_outcomes, write_report

    over = ("variants=[none,ours,spartn]", "sizes=[25]", "sweep_thetas=[]", f"record_dir={tmp_path / 'record'}",
            f"demos_dir={tmp_path / 'demos'}")
    cfg = _cfg(tmp_path, *over, "eval_handover=true", "handover_configs=0:1000:10")
    assert st.expected_rollouts(cfg) == 200 and st.expected_rollouts(cfg, handover=True) == 100
    cmd = st.eval_command(cfg, {"name": "none_n25"}, handover=True)
    assert "handover=expert" in cmd and "configs=0:1000:10" in cmd
    assert f"out_dir={cfg.out / 'evals_handover' / 'none_n25'}" in cmd
    assert "handover=expert" not in st.eval_command(cfg, {"name": "none_n25"})
    calls: list[str] = []
    _fake_steps(monkeypatch, calls, unfinished_eval="ours_n25")  # the fake writes 200 rollouts (5 for ours_n25)
    st.run_study(cfg, ("data", "train", "eval"))
    assert calls == ["demos", "export", "variant/none_n25", "train/none_n25", "eval/none_n25",
                     "eval_handover/none_n25", "variant/ours_n25", "train/ours_n25", "eval/ours_n25",
                     "eval_handover/ours_n25", "variant/spartn_n25", "train/spartn_n25", "eval/spartn_n25",
                     "eval_handover/spartn_n25"]
    rec = tmp_path / "record" / "evals_handover"
    assert sorted(p.name for p in rec.iterdir()) == ["none_n25", "spartn_n25"]  # ours_n25's are unfinished
    calls.clear()
    st.run_study(cfg, ("data", "train", "eval"))
    assert calls == ["eval/ours_n25", "eval_handover/ours_n25"]
    # a finished cell whose handover evaluation is missing is not finished
    import shutil

    shutil.rmtree(rec / "none_n25")
    assert not st.cell_finished(cfg, {"name": "none_n25"})
    calls.clear()
    _fake_steps(monkeypatch, calls)
    st.run_study(cfg, ("data", "train", "eval"))
    assert calls == ["eval_handover/none_n25", "eval/ours_n25", "eval_handover/ours_n25"]
    # without eval_handover (the default, every earlier recipe) nothing changes
    assert not _cfg(tmp_path).eval_handover
    assert all(not s[0].startswith("eval_handover") for s in st._cell_steps(_cfg(tmp_path), {
        "name": "none_n10", "variant": "none", "n": 10, "theta": None}, ("eval",)))
    # the report: paired outcomes of ours against the other variants, and (c) in its own column
    n = 60
    ours_ok = rng.random(n) < 0.5
    other_ok = np.where(rng.random(n) < 0.3, ~ours_ok, ours_ok)
    for name, ok in (("ours_n25", ours_ok), ("none_n25", other_ok), ("spartn_n25", ours_ok)):
        for handover in (False, True):
            d = st.record_eval_dir(cfg, {"name": name}, handover)
            shutil.rmtree(d, ignore_errors=True)
            _write_results(d, [{"config": i, "success": bool(ok[i]) or handover, "pregrasp_reached": bool(ok[i])}
                               for i in range(n)])
    p = paired_outcomes(st.record_eval_dir(cfg, {"name": "ours_n25"}), st.record_eval_dir(cfg, {"name": "none_n25"}))
    only_o, only_n = int((ours_ok & ~other_ok).sum()), int((~ours_ok & other_ok).sum())
    assert (p["n"], p["cell"], p["other"]) == (n, int(ours_ok.sum()), int(other_ok.sum()))
    assert (p["only_cell"], p["only_other"]) == (only_o, only_n)
    assert p["diff"] == pytest.approx((only_o - only_n) / n) and p["diff_ci95"][0] <= p["diff"] <= p["diff_ci95"][1]
    from umi_aug.eval.stats import mcnemar_exact_p

    assert p["mcnemar_p"] == mcnemar_exact_p(only_o, only_n)
    same = paired_outcomes(st.record_eval_dir(cfg, {"name": "ours_n25"}),
                           st.record_eval_dir(cfg, {"name": "spartn_n25"}))
    assert same["mcnemar_p"] == 1.0 and same["diff_ci95"] == [0.0, 0.0]
    assert paired_outcomes(st.record_eval_dir(cfg, {"name": "ours_n25"}), tmp_path / "nothing") is None
    rep = write_report(cfg, st.study_cells(cfg), st.load_state(cfg))
    md = Path(cfg.report_md).read_text()
    assert "(c) learned approach + scripted grasp |" in md and rep["handover_metrics"]["none_n25"]["n"] == n
    assert "| none | 25 | 60 | " in md and md.count("| 100.0 [") == 3  # (c): every handover rollout succeeded
    for label in ("(a) success", "(b) pre-grasp reached", "(c) learned approach + scripted grasp"):
        assert f"| none | 25 | {label} | {n} |" in md and f"| spartn | 25 | {label} | {n} |" in md
    row = next(line for line in md.splitlines() if line.startswith("| none | 25 | (a) success |"))
    assert f"| {only_o} / {only_n} |" in row and f"{100 * p['diff']:+.1f} [" in row
    assert "handover=expert" in md  # its command
    assert "‡" not in md  # every cell evaluated on one machine
    # ours_n25's (a)/(b) evaluation made on a lent machine: its pairs with cells evaluated here are marked, and (c)
    # (evaluated here for both) is not
    lent = cfg.record / "lent_machine" / "steps.json"
    lent.parent.mkdir(parents=True, exist_ok=True)
    lent.write_text(json.dumps({"eval/ours_n25": {"seconds": 250.0, "machine": "lent GPU machine"}}))
    write_report(cfg, st.study_cells(cfg), st.load_state(cfg))
    md_lent = Path(cfg.report_md).read_text()
    for label in ("(a) success", "(b) pre-grasp reached"):
        assert f"| none ‡ | 25 | {label} | {n} |" in md_lent and f"| spartn ‡ | 25 | {label} | {n} |" in md_lent
    assert "| none | 25 | (c) learned approach + scripted grasp |" in md_lent
    assert "‡ the two cells were evaluated on different machines" in md_lent
    lent.unlink()
    no_c = _cfg(tmp_path, *over, f"report_md={tmp_path / 'r2.md'}")
    write_report(no_c, st.study_cells(no_c), st.load_state(no_c))
    md2 = Path(no_c.report_md).read_text()
    assert "(c)" not in md2 and "| none | 25 | (a) success |" in md2  # (a) and (b) pair without the handover


def test_rollout_ends_partition_the_rollouts_and_the_report_shows_them(tmp_path, rng):
    from umi_aug.square.report import ENDS, cell_metrics, rollout_ends, write_report

    n = 300
    flags = rng.random((n, 4)) < [0.1, 0.3, 0.4, 0.3]  # success, lifted, pre-grasp, peg contact
    rows = [{"config": i, "success": bool(s), "inserted": bool(s), "lifted": bool(lf or (s and i % 2)),
             "pregrasp_reached": bool(p), "collision_peg": bool(c), "collision_table": False,
             "pregrasp_min_pos_err_m": 0.01, "pregrasp_min_rot_err_deg": 1.0, "max_nut_rise_m": 0.0}
            for i, (s, lf, p, c) in enumerate(flags)]
    e = rollout_ends(rows)
    assert sum(e[k] for k in ENDS) == n
    s, lf, p, c = (np.array([r[k] for r in rows]) for k in ("success", "lifted", "pregrasp_reached", "collision_peg"))
    assert e["success"] == s.sum()  # a success counts as one whether or not its record says lifted
    assert e["lifted_touched_peg"] == (~s & lf & c).sum() and e["lifted_no_peg_contact"] == (~s & lf & ~c).sum()
    assert e["pregrasp_not_lifted"] == (~s & ~lf & p).sum() and e["no_pregrasp_not_lifted"] == (~s & ~lf & ~p).sum()
    assert e["lifted_without_pregrasp"] == ((s | lf) & ~p).sum()
    assert rollout_ends([]) == dict.fromkeys(ENDS, 0) | {"lifted_without_pregrasp": 0}
    cfg = _cfg(tmp_path, "variants=[none,ours]", "sweep_thetas=[]")
    _write_results(st.eval_dir(cfg, {"name": "ours_n10"}), rows)
    assert cell_metrics(st.eval_dir(cfg, {"name": "ours_n10"}))["ends"] == e
    write_report(cfg, st.study_cells(cfg), {"steps": {}})
    md = Path(cfg.report_md).read_text()
    assert "## Where the rollouts end" in md
    assert f"| `ours_n10` | {n} | " + " | ".join(str(e[k]) for k in ENDS) + f" | {e['lifted_without_pregrasp']} |" in md
    assert "| `none_n10` |" not in md  # not evaluated: no row
