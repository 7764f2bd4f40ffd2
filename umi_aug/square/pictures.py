"""Contact sheets of the square task's fisheye wrist views (docs/square_*.png, < 300 kB).

``python -m umi_aug.square.pictures --out docs [--init-configs FILE] [--seed 0]`` writes
``square_demo_wrist`` (frames of one expert demo, 224²) and ``square_init_configs`` (start views of a sample of
an init-config set; without ``--init-configs`` a 24-config set is sampled from seeded resets).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from umi_aug.io_utils import atomic_write_bytes

__all__ = ["tile", "save_small", "demo_sheet", "init_config_sheet"]

#: Largest file written (bytes).
MAX_BYTES: int = 300_000


def tile(images: list[np.ndarray], labels: list[str], n_cols: int, size: int = 160) -> np.ndarray:
    """Grid of uint8 RGB tiles (resized to ``size``²) with a label in each tile's top-left corner."""
    import cv2  # lazy, start-up: cv2

    n_rows = -(-len(images) // n_cols)
    sheet = np.full((n_rows * size, n_cols * size, 3), 255, np.uint8)
    for i, (img, lab) in enumerate(zip(images, labels)):
        t = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
        cv2.putText(t, lab, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1, cv2.LINE_AA)
        r, c = divmod(i, n_cols)
        sheet[r * size:(r + 1) * size, c * size:(c + 1) * size] = t
    return sheet


def save_small(sheet: np.ndarray, stem: Path) -> Path:
    """Save as ``stem.png``, downscaled (×0.85 steps) until the file is < :data:`MAX_BYTES`."""
    import cv2  # lazy, start-up: cv2

    bgr = cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR)
    while True:
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if buf.nbytes < MAX_BYTES or min(bgr.shape[:2]) < 64:
            return atomic_write_bytes(stem.with_suffix(".png"), buf.tobytes())
        bgr = cv2.resize(bgr, None, fx=0.85, fy=0.85, interpolation=cv2.INTER_AREA)


def demo_sheet(out_dir: Path, seed: int = 0, n: int = 24) -> Path:
    """Frames of one 224² expert demo (``n`` evenly spaced, phase names in the labels)."""
    # lazy, start-up: cv2
    from umi_aug.square.env import FISHEYE_KEY, SquareEnv
    from umi_aug.square.episode import rollout_expert

    env = SquareEnv(image_size=224)
    ep = rollout_expert(env, seed, render=True)
    env.close()
    frames = ep.obs[FISHEYE_KEY]
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    sheet = tile([frames[i] for i in idx], [f"t={i}" for i in idx], n_cols=6)
    return save_small(sheet, out_dir / "square_demo_wrist")


def init_config_sheet(out_dir: Path, configs_path: str | None, n: int = 24, seed: int = 0) -> Path:
    """Start views (224² fisheye) of ``n`` configurations of an init-config set (evenly spaced indices)."""
    # lazy, start-up: cv2
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.init_configs import (InitConfigSpec, apply_init_config, load_init_configs,
                                                 sample_init_configs, source_states_from_seeds)

    env = SquareEnv(image_size=224)
    if configs_path:
        configs = load_init_configs(configs_path)
    else:
        src = source_states_from_seeds(env, list(range(n)))
        configs = sample_init_configs(env, src, InitConfigSpec(n=n, seed=seed), progress=False)
    idx = np.linspace(0, len(configs["states"]) - 1, n).round().astype(int)
    images = []
    for i in idx:
        apply_init_config(env, configs, int(i))
        images.append(env.render_wrist())
    env.close()
    sheet = tile(images, [f"#{i}" for i in idx], n_cols=6)
    return save_small(sheet, out_dir / "square_init_configs")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs")
    ap.add_argument("--init-configs", default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    out = Path(args.out)
    os.makedirs(out, exist_ok=True)
    print(demo_sheet(out, args.seed))
    print(init_config_sheet(out, args.init_configs, seed=args.seed))


if __name__ == "__main__":
    main()
