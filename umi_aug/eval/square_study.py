"""The square study (issue #15, paper §4.1–4.3, Fig. 3b): data generation → training → evaluation → report.

One recipe (``configs/square_study/<name>.yaml``, overridable ``key=value``) fixes everything: the source demos,
data sizes, variants (:data:`umi_aug.augment.square_variants.VARIANTS`), augmentation (N per demo, cone θ / r),
the training recipe (identical for every variant) and the evaluation subset. Work is split into steps, each
skipped when its output is complete, so the study is resumable and can be run in time slices
(``budget_min``: no new step starts after that many minutes; a running training or evaluation resumes from its own
checkpoint / results file next time):

1. ``export`` — ONE augmented export of the largest data size's demos (:func:`umi_aug.augment.export` with
   :class:`~umi_aug.augment.square_source.SquareSource`; scene model, Panda-feasible trajectories), plus one per
   extra cone angle of the sweep (its data size only);
2. ``variant/<v>_n<n>`` — the training datasets (:func:`~umi_aug.augment.square_variants.write_variant`);
3. ``train/<cell>`` — ``train/train.py`` on each dataset (subprocess; resumes from ``latest.ckpt``);
4. ``eval/<cell>`` — ``eval/eval_sim.py`` on the fixed configuration subset (subprocess; resumes); steps 3 and 4
   run cell by cell (:func:`study_cells` order), so a time slice leaves whole cells behind;
5. ``report`` — ``<report_md>`` (tables, commands, wall times) and ``<report_png>`` (success vs data size per
   variant with Wilson 95 % intervals; the cone-angle sweep; sub-goals), plus the rendering fidelity of ``ours``
   vs ``gt_render`` at the augmented poses (PSNR / SSIM, median and 5th percentile).

Wall time of every step is recorded in ``<out_dir>/study_state.json``.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.errors import UmiAugError
from umi_aug.io_utils import atomic_write_text

__all__ = ["StudyConfig", "load_recipe", "study_cells", "run_study", "StudyError"]

log = logging.getLogger(__name__)


class StudyError(UmiAugError):
    """A study recipe or step failed (names the step)."""


@dataclass
class StudyConfig:
    """A study recipe (see ``configs/square_study/cpu.yaml`` for every field's meaning)."""

    name: str = "square_study"
    out_dir: str = "square_study"
    demos_dir: str = "square_demos"
    image_size: int = 84
    sizes: list[int] = field(default_factory=lambda: [10, 25])
    variants: list[str] = field(default_factory=lambda: ["none", "ours", "gt_render", "action_only", "spartn"])
    n_per_demo: int = 20
    theta_deg: float = 50.0
    radius_m: float = 0.15
    sweep_thetas: list[float] = field(default_factory=lambda: [20.0, 30.0, 40.0, 50.0, 60.0])
    sweep_size: int = 10
    seed: int = 0
    augment_workers: int = 2
    scene: dict[str, Any] = field(default_factory=dict)
    spartn: dict[str, Any] = field(default_factory=dict)
    train_overrides: list[str] = field(default_factory=list)
    eval_overrides: list[str] = field(default_factory=list)
    eval_configs_file: str = "eval/square_init_configs_1000.npz"
    eval_configs: str = "0:1000:5"
    eval_workers: int = 2
    budget_min: float = 0.0
    report_md: str = "docs/square_study.md"
    report_png: str = "docs/square_study.png"
    python: str = sys.executable

    @property
    def out(self) -> Path:
        return Path(self.out_dir)


def load_recipe(path: str | os.PathLike, overrides: list[str] = ()) -> StudyConfig:
    """Recipe YAML + ``key=value`` overrides (OmegaConf dotlist) → :class:`StudyConfig` (typed, unknown keys
    rejected with one error naming them)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        base = OmegaConf.structured(StudyConfig)
        cfg = OmegaConf.merge(base, OmegaConf.load(path), OmegaConf.from_dotlist(list(overrides)))
        out = OmegaConf.to_object(cfg)
    except (OSError, OmegaConfBaseException) as exc:
        raise StudyError(f"square study recipe {path} (overrides {list(overrides)}): {exc}") from None
    from umi_aug.augment.square_variants import VARIANTS

    bad = [v for v in out.variants if v not in VARIANTS]
    if bad:
        raise StudyError(f"{path}: variants {bad} unknown; expected a subset of {list(VARIANTS)}")
    if not out.sizes or min(out.sizes) < 1:
        raise StudyError(f"{path}: sizes = {out.sizes}; expected data sizes >= 1")
    return out


def cell_name(variant: str, n: int, theta: float | None = None) -> str:
    """``<variant>_n<n>`` (main cone) or ``<variant>_n<n>_theta<θ>`` (sweep)."""
    return f"{variant}_n{n}" + ("" if theta is None else f"_theta{theta:g}")


def study_cells(cfg: StudyConfig) -> list[dict[str, Any]]:
    """Every (variant, size[, θ]) the recipe trains and evaluates, in the order they run: the main grid variant by
    variant in the recipe's order (each over every data size, so the first variants' curves complete first), then
    the sweep."""
    cells = [{"variant": v, "n": int(n), "theta": None, "name": cell_name(v, n)} for v in cfg.variants
             for n in cfg.sizes]
    for th in cfg.sweep_thetas:
        if float(th) != float(cfg.theta_deg) and "ours" in cfg.variants:
            cells.append({"variant": "ours", "n": int(cfg.sweep_size), "theta": float(th),
                          "name": cell_name("ours", cfg.sweep_size, th)})
    return cells


# ------------------------------------------------------------------------------------------------- state
class _State:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = json.loads(path.read_text()) if path.exists() else {"steps": {}}

    def done(self, step: str) -> bool:
        return bool(self.data["steps"].get(step, {}).get("done"))

    def record(self, step: str, seconds: float, done: bool, **info) -> None:
        row = self.data["steps"].setdefault(step, {"seconds": 0.0})
        row["seconds"] = float(row.get("seconds", 0.0)) + float(seconds)
        row.update(done=bool(done), finished_unix=time.time(), **info)
        atomic_write_text(self.path, json.dumps(self.data, indent=1) + "\n")


def _augment_config(cfg: StudyConfig, theta: float):
    from umi_aug.augment.config import AugmentConfig

    return AugmentConfig(mode="freespace", n_per_demo=cfg.n_per_demo, seed=cfg.seed, cone_half_angle_deg=theta,
                         cone_radius_m=cfg.radius_m, image_size=cfg.image_size, workers=cfg.augment_workers,
                         include_original=True)


def export_path(cfg: StudyConfig, theta: float | None = None) -> Path:
    return cfg.out / "data" / ("ours_export.zarr.zip" if theta is None else f"ours_export_theta{theta:g}.zarr.zip")


def variant_path(cfg: StudyConfig, cell: dict[str, Any]) -> Path:
    return cfg.out / "data" / f"{cell['name']}.zarr.zip"


def _step_export(cfg: StudyConfig, theta: float | None) -> dict[str, Any]:
    from umi_aug.augment import export
    from umi_aug.augment.square_source import SquareInput, SquareSource

    n = max(cfg.sizes) if theta is None else int(cfg.sweep_size)
    src = SquareSource(Path(cfg.demos_dir), SquareInput(episodes=tuple(range(n)), scene=dict(cfg.scene)))
    out = export_path(cfg, theta)
    s = export(cfg.demos_dir, out, _augment_config(cfg, cfg.theta_deg if theta is None else theta),
               work_dir=cfg.out / "work", source=src, pictures=True)
    return {"n_augmented": int(s.n_augmented), "n_failed": int(s.n_failed), "n_resampled": int(s.n_resampled),
            "summary": str(out) + ".summary.json"}


def _step_variant(cfg: StudyConfig, cell: dict[str, Any]) -> dict[str, Any]:
    from umi_aug.augment.square_source import SquareInput, gt_render_function, prepare_square, spartn_render_function
    from umi_aug.augment.square_variants import SpartnConfig, write_variant

    from umi_aug.augment.square_variants import subset_variant

    v, n = cell["variant"], cell["n"]
    big = {**cell, "n": max(cfg.sizes), "name": cell_name(v, max(cfg.sizes))}
    if cell["theta"] is None and n < big["n"] and variant_path(cfg, big).exists():
        return subset_variant(variant_path(cfg, big), variant_path(cfg, cell), n)  # same episodes, not re-rendered
    ours = export_path(cfg, cell["theta"])
    render_new, close = None, None
    if v in ("gt_render", "spartn"):
        assets = prepare_square(cfg.demos_dir, cfg.out / "work", _augment_config(cfg, cfg.theta_deg),
                                SquareInput(episodes=tuple(range(max(cfg.sizes))), scene=dict(cfg.scene)))
        render_new = gt_render_function(assets) if v == "gt_render" else spartn_render_function(assets)
        close = getattr(render_new, "close", None)
    try:
        return write_variant(v, ours, variant_path(cfg, cell), n, render_new=render_new,
                             spartn=SpartnConfig(**{"seed": cfg.seed, **cfg.spartn}))
    finally:
        if close is not None:
            close()


def train_command(cfg: StudyConfig, cell: dict[str, Any]) -> list[str]:
    """The ``train/train.py`` command of a cell (same recipe for every variant; resumes)."""
    return [cfg.python, "train/train.py", "task=square", f"task.dataset_path={variant_path(cfg, cell)}",
            f"task.image_size={cfg.image_size}", f"hydra.run.dir={cfg.out / 'runs' / cell['name']}",
            *cfg.train_overrides]


def checkpoint_path(cfg: StudyConfig, cell: dict[str, Any]) -> Path:
    return cfg.out / "runs" / cell["name"] / "checkpoints" / "latest.ckpt"


def eval_dir(cfg: StudyConfig, cell: dict[str, Any]) -> Path:
    return cfg.out / "evals" / cell["name"]


def eval_command(cfg: StudyConfig, cell: dict[str, Any]) -> list[str]:
    """The ``eval/eval_sim.py`` command of a cell (fixed configuration subset; resumes)."""
    return [cfg.python, "eval/eval_sim.py", f"checkpoint={checkpoint_path(cfg, cell)}",
            f"configs_file={cfg.eval_configs_file}", f"configs='{cfg.eval_configs}'" if "," in cfg.eval_configs
            else f"configs={cfg.eval_configs}", f"workers={cfg.eval_workers}", f"out_dir={eval_dir(cfg, cell)}",
            *cfg.eval_overrides]


def _run(cmd: list[str], log_path: Path) -> int:
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        return subprocess.call(cmd, stdout=fh, stderr=subprocess.STDOUT)


def run_study(cfg: StudyConfig, phases: tuple[str, ...] = ("data", "train", "eval", "report")) -> dict[str, Any]:
    """Run (or resume) the study's steps in order; returns the state dict."""
    from tqdm import tqdm

    cfg.out.mkdir(parents=True, exist_ok=True)
    state = _State(cfg.out / "study_state.json")
    t_start = time.perf_counter()
    cells = study_cells(cfg)

    def over_budget() -> bool:
        return cfg.budget_min > 0 and (time.perf_counter() - t_start) / 60.0 > cfg.budget_min

    def step(name: str, fn) -> bool:
        if state.done(name):
            return True
        if over_budget():
            log.warning("square study: budget of %.0f min used; stopping before %s (rerun to continue)",
                        cfg.budget_min, name)
            return False
        t0 = time.perf_counter()
        try:
            info = fn() or {}
            ok = bool(info.pop("_done", True))
        except UmiAugError as exc:
            state.record(name, time.perf_counter() - t0, False, error=str(exc))
            raise StudyError(f"square study step {name}: {exc}") from exc
        state.record(name, time.perf_counter() - t0, ok, **{k: v for k, v in info.items()
                                                            if isinstance(v, (int, float, str, bool))})
        return ok

    steps: list[tuple[str, Any]] = []
    if "data" in phases:
        steps.append(("export", lambda: _step_export(cfg, None)))
        for th in sorted({c["theta"] for c in cells if c["theta"] is not None}):
            steps.append((f"export_theta{th:g}", lambda th=th: _step_export(cfg, th)))
        for c in sorted(cells, key=lambda c: -c["n"]):  # largest first: smaller sizes are cut from it
            steps.append((f"variant/{c['name']}", lambda c=c: _step_variant(cfg, c)))
    # cell by cell (train, then evaluate it) so every time slice leaves finished cells for the report
    for c in cells:
        if "train" in phases:
            steps.append((f"train/{c['name']}", lambda c=c: _step_train(cfg, c)))
        if "eval" in phases:
            steps.append((f"eval/{c['name']}", lambda c=c: _step_eval(cfg, c)))
    for name, fn in tqdm(steps, desc="square study", unit="step"):
        if not step(name, fn) and over_budget():
            break
    if "report" in phases:
        from umi_aug.eval.square_report import write_report

        write_report(cfg, cells, state.data)
    return state.data


def _step_train(cfg: StudyConfig, cell: dict[str, Any]) -> dict[str, Any]:
    rc = _run(train_command(cfg, cell), cfg.out / "runs" / f"{cell['name']}.log")
    if rc != 0:
        raise StudyError(f"train {cell['name']}: exit status {rc}; see {cfg.out / 'runs' / (cell['name'] + '.log')}")
    if not checkpoint_path(cfg, cell).exists():
        raise StudyError(f"train {cell['name']}: no checkpoint at {checkpoint_path(cfg, cell)}")
    return {"checkpoint": str(checkpoint_path(cfg, cell))}


def expected_rollouts(cfg: StudyConfig) -> int:
    """Number of configurations in ``eval_configs`` (``a:b[:s]`` or a comma list)."""
    spec = str(cfg.eval_configs)
    if ":" in spec:
        parts = [int(p) for p in spec.split(":")]
        return len(range(*parts))
    return len([p for p in spec.split(",") if p.strip()])


def _step_eval(cfg: StudyConfig, cell: dict[str, Any]) -> dict[str, Any]:
    rc = _run(eval_command(cfg, cell), eval_dir(cfg, cell) / "study_eval.log")
    if rc != 0:
        raise StudyError(f"eval {cell['name']}: exit status {rc}; see {eval_dir(cfg, cell) / 'study_eval.log'}")
    summ = json.loads((eval_dir(cfg, cell) / "summary.json").read_text())
    return {"n": int(summ["n"]), "success_rate": float(summ["success_rate"]),
            "_done": int(summ["n"]) >= expected_rollouts(cfg)}


def fidelity(ours: Path, gt: Path, max_frames: int = 2000, seed: int = 0) -> dict[str, Any]:
    """PSNR / SSIM of ``ours`` vs ``gt_render`` on the new frames of the augmented episodes they share (inside the
    fisheye image circle): median and 5th percentile."""
    from umi_aug.augment.exporter import read_episode_records
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
        import torch

        from umi_aug.camera.kb import unproject
        from umi_aug.sim.square.camera import wrist_intrinsics
        from umi_aug.splat.losses import masked_psnr, masked_ssim

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
    return {"frames": int(len(p)), "psnr_median": float(np.median(p)) if len(p) else None,
            "psnr_p5": float(np.percentile(p, 5)) if len(p) else None,
            "ssim_median": float(np.median(s)) if len(s) else None,
            "ssim_p5": float(np.percentile(s, 5)) if len(s) else None}
