"""The evaluation loop over stored start configurations: selection, workers, resume, summary, pictures.

:func:`run_eval` is what ``python eval/eval_sim.py`` calls, with the benchmark to run on (a
:class:`~umi_aug.eval.task.SimTask`; eval_sim's is the square task, :data:`umi_aug.square.eval.SQUARE_TASK`).
Each selected configuration is one job ``(configuration index, state, rollout seed)``; jobs run through
:func:`umi_aug.augment.executor.map_ordered` (in this process for ``workers=1``, spawned processes otherwise — one
environment + one policy per process, built on its first job and reused, 1 torch/BLAS thread — or Ray with
``executor=ray``). Finished configurations are appended to ``results.jsonl`` as they come back; a rerun skips
them, so an interrupted run resumes and a finished one only recomputes its summary (the same, since it is computed
from the records alone).
"""

from __future__ import annotations

import atexit
import contextlib
import io
import json
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table
from tqdm import tqdm

from umi_aug.augment.executor import map_ordered, usable_cores
from umi_aug.errors import EvalError
from umi_aug.eval.config import EvalSimConfig, parse_config_selection
from umi_aug.eval.pictures import plot_init_success
from umi_aug.eval.policies import CheckpointEvalPolicy, RolloutSpec
from umi_aug.eval.results import ResultsLog, check_run_key, file_sha256
from umi_aug.eval.rollout import Handover, VideoSpec, rollout_config
from umi_aug.eval.stats import summarise
from umi_aug.eval.task import SimTask
from umi_aug.io_utils import atomic_write_text

__all__ = ["run_eval", "load_eval_configs", "rollout_seed", "default_out_dir", "policy_kinds"]

log = logging.getLogger(__name__)

_WORKER: dict[str, Any] = {}  # per-process env + policy, keyed by the policy spec


def rollout_seed(base_seed: int, config: int) -> int:
    """Seed of rollout ``config`` (independent of worker and order): ``SeedSequence([base_seed, config])``."""
    return int(np.random.SeedSequence([int(base_seed), int(config)]).generate_state(1)[0])


def load_eval_configs(path: str | Path) -> dict[str, Any]:
    """Read and validate a start-configuration file (``umi-aug square-init-configs``).

    Returns:
        ``{"states": float64 [N, S], "T_world_cam": float64 [N, 4, 4], "source_index": [N] or None, "env_args":
        dict or None}``.
    Raises:
        EvalError: missing/unreadable file, missing key, wrong shape or non-finite values (names file and key).
    """
    path = Path(path)
    if not path.is_file():
        raise EvalError(f"configs_file={str(path)!r}: no such file (the 1000 square configurations are "
                        f"eval/square_init_configs_1000.npz; run from the repository root)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # numpy raises several types for a damaged archive
        raise EvalError(f"configs_file={str(path)!r}: not a readable .npz ({type(exc).__name__}: {exc})") from exc
    for key in ("states", "T_world_cam"):
        if key not in data:
            raise EvalError(f"configs_file={str(path)!r}: key {key!r} missing (keys: {sorted(data)})")
    states = np.asarray(data["states"])
    T = np.asarray(data["T_world_cam"])
    if states.ndim != 2 or states.shape[0] < 1 or not np.issubdtype(states.dtype, np.floating):
        raise EvalError(f"configs_file={str(path)!r}: 'states' must be float [N, S], got {states.dtype} "
                        f"{states.shape}")
    if T.shape != (len(states), 4, 4):
        raise EvalError(f"configs_file={str(path)!r}: 'T_world_cam' must be [{len(states)}, 4, 4], got {T.shape}")
    for key, arr in (("states", states), ("T_world_cam", T)):
        bad = np.where(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))[0]
        if len(bad):
            raise EvalError(f"configs_file={str(path)!r}: key {key!r} has non-finite values in rows "
                            f"{bad[:5].tolist()}")
    env_args = None
    if "env_args" in data:
        try:
            env_args = json.loads(str(data["env_args"]))
        except ValueError as exc:
            raise EvalError(f"configs_file={str(path)!r}: key 'env_args' is not JSON ({exc})") from exc
    return {"states": states.astype(np.float64), "T_world_cam": T.astype(np.float64),
            "source_index": data.get("source_index"), "env_args": env_args}


def policy_kinds(task: SimTask) -> tuple[str, ...]:
    """The values of ``policy=`` on ``task``: ``checkpoint`` (the harness's own) and the task's scripted controls."""
    return ("checkpoint", *task.controls)


def default_out_dir(cfg: EvalSimConfig) -> Path:
    """``eval_runs/<policy>`` or, for a checkpoint, ``eval_runs/<checkpoint folder>_<file stem>``."""
    if cfg.policy == "checkpoint" and cfg.checkpoint:
        p = Path(cfg.checkpoint)
        return Path("eval_runs") / f"{p.parent.name}_{p.stem}"
    return Path("eval_runs") / cfg.policy


def _build_policy(spec: dict[str, Any]):
    """The policy of a job's spec: a checkpoint, or one of the task's scripted controls."""
    if spec["policy"] == "checkpoint":
        return CheckpointEvalPolicy.from_checkpoint(spec["checkpoint"], device=spec["device"],
                                                    n_action_steps=spec["n_action_steps"],
                                                    gripper_close_below_m=spec["gripper_close_below_m"])
    return spec["task"].control(spec["policy"], spec)


def _check_handover(cfg: EvalSimConfig, task: SimTask) -> dict[str, Any]:
    """The handover settings of ``cfg`` as a plain dict (part of the run key).

    Raises:
        EvalError: a handover kind that is not one of the task's scripted controls, a sub-goal the task does not
            record, or a step limit below 1.
    """
    if cfg.handover not in task.controls or cfg.handover == "replay":  # replay needs the demos' own starts
        raise EvalError(f"handover={cfg.handover!r}: expected one of the task's scripted controls "
                        f"{list(task.controls)} (or null)")
    if cfg.handover_subgoal is not None and cfg.handover_subgoal not in task.subgoals:
        raise EvalError(f"handover_subgoal={cfg.handover_subgoal!r}: expected one of {list(task.subgoals)}")
    limit = cfg.handover_step_limit
    if limit is not None and int(limit) < 1:
        raise EvalError(f"handover_step_limit={limit!r}: need at least 1 control step (or null)")
    if cfg.handover_subgoal is None and limit is None:
        raise EvalError("handover: neither handover_subgoal nor handover_step_limit is set; nothing would hand over")
    return {"kind": cfg.handover, "subgoal": cfg.handover_subgoal, "step_limit": None if limit is None else int(limit)}


def _worker_state(spec: dict[str, Any]) -> dict[str, Any]:
    """This process's env (+ probe, cameras; rebuilt only when the task or its env_meta changes) and policy
    (rebuilt when the policy spec changes)."""
    task: SimTask = spec["task"]
    env_key = json.dumps([type(task).__qualname__, spec["env_meta"]], sort_keys=True, default=str)
    if _WORKER.get("env_key") != env_key:
        _close_worker_state()
        chatter = io.StringIO()  # simulators print banners and macro warnings (robosuite): keep them off the console
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            env = task.make_env(spec["env_meta"])
        log.debug("environment created: %s", chatter.getvalue())
        cams: dict[int, Any] = {}

        def camera(size: int):
            if size not in cams:
                cams[size] = task.camera(env, size)
                if not _WORKER_CLOSE_REGISTERED:
                    # Free the GL contexts before MuJoCo's EGL atexit (registered at the first context, so it
                    # runs after this one) terminates the display; left to interpreter teardown, every context
                    # prints an EGLError traceback from GLContext.__del__.
                    atexit.register(_close_worker_state)
                    _WORKER_CLOSE_REGISTERED.append(True)
            return cams[size]

        _WORKER.update(env_key=env_key, env=env, probe=task.probe(env), camera=camera, cameras=cams)
    if _WORKER.get("policy_key") != spec["key"]:
        _WORKER["policy"] = _build_policy(spec)
        h = spec.get("handover")
        _WORKER["handover"] = (Handover(task.control(h["kind"], spec), h["subgoal"], h["step_limit"])
                               if h else None)
        _WORKER["policy_key"] = spec["key"]
    return _WORKER


_WORKER_CLOSE_REGISTERED: list[bool] = []


def _close_worker_state() -> None:
    """Close this process's cameras (GL contexts) and env while EGL is still alive (registered with atexit)."""
    for cam in _WORKER.get("cameras", {}).values():
        cam.close()
    if "env" in _WORKER:
        _WORKER["env"].close()
    _WORKER.clear()


def _run_task(job: tuple[dict[str, Any], int, np.ndarray, int, dict | None]) -> dict[str, Any]:
    """Worker body: one rollout (top-level so spawned processes and Ray can pickle it)."""
    spec, config, state, seed, video = job
    w = _worker_state(spec)
    policy = w["policy"]
    size = RolloutSpec.of(policy).image_size
    cam = w["camera"](size) if size else None
    vspec = VideoSpec(**video) if video else None
    return rollout_config(w["env"], w["probe"], policy, state, config, seed, horizon=spec["horizon"], camera=cam,
                          stop_on_success=spec["stop_on_success"], video=vspec, camera_factory=w["camera"],
                          handover=w["handover"])


def _print_table(summary: dict[str, Any], title: str) -> None:
    def pct(d: dict[str, Any]) -> str:
        lo, hi = d["wilson95"]
        return f"{100 * d['rate']:.1f} % ({d['count']}/{summary['n']})  [{100 * lo:.1f}, {100 * hi:.1f}]"

    t = Table(title=title)
    t.add_column("metric")
    t.add_column("value (Wilson 95 %)")
    lo, hi = summary["success_wilson95"]
    t.add_row("success", f"{100 * summary['success_rate']:.1f} % ({summary['successes']}/{summary['n']})  "
                         f"[{100 * lo:.1f}, {100 * hi:.1f}]")
    for k, v in summary["subgoals"].items():
        t.add_row(k, pct(v))
    for k, v in summary["collisions"].items():
        t.add_row(k, pct(v))
    for why, h in summary.get("handover", {}).items():
        lo, hi = h["success_wilson95"]
        t.add_row(f"handed over: {why}", f"{h['count']}/{summary['n']}, of which {h['successes']} succeeded  "
                                         f"[{100 * lo:.1f}, {100 * hi:.1f}]")
    s2s = summary["mean_steps_to_success"]
    t.add_row("mean steps to success", "—" if s2s is None else f"{s2s:.1f}")
    t.add_row("rollouts / hour", f"{summary['rollouts_per_hour']:.0f} ({summary['workers']} worker(s))")
    ms = summary["time_per_step_ms"]
    t.add_row("ms / step: sim | render | policy | other",
              f"{ms['sim']:.1f} | {ms['render']:.1f} | {ms['policy']:.1f} | {ms['other']:.1f}")
    Console().print(t)


def run_eval(cfg: EvalSimConfig, task: SimTask) -> dict[str, Any]:
    """Evaluate ``cfg.policy`` on the selected configurations of ``task``; returns the summary (also
    ``summary.json``).

    Raises:
        EvalError: bad configuration file / selection / policy settings, or ``out_dir`` of a different run.
        PolicyError: a malformed checkpoint.
    """
    kinds = policy_kinds(task)
    if cfg.policy not in kinds:
        raise EvalError(f"policy={cfg.policy!r}: expected one of {list(kinds)}")
    if int(cfg.horizon) < 1:
        raise EvalError(f"horizon={cfg.horizon!r}: need at least 1 control step")
    out_dir = Path(cfg.out_dir) if cfg.out_dir else default_out_dir(cfg)
    key: dict[str, Any] = {"policy": cfg.policy, "horizon": int(cfg.horizon), "seed": int(cfg.seed),
                           "stop_on_success": bool(cfg.stop_on_success)}
    spec: dict[str, Any] = {"task": task, "policy": cfg.policy, "horizon": int(cfg.horizon),
                            "stop_on_success": bool(cfg.stop_on_success)}
    replay_actions = None
    if cfg.policy == "replay":
        if not cfg.replay_dir:
            raise EvalError("policy=replay needs replay_dir=<folder of episode shards seed_*.npz>")
        configs, replay_actions, names = task.replay_configs(cfg.replay_dir)
        key["replay_episodes"] = names
        spec["replay_actions"] = replay_actions
    else:
        configs = load_eval_configs(cfg.configs_file)
        key["configs_file_sha256"] = file_sha256(cfg.configs_file)
    if cfg.policy == "checkpoint":
        if not cfg.checkpoint:
            raise EvalError(f"policy=checkpoint needs checkpoint=PATH (or policy={'|'.join(task.controls)})")
        from umi_aug.policy.checkpoint import checkpoint_file_problem  # lazy: torch, only for a checkpoint

        problem = checkpoint_file_problem(cfg.checkpoint)
        if problem:
            raise EvalError(f"checkpoint={cfg.checkpoint}: {problem}")
        key |= {"checkpoint_sha256": file_sha256(cfg.checkpoint), "n_action_steps": cfg.n_action_steps,
                "gripper_close_below_m": float(cfg.gripper_close_below_m)}
        spec |= {"checkpoint": str(Path(cfg.checkpoint).resolve()), "device": cfg.device,
                 "n_action_steps": cfg.n_action_steps, "gripper_close_below_m": float(cfg.gripper_close_below_m)}
        CheckpointEvalPolicy.from_checkpoint(cfg.checkpoint, device=cfg.device,
                                             n_action_steps=cfg.n_action_steps)  # a bad checkpoint fails here
    if cfg.policy == "random":
        key["random_scale"] = spec["random_scale"] = float(cfg.random_scale)
    if cfg.handover is not None:
        spec["handover"] = key["handover"] = _check_handover(cfg, task)
        spec.setdefault("random_scale", float(cfg.random_scale))
    if cfg.executor not in ("local", "ray"):
        raise EvalError(f"executor={cfg.executor!r}: expected 'local' or 'ray'")
    selected = parse_config_selection(cfg.configs, len(configs["states"]))
    spec["env_meta"] = configs["env_args"]
    spec["key"] = repr(sorted((k, str(v)) for k, v in key.items()))
    check_run_key(out_dir, key)
    results = ResultsLog(out_dir / "results.jsonl")
    done = results.read()
    todo = [i for i in selected if i not in done]
    workers = int(cfg.workers) if cfg.workers else usable_cores()
    pool_workers = max(1, min(workers, max(len(todo), 1)))  # `workers` itself goes into the rollouts/hour rate
    video_dir = out_dir / "videos"
    tasks = []
    for k, i in enumerate(selected):
        if i in done:
            continue
        video = None
        if cfg.video_every and k % int(cfg.video_every) == 0:
            video_dir.mkdir(parents=True, exist_ok=True)
            video = {"wrist_path": str(video_dir / f"config_{i:04d}_wrist.mp4"),
                     "external_path": str(video_dir / f"config_{i:04d}_external.mp4"), "size": int(cfg.video_size)}
        tasks.append((spec, i, configs["states"][i], rollout_seed(cfg.seed, i), video))
    log.info("eval %s: %d selected, %d already done, %d to run on %d worker(s) (%s) → %s", cfg.policy,
             len(selected), len(selected) - len(todo), len(todo), pool_workers, cfg.executor, out_dir)
    t0 = time.perf_counter()
    n_ok = sum(bool(done[i]["success"]) for i in selected if i in done)
    n_seen = len(selected) - len(todo)
    bar = tqdm(total=len(selected), initial=n_seen, desc=f"eval {cfg.policy}", disable=not cfg.progress,
               dynamic_ncols=True)
    try:
        if tasks:
            it = map_ordered(_run_task, tasks, executor=cfg.executor, workers=pool_workers,
                             address=cfg.ray_address, threads_per_worker=1)
            for rec in it:
                if configs.get("source_index") is not None:
                    rec["source_index"] = int(configs["source_index"][rec["config"]])
                results.append(rec)
                done[rec["config"]] = rec
                n_ok += int(rec["success"])
                n_seen += 1
                bar.set_postfix_str(f"success {n_ok}/{n_seen} = {100.0 * n_ok / n_seen:.1f} %")
                bar.update(1)
    finally:
        bar.close()
    recs = [done[i] for i in selected]
    summary = summarise(recs, wall_seconds=time.perf_counter() - t0, workers=workers, subgoals=task.subgoals,
                        collisions=task.collisions)
    summary |= {"workers": workers, "policy": cfg.policy, "checkpoint": cfg.checkpoint,
                "configs_file": None if cfg.policy == "replay" else cfg.configs_file, "configs": cfg.configs,
                "horizon": int(cfg.horizon), "seed": int(cfg.seed), **task.summary_info(),
                "config": asdict(cfg)}
    atomic_write_text(out_dir / "summary.json", _json(summary))
    plot_init_success(out_dir / "init_success.png", configs["T_world_cam"], done, selected,
                      title=f"{cfg.policy}{' ' + Path(cfg.checkpoint).name if cfg.checkpoint else ''}: "
                            f"{summary['successes']}/{summary['n']} successful")
    if cfg.progress:
        _print_table(summary, f"eval_sim: {cfg.policy} on {len(selected)} configurations → {out_dir}")
    return summary


def _json(obj: Any) -> str:
    def clean(o):
        if isinstance(o, float) and not math.isfinite(o):
            return None
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [clean(v) for v in o]
        return o

    return json.dumps(clean(obj), indent=1)
