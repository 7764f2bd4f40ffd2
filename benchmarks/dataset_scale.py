"""A plain UMI dataset at scale (issue #34 item 3): the export's scene builds and episodes as tasks — one process
against a local Ray cluster — and the cost model they give for a dataset of UMI's size on N machines.

The dataset is the real UMI episode (``../shared/realdata``) copied ``--copies`` times, so every scene is a real
scene with the defaults of ``umi-aug augment <dataset>`` (one scene per episode). Each run starts from an empty
stage cache and writes ``--per-demo`` free-space episodes per demo:

* ``one process`` — ``--executor local --workers 1``: the scenes one after another, each on all cores;
* ``ray N`` — ``--executor ray --workers N`` on a local cluster: N tasks of one CPU each; the scenes build as tasks
  of their own, N at once, ahead of their episodes.

Both runs must write the same bytes (checked here). Worker memory is sampled every 0.2 s over the run's process
tree (resident set size). From the Ray run's per-task seconds (one CPU each) the cost model gives, for
``--demos`` demonstrations × ``--per-demo-target`` augmented episodes each on ``--machines`` machines of
``--cores`` cores (one task per core): total core-hours, wall hours with the scenes' tail, the memory per machine,
and the driver's load: it stores every new frame; by default the episode tasks encode their own frames
(``encode_in_task``), and a third run, ``ray N, driver encodes``, measures the export before that, where the driver
encoded every worker's frames on its threads (driver CPU seconds per episode are reported for every run).

    python benchmarks/dataset_scale.py --work /tmp/dscale             # 2 copies, 10 episodes each, 2 workers

Timings are wall seconds on this machine as it is: run on idle cores (nothing else running).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _scratch import claim_scratch_folder, real_episode_missing  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"


class TreeMemory:
    """Peak resident set size (bytes) per process of this process's tree, sampled every ``period_s``."""

    def __init__(self, period_s: float = 0.2) -> None:
        import psutil

        self.me, self.period_s = psutil.Process(), period_s
        self.peak: dict[int, tuple[str, int]] = {}  # pid → (name, peak bytes)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            for p in [self.me, *self.me.children(recursive=True)]:
                try:
                    name, rss = p.name(), p.memory_info().rss
                    cmd = " ".join(p.cmdline()[:3])
                except psutil.Error:
                    continue
                kind = ("driver" if p.pid == self.me.pid else "ray worker" if name.startswith("ray::") else
                        "pool worker" if "multiprocessing" in cmd else "ray daemon" if "ray" in cmd else "other")
                old = self.peak.get(p.pid, (kind, 0))
                self.peak[p.pid] = (kind, max(old[1], rss))
            self._stop.wait(self.period_s)

    def __enter__(self) -> "TreeMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def by_kind(self) -> dict[str, dict[str, float]]:
        """{kind: {"n": processes, "max_gb": the largest peak, "sum_gb": the peaks summed}}."""
        out: dict[str, dict[str, float]] = {}
        for kind, rss in self.peak.values():
            row = out.setdefault(kind, {"n": 0, "max_gb": 0.0, "sum_gb": 0.0})
            row["n"] += 1
            row["max_gb"] = max(row["max_gb"], rss / 2**30)
            row["sum_gb"] += rss / 2**30
        return out


def copies_of_the_real_episode(src: Path, n: int, out: Path) -> Path:
    """A dataset of ``n`` copies of the real episode (each its own scene group)."""
    from umi_aug.data import ReplayBuffer

    if out.exists():
        return out
    with ReplayBuffer.open(src) as buf:
        ep = buf.get_episode(0)
    dst = ReplayBuffer.create()
    for _ in range(n):
        dst.add_episode(ep)
    return dst.save(out)


def export_run(dataset: Path, work: Path, name: str, per_demo: int, fast_paths=None, **executor) -> dict:
    """One export from an empty cache: wall seconds, the summary's timings, per-scene seconds, memory, the driver's
    CPU seconds (this process, all its threads)."""
    import resource

    from umi_aug.augment.config import AugmentConfig, dataset_splat_stage
    from umi_aug.augment.exporter import export

    import dataclasses

    base = AugmentConfig()
    cfg = dataclasses.replace(
        base, mode="freespace", n_per_demo=per_demo, **executor,
        splat=dataset_splat_stage(),
        recon=dataclasses.replace(base.recon, sfm=dataclasses.replace(base.recon.sfm, mode="known_poses")))
    out = work / f"{name}.zarr"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(work / f"{name}.zarr.work", ignore_errors=True)
    t0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    with TreeMemory() as mem:
        s = export(dataset, out, cfg, progress=False, pictures=False, fast_paths=fast_paths)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    driver_cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    scenes = {}
    for g in sorted((work / f"{name}.zarr.work" / "scenes").iterdir()):
        secs = {}
        for st in ("scene", "sdf", "contact", "splat", "gripper_mask"):
            m = g / st / "manifest.json"
            if m.exists():
                secs[st] = json.loads(m.read_text())["seconds"]
        scenes[g.name] = secs
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"run": name, "executor": executor.get("executor", "local"), "workers": executor.get("workers", 1),
            "wall_s": wall, "timings_s": s.timings_s, "n_augmented": s.n_augmented, "n_failed": s.n_failed,
            "n_original": s.n_original, "scenes_s": scenes, "memory": mem.by_kind(), "out_bytes": size,
            "out": str(out), "driver_cpu_s": driver_cpu,
            "encode_in_task": executor.get("workers", 1) > 1 and (fast_paths is None or "encode_in_task" in fast_paths)}


def same_bytes(a: Path, b: Path) -> bool:
    import numpy as np

    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(a) as x, ReplayBuffer.open(b) as y:
        if x.keys() != y.keys() or sorted(x.meta.array_keys()) != sorted(y.meta.array_keys()):
            return False
        return (all(np.array_equal(x[k][:], y[k][:]) for k in x.keys())
                and all(np.array_equal(x.meta[k][:], y.meta[k][:]) for k in x.meta.array_keys()))


def cost_model(ray_run: dict, demos: int, per_demo: int, machines: list[int], cores: int, ram_gb: float) -> list:
    """Rows of the model for ``demos`` × ``per_demo`` on each machine count, from one-CPU task seconds. The driver
    commits every episode on its main thread (the measured write seconds: chunks stored, the replayed tail's chunks
    copied, records): that bounds the run whatever the cluster. When the run's tasks encoded their frames,
    encoding is task work; otherwise the driver also encodes, on half its machine's cores, beside the commits."""
    scene_s = [sum(v.values()) for v in ray_run["scenes_s"].values()]
    scene_core_s = sum(scene_s) / len(scene_s)
    n_eps = max(1, ray_run["n_augmented"])
    t = ray_run["timings_s"]
    in_task = bool(ray_run.get("encode_in_task"))
    # inside the tasks (one CPU each); scene reads included; + the frames' encoding when the tasks encode
    episode_core_s = (t["plan_s"] + t["render_s"] + (t["encode_s"] if in_task else 0.0)) / n_eps
    # the driver's seconds per episode: its main thread's commits, or the encode threads when they are slower
    driver_s = max(t["write_s"], 0.0 if in_task else t["encode_s"] / max(1, cores // 2)) / n_eps
    worker_gb = ray_run["memory"].get("ray worker", {}).get("max_gb", 0.0)
    mb_per_episode = ray_run["out_bytes"] / max(1, ray_run["n_augmented"] + ray_run["n_original"]) / 2**20
    rows = []
    total_core_h = (demos * scene_core_s + demos * per_demo * episode_core_s) / 3600
    for n in machines:
        slots = n * cores
        wall_h = total_core_h / slots + scene_core_s / 3600  # + one scene's build: the last scenes' tail
        driver_h = demos * per_demo * driver_s / 3600
        rows.append({"machines": n, "cores": slots, "total_core_h": total_core_h, "wall_h": max(wall_h, driver_h),
                     "tasks_h": wall_h,
                     "driver_h": driver_h, "bound": "the driver" if driver_h > wall_h else "tasks",
                     "ram_per_machine_gb": cores * worker_gb, "fits_ram": cores * worker_gb <= ram_gb,
                     "episodes_per_h_per_core": 3600 / episode_core_s,
                     "scene_core_min": scene_core_s / 60, "episode_core_s": episode_core_s,
                     "driver_s_per_episode": driver_s, "worker_gb": worker_gb,
                     "output_gb": demos * (per_demo + 1) * mb_per_episode / 1024})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--work", default="/tmp/umi_aug_dataset_scale", help="scratch folder (its runs are replaced)")
    ap.add_argument("--copies", type=int, default=2, help="copies of the real episode (= scenes)")
    ap.add_argument("--per-demo", type=int, default=10, help="augmented episodes per demo in the measured runs")
    ap.add_argument("--workers", type=int, default=2, help="Ray workers (one CPU each)")
    ap.add_argument("--skip-driver-encodes", action="store_true",
                    help="leave out the third run (Ray with the driver encoding every frame, as before encode_in_task)")
    ap.add_argument("--demos", type=int, default=1400, help="model: demonstrations in the dataset")
    ap.add_argument("--per-demo-target", type=int, default=20, help="model: augmented episodes per demo")
    ap.add_argument("--machines", type=int, nargs="+", default=[1, 2, 5, 10, 20, 50])
    ap.add_argument("--cores", type=int, default=16, help="model: cores per machine")
    ap.add_argument("--ram-gb", type=float, default=64.0, help="model: memory per machine")
    ap.add_argument("--out", default=None, help="JSON of the runs and the model (default <work>/dataset_scale.json)")
    args = ap.parse_args()
    configure_threads()
    from rich.console import Console
    from rich.table import Table

    from umi_aug.io_utils import atomic_write_text

    src = Path(args.dataset)
    work = Path(args.work)
    error = real_episode_missing(src) or claim_scratch_folder(work, ".dataset_scale",
                                                              "its runs' outputs and caches in it are replaced")
    if error:
        print(error, file=sys.stderr)
        return 2
    dataset = copies_of_the_real_episode(src, args.copies, work / f"real_x{args.copies}.zarr.zip")
    console = Console(width=200)
    runs = []
    from umi_aug.augment.exporter import FAST_PATHS

    ray = {"executor": "ray", "workers": args.workers}
    plan = [("one process", {}, None), (f"ray {args.workers}", ray, None)]
    if not args.skip_driver_encodes:
        plan.append((f"ray {args.workers}, driver encodes", ray, tuple(f for f in FAST_PATHS if f != "encode_in_task")))
    for name, ex, fast in plan:
        r = export_run(dataset, work, name.replace(" ", "_").replace(",", ""), args.per_demo, fast_paths=fast, **ex)
        r["run"] = name
        runs.append(r)
        console.print(f"{name}: {r['wall_s']:.1f} s, {r['n_augmented']} episodes, {r['n_failed']} failed")
    identical = all(same_bytes(Path(runs[0]["out"]), Path(r["out"])) for r in runs[1:])
    t = Table(title=f"{args.copies} scenes (the real episode) + {args.per_demo} free-space episodes each, from an "
                    f"empty cache; same bytes: {identical}")
    for c in ("run", "wall s", "scene s / scene", "3DGS s / scene", "episode s (plan+render)", "encode s",
              "write s", "driver CPU s / episode", "episodes/h", "peak GB / worker", "driver GB"):
        t.add_column(c, justify="right")
    for r in runs:
        sc = list(r["scenes_s"].values())
        tm = r["timings_s"]
        worker = r["memory"].get("ray worker", {}).get("max_gb", r["memory"].get("driver", {}).get("max_gb", 0))
        t.add_row(r["run"], f"{r['wall_s']:.0f}", f"{sum(sum(s.values()) for s in sc) / len(sc):.0f}",
                  f"{sum(s.get('splat', 0) for s in sc) / len(sc):.0f}",
                  f"{(tm['plan_s'] + tm['render_s']) / max(1, r['n_augmented']):.1f}",
                  f"{tm['encode_s'] / max(1, r['n_augmented']):.2f}" + (" (tasks)" if r["encode_in_task"] else ""),
                  f"{tm['write_s'] / max(1, r['n_augmented']):.2f}",
                  f"{r['driver_cpu_s'] / max(1, r['n_augmented']):.2f}",
                  f"{3600 * r['n_augmented'] / r['wall_s']:.0f}", f"{worker:.2f}",
                  f"{r['memory'].get('driver', {}).get('max_gb', 0):.2f}")
    console.print(t)
    model = cost_model(runs[1], args.demos, args.per_demo_target, args.machines, args.cores, args.ram_gb)
    m0 = model[0]
    t = Table(title=f"model: {args.demos} demos x {args.per_demo_target} augmented episodes on machines of "
                    f"{args.cores} cores ({m0['scene_core_min']:.1f} core-min per scene, "
                    f"{m0['episode_core_s']:.1f} core-s per episode, {m0['worker_gb']:.2f} GB per task, "
                    f"output {m0['output_gb']:.0f} GB)")
    for c in ("machines", "cores", "core-hours", "tasks h", "driver h", "wall hours", "bound",
              f"RAM / machine GB (of {args.ram_gb:.0f})"):
        t.add_column(c, justify="right")
    for m in model:
        t.add_row(str(m["machines"]), str(m["cores"]), f"{m['total_core_h']:.0f}", f"{m['tasks_h']:.1f}",
                  f"{m['driver_h']:.1f}", f"{m['wall_h']:.1f}", m["bound"],
                  f"{m['ram_per_machine_gb']:.0f}" + ("" if m["fits_ram"] else " (does not fit)"))
    console.print(t)
    out = Path(args.out) if args.out else work / "dataset_scale.json"
    atomic_write_text(out, json.dumps({"runs": runs, "same_bytes": identical, "model": model,
                                       "args": vars(args)}, indent=2, default=float) + "\n")
    console.print(f"rows: {out}")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
