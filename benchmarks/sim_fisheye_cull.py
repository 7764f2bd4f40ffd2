"""Speed of the MuJoCo fisheye wrist camera with per-face geom culling against the same renderer without it.

Run: ``python benchmarks/sim_fisheye_cull.py [--seeds 2] [--sizes 84 224] [--every 2]``

What is rendered: the square task's wrist view (robosuite's Panda, :class:`umi_aug.square.env.SquareEnv`) along
scripted-expert episodes (:class:`umi_aug.square.expert.SquareExpert`, reset seeds ``0 .. --seeds-1``, every
``--every``-th control step), i.e. the poses a demo or an evaluation renders. Both renderers
(:class:`umi_aug.sim.fisheye_renderer.FisheyeRenderer` with ``cull_geoms`` True and False, the latter the reference)
render every pose, alternating which goes first, in this process on one thread. Printed per image size: median ms
per frame (RGB only, the evaluation's output; and RGB + ray depth + segmentation, a demo's), the ratio, how many
frames differ in any output (0 expected: culling is exact), and the mesh triangles each face draws with and without
culling (mean over the poses; a face's cost on llvmpipe is mostly its triangles). Timings are wall clock on whatever
cores this process gets (project machines: 2 shared cores); the ratio is measured pose for pose in the same run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _expert_states(seeds: int, every: int) -> list:
    """Flattened MuJoCo states along scripted-expert episodes (privileged state only: no rendering)."""
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.expert import SquareExpert

    env = SquareEnv(image_size=None)
    states = []
    for seed in range(seeds):
        env.reset(seed=seed)
        expert = SquareExpert()
        for t in range(400):
            if t % every == 0:
                states.append(env.get_state())
            env.step(expert.act(env))
            if env.is_success():
                break
    env.close()
    return states


def _triangles(model, data, renderer, T_world_cam, culled: bool) -> dict[str, int]:
    """Mesh triangles each face draws (primitives: 12 each, a rough count) at this pose."""
    import numpy as np

    from umi_aug.sim.raster import geoms_in_view

    tri = np.where(model.geom_type == 7, model.mesh_facenum[np.maximum(model.geom_dataid, 0)], 12)
    out = {}
    for name, Tf in renderer.face_poses(T_world_cam).items():
        keep = (geoms_in_view(model, data, Tf, renderer.face_boxes[name], renderer.near, renderer.far)
                if culled else np.ones(model.ngeom, dtype=bool))
        out[name] = int(tri[keep & (model.geom_group < 3)].sum())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="expert episodes (reset seeds 0..N-1)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[84, 224], help="fisheye image sizes (square)")
    ap.add_argument("--every", type=int, default=2, help="render every k-th control step of the episodes")
    args = ap.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from umi_aug.runtime import configure_threads

    configure_threads(1)
    import numpy as np

    from umi_aug.sim.fisheye_renderer import FisheyeRenderer, RasterOptions
    from umi_aug.square.camera import FAR_M, NEAR_M, wrist_intrinsics
    from umi_aug.square.env import SquareEnv

    states = _expert_states(args.seeds, max(1, args.every))
    env = SquareEnv(image_size=None)
    env.reset(seed=0)
    model, data = env.model, env.data
    print(f"square wrist camera, {len(states)} poses along {args.seeds} expert episodes; one thread, this "
          "machine's load")
    print("| size | outputs | reference ms/frame | culled ms/frame | ratio | frames that differ | "
          "triangles/frame reference → culled |")
    print("|---|---|---|---|---|---|---|")
    for size in args.sizes:
        opts = RasterOptions(near=NEAR_M, far=FAR_M)
        intr = wrist_intrinsics(size)
        with FisheyeRenderer(model, intr, options=opts, cull_geoms=False) as ref, \
                FisheyeRenderer(model, intr, options=opts) as fast:
            for outputs, kw in (("rgb", dict(depth=False)), ("rgb+depth+seg", dict(segmentation=True))):
                t_ref, t_fast, differ, tri_ref, tri_fast = [], [], 0, [], []
                for k, st in enumerate(states):
                    env.reset_to(st)
                    T = env.wrist_pose()
                    order = ((ref, t_ref), (fast, t_fast)) if k % 2 else ((fast, t_fast), (ref, t_ref))
                    frames = {}
                    for r, times in order:
                        t0 = time.perf_counter()
                        frames[id(r)] = r.render(T, data, **kw)
                        times.append(time.perf_counter() - t0)
                    a, b = frames[id(ref)], frames[id(fast)]
                    same = all(np.array_equal(getattr(a, f), getattr(b, f))
                               for f in ("rgb", "ray_depth", "geom_id"))
                    differ += not same
                    if outputs == "rgb":
                        tri_ref.append(sum(_triangles(model, data, ref, T, False).values()))
                        tri_fast.append(sum(_triangles(model, data, fast, T, True).values()))
                m_ref, m_fast = statistics.median(t_ref) * 1e3, statistics.median(t_fast) * 1e3
                tris = f"{statistics.mean(tri_ref):,.0f} → {statistics.mean(tri_fast):,.0f}" if tri_ref else ""
                print(f"| {size}² | {outputs} | {m_ref:.1f} | {m_fast:.1f} | {m_ref / m_fast:.2f}× | "
                      f"{differ} of {len(states)} | {tris} |")
    env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
