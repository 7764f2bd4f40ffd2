"""What an export reports: its :class:`ExportSummary` (also ``<out>.summary.json``), the console table, and the
pictures beside the dataset (contact sheet, planned trajectories)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
from rich.table import Table

from umi_aug.augment.pictures import contact_sheet
from umi_aug.augment.plan import MODE_CODES, RERENDER_MODE
from umi_aug.augment.session_assets import SessionAssets
from umi_aug.traj import plot_trajectories

__all__ = ["ExportSummary", "export_pictures", "summary_table"]


@dataclass
class ExportSummary:
    """What :func:`export` did (also written as ``<out>.summary.json``).

    Attributes:
        out_path / work_dir: paths; n_original / n_augmented: episodes in the dataset; n_rerendered: demos
        written again with their approach rendered (``rerender_originals``); n_failed: jobs that
        failed after the retry budget; n_resampled: extra attempts over all emitted episodes;
        n_jobs: augmented jobs; resumed_jobs: jobs already done when this run started;
        status_counts: reasons of failed attempts by status; stages: per stage seconds / skipped;
        timings_s: scene (plain dataset: groups built lazily) / plan / render / write / pictures / total;
        frames_rendered: new frames rendered in this run;
        episodes_per_s: jobs finished per second in this run; pictures: contact sheet + trajectory plots.
    """

    out_path: str
    work_dir: str
    n_original: int
    n_augmented: int
    n_failed: int
    n_resampled: int
    n_jobs: int
    resumed_jobs: int
    status_counts: dict = field(default_factory=dict)
    stages: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    frames_rendered: int = 0
    episodes_per_s: float = 0.0
    pictures: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)
    n_rerendered: int = 0


class _EpisodeFrames:
    """One episode's frames of a zarr image array, decoded on access: a contact sheet shows 7 of an episode's
    hundreds of frames (decoding them all took most of a real episode's picture time)."""

    def __init__(self, arr, sl: slice) -> None:
        self.arr, self.start, self.n = arr, int(sl.start), int(sl.stop - sl.start)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k: int) -> np.ndarray:
        if not -self.n <= int(k) < self.n:
            raise IndexError(f"frame {k} of an episode of {self.n}")
        return self.arr[self.start + int(k) % self.n]


def export_pictures(out: Path, assets: SessionAssets, buf, rec: dict, episodes_by_demo: Mapping[int, list]) -> dict:
    """The export's pictures beside ``out``: a contact sheet of 2 original + 6 augmented episodes (one of them a
    re-rendered demo, when the export has any; splice frames marked) and, per augmented demo, its planned
    trajectories (``episodes_by_demo``: demo index → the planned :class:`umi_aug.traj.Episode` list). Returns
    name → path."""
    pics = {}
    E = buf.n_episodes
    orig = [i for i in range(E) if rec["aug_mode"][i] == 0][:2]
    code = MODE_CODES[RERENDER_MODE]
    rerendered = [i for i in range(E) if rec["aug_mode"][i] == code][:1]
    augm = rerendered + [i for i in range(E) if 0 < rec["aug_mode"][i] != code][:6 - len(rerendered)]
    rows = orig + augm
    if rows:
        frames = [_EpisodeFrames(buf["camera0_rgb"], buf.get_episode_slice(i)) for i in rows]
        splice = [int(rec["aug_splice_index"][i]) if rec["aug_splice_index"][i] >= 0 else len(f) - 1
                  for i, f in zip(rows, frames)]
        inv = {v: k for k, v in MODE_CODES.items()}
        names = [f"{inv[int(rec['aug_mode'][i])]} d{int(rec['aug_source_episode'][i])}"
                 + (f" a{int(rec['aug_id'][i])}" if rec["aug_id"][i] >= 0 else "") for i in rows]
        pics["contact_sheet"] = str(contact_sheet(frames, out.with_name(out.name + ".contact_sheet.png"),
                                                  splice_indices=splice, row_names=names))
    for d in assets.augmentable:
        eps = episodes_by_demo.get(d, [])
        if eps:
            name = assets.demos[d].name
            path = out.with_name(f"{out.name}.trajectories_{name}.png")
            pics[f"trajectories/{name}"] = str(plot_trajectories(
                path, assets.for_demo(d).traj_problem(d), eps,
                title=f"{name}: {len(eps)} augmented trajectories ({assets.cfg.mode}; obstacles not drawn)"))
    return pics


def summary_table(summary: ExportSummary) -> Table:
    """A ``rich.table.Table`` of the summary (episodes, failures, resampling, per-stage timings)."""
    t = Table(title=f"umi-aug augment → {summary.out_path}")
    t.add_column("item")
    t.add_column("value", justify="right")
    for k, v in [("original episodes", summary.n_original), ("augmented episodes", summary.n_augmented),
                 *([("re-rendered demos", summary.n_rerendered)] if summary.n_rerendered else []),
                 ("failed jobs", summary.n_failed), ("resampled attempts", summary.n_resampled),
                 ("jobs resumed", summary.resumed_jobs), ("new frames rendered", summary.frames_rendered),
                 ("episodes/s (this run)", summary.episodes_per_s)]:
        t.add_row(k, str(v))
    for k, v in summary.stages.items():
        t.add_row(f"stage {k}", "cached" if v["skipped"] else f"{v['seconds']:.1f} s")
    for k, v in summary.timings_s.items():
        t.add_row(k, f"{v:.2f}")
    for k, v in summary.status_counts.items():
        t.add_row(f"failed attempts: {k}", str(v))
    return t
