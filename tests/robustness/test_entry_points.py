"""Bad-input suite, round two (issue #32): the Hydra scripts ``train/train.py``, ``eval/eval_sim.py`` and
``eval/deploy_ur.py`` check every key before any work, and a training rerun into a used folder resumes or is
refused (its ``logs.jsonl`` never holds two runs).

Every case asserts the message and that the inputs are byte-identical afterwards.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.robustness.conftest import snapshot

pytest.importorskip("hydra")
ROOT = Path(__file__).resolve().parents[2]
CONFIGS = str(ROOT / "configs")


def _script(rel: str, *args: str, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), HYDRA_FULL_ERROR="0")
    return subprocess.run([sys.executable, str(ROOT / rel), *args], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=timeout)


def _errors(res: subprocess.CompletedProcess) -> list[str]:
    assert "Traceback" not in res.stderr + res.stdout, res.stderr[-3000:]
    return [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]


def _compose_train(*overrides: str):
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from umi_aug.policy.config import TrainConfig

    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        return compose("train", overrides=list(overrides))


# ------------------------------------------------------------------------------------------- train.py keys
def test_train_plus_key_typo_is_refused_not_dropped():
    """``+training.max_stepz=3``: Hydra adds the key, ``OmegaConf.to_object`` used to drop it (exit 0)."""
    from umi_aug.config_keys import check_known_keys
    from umi_aug.errors import PolicyError
    from umi_aug.policy.config import TrainConfig, structured_config

    cfg = _compose_train("+training.max_stepz=3")
    assert structured_config(cfg).training.max_steps is None  # what OmegaConf alone does: the typo vanishes
    with pytest.raises(PolicyError) as e:
        check_known_keys(cfg, TrainConfig, "train/train.py", PolicyError)
    assert str(e.value) == ("config key 'training.max_stepz' does not exist; did you mean training.max_steps? "
                            "`python train/train.py --cfg job` prints every key")
    check_known_keys(_compose_train("device=cpu_smoke", "task=umi", "policy=small"), TrainConfig, "train/train.py",
                     PolicyError)  # every shipped group composes to known keys only


def test_train_override_keys_are_checked_before_hydra():
    """Hydra's own message for ``training.max_stepz=3`` advised ``+training.max_stepz=3``."""
    from umi_aug.config_keys import unknown_override_keys
    from umi_aug.policy.config import TrainConfig

    argv = ["task=umi", "device=cpu_smoke", "training.max_stepz=3", "++policy.encoder.nam=x", "~training.lr",
            "--cfg", "job", "hydra.run.dir=x", "training.lr=1e-3", "policy.down_dims=[32,64]", "+foo=1"]
    assert unknown_override_keys(argv, TrainConfig) == [("training.max_stepz", ["training.max_steps"]),
                                                        ("policy.encoder.nam", ["policy.encoder.name"]),
                                                        ("foo", [])]


@pytest.mark.parametrize("override, msg", [
    ("training.max_steps=-3", "training.max_steps=-3: must be an integer >= 1, or null to run every epoch of "
                              "training.num_epochs"),
    ("training.num_epochs=0", "training.num_epochs=0: must be an integer >= 1"),
    ("training.lr=-0.1", "training.lr=-0.1: must be a finite number > 0"),
    ("device.num_workers=-1", "device.num_workers=-1: must be an integer >= 0"),
    ("aug.scene_group=0", "aug.scene_group=0: must be an integer >= 1 or 'auto'"),
    ("aug.scene_group=everything", "aug.scene_group='everything': must be an integer >= 1 or 'auto'"),
])
def test_train_out_of_range_values_are_refused(override, msg):
    from umi_aug.errors import PolicyError
    from umi_aug.policy.config import structured_config
    from umi_aug.policy.train_checks import check_train_values

    typed = structured_config(_compose_train(override))
    with pytest.raises(PolicyError) as e:
        check_train_values(typed)
    assert str(e.value) == msg
    check_train_values(structured_config(_compose_train("device=cpu_smoke")))  # the shipped configs pass


@pytest.mark.parametrize("value, typed", [("auto", "auto"), ("AUTO", "AUTO"), ("3", 3)])
def test_train_takes_scene_group_auto_or_a_count(value, typed):
    """``aug.scene_group=auto`` (the episodes of one place share a scene, as ``umi-aug augment --scene-group
    auto``) passes the schema and the checks, and reaches the dataset input as "auto"."""
    from umi_aug.augment.dataset_source import parse_scene_group
    from umi_aug.policy.config import check_aug, structured_config
    from umi_aug.policy.train_checks import check_train_values

    cfg = structured_config(_compose_train("aug=freespace", f"aug.scene_group={value}"))
    assert cfg.aug.scene_group == typed
    check_train_values(cfg)
    check_aug(cfg.aug)
    assert parse_scene_group(cfg.aug.scene_group) == ("auto" if value.lower() == "auto" else 3)


def test_train_py_refuses_a_typo_key_and_a_negative_max_steps(tmp_path):
    """End to end through ``train/train.py``: exit 2, one ``error:`` line, no traceback, nothing trained."""
    run = tmp_path / "run"
    for args, msg in ((["+training.max_stepz=3"], "error: config key 'training.max_stepz' does not exist; did you "
                       "mean training.max_steps? `python train/train.py --cfg job` prints every key"),
                      (["training.max_stepz=3"], "error: config key 'training.max_stepz' does not exist; did you "
                       "mean training.max_steps? `python train/train.py --cfg job` prints every key"),
                      (["training.max_steps=-3"], "error: training.max_steps=-3: must be an integer >= 1, or null "
                       "to run every epoch of training.num_epochs")):
        res = _script("train/train.py", "device=cpu_smoke", f"task.dataset_path={tmp_path / 'none.zarr.zip'}",
                      f"hydra.run.dir={run}", *args, cwd=tmp_path)
        assert res.returncode == 2, res.stderr[-2000:]
        assert _errors(res) == [msg]
        assert not (run / "logs.jsonl").exists() and not (run / "checkpoints").exists()


# ------------------------------------------------------------------------------------------- train reruns
def _logs(run: Path, steps, torn: bool = False) -> Path:
    run.mkdir(parents=True, exist_ok=True)
    rows = [json.dumps({"step": s, "epoch": 0, "train_loss": 1.0 / s}) for s in steps]
    text = "\n".join(rows) + "\n" + ('{"step": 99, "ep' if torn else "")
    (run / "logs.jsonl").write_text(text)
    return run / "logs.jsonl"


def _ckpt(run: Path, step: int) -> Path:
    from umi_aug.policy.checkpoint import save_checkpoint

    return save_checkpoint(run / "checkpoints" / "latest.ckpt",
                           {"cfg": {}, "state_dicts": {}, "pickles": {"global_step": step, "epoch": 0}})


def test_rerun_into_a_folder_of_a_run_without_checkpoint_is_refused(tmp_path):
    """The issue's case: killed at step 15 before its first checkpoint; the rerun started at step 1 and appended."""
    from umi_aug.errors import PolicyError
    from umi_aug.policy.train_checks import prepare_run_folder

    run = tmp_path / "run"
    logs = _logs(run, range(1, 16))
    before = snapshot(run)
    with pytest.raises(PolicyError) as e:
        prepare_run_folder(run, run / "checkpoints" / "latest.ckpt", resume=True)
    assert str(e.value) == (f"{logs}: holds 15 rows (steps 1..15) of an earlier run that left no checkpoint "
                            f"({run / 'checkpoints' / 'latest.ckpt'} is missing), so there is nothing to resume and "
                            f"a new run would append its rows after them: choose a new folder "
                            f"(hydra.run.dir=<new folder>) or move {run} away")
    assert snapshot(run) == before


def test_rerun_with_resume_false_into_a_used_folder_is_refused(tmp_path):
    from umi_aug.errors import PolicyError
    from umi_aug.policy.train_checks import prepare_run_folder

    run = tmp_path / "run"
    logs, ck = _logs(run, range(1, 6)), _ckpt(run, 5)
    before = snapshot(run)
    with pytest.raises(PolicyError) as e:
        prepare_run_folder(run, ck, resume=False)
    assert str(e.value) == (f"training.resume=false but {run} holds an earlier run ({logs}: 5 rows, steps 1..5); a "
                            f"new run would overwrite its checkpoint {ck} and append to its logs: choose a new folder "
                            f"(hydra.run.dir=<new folder>) or drop training.resume=false to continue it")
    assert snapshot(run) == before


def test_resumed_rerun_drops_the_dead_runs_rows_past_the_checkpoint(tmp_path):
    from umi_aug.policy.train_checks import prepare_run_folder

    run = tmp_path / "run"
    logs, ck = _logs(run, range(1, 8), torn=True), _ckpt(run, 5)
    msg = prepare_run_folder(run, ck, resume=True)
    assert msg == (f"{logs}: dropped 3 row(s) of the interrupted run after its checkpoint at step 5 (those steps "
                   f"are trained again)")
    assert [json.loads(x)["step"] for x in logs.read_text().splitlines()] == [1, 2, 3, 4, 5]
    before = snapshot(run)
    assert prepare_run_folder(run, ck, resume=True) is None  # a clean log is left alone
    assert snapshot(run) == before
    assert prepare_run_folder(tmp_path / "fresh", tmp_path / "fresh" / "x.ckpt", resume=True) is None


def test_train_py_rerun_after_a_kill_before_the_first_checkpoint(tmp_path):
    """Through ``train/train.py``: exit 2 before the dataset is opened, the dead run's files untouched."""
    run = tmp_path / "run"
    logs = _logs(run, range(1, 16))
    before = snapshot(run)
    res = _script("train/train.py", "device=cpu_smoke", f"task.dataset_path={tmp_path / 'none.zarr.zip'}",
                  f"hydra.run.dir={run}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    assert _errors(res) == [f"error: {logs}: holds 15 rows (steps 1..15) of an earlier run that left no checkpoint "
                            f"({run / 'checkpoints' / 'latest.ckpt'} is missing), so there is nothing to resume and "
                            f"a new run would append its rows after them: choose a new folder "
                            f"(hydra.run.dir=<new folder>) or move {run} away"]
    assert {k: v for k, v in snapshot(run).items() if "/.hydra/" not in k and not k.endswith(".log")} == before


def test_resumed_training_logs_each_step_once(tmp_path):
    """A run checkpointed at step 3, killed after logging steps 4-5, resumed: ``logs.jsonl`` holds 1..6 once."""
    from tests.policy.helpers import make_dataset, tiny_config
    from umi_aug.policy.train_checks import prepare_run_folder
    from umi_aug.policy.workspace import TrainWorkspace, iter_jsonl

    ds = make_dataset(tmp_path / "d.zarr.zip", np.random.default_rng(0))
    cfg = tiny_config(ds, tmp_path)
    t = cfg.training
    t.num_epochs, t.max_steps, t.pause_at_step, t.val_every, t.sample_every, t.checkpoint_every = 50, 6, 3, 0, 0, 0
    cfg.dataloader.batch_size = 4
    ws = TrainWorkspace(cfg)
    assert ws.run()["global_step"] == 3
    with open(Path(cfg.output_dir) / "logs.jsonl", "a") as f:  # the killed continuation's rows, no checkpoint
        f.write('{"step": 4, "train_loss": 9.0}\n{"step": 5, "train_loss": 9.0}\n{"st')
    t.pause_at_step = None
    ws = TrainWorkspace(cfg)
    assert "dropped 3 row(s)" in prepare_run_folder(ws.output_dir, ws.ckpt_path, t.resume)
    assert ws.run()["global_step"] == 6
    steps = [r["step"] for r in iter_jsonl(Path(cfg.output_dir) / "logs.jsonl") if "train_loss" in r]
    assert steps == [1, 2, 3, 4, 5, 6]


# ------------------------------------------------------------------------------------------- eval_sim / deploy_ur
def test_eval_sim_out_dir_that_is_a_file(tmp_path):
    """Before: Hydra's "Error executing job" and a ``FileExistsError`` traceback."""
    f = tmp_path / "notes.txt"
    f.write_text("my notes")
    before = snapshot(tmp_path)
    res = _script("eval/eval_sim.py", "policy=hold", "configs=0:1", f"out_dir={f}", cwd=ROOT)
    assert res.returncode == 2, res.stderr[-2000:]
    assert _errors(res) == [f"error: out_dir={f}: is a file, not a folder; the results are written into a folder: "
                            "choose another out_dir"]
    res = _script("eval/eval_sim.py", "policy=hold", "configs=0:1", f"out_dir={f / 'sub'}", cwd=ROOT)
    assert _errors(res) == [f"error: out_dir={f / 'sub'}: the folder cannot be created (Not a directory: "
                            f"{f / 'sub'}); choose another out_dir"]
    assert snapshot(tmp_path) == before


def test_eval_sim_checkpoint_that_is_a_run_folder(tmp_path):
    """Before: ``checkpoint='…': no such file`` for a folder that exists."""
    run = tmp_path / "run"
    ck = _ckpt(run, 5)
    before = snapshot(tmp_path)
    res = _script("eval/eval_sim.py", f"checkpoint={run}", "configs=0:1", f"out_dir={tmp_path / 'ev'}", cwd=ROOT)
    assert res.returncode == 2, res.stderr[-2000:]
    assert _errors(res) == [f"error: checkpoint={run}: is a directory, not a checkpoint file; did you mean {ck}?"]
    assert {k: v for k, v in snapshot(tmp_path).items() if "/ev/" not in k} == before


def test_eval_sim_unknown_keys(tmp_path):
    for arg in ("+workerz=2", "workerz=2"):
        res = _script("eval/eval_sim.py", "policy=hold", "configs=0:1", f"out_dir={tmp_path / 'ev'}", arg, cwd=ROOT)
        assert res.returncode == 2, res.stderr[-2000:]
        assert _errors(res) == ["error: config key 'workerz' does not exist; did you mean workers? "
                                "`python eval/eval_sim.py --cfg job` prints every key"]
    from umi_aug.config_keys import unknown_keys
    from umi_aug.eval.config import EvalSimConfig

    assert unknown_keys({"policy": "hold", "workers": 2, "seeed": 1}, EvalSimConfig) == [("seeed", ["seed"])]


def test_deploy_ur_checkpoint_that_is_a_text_file(tmp_path):
    """Before: torch's "weights_only=False will likely succeed … file an issue" advice."""
    f = tmp_path / "model.ckpt"
    f.write_text("these are my notes, not weights\n")
    before = snapshot(f)
    res = _script("eval/deploy_ur.py", f"checkpoint={f}", "dry_run=true", f"out_dir={tmp_path / 'o'}",
                  f"hydra.run.dir={tmp_path / 'h'}", cwd=ROOT)
    assert res.returncode == 2, res.stderr[-2000:]
    assert _errors(res) == [f"error: checkpoint {f}: cannot be read (a text file, not a PyTorch checkpoint); "
                            "expected the latest.ckpt a training run writes (train/train.py → <run "
                            "folder>/checkpoints/latest.ckpt)"]
    assert "weights_only" not in res.stderr
    assert snapshot(f) == before


def test_load_checkpoint_names_what_the_file_is(tmp_path):
    from umi_aug.errors import PolicyError
    from umi_aug.policy.checkpoint import load_checkpoint

    cases = {"empty.ckpt": (b"", "the file is empty"),
             "binary.ckpt": (b"\xff\xfe\x00garbage" * 10, "not a PyTorch checkpoint (neither a torch zip archive "
                                                           "nor a pickle)")}
    for name, (data, why) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(PolicyError) as e:
            load_checkpoint(tmp_path / name)
        assert str(e.value).startswith(f"checkpoint {tmp_path / name}: cannot be read ({why}); "), str(e.value)
    with pytest.raises(PolicyError) as e:
        load_checkpoint(tmp_path)
    assert str(e.value) == (f"checkpoint {tmp_path}: is a directory, not a checkpoint file; pass the .ckpt file "
                            "itself (train/train.py writes <run folder>/checkpoints/latest.ckpt)")


# ------------------------------------------------------------------------------------------- training data
def test_training_on_a_garbage_image_chunk_names_the_chunk(tmp_path):
    """Before: a 40-line traceback ending ``ValueError: not a JPEG XL codestream`` (``validate --deep`` named the
    chunk, training did not)."""
    from tests.policy.helpers import make_dataset, tiny_config
    from umi_aug.errors import PolicyError
    from umi_aug.policy.dataset import UmiPolicyDataset

    ds = make_dataset(tmp_path / "d.zarr", np.random.default_rng(0), n_episodes=2)
    (ds / "data" / "camera0_rgb" / "5.0.0.0").write_bytes(b"\x00garbage" * 40)
    before = snapshot(ds)
    task = tiny_config(ds, tmp_path).task
    want = (f"{ds}: key 'data/camera0_rgb': chunk 5 (rows 5..5) cannot be decoded (")
    tail = (f"); the chunk is corrupt: re-copy or re-create the dataset (`umi-aug validate --deep {ds}` checks every "
            "chunk)")
    with pytest.raises(PolicyError) as e:  # all frames decoded into memory once (the default)
        UmiPolicyDataset(ds, task, "train").frames_in_memory(4.0)
    assert str(e.value).startswith(want) and str(e.value).endswith(tail), str(e.value)
    with pytest.raises(PolicyError) as e:  # frames decoded per sample
        UmiPolicyDataset(ds, task, "train").read_frames("camera0_rgb", np.array([1, 3, 5, 7]))
    assert str(e.value).startswith(want) and str(e.value).endswith(tail), str(e.value)
    assert snapshot(ds) == before


def test_training_on_a_session_folder_suggests_its_dataset(tmp_path):
    """Before: ``task.dataset_path=<a session folder>`` said "not a zarr group" only."""
    from tests.policy.helpers import make_dataset, tiny_config
    from umi_aug.errors import PolicyError
    from umi_aug.policy.dataset import UmiPolicyDataset

    sess = tmp_path / "session"
    (sess / "demos").mkdir(parents=True)
    make_dataset(sess / "dataset.zarr.zip", np.random.default_rng(0), n_episodes=2)
    with pytest.raises(PolicyError) as e:
        UmiPolicyDataset(sess, tiny_config(sess, tmp_path).task, "train")
    assert str(e.value).startswith(f"task.dataset_path: {sess}: not a zarr group (")
    assert str(e.value).endswith(f"; did you mean {sess / 'dataset.zarr.zip'}? ({sess} looks like a UMI session "
                                 "folder)")


# ------------------------------------------------------------------------------------------- SIGTERM in the scripts
#: ``python -c`` prelude: SIGTERM this process right after a given call (deterministic: the handler runs before the
#: next bytecode), then run the script as ``__main__`` with the remaining arguments.
_KILL_AFTER = (
    "import os, runpy, signal, sys\n"
    "mod, cls, meth, key, value, script = sys.argv[1:7]\n"
    "import importlib\n"
    "owner = getattr(importlib.import_module(mod), cls)\n"
    "real = getattr(owner, meth)\n"
    "def patched(self, row, *a, **k):\n"
    "    out = real(self, row, *a, **k)\n"
    "    if str(row.get(key)) == value:\n"
    "        os.kill(os.getpid(), signal.SIGTERM)\n"
    "    return out\n"
    "setattr(owner, meth, patched)\n"
    "sys.argv = [script, *sys.argv[7:]]\n"
    "runpy.run_path(script, run_name='__main__')\n")


def _killed_script(rel: str, patch: tuple[str, ...], *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), HYDRA_FULL_ERROR="0")
    return subprocess.run([sys.executable, "-c", _KILL_AFTER, *patch, str(ROOT / rel), *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=240)


def _tiny_train_args(ds: Path) -> list[str]:
    """Hydra overrides of a CPU-sized training run (the shapes of ``tests/policy/helpers.tiny_config``)."""
    return ["device=cpu_smoke", f"task.dataset_path={ds}", "task.image_size=32", "task.obs_down_sample_steps=2",
            "task.val_ratio=0.25", "policy.encoder.resnet_width=8", "policy.encoder.resnet_blocks=[1,1,1,1]",
            "policy.down_dims=[32,64]", "policy.diffusion_step_embed_dim=32", "policy.num_inference_steps=4",
            "policy.noise_scheduler.num_train_timesteps=20", "training.max_steps=6", "training.num_epochs=50",
            "training.checkpoint_every_steps=2", "training.val_every=0", "training.sample_every=0",
            "training.progress_bar=false", "device.threads=1"]


def test_train_py_sigterm_is_one_line_exit_143_and_the_named_command_resumes(tmp_path):
    """Before: SIGTERM (``timeout``, ``kill``) during training ended with rc 143 and no line; Ctrl-C with a
    traceback. Now one line naming the command that resumes (a Hydra-dated folder is named, since a plain rerun
    would start a new one), and that command finishes the run with every step logged once."""
    import shlex

    from tests.policy.helpers import make_dataset
    from umi_aug.policy.workspace import iter_jsonl

    ds = make_dataset(tmp_path / "d.zarr.zip", np.random.default_rng(0))
    before = snapshot(ds)
    args = _tiny_train_args(ds)
    res = _killed_script("train/train.py", ("umi_aug.policy.workspace", "_JsonlLog", "write", "step", "3"), *args,
                         cwd=tmp_path)
    assert res.returncode == 143, res.stderr[-3000:]
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    (run,) = (tmp_path / "outputs").glob("*/*")  # Hydra's dated folder
    ckpt = run / "checkpoints" / "latest.ckpt"
    cmd = shlex.join(["python", "train/train.py", *args, f"hydra.run.dir={run}"])
    assert lines == [f"train/train.py: interrupted (SIGTERM); its checkpoint {ckpt} is kept (steps after it are "
                     f"trained again): resume with `{cmd}`"]
    assert ckpt.is_file()
    argv = shlex.split(cmd)
    done = _script(argv[1], *argv[2:], cwd=tmp_path)  # the command as printed (python → this interpreter)
    assert done.returncode == 0, done.stderr[-3000:]
    steps = [r["step"] for r in iter_jsonl(run / "logs.jsonl") if "train_loss" in r]
    assert steps == [1, 2, 3, 4, 5, 6]
    assert snapshot(ds) == before


def test_train_py_sigterm_before_the_first_checkpoint_says_there_is_nothing_to_resume(tmp_path):
    from tests.policy.helpers import make_dataset

    ds = make_dataset(tmp_path / "d.zarr.zip", np.random.default_rng(0))
    run = tmp_path / "run"
    res = _killed_script("train/train.py", ("umi_aug.policy.workspace", "_JsonlLog", "write", "step", "1"),
                         *_tiny_train_args(ds), f"hydra.run.dir={run}", cwd=tmp_path)
    assert res.returncode == 143, res.stderr[-3000:]
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [
        f"train/train.py: interrupted (SIGTERM) before its first checkpoint ({run / 'checkpoints' / 'latest.ckpt'} "
        f"was not written), so there is nothing to resume: rerun into a new folder (hydra.run.dir=<new folder>); "
        f"{run} holds only the interrupted run's logs"]


def test_eval_sim_sigterm_is_one_line_exit_143_and_a_rerun_resumes(tmp_path):
    """Before: rc 143 and no line (Ctrl-C: a traceback). The rerun of the same command skips the finished
    configuration."""
    out = tmp_path / "ev"
    args = ["policy=hold", "configs=0:3", "horizon=3", "workers=1", "progress=false", f"out_dir={out}"]
    res = _killed_script("eval/eval_sim.py", ("umi_aug.eval.results", "ResultsLog", "append", "config", "0"), *args,
                         cwd=ROOT)
    assert res.returncode == 143, res.stderr[-3000:]
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [
        f"eval/eval_sim.py: interrupted (SIGTERM); the finished configurations are kept in {out / 'results.jsonl'} "
        "— rerun the same command to resume"]
    assert [json.loads(x)["config"] for x in (out / "results.jsonl").read_text().splitlines()] == [0]
    done = _script("eval/eval_sim.py", *args, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(json.loads(x)["config"] for x in (out / "results.jsonl").read_text().splitlines()) == [0, 1, 2]


# ------------------------------------------------------------------------------------------- square_study.py keys
@pytest.mark.parametrize("args, msg", [
    (["out_dirr=x"], "config key 'out_dirr' does not exist; did you mean out_dir? `python eval/square_study.py "
                     "recipe={recipe} --cfg` prints every key"),
    (["+n_per_demoo=3"], "config key 'n_per_demoo' does not exist; did you mean n_per_demo? `python "
                         "eval/square_study.py recipe={recipe} --cfg` prints every key"),
    (["scene.n_scan_viewz=3"], "{recipe}: config key 'scene.n_scan_viewz' does not exist; did you mean "
                               "scene.n_scan_views? scene holds fields of SquareSceneConfig: "),
    (["spartn.strid=3"], "{recipe}: config key 'spartn.strid' does not exist; did you mean spartn.stride? spartn "
                         "holds fields of SpartnConfig: "),
    (["train_overrides=[policy=small,training.max_stepz=3]"],
     "{recipe}: train_overrides: config key 'training.max_stepz' does not exist; did you mean training.max_steps? "
     "`python train/train.py --cfg job` prints every key"),
    (["train_overrides=[policy=small,training.max_steps=-3]"],
     "{recipe}: train_overrides: training.max_steps=-3: must be an integer >= 1, or null to run every epoch of "
     "training.num_epochs"),
    (["eval_overrides=[workerz=2]"], "{recipe}: eval_overrides: config key 'workerz' does not exist; did you mean "
                                     "workers? `python eval/eval_sim.py --cfg job` prints every key"),
    (["n_per_demo=0"], "{recipe}: n_per_demo = 0: must be >= 1"),
    (["theta_deg=500"], "{recipe}: theta_deg = 500.0: must be in (0, 180] degrees"),
    (["eval_workers=0"], "{recipe}: eval_workers = 0: must be >= 1"),
])
def test_square_study_refuses_unknown_keys_and_bad_values_before_any_work(tmp_path, args, msg):
    """Before: an override typo gave a 3-line OmegaConf message; a typo in ``scene``/``spartn`` or in the recipe's
    ``train_overrides``/``eval_overrides`` (and ``training.max_steps=-3``) passed, to fail (or train silently)
    after hours of data generation."""
    recipe = ROOT / "configs" / "square_study" / "cpu.yaml"
    out = tmp_path / "study"
    res = _script("eval/square_study.py", "recipe=cpu", f"out_dir={out}", f"record_dir={tmp_path / 'rec'}", *args,
                  cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("square_study: " + msg.format(recipe=recipe)), lines
    assert not out.exists() and not (tmp_path / "rec").exists()


def test_square_study_recipe_file_keys_and_listing(tmp_path):
    """A key in the recipe file itself is checked too; ``--cfg`` (the hint's command) lists every key; an unknown
    recipe name lists the shipped ones."""
    text = (ROOT / "configs" / "square_study" / "cpu.yaml").read_text()
    mine = tmp_path / "mine.yaml"
    mine.write_text(text.replace("n_per_demo: 20", "n_per_dem0: 20"))
    before = snapshot(mine)
    res = _script("eval/square_study.py", f"recipe={mine}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.strip() == (f"square_study: {mine}: config key 'n_per_dem0' does not exist; did you mean "
                                  f"n_per_demo? `python eval/square_study.py recipe={mine} --cfg` prints every key")
    assert snapshot(mine) == before
    res = _script("eval/square_study.py", "recipe=cpu", "n_per_demo=7", "--cfg", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    import yaml

    shown = yaml.safe_load(res.stdout)
    assert shown["n_per_demo"] == 7 and shown["spartn"]["stride"] == 2 and "train_overrides" in shown
    res = _script("eval/square_study.py", "recipe=cpux", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip() == (f"square_study: recipe=cpux: no recipe file {ROOT / 'configs/square_study/cpux.yaml'}"
                                  "; the shipped recipes are cpu, cpu_abs, cpu_regression, paper (or pass a .yaml path)")


def test_square_oracle_export_mode_names_bad_input(tmp_path):
    """``eval/square_oracle.py --export``: a missing export, an unknown action representation and an empty episode
    range each give one ``error:`` line naming the value and exit 2 (no traceback, nothing written)."""
    missing = tmp_path / "missing.zarr.zip"
    out = tmp_path / "o.json"
    for args, want in (([f"--export={missing}"], str(missing)),
                       ([f"--export={missing}", "--action-pose-repr", "relative,absolute"], "'relative,absolute'"),
                       ([f"--export={missing}", "--episodes", "5:5"], "'5:5'")):
        res = _script("eval/square_oracle.py", *args, "--out", str(out), cwd=tmp_path)
        assert res.returncode == 2, res.stderr[-2000:]
        errs = _errors(res)
        assert len(errs) == 1 and want in errs[0], res.stderr[-2000:]
        assert not out.exists()
