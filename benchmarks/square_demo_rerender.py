"""Our square scene model at the demos' OWN poses against the recorded frames: how far the renders' look is from
the simulator's, where the two can be compared pixel for pixel (issue #29: the policy trained on ``ours`` fits its
renders and errs twice as much on the simulator's frames of the same augmented episodes).

Run: ``python benchmarks/square_demo_rerender.py [--demos-dir square_demos] [--work DIR] [--n 50]
[--scene nut_iterations=1600 ...]``

For each of the first ``--n`` demos, its pre-splice frames (the approach, where the nut stands still) are rendered
by the scene model (static 3DGS + the nut asset at the demo's nut pose) at the demo's recorded camera poses, with
the gripper of the same recorded frames overlaid — exactly the frames the ``ours_rerender`` variant adds
(:func:`umi_aug.square.source.spartn_render_function`) — and compared with the recorded frames: PSNR inside the
fisheye circle, and on the nut's pixels (recorded frame pixels of the nut's orange-brown: OpenCV hue 5–25,
saturation > 90, value > 60) PSNR, mean RGB and mean saturation of both; and how soft each is: the mean variance
of the grey image's Laplacian inside the circle, also for the recorded frames blurred by a Gaussian of
``--blur-sigmas`` pixels (with their nut PSNR and saturation), which says how much of the difference softness alone
explains. ``--scene`` sets
:class:`umi_aug.square.scene.SquareSceneConfig` fields (the stages retrain only what they change; ``--work`` is the
stage cache: a copy of a study's ``work`` folder reuses its static scene). Prints a table; quality only, no timing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _value(text: str):
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def nut_pixels(frames: np.ndarray) -> np.ndarray:
    """[N, H, W] bool: the recorded frames' nut-coloured pixels (orange-brown)."""
    import cv2  # lazy, start-up

    hsv = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2HSV) for f in frames])
    return (hsv[..., 0] >= 5) & (hsv[..., 0] <= 25) & (hsv[..., 1] > 90) & (hsv[..., 2] > 60)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    err = ((a.astype(np.float64) - b.astype(np.float64)) ** 2)[mask].mean()
    return float(10 * np.log10(255.0 ** 2 / max(err, 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demos-dir", type=Path, default=ROOT / "square_demos")
    ap.add_argument("--work", type=Path, default=Path("/tmp/square_demo_rerender"))
    ap.add_argument("--n", type=int, default=50, help="demos compared")
    ap.add_argument("--image-size", type=int, default=84)
    ap.add_argument("--scene", nargs="*", default=[], metavar="KEY=VALUE", help="SquareSceneConfig fields")
    ap.add_argument("--blur-sigmas", type=float, nargs="*", default=[0.5, 1.0],
                    help="also compare the recorded frames blurred by these Gaussian sigmas (pixels)")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()

    import cv2  # lazy, start-up

    from umi_aug.augment.config import AugmentConfig
    from umi_aug.camera.kb import unproject
    from umi_aug.square.camera import wrist_intrinsics
    from umi_aug.square.source import SquareInput, prepare_square, spartn_render_function

    scene = dict(kv.split("=", 1) for kv in args.scene)
    scene = {k: _value(v) for k, v in scene.items()}
    cfg = AugmentConfig(mode="freespace", image_size=args.image_size, include_original=True, workers=1)
    assets = prepare_square(args.demos_dir, args.work, cfg, SquareInput(episodes=tuple(range(args.n)), scene=scene))
    render_new = spartn_render_function(assets)
    intr = wrist_intrinsics(args.image_size)
    vv, uu = np.mgrid[0:intr.height, 0:intr.width]
    circle = unproject(np.stack([uu, vv], axis=-1).astype(np.float64), intr)[1]
    rec_all, ren_all = [], []
    for d in range(args.n):
        demo = assets.demos[d]
        if demo.contact_index is None:
            continue
        k = np.arange(int(demo.contact_index))
        ren_all.append(np.asarray(render_new(d, {"T_world_cam": demo.T_world_cam[k], "overlay_rows": k,
                                                 "source": d})))
        rec_all.append(np.asarray(assets.original_frames(d, k)))
    rec, ren = np.concatenate(rec_all), np.concatenate(ren_all)
    nut = nut_pixels(rec) & circle[None]
    sat = lambda f: np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2HSV)[..., 1] for x in f])  # noqa: E731
    out = {"scene": scene, "demos": len(rec_all), "frames": int(len(rec)),
           "psnr_circle_db": psnr(rec, ren, np.broadcast_to(circle, rec.shape[:3])),
           "nut_pixels_per_frame": float(nut.sum() / len(rec)), "nut_psnr_db": psnr(rec, ren, nut),
           "nut_rgb_recorded": rec[nut].mean(0).round(1).tolist(),
           "nut_rgb_rendered": ren[nut].mean(0).round(1).tolist(),
           "nut_saturation_recorded": float(sat(rec)[nut].mean()),
           "nut_saturation_rendered": float(sat(ren)[nut].mean()),
           "nut_asset": assets.square["scene"].report.get("nut", {})}
    print(f"scene {scene or 'defaults'}: {out['demos']} demos, {out['frames']} pre-splice frames at "
          f"{args.image_size}^2")
    print(f"  PSNR in the circle {out['psnr_circle_db']:.2f} dB; nut pixels ({out['nut_pixels_per_frame']:.0f} "
          f"per frame) {out['nut_psnr_db']:.2f} dB")
    print(f"  nut mean RGB recorded {out['nut_rgb_recorded']} rendered {out['nut_rgb_rendered']}; saturation "
          f"{out['nut_saturation_recorded']:.0f} vs {out['nut_saturation_rendered']:.0f} (OpenCV 0-255)")
    inner = cv2.erode(circle.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)

    def softness(frames: np.ndarray) -> float:  # mean Laplacian variance of the grey image inside the circle
        return float(np.mean([cv2.Laplacian(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.float32),
                                            cv2.CV_32F)[inner].var() for f in frames]))

    out["laplacian_var_recorded"], out["laplacian_var_rendered"] = softness(rec), softness(ren)
    print(f"  sharpness (Laplacian variance): recorded {out['laplacian_var_recorded']:.0f}, rendered "
          f"{out['laplacian_var_rendered']:.0f}")
    out["recorded_blurred"] = []
    for sigma in args.blur_sigmas:
        blurred = np.stack([cv2.GaussianBlur(f, (0, 0), float(sigma)) for f in rec])
        row = {"sigma_px": float(sigma), "laplacian_var": softness(blurred),
               "psnr_circle_db": psnr(blurred, ren, np.broadcast_to(circle, rec.shape[:3])),
               "nut_psnr_db": psnr(blurred, ren, nut), "nut_saturation": float(sat(blurred)[nut].mean())}
        out["recorded_blurred"].append(row)
        print(f"  recorded blurred by sigma {sigma:g} px: Laplacian variance {row['laplacian_var']:.0f}, against "
              f"the renders {row['psnr_circle_db']:.2f} dB (nut {row['nut_psnr_db']:.2f} dB), nut saturation "
              f"{row['nut_saturation']:.0f}")
    print(f"  nut asset: {json.dumps(out['nut_asset'])}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
