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

``--ours EXPORT --gt-render VARIANT --augmented K`` also compares at AUGMENTED poses (the cone starts and their
paths, where the policy is evaluated): for K augmented episodes shared by a study's ``ours`` data and its
``gt_render`` variant (same poses; the simulator's frames), the new frames are rendered again by this scene model
(with the gripper of the demo frames the export overlays) and compared with the simulator's, beside the export's
frames as stored (the scene model the study exported with) — nut and circle PSNR and nut saturation of both.
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
    if "," in text:  # a tuple field, e.g. nut_radius=0.1,0.4
        return tuple(_value(t) for t in text.split(","))
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
    ap.add_argument("--ours", type=Path, default=None, help="a study's ours_n* dataset (augmented poses)")
    ap.add_argument("--gt-render", type=Path, default=None, help="the same study's gt_render_n* dataset")
    ap.add_argument("--augmented", type=int, default=40, help="augmented episodes compared (with --ours)")
    ap.add_argument("--picture", type=Path, default=None,
                    help="with --ours: a PNG of augmented frames, simulator | stored | this scene model (x3)")
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
    if args.ours is not None:
        out["augmented"] = augmented_poses(args, assets, circle, sat)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


def augmented_poses(args, assets, circle: np.ndarray, sat) -> dict:
    """The new frames of ``--augmented`` augmented episodes (spread over the export), rendered again by ``assets``'
    scene model, against ``--gt-render``'s simulator frames; the export's stored frames beside them."""
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.augment.overlay import composite_overlay
    from umi_aug.augment.render import overlay_source_rows, render_view
    from umi_aug.data import ReplayBuffer
    from umi_aug.square.variants import _camera_path, _lowdim

    if args.gt_render is None:
        raise SystemExit("--ours needs --gt-render")
    ra, rb = read_episode_records(args.ours), read_episode_records(args.gt_render)
    key = lambda r, e: (int(r["aug_source_episode"][e]), int(r["aug_id"][e]))  # noqa: E731
    ia = {key(ra, e): e for e in range(len(ra["aug_id"])) if ra["aug_id"][e] >= 0}
    shared = [e for e in range(len(rb["aug_id"])) if rb["aug_id"][e] >= 0 and key(rb, e) in ia]
    pick = [shared[i] for i in np.linspace(0, len(shared) - 1, min(args.augmented, len(shared))).astype(int)]
    gt_all, stored_all, new_all = [], [], []
    with ReplayBuffer.open(args.ours) as A, ReplayBuffer.open(args.gt_render) as B:
        for e in pick:
            a, s, d = ia[key(rb, e)], int(rb["aug_splice_index"][e]), int(rb["aug_source_episode"][e])
            rows_a = np.arange(A.get_episode_slice(a).start, A.get_episode_slice(a).start + s)
            rows_b = np.arange(B.get_episode_slice(e).start, B.get_episode_slice(e).start + s)
            path = _camera_path(A, _lowdim(A, rows_a))
            stored = np.asarray(A["camera0_rgb"].get_orthogonal_selection((rows_a,)))
            h = assets.for_demo(d)
            demo = h.demos[d]  # the gripper of the demo frames the export overlays
            src_rows = overlay_source_rows(demo.gripper_width, demo.contact_index, path["gripper_width"], s,
                                           np.arange(s))
            rendered = np.stack([render_view(h, t) for t in path["T_world_cam"]])
            new_all.append(composite_overlay(rendered, h.original_frames(d, src_rows), h.overlay_alpha))
            stored_all.append(stored)
            gt_all.append(np.asarray(B["camera0_rgb"].get_orthogonal_selection((rows_b,))))
    gt, stored, new = np.concatenate(gt_all), np.concatenate(stored_all), np.concatenate(new_all)
    nut = nut_pixels(gt) & circle[None]
    full = np.broadcast_to(circle, gt.shape[:3])
    out = {"episodes": len(pick), "frames": int(len(gt)), "nut_saturation_simulator": float(sat(gt)[nut].mean())}
    for name, f in (("stored", stored), ("this_scene", new)):
        out[name] = {"psnr_circle_db": psnr(gt, f, full), "nut_psnr_db": psnr(gt, f, nut),
                     "nut_saturation": float(sat(f)[nut].mean())}
    if args.picture is not None:
        _picture(args.picture, gt, stored, new, nut)
    print(f"  augmented poses ({out['episodes']} episodes, {out['frames']} new frames; simulator nut saturation "
          f"{out['nut_saturation_simulator']:.0f}):")
    for name in ("stored", "this_scene"):
        r = out[name]
        print(f"    {name:10s}: circle {r['psnr_circle_db']:.2f} dB, nut {r['nut_psnr_db']:.2f} dB, nut saturation "
              f"{r['nut_saturation']:.0f}")
    return out


def _picture(path: Path, gt: np.ndarray, stored: np.ndarray, new: np.ndarray, nut: np.ndarray, rows: int = 6) -> None:
    """Rows of augmented frames with the most nut pixels among evenly spaced ones: simulator | as stored | this
    scene model, enlarged 3x (nearest)."""
    import cv2  # lazy, start-up

    cand = np.linspace(0, len(gt) - 1, 8 * rows).astype(int)
    pick = np.sort(cand[np.argsort(-nut[cand].sum(axis=(1, 2)))[:rows]])
    img = np.concatenate([np.concatenate([gt[i], stored[i], new[i]], axis=1) for i in pick], axis=0)
    img = cv2.resize(img, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img[..., ::-1])
    print(f"  picture: {path} (columns: simulator | stored | this scene model)")


if __name__ == "__main__":
    main()
