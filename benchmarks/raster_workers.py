"""How the rasteriser's tiles are shared among threads and how each tile's rows are evaluated, on the real UMI
episode's 3DGS scene (issue #34 item 1), three kernels that give the same bytes:

* ``per tile, scalar`` (before session 37): numba hands out one tile per ``prange`` iteration and each (Gaussian,
  pixel) pair is evaluated on its own (``_kernels._raster_fwd_kernel_per_tile`` / ``_raster_bwd_kernel_per_tile``);
* ``per worker, scalar`` (session 37): one ``prange`` iteration per worker, worker k taking tiles k, k + n, ...
  (``_raster_fwd_kernel_scalar`` / ``_raster_bwd_kernel_scalar``);
* ``per worker, lanes`` (now): as session 37's, each row's 16 alphas first computed in vector lanes
  (``raster_fwd_kernel`` / ``raster_bwd_kernel``; ``raster_fwd_fused_kernel`` shares the loop).


For pre-contact frames of the episode: the training forward and backward at full and half size (only the loss
mask's pixels, as the trainer renders them; random pixel gradients) and the export's forward (only the pixels the
gripper overlay leaves; timed with the plain kernel, whose loop the export's fused twin shares). The three must give
the same bytes (checked on every call). Calls alternate per frame over ``--rounds`` rounds; the table prints median
ms and the ratios of the sums.

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

    kernels = ("per tile, scalar", "per worker, scalar", "per worker, lanes")

    def add(name: str, seconds: list[float]) -> None:
        if warm_up:
            return
        r = rows.setdefault(name, {k: [] for k in kernels})
        for k, sec in zip(kernels, seconds):
            r[k].append(sec)

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

    def forward_three(head, act, b, dt):
        """Seconds of the three forwards on the same inputs, the reference's outputs, and whether all are the same
        bytes."""
        outs = [fwd_outputs(b, dt) for _ in kernels]
        sec = [_timed(K._raster_fwd_kernel_per_tile, *head, act, *outs[0]),
               _timed(K._raster_fwd_kernel_scalar, *head, act, *outs[1], n_workers),
               _timed(K.raster_fwd_kernel, *head, act, *outs[2], n_workers)]
        same = all(np.array_equal(x, y) for o in outs[1:] for x, y in zip(outs[0], o))
        return sec, outs[0], same

    with numba.parallel_chunksize(PARALLEL_CHUNK):
        for rnd in range(args.rounds + 1):  # round 0 (one frame, not timed): every kernel compiled or loaded
            warm_up = rnd == 0
            frames = idx[:1] if warm_up else idx
            for f in (1, 2):  # the trainer's full-size and coarse (half-size) steps
                it = intr if f == 1 else intr.scaled(intr.width // f, intr.height // f)
                mask = loss_mask(it)
                for k in frames:
                    packed, uv64, b, xs, ys, act = frame_inputs(d.T_world_cam[k], it, mask)
                    cst = K.raster_constants(packed.dtype)
                    head = (packed, uv64, b.tile_start, b.sorted_row, it.width, it.height, b.tiles_x, xs, ys, cst)
                    sec, o1, same = forward_three(head, act, b, packed.dtype)
                    if not same:
                        print(f"error: frame {k} at 1/{f}: the forward differs", file=sys.stderr)
                        return 1
                    add(f"training forward, {it.width}x{it.height}", sec)
                    grads = tuple(rng.normal(size=s).astype(packed.dtype) for s in
                                  ((it.height, it.width, 3), (it.height, it.width), (it.height, it.width)))
                    gs = [np.empty((b.n_isects, K.GRAD_COLS), packed.dtype) for _ in kernels]
                    sec = [_timed(K._raster_bwd_kernel_per_tile, *head, o1[2], o1[3], *grads, gs[0]),
                           _timed(K._raster_bwd_kernel_scalar, *head, o1[2], o1[3], *grads, gs[1], n_workers),
                           _timed(K.raster_bwd_kernel, *head, o1[2], o1[3], *grads, gs[2], n_workers)]
                    if not all(np.array_equal(gs[0], x) for x in gs[1:]):
                        print(f"error: frame {k} at 1/{f}: the backward differs", file=sys.stderr)
                        return 1
                    add(f"training backward, {it.width}x{it.height}", sec)
            for k in frames:  # the export's forward: the overlay's open pixels (the plain kernel; the export runs its
                # fused twin, raster_fwd_fused_kernel, with the same loop)
                packed, uv64, b, xs, ys, act = frame_inputs(d.T_world_cam[k], intr, assets.rendered_pixels)
                head = (packed, uv64, b.tile_start, b.sorted_row, intr.width, intr.height, b.tiles_x, xs, ys,
                        K.raster_constants(packed.dtype))
                sec, _, same = forward_three(head, act, b, packed.dtype)
                if not same:
                    print(f"error: frame {k}: the export forward differs", file=sys.stderr)
                    return 1
                add(f"export forward, {intr.width}x{intr.height}", sec)
    console = Console(width=160)
    t = Table(title=f"the real episode's 3DGS ({g.n} Gaussians), {len(idx)} pre-contact frames x {args.rounds} rounds, "
                    f"{n_workers} threads")
    for c in ("what", *(f"{k}: median ms" for k in kernels), "x workers (sums)", "x lanes (sums)", "x both"):
        t.add_column(c, justify="right")
    for name, r in rows.items():
        tot = [sum(r[k]) for k in kernels]
        t.add_row(name, *(f"{1e3 * statistics.median(r[k]):.2f}" for k in kernels),
                  f"{tot[0] / tot[1]:.2f}", f"{tot[1] / tot[2]:.2f}", f"{tot[0] / tot[2]:.2f}")
    console.print(t)
    console.print("the same bytes on every forward and backward")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
