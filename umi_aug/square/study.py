"""The square study (issue #15, paper §4.1–4.3, Fig. 3b): data generation → training → evaluation → report.

One recipe (``configs/square_study/<name>.yaml``, overridable ``key=value``) fixes everything: the source demos,
data sizes, variants (:data:`umi_aug.square.variants.VARIANTS`), augmentation (N per demo, cone θ / r),
the training recipe (identical for every variant) and the evaluation subset. Work is split into steps, each
skipped when its output is complete, so the study is resumable and can be run in time slices
(``budget_min``: no new step starts after that many minutes, and no cell starts training when the cells recorded so
far took longer than what is left; a running training or evaluation resumes from its own checkpoint / results file
next time).

The study outlives the machine it runs on: ``record_dir`` (committed; ``docs/square_study_cpu`` for the CPU recipe)
holds what the report is made of — ``study_state.json`` (every step's wall time and summary), each finished cell's
``evals/<cell>/results.jsonl`` + ``summary.json``, the exports' summaries and the rendering fidelity — while
``out_dir`` holds what can be made again (demos, datasets, checkpoints, videos). A cell whose evaluation is in the
record is finished for good; the data a remaining cell needs is (re)made only when that cell is next, so a fresh
machine continues the study where the record stops. Steps, in the order they run, for each cell not yet recorded
(:func:`study_cells` order):

0. ``demos`` — the source demos (:func:`umi_aug.square.generate.generate_demos`, resumable) when ``demos_dir``
   does not hold enough of them at the recipe's image size;
1. ``export`` — ONE augmented export of the largest data size's demos (:func:`umi_aug.augment.export` with
   :class:`~umi_aug.square.source.SquareSource`; scene model, Panda-feasible trajectories), plus one per
   extra cone angle of the sweep (its data size only);
2. ``variant/<v>_n<n>`` — the training datasets (:func:`~umi_aug.square.variants.write_variant`);
3. ``train/<cell>`` — ``train/train.py`` on each dataset (subprocess; resumes from ``latest.ckpt``);
4. ``eval/<cell>`` — ``eval/eval_sim.py`` on the fixed configuration subset (subprocess; resumes); its results go
   into the record when all configurations are done;
4b. ``eval_handover/<cell>`` (when ``eval_handover``) — the same evaluation as "learned approach + scripted grasp"
   (issue #29 part 4, metric c: ``eval_sim.py handover=expert``: the scripted expert takes over once the policy
   reaches the pre-grasp pose or after ``handover_step_limit`` steps) on ``handover_configs``, recorded alike
   under ``evals_handover/<cell>``;
5. the report (:func:`umi_aug.square.report.report_study`) — ``<report_md>`` (tables, commands, wall times) and ``<report_png>`` (success vs data size per
   variant with Wilson 95 % intervals; the cone-angle sweep; sub-goals), plus the rendering fidelity of ``ours``
   vs ``gt_render`` at the augmented poses (PSNR / SSIM, median and 5th percentile).

Wall time of every step is recorded in ``study_state.json`` (a step made again on a new machine because its
output was gone starts its time over and counts ``reruns``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
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
from tqdm import tqdm

from umi_aug.config_keys import check_known_keys, check_override_keys
from umi_aug.errors import EvalError, PolicyError, UmiAugError
from umi_aug.eval.config import EvalSimConfig
from umi_aug.io_utils import RunLockedError, atomic_write_text, exclusive_run_lock
from umi_aug.square.generate import DemoConfig, generate_demos

__all__ = ["StudyConfig", "load_recipe", "study_cells", "run_study", "load_state", "StudyError", "record_eval_dir",
           "record_export_summary", "cell_minutes_estimate", "cell_finished", "handover_configs"]

log = logging.getLogger(__name__)


#: Lock file (in ``out_dir`` and in ``record_dir``) held by a running study (:func:`run_study`).
STUDY_LOCK = ".study.lock"


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
    eval_handover: bool = False
    handover_configs: str = ""
    budget_min: float = 0.0
    record_dir: str = ""
    report_md: str = ""  # "": docs/square_study_<name>.md
    report_png: str = ""  # "": docs/square_study_<name>.png
    python: str = sys.executable

    def __post_init__(self) -> None:
        # docs/square_study.md is the hand-written overview of every recipe's report: no recipe writes over it
        self.report_md = self.report_md or f"docs/square_study_{self.name}.md"
        self.report_png = self.report_png or f"docs/square_study_{self.name}.png"

    @property
    def out(self) -> Path:
        return Path(self.out_dir)

    @property
    def record(self) -> Path:
        """Where the study's results are kept (``record_dir``, or ``out_dir`` when it is not set)."""
        return Path(self.record_dir) if self.record_dir else self.out


#: Where the shipped configs live (``configs/square_study/<recipe>.yaml``, ``configs/train.yaml``).
CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
#: Ranges of the recipe's numbers: field → (check, what the message says it must be).
RECIPE_RANGES: dict[str, tuple[Any, str]] = {
    "image_size": (lambda v: v >= 8, "must be >= 8 pixels"),
    "n_per_demo": (lambda v: v >= 1, "must be >= 1"),
    "theta_deg": (lambda v: 0.0 < v <= 180.0, "must be in (0, 180] degrees"),
    "radius_m": (lambda v: 0.0 < v < 10.0, "must be in (0, 10) metres"),
    "sweep_thetas": (lambda v: all(0.0 < float(t) <= 180.0 for t in v), "every angle must be in (0, 180] degrees"),
    "sweep_size": (lambda v: v >= 1, "must be >= 1"),
    "augment_workers": (lambda v: v >= 1, "must be >= 1"),
    "eval_workers": (lambda v: v >= 1, "must be >= 1"),
    "budget_min": (lambda v: v >= 0.0 and np.isfinite(v), "must be >= 0 minutes (0: no budget)"),
}


def _one_line(exc: Exception) -> str:
    """An OmegaConf error in one line: ``<key>: <its first line>``."""
    key = getattr(exc, "full_key", None)
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"{key}: {first}" if key else first


def load_recipe(path: str | os.PathLike, overrides: list[str] = ()) -> StudyConfig:
    """Recipe YAML + ``key=value`` overrides (OmegaConf dotlist; ``+key=value`` alike) → :class:`StudyConfig`,
    every key checked before any work (issue #32): unknown keys of the overrides, of the recipe file, of ``scene``
    (:class:`~umi_aug.square.scene.SquareSceneConfig`) and ``spartn``
    (:class:`~umi_aug.square.variants.SpartnConfig`), the ranges of :data:`RECIPE_RANGES`, and the keys and
    values of ``train_overrides`` / ``eval_overrides`` as ``train/train.py`` / ``eval/eval_sim.py`` would check
    them (those run hours later, after the data steps). One :class:`StudyError` line naming the key."""
    # lazy, optional dependency: omegaconf
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    overrides = list(overrides)
    listing = f"`python eval/square_study.py recipe={path} --cfg` prints every key"
    check_override_keys(overrides, StudyConfig, "eval/square_study.py", StudyError, hint=listing)
    try:
        raw = OmegaConf.load(path)
    except (OSError, OmegaConfBaseException) as exc:
        raise StudyError(f"square study recipe {path}: cannot be read ({_one_line(exc)})") from None
    check_known_keys(raw, StudyConfig, "eval/square_study.py", StudyError, hint=listing, where=f"{path}: ")
    try:
        base = OmegaConf.structured(StudyConfig)
        dotlist = [o[1:] if o.startswith("+") and not o.startswith("++") else o.lstrip("+") for o in overrides]
        cfg = OmegaConf.merge(base, raw, OmegaConf.from_dotlist(dotlist))
        out = OmegaConf.to_object(cfg)
    except (OSError, OmegaConfBaseException) as exc:
        raise StudyError(f"square study recipe {path} (overrides {overrides}): {_one_line(exc)}") from None
    from umi_aug.square.variants import VARIANTS  # lazy, start-up: cv2, scipy, zarr

    bad = [v for v in out.variants if v not in VARIANTS]
    if bad:
        raise StudyError(f"{path}: variants {bad} unknown; expected a subset of {list(VARIANTS)}")
    if not out.sizes or min(out.sizes) < 1:
        raise StudyError(f"{path}: sizes = {out.sizes}; expected data sizes >= 1")
    for key, (ok, want) in RECIPE_RANGES.items():
        if not ok(getattr(out, key)):
            raise StudyError(f"{path}: {key} = {getattr(out, key)}: {want}")
    _check_nested_keys(path, out)
    _check_train_overrides(path, out)
    _check_eval_overrides(path, out)
    return out


def _check_nested_keys(path, cfg: StudyConfig) -> None:
    """``scene`` / ``spartn``: dicts of another config's fields (a typo was dropped or failed mid-study)."""
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.square.scene import SquareSceneConfig
    from umi_aug.square.variants import SpartnConfig

    for key, schema in (("scene", SquareSceneConfig), ("spartn", SpartnConfig)):
        fields = [f.name for f in dataclasses.fields(schema)]
        for k in getattr(cfg, key):
            if k not in fields:
                near = difflib.get_close_matches(str(k), fields, n=1)
                mean = f"did you mean {key}.{near[0]}? " if near else ""
                raise StudyError(f"{path}: config key '{key}.{k}' does not exist; {mean}{key} holds fields of "
                                 f"{schema.__name__}: {', '.join(fields)}")


def _train_overrides(cfg: StudyConfig) -> list[str]:
    """The Hydra overrides :func:`train_command` passes to ``train/train.py``, but the run folder and a stand-in
    dataset path (the variants are written later)."""
    return ["task=square", "task.dataset_path=variant.zarr.zip", f"task.image_size={cfg.image_size}",
            *cfg.train_overrides]


def _check_train_overrides(path, cfg: StudyConfig) -> None:
    """``train_overrides``: the keys (``train/train.py``'s own check) and, composed as train.py composes them, the
    values (:func:`umi_aug.policy.train_checks.check_train_values`)."""
    from umi_aug.policy.config import TrainConfig  # lazy, start-up: zarr

    try:
        check_override_keys(cfg.train_overrides, TrainConfig, "train/train.py", PolicyError)
    except PolicyError as exc:
        raise StudyError(f"{path}: train_overrides: {exc}") from None
    try:
        from hydra import compose, initialize_config_dir
        from hydra.core.config_store import ConfigStore
        from hydra.core.global_hydra import GlobalHydra
    except ImportError:  # pragma: no cover - hydra is a dependency of training; without it train.py cannot run
        return
    from omegaconf.errors import OmegaConfBaseException  # lazy, optional dependency: omegaconf

    # lazy, start-up: zarr
    from umi_aug.policy.config import structured_config
    from umi_aug.policy.train_checks import check_train_values

    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
    if GlobalHydra.instance().is_initialized():  # pragma: no cover - a Hydra app calling this
        return
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            composed = compose("train", overrides=_train_overrides(cfg))
        check_known_keys(composed, TrainConfig, "train/train.py", PolicyError)
        check_train_values(structured_config(composed))
    except PolicyError as exc:
        raise StudyError(f"{path}: train_overrides: {exc}") from None
    except (OmegaConfBaseException, ValueError) as exc:  # hydra's own override / composition errors
        raise StudyError(f"{path}: train_overrides {cfg.train_overrides}: {_one_line(exc)}") from None


def _check_eval_overrides(path, cfg: StudyConfig) -> None:
    """``eval_overrides``: the keys ``eval/eval_sim.py`` checks (``policy=NAME`` is its policy group)."""
    argv = ["eval_policy=" + a[len("policy="):] if a.startswith("policy=") else a for a in cfg.eval_overrides]
    try:
        check_override_keys(argv, EvalSimConfig, "eval/eval_sim.py", EvalError, groups=("eval_policy",))
    except EvalError as exc:
        raise StudyError(f"{path}: eval_overrides: {exc}") from None


def handover_configs(cfg: StudyConfig) -> str:
    """The configurations of the handover evaluation (``handover_configs``, or ``eval_configs`` when empty)."""
    return str(cfg.handover_configs) if str(cfg.handover_configs).strip() else str(cfg.eval_configs)


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

    def record(self, step: str, seconds: float, done: bool, resumed: bool = True, **info) -> None:
        """Add ``seconds`` to the step's time when it ``resumed`` its own partial output; otherwise its time starts
        over (``reruns`` + 1 when it had been run before, e.g. its output was gone on a new machine)."""
        row = self.data["steps"].setdefault(step, {"seconds": 0.0})
        if not resumed and "finished_unix" in row:
            row["seconds"] = 0.0
            row["reruns"] = int(row.get("reruns", 0)) + 1
            row.pop("error", None)
        row["seconds"] = float(row.get("seconds", 0.0)) + float(seconds)
        if done:  # an earlier attempt's error no longer describes the step
            row.pop("error", None)
        row.update(done=bool(done), finished_unix=time.time(), **info)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps(self.data, indent=1) + "\n")


def _augment_config(cfg: StudyConfig, theta: float):
    from umi_aug.augment.config import AugmentConfig  # lazy, start-up: cv2, scipy

    return AugmentConfig(mode="freespace", n_per_demo=cfg.n_per_demo, seed=cfg.seed, cone_half_angle_deg=theta,
                         cone_radius_m=cfg.radius_m, image_size=cfg.image_size, workers=cfg.augment_workers,
                         include_original=True,
                         # the study's first exports were encoded at libjxl's default effort: keep every cell alike
                         jpegxl_effort=None)


def export_path(cfg: StudyConfig, theta: float | None = None) -> Path:
    return cfg.out / "data" / ("ours_export.zarr.zip" if theta is None else f"ours_export_theta{theta:g}.zarr.zip")


def variant_path(cfg: StudyConfig, cell: dict[str, Any]) -> Path:
    return cfg.out / "data" / f"{cell['name']}.zarr.zip"


def _step_export(cfg: StudyConfig, theta: float | None) -> dict[str, Any]:
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment import export
    from umi_aug.square.source import SquareInput, SquareSource

    n = max(cfg.sizes) if theta is None else int(cfg.sweep_size)
    src = SquareSource(Path(cfg.demos_dir), SquareInput(episodes=tuple(range(n)), scene=dict(cfg.scene)))
    out = export_path(cfg, theta)
    s = export(cfg.demos_dir, out, _augment_config(cfg, cfg.theta_deg if theta is None else theta),
               work_dir=cfg.out / "work", source=src, pictures=True)
    _keep(Path(str(out) + ".summary.json"), record_export_summary(cfg, theta))
    return {"n_augmented": int(s.n_augmented), "n_failed": int(s.n_failed), "n_resampled": int(s.n_resampled),
            "summary": str(out) + ".summary.json"}


def record_export_summary(cfg: StudyConfig, theta: float | None = None) -> Path:
    """The record's copy of an export's ``.summary.json``."""
    return cfg.record / "exports" / (export_path(cfg, theta).name + ".summary.json")


def _keep(src: Path, dst: Path) -> None:
    """Copy ``src`` into the record at ``dst`` (atomically; nothing when they are the same file)."""
    if Path(src).resolve() != Path(dst).resolve():
        dst.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(dst, Path(src).read_text())


def _step_variant(cfg: StudyConfig, cell: dict[str, Any]) -> dict[str, Any]:
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.square.source import SquareInput, gt_render_function, prepare_square, spartn_render_function
    from umi_aug.square.variants import SpartnConfig, write_variant

    from umi_aug.square.variants import subset_variant  # lazy, start-up: cv2, scipy, zarr

    v, n = cell["variant"], cell["n"]
    big = {**cell, "n": max(cfg.sizes), "name": cell_name(v, max(cfg.sizes))}
    if cell["theta"] is None and n < big["n"] and variant_path(cfg, big).exists():
        return subset_variant(variant_path(cfg, big), variant_path(cfg, cell), n)  # same episodes, not re-rendered
    ours = export_path(cfg, cell["theta"])
    render_new, close = None, None
    if v in ("gt_render", "spartn", "ours_spartn", "ours_rerender"):
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


def eval_dir(cfg: StudyConfig, cell: dict[str, Any], handover: bool = False) -> Path:
    """A cell's evaluation folder (``evals/``; ``evals_handover/`` for the handover evaluation)."""
    return cfg.out / ("evals_handover" if handover else "evals") / cell["name"]


def eval_command(cfg: StudyConfig, cell: dict[str, Any], handover: bool = False) -> list[str]:
    """The ``eval/eval_sim.py`` command of a cell (fixed configuration subset; resumes); with ``handover`` the
    learned-approach + scripted-grasp evaluation (``handover=expert`` on :func:`handover_configs`)."""
    spec = handover_configs(cfg) if handover else str(cfg.eval_configs)
    return [cfg.python, "eval/eval_sim.py", f"checkpoint={checkpoint_path(cfg, cell)}",
            f"configs_file={cfg.eval_configs_file}", f"configs='{spec}'" if "," in spec else f"configs={spec}",
            f"workers={cfg.eval_workers}", f"out_dir={eval_dir(cfg, cell, handover)}", *cfg.eval_overrides,
            *(["handover=expert"] if handover else [])]


def _run(cmd: list[str], log_path: Path) -> int:
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        return subprocess.call(cmd, stdout=fh, stderr=subprocess.STDOUT)


def record_eval_dir(cfg: StudyConfig, cell: dict[str, Any], handover: bool = False) -> Path:
    """Where a finished cell's ``results.jsonl`` / ``summary.json`` are kept (the record; ``evals_handover/`` for
    the handover evaluation)."""
    return cfg.record / ("evals_handover" if handover else "evals") / cell["name"]


def _recorded_rollouts(cfg: StudyConfig, cell: dict[str, Any], handover: bool = False) -> int:
    p = record_eval_dir(cfg, cell, handover) / "summary.json"
    if not p.exists():
        return 0
    try:
        return int(json.loads(p.read_text())["n"])
    except (ValueError, KeyError, TypeError) as exc:
        raise StudyError(f"{p}: unreadable evaluation summary ({exc}); delete it to evaluate the cell again") from None


def demos_ready(cfg: StudyConfig) -> bool:
    """``demos_dir`` holds at least ``max(sizes)`` demos at the recipe's image size."""
    p = Path(cfg.demos_dir) / "report.json"
    if not p.exists():
        return False
    try:
        rep = json.loads(p.read_text())
    except ValueError as exc:
        raise StudyError(f"{p}: unreadable square-demos report ({exc}); rerun umi-aug square-demos there") from None
    return (int(rep.get("successes", 0)) >= max(cfg.sizes)
            and int(rep.get("config", {}).get("image_size", cfg.image_size)) == int(cfg.image_size))


def _step_demos(cfg: StudyConfig) -> dict[str, Any]:
    rep = generate_demos(cfg.demos_dir, DemoConfig(n=max(cfg.sizes), image_size=cfg.image_size,
                                                   workers=cfg.augment_workers))
    return {"successes": int(rep["successes"]), "tried": int(rep["tried"])}


def _cell_steps(cfg: StudyConfig, cell: dict[str, Any], phases: tuple[str, ...]) -> list[tuple[str, Any, Any]]:
    """``(step, run, output_exists)`` of one cell, dependencies first: demos, its export, the largest data size's
    dataset it is cut from, its dataset, training, evaluation."""
    out: list[tuple[str, Any, Any]] = []
    if "data" in phases:
        th = cell["theta"]
        out.append(("demos", lambda: _step_demos(cfg), lambda: demos_ready(cfg)))
        out.append(("export" if th is None else f"export_theta{th:g}", lambda: _step_export(cfg, th),
                    lambda: export_path(cfg, th).exists()))
        big = {**cell, "n": max(cfg.sizes), "name": cell_name(cell["variant"], max(cfg.sizes))}
        for c in ([big] if th is None and cell["n"] < big["n"] else []) + [cell]:
            out.append((f"variant/{c['name']}", lambda c=c: _step_variant(cfg, c),
                        lambda c=c: variant_path(cfg, c).exists()))
    if "train" in phases:
        out.append((f"train/{cell['name']}", lambda: _step_train(cfg, cell),
                    lambda: checkpoint_path(cfg, cell).exists()))
    if "eval" in phases:
        out.append((f"eval/{cell['name']}", lambda: _step_eval(cfg, cell),
                    lambda: _recorded_rollouts(cfg, cell) >= expected_rollouts(cfg)))
        if cfg.eval_handover:
            out.append((f"eval_handover/{cell['name']}", lambda: _step_eval(cfg, cell, handover=True),
                        lambda: _recorded_rollouts(cfg, cell, True) >= expected_rollouts(cfg, True)))
    return out


def cell_finished(cfg: StudyConfig, cell: dict[str, Any]) -> bool:
    """Every evaluation of the cell is in the record (then nothing it needed is made again)."""
    return (_recorded_rollouts(cfg, cell) >= expected_rollouts(cfg)
            and (not cfg.eval_handover or _recorded_rollouts(cfg, cell, True) >= expected_rollouts(cfg, True)))


def cell_minutes_estimate(cfg: StudyConfig, state: dict[str, Any]) -> float:
    """Median minutes of train + eval (+ the handover evaluation, when the recipe has it) over the cells finished
    so far (0 when none is): a cell is not started in a time slice that has less than this left, because its
    checkpoint would not outlive the machine."""
    steps = state.get("steps", {})
    kinds = ("train", "eval", "eval_handover") if cfg.eval_handover else ("train", "eval")
    mins = [sum(steps[f"{k}/{c['name']}"]["seconds"] for k in kinds) / 60.0
            for c in study_cells(cfg) if all(steps.get(f"{k}/{c['name']}", {}).get("done") for k in kinds[1:])
            and f"train/{c['name']}" in steps]
    return float(np.median(mins)) if mins else 0.0


def run_study(cfg: StudyConfig, phases: tuple[str, ...] = ("data", "train", "eval")) -> dict[str, Any]:
    """Run (or resume) the study's steps of ``phases`` (data, train, eval) in order; returns the state dict. A cell
    whose evaluations are in the record is skipped in every phase (``phases=data,train`` on a fresh machine does not
    train it again). The report is :func:`umi_aug.square.report.report_study`."""
    # one run at a time per outputs and record: a second run would interleave its steps and overwrite the state
    locks = {(cfg.out / STUDY_LOCK).resolve(): f"square study on {cfg.out}",
             (cfg.record / STUDY_LOCK).resolve(): f"square study recording into {cfg.record}"}  # one if they coincide
    try:
        with contextlib.ExitStack() as stack:
            for path, what in locks.items():
                stack.enter_context(exclusive_run_lock(path, what))
            return _run_study_locked(cfg, phases)
    except RunLockedError as exc:
        raise StudyError(str(exc)) from None


def _run_study_locked(cfg: StudyConfig, phases: tuple[str, ...]) -> dict[str, Any]:
    cfg.out.mkdir(parents=True, exist_ok=True)
    state = _State(cfg.record / "study_state.json")
    t_start = time.perf_counter()
    cells = study_cells(cfg)

    def minutes_left() -> float:
        return cfg.budget_min - (time.perf_counter() - t_start) / 60.0 if cfg.budget_min > 0 else float("inf")

    def step(name: str, fn, exists) -> bool:
        if exists() and (state.done(name) or name == "demos"):
            return True
        if minutes_left() < 0:
            log.warning("square study: budget of %.0f min used; stopping before %s (rerun to continue)",
                        cfg.budget_min, name)
            return False
        need = cell_minutes_estimate(cfg, state.data)
        if name.startswith("train/") and not exists() and need > minutes_left():
            log.warning("square study: %.0f min left, a cell takes %.0f; stopping before %s (rerun to continue)",
                        minutes_left(), need, name)
            return False
        kind = name.split("/")[0]
        partial = {"train": lambda: exists(),
                   "eval": lambda: (eval_dir(cfg, {"name": name.split("/", 1)[1]}) / "results.jsonl").exists(),
                   "eval_handover": lambda: (eval_dir(cfg, {"name": name.split("/", 1)[1]}, True)
                                             / "results.jsonl").exists()}
        resumed = bool(partial.get(kind, lambda: False)())
        t0 = time.perf_counter()
        try:
            info = fn() or {}
            ok = bool(info.pop("_done", True))
        except UmiAugError as exc:
            state.record(name, time.perf_counter() - t0, False, resumed, error=str(exc))
            raise StudyError(f"square study step {name}: {exc}") from exc
        state.record(name, time.perf_counter() - t0, ok, resumed, **{k: v for k, v in info.items()
                                                                     if isinstance(v, (int, float, str, bool))})
        return ok

    # cell by cell (its data, train, then evaluate it) so every time slice leaves finished cells in the record
    steps: list[tuple[str, Any, Any]] = []
    seen: set[str] = set()
    for c in cells:
        if cell_finished(cfg, c):
            continue  # finished for good, whatever the phases: nothing it needed is made or trained again
        for name, fn, exists in _cell_steps(cfg, c, phases):
            if name not in seen:
                seen.add(name)
                steps.append((name, fn, exists))
    for name, fn, exists in tqdm(steps, desc="square study", unit="step"):
        if not step(name, fn, exists) and minutes_left() < cell_minutes_estimate(cfg, state.data):
            break
    return state.data


def load_state(cfg: StudyConfig) -> dict[str, Any]:
    """The study's ``study_state.json`` (from the record; empty when there is none yet)."""
    return _State(cfg.record / "study_state.json").data


def _step_train(cfg: StudyConfig, cell: dict[str, Any]) -> dict[str, Any]:
    for stale in (eval_dir(cfg, cell) / "results.jsonl", eval_dir(cfg, cell, True) / "results.jsonl"):
        if not checkpoint_path(cfg, cell).exists() and stale.exists():
            # rollouts of an earlier checkpoint must not count towards the one trained now: set aside, not deleted
            stale.rename(stale.with_name(f"results.jsonl.before-{time.strftime('%Y%m%d-%H%M%S')}"))
    run_dir = cfg.out / "runs" / cell["name"]
    if not checkpoint_path(cfg, cell).exists() and (run_dir / "logs.jsonl").exists():
        # a training stopped before its first checkpoint (e.g. the session ended): nothing to resume, and train.py
        # refuses to append to its logs, so the folder is set aside (not deleted) and the cell trains from step 0
        run_dir.rename(run_dir.with_name(f"{cell['name']}.before-{time.strftime('%Y%m%d-%H%M%S')}"))
    rc = _run(train_command(cfg, cell), cfg.out / "runs" / f"{cell['name']}.log")
    if rc != 0:
        raise StudyError(f"train {cell['name']}: exit status {rc}; see {cfg.out / 'runs' / (cell['name'] + '.log')}")
    if not checkpoint_path(cfg, cell).exists():
        raise StudyError(f"train {cell['name']}: no checkpoint at {checkpoint_path(cfg, cell)}")
    return {"checkpoint": str(checkpoint_path(cfg, cell))}


def expected_rollouts(cfg: StudyConfig, handover: bool = False) -> int:
    """Number of configurations in ``eval_configs`` (``a:b[:s]`` or a comma list; :func:`handover_configs` for the
    handover evaluation)."""
    spec = handover_configs(cfg) if handover else str(cfg.eval_configs)
    if ":" in spec:
        parts = [int(p) for p in spec.split(":")]
        return len(range(*parts))
    return len([p for p in spec.split(",") if p.strip()])


def _step_eval(cfg: StudyConfig, cell: dict[str, Any], handover: bool = False) -> dict[str, Any]:
    where = eval_dir(cfg, cell, handover)
    rc = _run(eval_command(cfg, cell, handover), where / "study_eval.log")
    what = "eval_handover" if handover else "eval"
    if rc != 0:
        raise StudyError(f"{what} {cell['name']}: exit status {rc}; see {where / 'study_eval.log'}")
    summ = json.loads((where / "summary.json").read_text())
    done = int(summ["n"]) >= expected_rollouts(cfg, handover)
    if done:  # results first, summary last: a summary in the record means its results are there
        for f in ("results.jsonl", "summary.json"):
            _keep(where / f, record_eval_dir(cfg, cell, handover) / f)
    return {"n": int(summ["n"]), "success_rate": float(summ["success_rate"]), "_done": done}
