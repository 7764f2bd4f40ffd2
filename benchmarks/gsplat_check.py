"""The gsplat GPU backend against the CPU reference renderer, on a CUDA machine (issue #4 item 6, #17).

Run (a machine with a CUDA torch and ``gsplat==1.5.3``; the first import JIT-compiles gsplat's CUDA code):
``python benchmarks/gsplat_check.py [--sizes 25000 100000 300000] [--res 224 448] [--out DIR]``

:func:`umi_aug.splat.render_with_backend` has two backends: ``"cpu"`` (numba, the reference every other stage
uses) and ``"gsplat"`` (gsplat's 3DGUT rasteriser with the OpenCV-fisheye camera). The two do not compute the
same thing exactly (3DGUT evaluates each Gaussian's maximum response along the pixel ray, ours the EWA 2D
footprint; gsplat's camera stops at 90 deg, the GoPro lens sees 104 deg), so this script measures how close
they are and what the GPU buys, on the same inputs in one run:

1. **Camera convention**: single small Gaussians at known angles off the optical axis (0..85 deg and one at
   95 deg, past the half-sphere): the intensity-weighted centroid of each render against the KB projection of
   its mean, in pixels. A wrong principal-point offset or axis flip shows here as a constant shift.
2. **Images**: the procedural tabletop room (:func:`umi_aug.splat.scenes.room_gaussians`, SH degree 3) seen
   by UMI's GoPro at ``res``² from three wrist-camera poses: PSNR of gsplat against the CPU render inside
   90 deg and on the 90..104 deg rim separately, alpha mean |difference|, ray-depth median relative
   difference where both alphas > 0.5; side-by-side pictures (CPU | gsplat | 4 x |difference|).
3. **Extreme inputs**: random Gaussians spread past 90 deg and behind the camera: both renders finite.
4. **Gradients**: ``loss = sum(w * rgb)`` with a fixed random ``w``, backward through both renderers: cosine
   similarity of the gradients of means, log-scales, logit-opacities and SH DC over the Gaussians both see.
5. **Speed**: ms per frame of the CPU renderer (this machine's cores, stated) and of gsplat (CUDA-synchronised,
   one camera per call, and ``batch`` cameras per call: ``rasterization`` alone, colour pass), and of the whole
   :func:`render_gsplat` (conversion, colour and depth passes, copy back) with the scene on the CPU and resident
   on the GPU; median of ``repeats`` after warm-up; ratios in the same run.

Writes ``gsplat_check.json``, ``gsplat_check.md`` (the tables) and ``gsplat_vs_cpu_<res>.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from umi_aug.camera import gopro_intrinsics_2_7k, kb  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402
from umi_aug.splat import Gaussians, render  # noqa: E402
from umi_aug.splat.gsplat_backend import (  # noqa: E402
    gsplat_available,
    gsplat_canvas_pad,
    gsplat_rasterization_kwargs,
    render_gsplat,
)
from umi_aug.splat.scenes import look_at_pose, random_gaussians, room_camera_pose, room_gaussians  # noqa: E402


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) if a.size else float("nan")
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def _pixel_theta(intr) -> tuple[np.ndarray, np.ndarray]:
    """Angle off the optical axis of every pixel's ray (rad) and whether the pixel is inside the lens' image."""
    vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
    rays, valid = kb.unproject(np.stack([uu, vv], axis=-1).astype(np.float64), intr)
    return np.arccos(np.clip(rays[..., 2], -1.0, 1.0)), valid


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _median_time(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
        _sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


# ------------------------------------------------------------------------------------------------ 1. camera
def check_centroids(res: int) -> list[dict]:
    """Centroid of one small Gaussian per angle, CPU vs gsplat vs the KB projection of its mean (pixels)."""
    intr = gopro_intrinsics_2_7k().umi_policy(res)
    T = np.eye(4)
    rows = []
    for theta_deg in (0.0, 20.0, 45.0, 70.0, 80.0, 85.0, 89.0, 95.0):
        th, ph = math.radians(theta_deg), math.radians(30.0)
        d = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
        mean = 1.0 * d
        g = Gaussians.from_numpy({"means": mean[None], "log_scales": np.log(np.full((1, 3), 0.004)),
                                  "quats_wxyz": np.array([[1.0, 0, 0, 0]]), "logit_opacities": np.array([3.0]),
                                  "sh0": np.full((1, 3), 1.5)})
        uv_kb, ok = kb.project(mean[None], intr)
        row = {"theta_deg": theta_deg, "kb_uv": uv_kb[0].tolist() if ok[0] else None}
        for name, fn in (("cpu", render), ("gsplat", render_gsplat)):
            a = fn(g, T, intr).alpha.numpy().astype(np.float64)
            s = a.sum()
            if s < 1e-6:
                row[f"{name}_uv"], row[f"{name}_mass"] = None, 0.0
                continue
            vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
            row[f"{name}_uv"] = [float((a * uu).sum() / s), float((a * vv).sum() / s)]
            row[f"{name}_mass"] = float(s)
        if row.get("cpu_uv") and row.get("gsplat_uv"):
            row["gsplat_minus_cpu_px"] = [row["gsplat_uv"][i] - row["cpu_uv"][i] for i in range(2)]
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------ 2. images
def compare_images(g: Gaussians, res: int, poses: list[np.ndarray], out: Path | None, tag: str,
                   pad_canvas: bool = True) -> list[dict]:
    intr = gopro_intrinsics_2_7k().umi_policy(res)
    theta, valid = _pixel_theta(intr)
    front = valid & (theta <= math.pi / 2)
    rim = valid & (theta > math.pi / 2)
    rows, panels = [], []
    for i, T in enumerate(poses):
        c = render(g, T, intr)
        s = render_gsplat(g, T, intr, pad_canvas=pad_canvas)
        rgb_c, rgb_s = c.rgb.numpy(), s.rgb.numpy()
        a_c, a_s = c.alpha.numpy(), s.alpha.numpy()
        both = (a_c > 0.5) & (a_s > 0.5) & front
        dc, ds = c.ray_depth.numpy()[both], s.ray_depth.numpy()[both]
        centre = valid & (theta <= math.radians(30))
        seen = valid & (a_s > 1e-3)
        rel = np.abs(ds - dc) / np.maximum(dc, 1e-9)
        rows.append({
            "scene": tag, "res": res, "pose": i, "pad_canvas": pad_canvas,
            "psnr_theta_0_30_db": _psnr(rgb_c[centre], rgb_s[centre]),
            "psnr_theta_80_90_db": _psnr(rgb_c[valid & (theta > math.radians(80)) & front],
                                         rgb_s[valid & (theta > math.radians(80)) & front]),
            "theta_max_gsplat_deg": float(np.degrees(theta[seen].max())) if seen.any() else None,
            "psnr_front_db": _psnr(rgb_c[front], rgb_s[front]),
            "psnr_rim_db": _psnr(rgb_c[rim], rgb_s[rim]) if rim.any() else None,
            "rim_px": int(rim.sum()), "front_px": int(front.sum()),
            "alpha_mad_front": float(np.abs(a_c - a_s)[front].mean()),
            "alpha_mean_rim_cpu": float(a_c[rim].mean()) if rim.any() else None,
            "alpha_mean_rim_gsplat": float(a_s[rim].mean()) if rim.any() else None,
            "depth_rel_median": float(np.median(rel)) if rel.size else None,
            "finite": bool(all(np.isfinite(x).all() for x in (rgb_s, a_s, s.ray_depth.numpy()))),
        })
        diff = np.clip(4.0 * np.abs(rgb_c - rgb_s), 0, 1)
        panels.append(np.concatenate([np.clip(rgb_c, 0, 1), np.clip(rgb_s, 0, 1), diff], axis=1))
    if out is not None and panels:
        import cv2

        img = (np.concatenate(panels, axis=0) * 255).round().astype(np.uint8)
        cv2.imwrite(str(out / f"gsplat_vs_cpu_{tag}_{res}{'' if pad_canvas else '_nopad'}.png"), img[..., ::-1])
    return rows


def diagnose(res: int, seed: int) -> list[dict]:
    """Where the CPU and gsplat renders differ: one factor at a time on random Gaussians (2000, 0.6..5 px unless
    stated) in front of the camera; PSNR over the pixels within 75 deg. ``conjugate quats`` hands gsplat the
    inverse rotations: if that agreed better, the quaternion convention would be wrong."""
    intr = gopro_intrinsics_2_7k().umi_policy(res)
    T = look_at_pose((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), up_hint=(0.0, -1.0, 0.0))
    theta, valid = _pixel_theta(intr)
    m = valid & (theta <= math.radians(75))
    cases = [
        ("isotropic, SH0, no filter", dict(anisotropy=1.0, sh_degree=0), "none", False),
        ("isotropic 3-15 px, SH0, no filter", dict(anisotropy=1.0, sh_degree=0, sigma_px_range=(3.0, 15.0)), "none",
         False),
        ("anisotropic x4, SH0, no filter", dict(anisotropy=4.0, sh_degree=0), "none", False),
        ("anisotropic x4, SH0, no filter, conjugate quats", dict(anisotropy=4.0, sh_degree=0), "none", True),
        ("anisotropic x4, SH0, inria filter", dict(anisotropy=4.0, sh_degree=0), "inria", False),
        ("anisotropic x4, SH3, inria filter", dict(anisotropy=4.0, sh_degree=3), "inria", False),
        ("anisotropic x20 (flat), SH0, no filter", dict(anisotropy=20.0, sh_degree=0), "none", False),
        ("anisotropic x20 (flat) 3-15 px, SH0, no filter",
         dict(anisotropy=20.0, sh_degree=0, sigma_px_range=(3.0, 15.0)), "none", False),
    ]
    rows = []
    for name, kw, filt, conj in cases:
        g = random_gaussians(2000, np.random.default_rng(seed), intr, T, theta_max=math.radians(75),
                             dtype=torch.float32, **kw)
        c = render(g, T, intr, filter=filt)
        gs = g
        if conj:
            q = g.quats_wxyz * torch.tensor([1.0, -1.0, -1.0, -1.0])
            gs = Gaussians(g.means, g.log_scales, q, g.logit_opacities, g.sh0, g.sh_rest)
        s = render_gsplat(gs, T, intr, filter=filt)
        rows.append({"case": name, "psnr_db": _psnr(c.rgb.numpy()[m], s.rgb.numpy()[m]),
                     "alpha_mad": float(np.abs(c.alpha.numpy() - s.alpha.numpy())[m].mean())})
    return rows


def check_extremes(res: int, seed: int) -> dict:
    """Random Gaussians past 90 deg (theta up to the lens' 104 deg) plus some behind the camera."""
    rng = np.random.default_rng(seed)
    intr = gopro_intrinsics_2_7k().umi_policy(res)
    T = look_at_pose((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), up_hint=(0.0, -1.0, 0.0))
    g = random_gaussians(3000, rng, intr, T, theta_max=intr.theta_max, dtype=torch.float32)
    behind = g.means.clone()
    behind[:500, 2] = -behind[:500, 2]  # the camera looks along +z of the world here: these are behind it
    g = Gaussians(behind, g.log_scales, g.quats_wxyz, g.logit_opacities, g.sh0, g.sh_rest)
    s = render_gsplat(g, T, intr)
    c = render(g, T, intr)
    return {"n": g.n, "gsplat_finite": bool(all(torch.isfinite(t).all() for t in (s.rgb, s.alpha, s.ray_depth))),
            "cpu_finite": bool(all(torch.isfinite(t).all() for t in (c.rgb, c.alpha, c.ray_depth)))}


# ------------------------------------------------------------------------------------------------ 4. gradients
def compare_gradients(g: Gaussians, res: int, T: np.ndarray, seed: int) -> dict:
    intr = gopro_intrinsics_2_7k().umi_policy(res)
    theta, valid = _pixel_theta(intr)
    w = torch.as_tensor(np.random.default_rng(seed).normal(size=(intr.height, intr.width, 3)), dtype=torch.float32)
    w = w * torch.as_tensor(valid & (theta <= math.pi / 2), dtype=torch.float32)[..., None]
    grads = {}
    for name in ("cpu", "gsplat"):
        gg = g.detach().clone().requires_grad_()
        if name == "cpu":
            rgb = render(gg, T, intr).rgb
        else:
            import gsplat

            kw = gsplat_rasterization_kwargs(gg, T, intr, device="cuda", differentiable=True)
            colors, alphas, _ = gsplat.rasterization(**kw)
            pad = gsplat_canvas_pad(intr)
            rgb = colors[0, pad : pad + intr.height, pad : pad + intr.width, :3].cpu()
        (rgb * w).sum().backward()
        grads[name] = {k: getattr(gg, k).grad.detach().double()
                       for k in ("means", "log_scales", "logit_opacities", "sh0")}
    seen = (grads["cpu"]["logit_opacities"].abs() > 0) & (grads["gsplat"]["logit_opacities"].abs() > 0)
    out = {"n_seen_both": int(seen.sum()), "n_seen_cpu": int((grads["cpu"]["logit_opacities"].abs() > 0).sum()),
           "n_seen_gsplat": int((grads["gsplat"]["logit_opacities"].abs() > 0).sum())}
    for k in grads["cpu"]:
        a, b = grads["cpu"][k][seen].reshape(-1), grads["gsplat"][k][seen].reshape(-1)
        out[f"cos_{k}"] = float(torch.dot(a, b) / (a.norm() * b.norm()).clamp_min(1e-30))
        out[f"finite_{k}"] = bool(torch.isfinite(grads["gsplat"][k]).all())
    return out


# ------------------------------------------------------------------------------------------------ 5. speed
def time_renderers(g: Gaussians, res: int, repeats: int, batch: int) -> dict:
    import gsplat

    intr = gopro_intrinsics_2_7k().umi_policy(res)
    T = room_camera_pose(0)
    t_cpu = _median_time(lambda: render(g, T, intr), max(3, repeats // 4), warmup=1)
    g_cuda = g.to(device="cuda")
    kw = gsplat_rasterization_kwargs(g_cuda, T, intr, device="cuda")
    t_gs = _median_time(lambda: gsplat.rasterization(**kw), repeats)
    poses = [room_camera_pose(i % 3) for i in range(batch)]
    kws = [gsplat_rasterization_kwargs(g_cuda, P, intr, device="cuda") for P in poses]
    kwb = dict(kw, viewmats=torch.cat([k["viewmats"] for k in kws]), Ks=torch.cat([k["Ks"] for k in kws]),
               radial_coeffs=torch.cat([k["radial_coeffs"] for k in kws]))
    t_gsb = _median_time(lambda: gsplat.rasterization(**kwb), repeats) / batch
    t_full = _median_time(lambda: render_gsplat(g, T, intr), repeats)
    t_res = _median_time(lambda: render_gsplat(g_cuda, T, intr), repeats)
    return {"n": g.n, "res": res, "cpu_ms": 1e3 * t_cpu, "gsplat_ms": 1e3 * t_gs, "gsplat_batched_ms": 1e3 * t_gsb,
            "render_gsplat_ms": 1e3 * t_full, "render_gsplat_resident_ms": 1e3 * t_res, "speedup": t_cpu / t_gs,
            "speedup_batched": t_cpu / t_gsb}


def _table(rows: list[dict], cols: list[str]) -> str:
    def f(v):
        if v is None:
            return "–"
        if isinstance(v, float):
            return "inf" if math.isinf(v) else f"{v:.3g}" if abs(v) < 100 else f"{v:.1f}"
        if isinstance(v, list):
            return "(" + ", ".join(f(x) for x in v) + ")"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(f(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[25_000, 100_000, 300_000])
    ap.add_argument("--res", type=int, nargs="+", default=[224, 448])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=None, help="CPU renderer threads (default: all cores)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("gsplat_check"))
    args = ap.parse_args(argv)
    ok, why = gsplat_available()
    if not ok:
        print(f"gsplat_check: {why}", file=sys.stderr)
        return 2
    threads = configure_threads(args.threads or os.cpu_count())
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    import gsplat

    t_import = time.perf_counter() - t0
    env = {"gsplat": gsplat.__version__, "torch": torch.__version__, "cuda": torch.version.cuda,
           "gpu": torch.cuda.get_device_name(0), "cpu_threads": threads,
           "cpu": platform.processor() or platform.machine(),
           "gsplat_import_s": t_import}
    print(json.dumps(env))
    rng = np.random.default_rng(args.seed)
    result: dict = {"env": env}
    result["centroids"] = check_centroids(max(args.res))
    print(_table(result["centroids"], ["theta_deg", "kb_uv", "cpu_uv", "gsplat_uv", "gsplat_minus_cpu_px"]))
    room = room_gaussians(min(args.sizes), rng)
    poses = [room_camera_pose(i) for i in range(3)]
    result["images"] = []
    for res in args.res:
        result["images"] += compare_images(room, res, poses, args.out, "room")
    result["images"] += compare_images(room, min(args.res), poses, args.out, "room", pad_canvas=False)
    img_cols = ["scene", "res", "pose", "pad_canvas", "theta_max_gsplat_deg", "psnr_theta_0_30_db",
                "psnr_theta_80_90_db", "psnr_front_db", "psnr_rim_db", "alpha_mad_front", "alpha_mean_rim_cpu",
                "alpha_mean_rim_gsplat", "depth_rel_median", "finite"]
    print(_table(result["images"], img_cols))
    result["diagnosis"] = diagnose(min(args.res), args.seed)
    print(_table(result["diagnosis"], ["case", "psnr_db", "alpha_mad"]))
    result["extremes"] = check_extremes(min(args.res), args.seed)
    print(json.dumps(result["extremes"]))
    result["gradients"] = compare_gradients(room, min(args.res), poses[0], args.seed)
    print(json.dumps(result["gradients"]))
    result["speed"] = []
    for n in args.sizes:
        g = room if n == room.n else room_gaussians(n, np.random.default_rng(args.seed + n))
        for res in args.res:
            result["speed"].append(time_renderers(g, res, args.repeats, args.batch))
            print(json.dumps(result["speed"][-1]))
    speed_cols = ["n", "res", "cpu_ms", "gsplat_ms", "gsplat_batched_ms", "render_gsplat_ms",
                  "render_gsplat_resident_ms", "speedup", "speedup_batched"]
    (args.out / "gsplat_check.json").write_text(json.dumps(result, indent=1))
    md = [f"# gsplat {env['gsplat']} vs the CPU renderer", "",
          f"{env['gpu']}, torch {env['torch']} (CUDA {env['cuda']}); CPU renderer on {threads} threads.", "",
          "## Camera convention (centroid of one small Gaussian, pixels)", "",
          _table(result["centroids"], ["theta_deg", "kb_uv", "cpu_uv", "gsplat_uv", "gsplat_minus_cpu_px"]), "",
          "## Images (room scene, gsplat against the CPU render)", "", _table(result["images"], img_cols), "",
          "## Where they differ (random Gaussians, pixels within 75 deg)", "",
          _table(result["diagnosis"], ["case", "psnr_db", "alpha_mad"]), "",
          "## Extreme inputs", "", "```", json.dumps(result["extremes"]), "```", "",
          "## Gradients (cosine similarity, Gaussians both renderers see)", "", "```",
          json.dumps(result["gradients"], indent=1), "```", "",
          "## Speed (ms per frame)", "", _table(result["speed"], speed_cols), ""]
    (args.out / "gsplat_check.md").write_text("\n".join(md))
    print(_table(result["speed"], speed_cols))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
