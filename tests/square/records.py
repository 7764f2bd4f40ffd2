"""Helpers of the study tests that write a small study record by hand: a recipe whose record lives in a temporary
folder, and a cell's ``results.jsonl`` with given success outcomes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from umi_aug.square import study as st

ROOT = Path(__file__).resolve().parents[2]


def cpu_recipe(tmp_path: Path, *over: str) -> st.StudyConfig:
    """``configs/square_study/cpu.yaml`` with its output, record and report under ``tmp_path`` (``over``: more
    ``key=value`` overrides)."""
    return st.load_recipe(ROOT / "configs" / "square_study" / "cpu.yaml",
                          [f"out_dir={tmp_path / 'out'}", "record_dir=''", f"report_md={tmp_path / 'r.md'}",
                           f"report_png={tmp_path / 'r.png'}", *over])


def write_success_record(cfg: st.StudyConfig, name: str, success: np.ndarray, configs=None) -> None:
    """Write the recorded evaluation of cell ``name``: one row per configuration (``configs``, default 0..n-1) with
    its ``success``."""
    d = st.record_eval_dir(cfg, {"name": name})
    d.mkdir(parents=True)
    configs = range(len(success)) if configs is None else configs
    (d / "results.jsonl").write_text("".join(json.dumps({"config": int(c), "success": bool(s)}) + "\n"
                                             for c, s in zip(configs, success)))


def committed_recipe_and_page_section(recipe: str) -> tuple[st.StudyConfig, list[str]]:
    """Recipe ``recipe`` reading its committed record (``docs/square_study_<recipe>``), and the lines of its section
    ``## Recipe `<recipe>` ...`` in the hand-written ``docs/square_study.md`` (minus signs read as ``-``)."""
    cfg = st.load_recipe(ROOT / "configs" / "square_study" / f"{recipe}.yaml",
                         [f"record_dir={ROOT / 'docs' / f'square_study_{recipe}'}"])
    page = (ROOT / "docs" / "square_study.md").read_text().replace("−", "-").splitlines()
    start = next(i for i, line in enumerate(page) if line.startswith(f"## Recipe `{recipe}`"))
    end = next((i for i in range(start + 1, len(page)) if page[i].startswith("## ")), len(page))
    return cfg, page[start:end]
