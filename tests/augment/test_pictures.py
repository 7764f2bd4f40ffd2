"""The export's contact sheet: one row per episode, and no band of blank space between its title and the grid."""

from __future__ import annotations

import numpy as np

from umi_aug.augment.pictures import contact_sheet


def _longest_blank_run(rows_blank: np.ndarray) -> int:
    best = run = 0
    for b in rows_blank:
        run = run + 1 if b else 0
        best = max(best, run)
    return best


def test_contact_sheet_has_no_blank_band_above_the_grid(tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    for n_rows in (2, 8):
        eps = [rng.integers(0, 255, (30, 84, 84, 3), dtype=np.uint8) for _ in range(n_rows)]
        path = contact_sheet(eps, tmp_path / f"sheet{n_rows}.png", splice_indices=[12] * n_rows)
        img = cv2.imread(str(path))
        assert img is not None
        h = img.shape[0]
        assert 0.8 * n_rows * 2.0 * 110 < h < 1.2 * n_rows * 2.0 * 110 + 100  # ~2 in per row at 110 dpi
        # blank rows (all near-white) from the top until the first frame's pixels: only margins, no band
        blank = (img.min(axis=(1, 2)) > 240)
        inked = (img.min(axis=2) < 200).mean(axis=1)  # share of non-white pixels per row
        first_frame_row = int(np.argmax(inked > 0.5))  # the first row through the first grid row's frames
        assert _longest_blank_run(blank[:first_frame_row]) < 0.35 * 110, (n_rows, first_frame_row)
