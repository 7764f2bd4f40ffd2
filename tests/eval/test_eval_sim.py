"""eval_sim harness: Wilson interval vs a root-finding reference, selection/config-file/checkpoint errors, resume
after an interrupted run, determinism, and the controls (replay succeeds; hold-still and random never succeed)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from umi_aug.errors import EvalError, PolicyError
from umi_aug.eval.config import EvalSimConfig, parse_config_selection
from umi_aug.eval.stats import wilson_interval
from umi_aug.square.eval import SQUARE_TASK
from tests.eval.conftest import CONFIGS_FILE

TIMING_KEYS = ("time_s", "wall_s")


def _wilson_ref(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Reference: the interval's ends are the roots of |p̂ − p| = z·sqrt(p(1 − p)/n) (bisection)."""
    phat = k / n

    def f(p):
        return (phat - p) ** 2 - z * z * p * (1 - p) / n

    def root(a, b):
        for _ in range(200):
            m = 0.5 * (a + b)
            if (f(a) > 0) == (f(m) > 0):
                a = m
            else:
                b = m
        return 0.5 * (a + b)

    lo = 0.0 if k == 0 else root(0.0, phat)
    hi = 1.0 if k == n else root(phat, 1.0)
    return lo, hi


@pytest.mark.parametrize("k,n", [(0, 1), (1, 1), (0, 10), (5, 10), (9, 10), (950, 1000), (1000, 1000), (1, 3),
                                 (37, 100), (0, 1000)])
def test_wilson_matches_reference(k, n):
    lo, hi = wilson_interval(k, n)
    rlo, rhi = _wilson_ref(k, n)
    assert 0.0 <= lo <= k / n <= hi <= 1.0
    assert lo == pytest.approx(rlo, abs=1e-9) and hi == pytest.approx(rhi, abs=1e-9)


def test_wilson_known_values_and_bad_input():
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)  # textbook value
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def test_selection():
    assert parse_config_selection("0:1000", 1000) == list(range(1000))
    assert parse_config_selection("10:20:5", 1000) == [10, 15]
    assert parse_config_selection("7,3,3", 10) == [3, 7]
    for bad in ("0:1001", "a:b", "12", "5:5", "1:2:3:4"):
        with pytest.raises(EvalError, match="configs="):
            parse_config_selection(bad, 10)


def _cfg(tmp_path, **kw) -> EvalSimConfig:
    base = dict(configs_file=str(CONFIGS_FILE), out_dir=str(tmp_path / "run"), workers=1, progress=False,
                horizon=30)
    base.update(kw)
    return EvalSimConfig(**base)


@pytest.mark.parametrize("breakage", ["missing_key", "bad_shape", "nan", "garbage", "absent"])
def test_malformed_configs_file_one_clear_error(tmp_path, breakage):
    from umi_aug.eval.runner import run_eval

    src = dict(np.load(CONFIGS_FILE))
    path = tmp_path / "configs.npz"
    if breakage == "missing_key":
        src.pop("states")
    elif breakage == "bad_shape":
        src["T_world_cam"] = src["T_world_cam"][:, :3]
    elif breakage == "nan":
        src["states"] = src["states"].copy()
        src["states"][7, 3] = np.nan
    if breakage == "garbage":
        path.write_bytes(b"PK\x03\x04 not really a zip")
    elif breakage != "absent":
        np.savez(path, **src)
    with pytest.raises(EvalError) as exc:
        run_eval(_cfg(tmp_path, policy="hold", configs_file=str(path)), SQUARE_TASK)
    msg = str(exc.value)
    assert "configs_file" in msg and str(path) in msg
    expected = {"missing_key": "'states'", "bad_shape": "'T_world_cam'", "nan": "rows [7]", "garbage": "npz",
                "absent": "no such file"}[breakage]
    assert expected in msg
    assert not (tmp_path / "run" / "results.jsonl").exists()


@pytest.mark.parametrize("breakage", ["garbage", "wrong_weights", "absent"])
def test_malformed_checkpoint_one_clear_error(tmp_path, tiny_checkpoint, breakage):
    import torch

    from umi_aug.eval.runner import run_eval

    bad = tmp_path / "bad.ckpt"
    if breakage == "garbage":
        bad.write_bytes(b"\x00not a checkpoint")
    elif breakage == "wrong_weights":
        payload = torch.load(str(tiny_checkpoint), weights_only=True)
        sd = payload["state_dicts"]["model"]
        sd.pop(next(k for k in sd if "weight" in k))
        torch.save(payload, str(bad))
    with pytest.raises((PolicyError, EvalError)) as exc:
        run_eval(_cfg(tmp_path, policy="checkpoint", checkpoint=str(bad), configs="0:2"), SQUARE_TASK)
    assert "bad.ckpt" in str(exc.value)


def _strip(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k not in TIMING_KEYS}


def test_resume_after_interrupted_run(tmp_path, square_env, monkeypatch):
    """Kill the run after 2 of 5 configurations (+ a torn half line as a killed writer leaves it): the rerun runs
    only the missing ones; no duplicate, no missing configuration; the same records as an uninterrupted run."""
    from umi_aug.eval import runner
    from umi_aug.eval.results import ResultsLog

    cfg = _cfg(tmp_path, policy="random", configs="3:8", horizon=5)  # the bookkeeping, not the rollout
    real_append = ResultsLog.append
    calls = {"n": 0}

    def dying_append(self, rec):
        if calls["n"] == 2:
            with open(self.path, "ab") as fh:  # a writer killed mid-line
                fh.write(json.dumps(rec)[:40].encode())
            raise KeyboardInterrupt("killed")
        calls["n"] += 1
        real_append(self, rec)

    monkeypatch.setattr(ResultsLog, "append", dying_append)
    with pytest.raises(KeyboardInterrupt):
        runner.run_eval(cfg, SQUARE_TASK)
    monkeypatch.setattr(ResultsLog, "append", real_append)
    path = tmp_path / "run" / "results.jsonl"
    assert len(path.read_bytes().split(b"\n")) == 3  # 2 lines + the torn one
    ran = []
    real_task = runner._run_task
    monkeypatch.setattr(runner, "_run_task", lambda t: ran.append(t[1]) or real_task(t))
    summary = runner.run_eval(cfg, SQUARE_TASK)
    assert ran == [5, 6, 7]
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    assert sorted(r["config"] for r in lines) == [3, 4, 5, 6, 7]
    assert summary["n"] == 5
    # a third run does nothing and gives the same summary; a fresh uninterrupted run gives the same records
    ran.clear()
    again = runner.run_eval(cfg, SQUARE_TASK)
    assert ran == [] and _strip_summary(again) == _strip_summary(summary)
    fresh = runner.run_eval(_cfg(tmp_path, policy="random", configs="3:8", horizon=5, out_dir=str(tmp_path / "b")),
                            SQUARE_TASK)
    fresh_lines = {json.loads(x)["config"]: json.loads(x) for x in (tmp_path / "b" / "results.jsonl").read_text()
                   .splitlines()}
    assert {r["config"]: _strip(r) for r in lines} == {k: _strip(v) for k, v in fresh_lines.items()}
    assert fresh["success_rate"] == summary["success_rate"]
    assert (tmp_path / "run" / "init_success.png").stat().st_size > 10_000
    # the same folder with different settings is refused (no silent mixing)
    with pytest.raises(EvalError, match="horizon"):
        runner.run_eval(_cfg(tmp_path, policy="random", configs="3:8", horizon=6), SQUARE_TASK)


def _strip_summary(s: dict) -> dict:
    drop = ("time_per_step_ms", "time_split", "mean_rollout_s", "rollouts_per_hour", "wall_s_this_run")
    return {k: v for k, v in s.items() if k not in drop}


def test_checkpoint_rollout_deterministic(square_env, tiny_checkpoint):
    """The same checkpoint + configuration + seed gives the same rollout, whatever ran before in that env."""
    from umi_aug.eval.policies import CheckpointEvalPolicy
    from umi_aug.eval.rollout import rollout_config
    from umi_aug.eval.runner import load_eval_configs, rollout_seed
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.eval import SceneProbe

    configs = load_eval_configs(CONFIGS_FILE)
    probe = SceneProbe(square_env)
    pol = CheckpointEvalPolicy.from_checkpoint(tiny_checkpoint)
    cam = WristFisheyeCamera(square_env.model, pol.image_size)
    try:
        def run(i, seed):
            return rollout_config(square_env, probe, pol, configs["states"][i], i, seed, horizon=12, camera=cam)

        a = run(11, rollout_seed(0, 11))
        run(500, rollout_seed(0, 500))  # something else in between
        b = run(11, rollout_seed(0, 11))
        c = run(11, rollout_seed(1, 11))
    finally:
        cam.close()
    assert a["final_state_sha1"] == b["final_state_sha1"] and _strip(a) == _strip(b)
    assert c["final_state_sha1"] != a["final_state_sha1"]  # the seed drives the sampling noise
    assert a["time_s"]["render"] > 0 and a["time_s"]["policy"] > 0 and pol.n_inferences >= 2


def test_expert_needs_no_rendering(square_env):
    from umi_aug.eval.rollout import rollout_config
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.square.controls import ExpertEvalPolicy
    from umi_aug.square.eval import SceneProbe

    configs = load_eval_configs(CONFIGS_FILE)
    rec = rollout_config(square_env, SceneProbe(square_env), ExpertEvalPolicy(), configs["states"][1], 1, 0,
                         horizon=400)
    assert rec["success"] and rec["pregrasp_reached"] and rec["lifted"] and rec["inserted"]
    assert rec["pregrasp_step"] < rec["lifted_step"] <= rec["inserted_step"] <= rec["steps_to_success"]
    assert rec["time_s"]["render"] == 0.0


@pytest.mark.slow
def test_controls_replay_succeeds_hold_and_random_never(tmp_path, square_env):
    """(b) replaying a recorded successful expert episode from its own start state succeeds; (c) hold-still and
    random actions never succeed (2 configurations each, 150 / 100 steps to stay CI-sized; the full-horizon
    controls over more configurations are in eval/README.md)."""
    from umi_aug.eval.runner import run_eval
    from umi_aug.square.episode import rollout_expert
    from umi_aug.square.writers import save_episode

    shards = tmp_path / "shards"
    ep = rollout_expert(square_env, seed=123, render=False)
    assert ep.success
    save_episode(shards / "seed_0000123.npz", ep)
    rep = run_eval(_cfg(tmp_path, policy="replay", replay_dir=str(shards), configs="0:1", horizon=400,
                        out_dir=str(tmp_path / "replay")), SQUARE_TASK)
    assert rep["successes"] == 1
    hold = run_eval(_cfg(tmp_path, policy="hold", configs="0:2", horizon=150, out_dir=str(tmp_path / "hold")),
                    SQUARE_TASK)
    rnd = run_eval(_cfg(tmp_path, policy="random", configs="0:2", horizon=100, out_dir=str(tmp_path / "rnd")),
                   SQUARE_TASK)
    assert hold["successes"] == 0 and hold["subgoals"]["lifted"]["count"] == 0
    assert rnd["successes"] == 0 and rnd["subgoals"]["inserted"]["count"] == 0


@pytest.mark.parametrize("n", [1, 2, 5, 6, 7, 20, 99, 200, 1000])
def test_median_interval_covers_the_median(n):
    """Exact coverage of the order-statistic interval (continuous data: P(j <= #below median < k) under
    Binomial(n, 1/2)) is >= 95 % from n = 6 on (below that even the widest interval has less); the interval is
    ordered, holds the sample median and is made of sample values, on fresh random data with ties and outliers."""
    from math import comb

    from umi_aug.eval.stats import median_interval

    lo, hi = median_interval(np.arange(n, dtype=float))  # ranks 0..n-1: the interval's 1-based ranks
    j, k = int(lo) + 1, int(hi) + 1
    cov = sum(comb(n, i) for i in range(j, k)) / 2**n
    assert cov >= (0.95 if n >= 6 else 1 - 2 / 2**n)
    rng = np.random.default_rng(int(np.random.SeedSequence().entropy % 2**32))
    x = np.concatenate([rng.standard_cauchy(n - n // 3), np.round(rng.normal(size=n // 3))])
    lo, hi = median_interval(x)
    assert lo <= np.median(x) <= hi and lo in x and hi in x


def test_median_interval_rejects_nan_and_is_nan_when_empty():
    from umi_aug.eval.stats import median_interval

    with pytest.raises(ValueError, match="1 of 3 values are not finite"):
        median_interval([1.0, float("nan"), 2.0])
    assert all(np.isnan(median_interval([])))


def test_handover_hands_over_at_the_subgoal_or_the_step_limit(square_env):
    """Issue #29's "learned approach + scripted grasp": the second policy takes over at the first step the
    sub-goal holds, or at the step limit. The expert handing over to hold-still at pre-grasp stops there (no
    lift); hold-still handing over to the expert after 20 steps succeeds as the expert does."""
    from umi_aug.eval.rollout import Handover, rollout_config
    from umi_aug.eval.runner import load_eval_configs
    from umi_aug.eval.stats import summarise
    from umi_aug.square.controls import ExpertEvalPolicy, HoldStillEvalPolicy
    from umi_aug.square.eval import SceneProbe

    configs = load_eval_configs(CONFIGS_FILE)
    probe = SceneProbe(square_env)
    stop = rollout_config(square_env, probe, ExpertEvalPolicy(), configs["states"][1], 1, 0, horizon=120,
                          handover=Handover(HoldStillEvalPolicy(), "pregrasp_reached", None))
    assert stop["handover_reason"] == "subgoal" and stop["handover_step"] == stop["pregrasp_step"]
    assert not stop["lifted"] and not stop["success"]
    late = rollout_config(square_env, probe, HoldStillEvalPolicy(), configs["states"][1], 1, 0, horizon=400,
                          handover=Handover(ExpertEvalPolicy(), "pregrasp_reached", 20))
    assert late["handover_reason"] == "step_limit" and late["handover_step"] == 20
    assert late["success"] and late["pregrasp_step"] > 20 and late["handover_info"]["expert_phase"] in (
        "release", "retreat", "done")
    s = summarise([stop, late] + [{**late, "config": 2, "handover_reason": None, "handover_step": None}],
                  subgoals=SQUARE_TASK.subgoals)
    assert {k: v["count"] for k, v in s["handover"].items()} == {"subgoal": 1, "step_limit": 1, "never": 1}
    assert s["handover"]["step_limit"]["successes"] == 1 and s["handover"]["subgoal"]["successes"] == 0


def test_bad_handover_settings_one_clear_error(tmp_path):
    from umi_aug.eval.runner import run_eval

    for bad, match in (({"handover": "teleop"}, "handover='teleop'"), ({"handover": "replay"}, "handover='replay'"),
                       ({"handover": "expert", "handover_subgoal": "flying"}, "handover_subgoal='flying'"),
                       ({"handover": "expert", "handover_step_limit": 0}, "handover_step_limit=0"),
                       ({"handover": "expert", "handover_subgoal": None, "handover_step_limit": None}, "nothing")):
        with pytest.raises(EvalError, match=match):
            run_eval(_cfg(tmp_path, policy="hold", configs="0:1", horizon=5, **bad), SQUARE_TASK)
