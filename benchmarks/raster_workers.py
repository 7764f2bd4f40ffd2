"""How the rasteriser's tiles are shared among threads, on the real UMI episode's 3DGS scene (issue #34 item 1):
numba handing out one tile per ``prange`` iteration (``_kernels._raster_fwd_kernel_per_tile`` /
``_raster_bwd_kernel_per_tile``, the schedule before) against one ``prange`` iteration per worker, worker k taking
tiles k, k + n, ... (``raster_fwd_kernel`` / ``raster_bwd_kernel`` / ``raster_fwd_fused_kernel``, now).

For pre-contact frames of the episode: the training forward and backward at full and half size (only the loss
mask's pixels, as the trainer renders them; random pixel gradients) and the export's forward (only the pixels the
gripper overlay leaves; timed with the plain kernel, whose schedule the export's fused twin shares). Both schedules
must give the same bytes (checked on every call). Calls alternate (before, now) per frame over ``--rounds`` rounds;
the table prints median ms and the ratio of the sums.

    python benchmarks/raster_workers.py --work /tmp/raster_workers   # builds the episode's scene once (cached there)

Run on idle cores: timings are wall seconds on this machine as it is.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_scene_cost import REAL, real_episode_assets  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402


def _timed(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--work", default="/tmp/umi_aug_raster_workers", help="stage cache of the episode's scene")
    ap.add_argument("--frames", type=int, default=12, help="pre-contact frames timed (evenly spaced)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    configure_threads()
    import numba
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    from umi_aug.splat import _kernels as K
    from umi_aug.splat._constants import DEFAULT_FILTER
    from umi_aug.splat.renderer import PARALLEL_CHUNK, _pixel_coords, bin_gaussians, project_numba
    from umi_aug.splat.train_session import loss_mask

    assets, error = real_episode_assets(Path(args.dataset), Path(args.work))
    if error:
        print(error, file=sys.stderr)
        return 2
    d = assets.demos[0]
    idx = np.linspace(0, int(d.contact_index), args.frames).round().astype(int)
    g = assets.gaussians
    intr = assets.policy_intrinsics
    rng = np.random.default_rng(0)
    n_workers = numba.get_num_threads()
    rows: dict[str, dict[str, list[float]]] = {}

    def add(name: str, before: float, now: float) -> None:
        r = rows.setdefault(name, {"before": [], "now": []})
        r["before"].append(before)
        r["now"].append(now)

    def frame_inputs(T, it, pixels):
        packed, uv64, depth64, valid, counts = project_numba(g, torch.as_tensor(T), it, g.sh_degree, DEFAULT_FILTER)
        rows_v = np.flatnonzero(valid)
        b = bin_gaussians(packed, rows_v, depth64[rows_v], it.width, it.height, counts[rows_v])
        xs, ys = _pixel_coords(b, packed.dtype)
        return packed, uv64, b, xs, ys, np.ascontiguousarray(pixels)

    def fwd_outputs(b, dt):
        H, W = b.height, b.width
        return (np.empty((H, W, 3), dt), np.empty((H, W), dt), np.empty((H, W), dt), np.empty((H, W), np.int32),
                np.zeros(b.tiles_x * b.tiles_y, np.int64))

    def forward_pair(head, act, b, dt):
        """Seconds of the per-tile and the per-worker forward on the same inputs, their outputs, and whether
        they are the same bytes."""
        o1, o2 = fwd_outputs(b, dt), fwd_outputs(b, dt)
        t1 = _timed(K._raster_fwd_kernel_per_tile, *head, act, *o1)
        t2 = _timed(K.raster_fwd_kernel, *head, act, *o2, n_workers)
        return t1, t2, o1, all(np.array_equal(x, y) for x, y in zip(o1, o2))

    with numba.parallel_chunksize(PARALLEL_CHUNK):
        for _ in range(args.rounds):
            for f in (1, 2):  # the trainer's full-size and coarse (half-size) steps
                it = intr if f == 1 else intr.scaled(intr.width // f, intr.height // f)
                mask = loss_mask(it)
                for k in idx:
                    packed, uv64, b, xs, ys, act = frame_inputs(d.T_world_cam[k], it, mask)
                    cst = K.raster_constants(packed.dtype)
                    head = (packed, uv64, b.tile_start, b.sorted_row, it.width, it.height, b.tiles_x, xs, ys, cst)
                    t1, t2, o1, same = forward_pair(head, act, b, packed.dtype)
                    if not same:
                        print(f"error: frame {k} at 1/{f}: the forward differs", file=sys.stderr)
                        return 1
                    add(f"training forward, {it.width}x{it.height}", t1, t2)
                    grads = tuple(rng.normal(size=s).astype(packed.dtype) for s in
                                  ((it.height, it.width, 3), (it.height, it.width), (it.height, it.width)))
                    g1 = np.empty((b.n_isects, K.GRAD_COLS), packed.dtype)
                    g2 = np.empty_like(g1)
                    t1 = _timed(K._raster_bwd_kernel_per_tile, *head, o1[2], o1[3], *grads, g1)
                    t2 = _timed(K.raster_bwd_kernel, *head, o1[2], o1[3], *grads, g2, n_workers)
                    if not np.array_equal(g1, g2):
                        print(f"error: frame {k} at 1/{f}: the backward differs", file=sys.stderr)
                        return 1
                    add(f"training backward, {it.width}x{it.height}", t1, t2)
            for k in idx:  # the export's forward: the overlay's open pixels (the plain kernel; the export runs its
                # fused twin, raster_fwd_fused_kernel, with the same schedule)
                packed, uv64, b, xs, ys, act = frame_inputs(d.T_world_cam[k], intr, assets.rendered_pixels)
                head = (packed, uv64, b.tile_start, b.sorted_row, intr.width, intr.height, b.tiles_x, xs, ys,
                        K.raster_constants(packed.dtype))
                t1, t2, _, same = forward_pair(head, act, b, packed.dtype)
                if not same:
                    print(f"error: frame {k}: the export forward differs", file=sys.stderr)
                    return 1
                add(f"export forward, {intr.width}x{intr.height}", t1, t2)

    console = Console(width=140)
    t = Table(title=f"the real episode's 3DGS ({g.n} Gaussians), {len(idx)} pre-contact frames x {args.rounds} rounds, "
                    f"{n_workers} threads: one tile per hand-out (before) against one share per worker (now)")
    for c in ("what", "before: median ms", "now: median ms", "x (sum before / sum now)"):
        t.add_column(c, justify="right")
    for name, r in rows.items():
        t.add_row(name, f"{1e3 * statistics.median(r['before']):.2f}", f"{1e3 * statistics.median(r['now']):.2f}",
                  f"{sum(r['before']) / sum(r['now']):.2f}")
    console.print(t)
    console.print("the same bytes on every forward and backward")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
