"""Learning curve of a square policy (issue #29 part 3): success and pre-grasp reached on in-distribution resets
against training steps and minutes, time-sliced and resumable.

    python eval/square_curve.py --demos square_demos --name none_n50 --every 3000 --max-steps 30000 \
        --budget-min 60 -- policy=small device.amp=bf16            # train.py overrides after `--`

One training run (``train/train.py task=square``, the schedule spanning ``--max-steps``) is paused every ``--every``
steps (``training.pause_at_step``); each pause's checkpoint is kept and evaluated by ``eval/eval_sim.py`` on the
in-distribution resets (``eval/square_init_configs_reset100.npz``: seeded resets the demos' way, seeds no demo
used), and one row is appended to ``<record>/<name>.jsonl`` (steps, training minutes, success with its Wilson 95 %
interval, pre-grasp reached, lifted, inserted). Rerunning the same command continues where it stopped; no new slice
starts after ``--budget-min`` minutes. ``--report`` writes ``<record>/curves.png`` from every record.

``--dataset X.zarr.zip`` trains on a UMI replay buffer instead of the demo folder's own, e.g. the demos plus their
augmented episodes (``umi-aug augment square_demos -n 3 --mode freespace --image-size 84 --out X.zarr.zip``); the
rows then record its original episodes as ``n_demos`` and all of them as ``n_episodes``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _run(cmd: list[str], log: Path) -> list[float]:
    """Run ``cmd`` with its output appended to ``log``; return the machine's 1-min load average sampled every 30 s."""
    log.parent.mkdir(parents=True, exist_ok=True)
    loads: list[float] = []
    with open(log, "a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
        while True:
            try:
                rc = proc.wait(timeout=30.0)
                break
            except subprocess.TimeoutExpired:
                loads.append(os.getloadavg()[0])
    if rc:
        raise SystemExit(f"error: `{' '.join(cmd[:3])} …` exited {rc}; see {log}")
    return loads


def _commit() -> str:
    """The repository commit the curve runs (``+dirty`` when tracked files differ from it), for the record."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    sha = git("rev-parse", "--short", "HEAD") or "unknown"
    return sha + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def _train_minutes(run_dir: Path) -> float:
    """Training wall minutes of a (possibly resumed) run: the sum of each process's last logged time."""
    from umi_aug.policy.workspace import iter_jsonl

    total, last = 0.0, 0.0
    for r in iter_jsonl(run_dir / "logs.jsonl"):
        if "time" not in r:
            continue
        if float(r["time"]) < last:  # a new process (a resumed slice) restarts its clock
            total += last
        last = float(r["time"])
    return (total + last) / 60.0


def _dataset_files(path: str) -> tuple[Path, int, int, int]:
    """``(zarr, image size, original episodes, all episodes)`` of a training buffer given by ``--dataset``.

    Raises:
        AugmentError: not a readable UMI replay buffer with square ``S x S x 3`` frames in ``data/camera0_rgb``.
    """
    from umi_aug.data.replay_buffer import ReplayBuffer
    from umi_aug.errors import AugmentError, UmiAugError

    p = Path(path)
    try:
        with ReplayBuffer.open(p) as buf:
            n = buf.n_episodes
            shape = tuple(buf["camera0_rgb"].shape[1:])
            aug_id = np.asarray(buf.meta["aug_id"]) if "aug_id" in buf.meta else np.full(n, -1)
    except (UmiAugError, KeyError, OSError) as exc:
        raise AugmentError(f"--dataset {p}: not a UMI replay buffer with data/camera0_rgb ({exc})") from None
    if len(shape) != 3 or shape[0] != shape[1] or shape[2] != 3:
        raise AugmentError(f"--dataset {p}: key 'data/camera0_rgb' has frames {shape}; expected S x S x 3")
    return p.resolve(), int(shape[0]), int((aug_id < 0).sum()), int(n)


def _rows(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []


def curve(args: argparse.Namespace, train_over: list[str]) -> None:
    """Run (or continue) the curve ``args.name``; one process per name at a time (a second is refused)."""
    from umi_aug.io_utils import exclusive_run_lock

    work = Path(args.out) / args.name
    with exclusive_run_lock(work / "curve.lock", f"square_curve run of {args.name!r}"):
        _curve_locked(args, train_over, work)


def _check_same_recipe(record: Path, train_over: list[str], max_steps: int, run_dir: Path) -> None:
    """A record continues only with the training overrides and the schedule length (``--max-steps``) it was started
    with: other overrides would mix recipes in one record, another ``--max-steps`` would silently re-stretch the
    learning-rate schedule of the resumed run (a cosine over 18,000 steps resumed at 12,000 as one over 27,000
    raises the learning rate again)."""
    from umi_aug.errors import EvalError
    from umi_aug.policy.checkpoint import load_checkpoint

    for row in _rows(record):
        if row.get("train_overrides") != train_over:
            raise EvalError(f"{record}: step {row.get('step')} was trained with overrides {row.get('train_overrides')}"
                            f", this run asks for {train_over}; use another --name for another recipe")
        if row.get("max_steps", max_steps) != max_steps:
            raise EvalError(f"{record}: step {row.get('step')} was trained on a schedule of --max-steps "
                            f"{row['max_steps']}, this run asks for {max_steps}; use another --name for another "
                            f"schedule")
    latest = run_dir / "checkpoints" / "latest.ckpt"
    if latest.exists():
        had = (load_checkpoint(latest)["cfg"].get("training") or {}).get("max_steps")
        if had is not None and int(had) != max_steps:
            raise EvalError(f"{latest}: this run's schedule spans training.max_steps={had}, this run asks for "
                            f"--max-steps {max_steps}; use another --name for another schedule")


def _curve_locked(args: argparse.Namespace, train_over: list[str], work: Path) -> None:
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.policy.checkpoint import load_checkpoint
    from umi_aug.square.source import check_square_demos

    record = Path(args.record) / f"{args.name}.jsonl"
    run_dir = work / "run"
    _check_same_recipe(record, train_over, args.max_steps, run_dir)
    if args.dataset:
        zarr, size, n_demos, n_episodes = _dataset_files(args.dataset)
    else:
        files = check_square_demos(args.demos)
        zarr, size, n_demos, n_episodes = files.zarr, files.size, files.n, files.n
    record.parent.mkdir(parents=True, exist_ok=True)
    done = {r["step"] for r in _rows(record)}
    t0 = time.monotonic()
    for k in range(args.every, args.max_steps + 1, args.every):
        if k in done:
            continue
        if (time.monotonic() - t0) / 60.0 > args.budget_min:
            print(f"budget of {args.budget_min} min spent; rerun the same command to continue at step {k}")
            return
        ckpt = work / "checkpoints" / f"step{k:07d}.ckpt"
        loads: list[float] = []
        if not ckpt.exists():
            latest = run_dir / "checkpoints" / "latest.ckpt"
            have = int(load_checkpoint(latest)["pickles"]["global_step"]) if latest.exists() else 0
            if have > k:
                raise SystemExit(f"error: {latest} is at step {have}, past the curve point {k} it was not kept at")
            if have < k:
                loads = _run([sys.executable, "train/train.py", "task=square", f"task.dataset_path={zarr}",
                      f"task.image_size={size}", f"hydra.run.dir={run_dir}",
                      f"training.max_steps={args.max_steps}",
                      f"training.pause_at_step={k}", "training.num_epochs=1000000", "training.val_every=0",
                      "training.sample_every=0", "training.checkpoint_every=0",
                      f"training.checkpoint_every_steps={args.every}", "training.progress_bar=false", *train_over],
                     work / "train.log")
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(latest, str(ckpt) + ".tmp")
            Path(str(ckpt) + ".tmp").replace(ckpt)
        ev = work / f"eval_step{k:07d}"
        _run([sys.executable, "eval/eval_sim.py", f"checkpoint={ckpt}", f"configs_file={args.configs_file}",
              f"configs={args.eval_configs}", f"workers={args.workers}", f"out_dir={ev}", "progress=false"],
             work / "eval.log")
        s = json.loads((ev / "summary.json").read_text())
        row = {"name": args.name, "step": k, "train_minutes": round(_train_minutes(run_dir), 2),
               "n_demos": n_demos, "n_episodes": n_episodes, "dataset": Path(zarr).name, "n": s["n"],
               "success": s["success_rate"], "success_ci95": s["success_wilson95"],
               **{k: s["subgoals"][g]["rate"] for k, g in (("pregrasp", "pregrasp_reached"), ("lifted", "lifted"),
                                                            ("inserted", "inserted"))},
               "train_overrides": train_over, "max_steps": args.max_steps, "eval_configs": args.eval_configs,
               "commit": _commit(),
               # mean 1-min load average while this slice trained (2 = the 2 cores busy with training alone)
               "train_load1": round(sum(loads) / len(loads), 2) if loads else None}
        atomic_write_text(record, record.read_text() + json.dumps(row) + "\n" if record.exists()
                          else json.dumps(row) + "\n")
        print(json.dumps(row))


def report(record_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    files = sorted(record_dir.glob("*.jsonl"))
    colours = plt.get_cmap("tab20")  # one colour per curve (the default cycle repeats after 10)
    for i, f in enumerate(files):
        rows = sorted(_rows(f), key=lambda r: r["step"])
        if not rows:
            continue
        # a row may record minutes its training process spent paused (SIGSTOP, for benchmarks on idle cores)
        m = [r["train_minutes"] - r.get("paused_minutes", 0.0) for r in rows]
        style = {"color": colours(i % 20), "marker": "os^"[i // 20 % 3], "label": f.stem}
        axes[0].plot(m, [100 * r["success"] for r in rows], "-", **style)
        axes[1].plot(m, [100 * (r["pregrasp"] or 0) for r in rows], "-", **style)
    for ax, what in zip(axes, ("full-task success", "pre-grasp reached")):
        ax.set_xlabel("training minutes (2 CPU cores)")
        ax.set_ylabel(f"{what} (%)")
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="center left", bbox_to_anchor=(0.79, 0.5), fontsize=8)
    fig.suptitle("square, in-distribution resets (eval/square_init_configs_reset100.npz)")
    out = record_dir / "curves.png"
    fig.tight_layout(rect=(0, 0, 0.78, 1))
    fig.savefig(out, dpi=110)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    over = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--demos", default="square_demos")
    ap.add_argument("--dataset", default=None, help="train on this UMI replay buffer (e.g. demos + augmented "
                    "episodes) instead of the demo folder's own")
    ap.add_argument("--name", default=None)
    ap.add_argument("--every", type=int, default=3000)
    ap.add_argument("--max-steps", type=int, default=30000)
    ap.add_argument("--budget-min", type=float, default=1e9)
    ap.add_argument("--eval-configs", default="0:50")
    ap.add_argument("--configs-file", default="eval/square_init_configs_reset100.npz")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="square_curve")
    ap.add_argument("--record", default="docs/square_curve")
    ap.add_argument("--report", action="store_true", help="only write <record>/curves.png")
    args = ap.parse_args(own)
    if args.report:
        print(report(Path(args.record)))
        return 0
    if not args.name or args.every < 1 or args.max_steps < args.every:
        ap.error("--name is required and 1 <= --every <= --max-steps")
    from umi_aug.errors import UmiAugError
    from umi_aug.io_utils import RunLockedError

    try:
        curve(args, over)
    except (UmiAugError, RunLockedError) as exc:  # a bad demo folder, another recipe, a second run: before training
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report(Path(args.record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
