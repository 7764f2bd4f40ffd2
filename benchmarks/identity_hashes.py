"""Hashes of the outputs a refactor must not change (issue #33 item 6): run at two commits, compare the JSON.

    python benchmarks/identity_hashes.py --out /tmp/ident_before        # at the commit before the change
    python benchmarks/identity_hashes.py --out /tmp/ident_after         # at the commit after it
    python benchmarks/identity_hashes.py --compare /tmp/ident_before/hashes.json /tmp/ident_after/hashes.json

A step whose output is already in ``--out`` is not run again (rerun to finish an interrupted run, or to rehash).
The commands (each run by the Python of this checkout, so ``PYTHONPATH=<checkout>`` picks the code under test):

1. ``umi-aug demo --out <out>/demo --episodes 1`` — the demo: synthetic session, scene, augmented dataset;
2. ``umi-aug augment ../shared/realdata/umi_cup_in_the_wild_ep0/dataset.zarr.zip -n 1 --mode freespace`` — a plain
   UMI dataset export (the real episode; its scene from its own frames);
3. ``umi-aug augment <square demos> --episodes 0:2 -n 1 --mode freespace --image-size 84`` — a square export (when ``--square-demos``
   names a folder from ``umi-aug square-demos``);
4. ``eval/eval_sim.py policy=expert configs=0:3`` and ``policy=hold`` — eval_sim results.

Every output file is hashed (sha256 of its bytes); files a run writes for people to look at (pictures, logs, the stage
cache) are listed separately, since a picture's encoder or a log's timestamps are not the outputs under test. The
eval_sim ``results.jsonl`` rows and JSON files are hashed without their wall-time and output-folder fields (named in ``TIMING_KEYS``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from umi_aug.io_utils import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
# fields that hold wall time or the run's own output folder, not results (eval_sim's summary.json and results.jsonl)
TIMING_KEYS = ("wall_s", "seconds", "time_s", "elapsed_s", "policy_s", "sim_s", "time_per_step_ms", "time_split",
               "mean_rollout_s", "rollouts_per_hour", "wall_s_this_run", "out_dir")
REAL_DATASET = ROOT.parent / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / "dataset.zarr.zip"
PICTURE_EXT = (".jpg", ".jpeg", ".png", ".log", ".txt", ".lock")


def _sha(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _hash_zarr_zip(path: Path) -> dict[str, str]:
    """sha256 of every member of a zarr zip store; the root ``.zattrs`` without the export's recorded command
    (``umi_aug_export.command``: argv and cwd, which name the output folder)."""
    out: dict[str, str] = {}
    with zipfile.ZipFile(path) as zf:
        for name in sorted(zf.namelist()):
            data = zf.read(name)
            if name == ".zattrs":
                attrs = json.loads(data)
                attrs.get("umi_aug_export", {}).pop("command", None)
                data = json.dumps(attrs, sort_keys=True).encode()
                name += " (command removed)"
            out[f"{path.name}/{name}"] = hashlib.sha256(data).hexdigest()
    return out


def _strip_timing(obj: object) -> object:
    if isinstance(obj, dict):
        return {k: _strip_timing(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [_strip_timing(v) for v in obj]
    return obj


def _hash_tree(root: Path, skip_dirs: tuple[str, ...] = ()) -> dict[str, str]:
    out: dict[str, str] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if not p.is_file() or any(rel.startswith(s) for s in skip_dirs) or p.suffix.lower() in PICTURE_EXT:
            continue
        if p.name == "results.jsonl":
            rows = [json.dumps(_strip_timing(json.loads(x)), sort_keys=True) for x in p.read_text().splitlines() if x]
            out[rel + " (timing fields removed)"] = hashlib.sha256("\n".join(rows).encode()).hexdigest()
        elif p.suffix == ".json":
            txt = json.dumps(_strip_timing(json.loads(p.read_text())), sort_keys=True)
            out[rel + " (timing fields removed)"] = hashlib.sha256(txt.encode()).hexdigest()
        elif p.name.endswith(".zarr.zip"):
            out.update({f"{rel}/{k.split('/', 1)[1]}": v for k, v in _hash_zarr_zip(p).items()})
        else:
            out[rel] = _sha(p)
    return out


def _run(cmd: list[str], log: Path) -> None:
    print("$", " ".join(cmd), flush=True)
    with open(log, "a") as fh:
        rc = subprocess.run(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT,
                            env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}).returncode
    if rc:
        raise SystemExit(f"error: exit {rc}: {' '.join(cmd)} (see {log})")


def run_all(out: Path, square_demos: Path | None) -> dict[str, dict[str, str]]:
    out.mkdir(parents=True, exist_ok=True)
    log = out / "commands.log"
    cli = [sys.executable, "-m", "umi_aug"]
    hashes: dict[str, dict[str, str]] = {}
    if not (out / "demo" / "summary.json").exists():
        _run([*cli, "demo", "--out", str(out / "demo"), "--episodes", "1"], log)
    hashes["demo"] = _hash_tree(out / "demo", skip_dirs=("work/",))
    if not (out / "dataset_export.zarr.zip").exists():
        _run([*cli, "augment", str(REAL_DATASET), "-n", "1", "--mode", "freespace",
              "--out", str(out / "dataset_export.zarr.zip"), "--work", str(out / "dataset_export.work"),
              "--no-pictures"], log)
    hashes["dataset_export"] = _hash_zarr_zip(out / "dataset_export.zarr.zip")
    if square_demos is not None and not (out / "square_export.zarr.zip").exists():
        _run([*cli, "augment", str(square_demos), "--episodes", "0:2", "-n", "1", "--mode", "freespace", "--image-size",
              "84",
              "--out", str(out / "square_export.zarr.zip"), "--work", str(out / "square_export.work"), "--no-pictures"],
             log)
    if (out / "square_export.zarr.zip").exists():
        hashes["square_export"] = _hash_zarr_zip(out / "square_export.zarr.zip")
    for pol in ("expert", "hold"):
        ev = out / f"eval_{pol}"
        if not (ev / "results.jsonl").exists():
            _run([sys.executable, "eval/eval_sim.py", f"policy={pol}", "configs=0:3", f"out_dir={ev}", "workers=1",
                  "progress=false"], log)
        hashes[f"eval_{pol}"] = _hash_tree(ev)
    atomic_write_text(out / "hashes.json", json.dumps(hashes, indent=1, sort_keys=True) + "\n")
    return hashes


def compare(a: Path, b: Path) -> int:
    ha, hb = json.loads(a.read_text()), json.loads(b.read_text())
    bad = 0
    print(f"{'output':<16} {'files':>6} {'identical':>10}  first that differ")
    for group in sorted(set(ha) | set(hb)):
        names = sorted(set(ha.get(group, {})) | set(hb.get(group, {})))
        diff = [n for n in names if ha.get(group, {}).get(n) is None or ha[group].get(n) != hb.get(group, {}).get(n)]
        bad += len(diff)
        print(f"{group:<16} {len(names):>6} {len(names) - len(diff):>10}  {', '.join(diff[:4])}")
    print(f"{bad} differ")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--square-demos", type=Path, default=None)
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    args = ap.parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    if args.out is None:
        ap.error("--out or --compare is needed")
    for group, files in run_all(args.out, args.square_demos).items():
        print(group, len(files), "files")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
