"""The export's contact sheet: one row per episode, each tile the source frame at its own size (the right frames:
evenly spaced to the splice, then the last), and no band of blank space between its title and the grid."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from umi_aug.augment.pictures import (
    SHEET_CAPTION_PX,
    SHEET_GAP_PX,
    SHEET_TITLE_PX,
    contact_sheet,
    sheet_columns,
    sheet_tile_origin,
)
from umi_aug.errors import AugmentError


def _longest_blank_run(rows_blank: np.ndarray) -> int:
    best = run = 0
    for b in rows_blank:
        run = run + 1 if b else 0
        best = max(best, run)
    return best


def test_sheet_columns_end_at_the_splice_then_the_last_frame():
    assert sheet_columns(30, 12, 7) == [0, 2, 5, 7, 10, 12, 29]
    assert sheet_columns(5, 4, 7)[-2:] == [4, 4]
    assert sheet_columns(1, 0, 3) == [0, 0, 0]


def test_contact_sheet_tiles_are_the_source_frames(tmp_path, rng):
    for n_rows, (H, W) in ((2, (84, 84)), (8, (60, 96))):
        eps = [rng.integers(0, 255, (int(rng.integers(20, 40)), H, W, 3), dtype=np.uint8) for _ in range(n_rows)]
        splice = [int(rng.integers(1, len(e) - 1)) for e in eps]
        names = [f"row {e} {'x' * e}" for e in range(n_rows)]
        path = contact_sheet(eps, tmp_path / f"sheet{n_rows}.png", splice_indices=splice, row_names=names)
        img = cv2.imread(str(path))[..., ::-1]  # RGB
        assert img.shape[0] == SHEET_TITLE_PX + n_rows * (SHEET_CAPTION_PX + H + SHEET_GAP_PX)
        left = img.shape[1] - 7 * (W + SHEET_GAP_PX)
        assert left > 2 * SHEET_GAP_PX  # the row names' column
        for e, frames in enumerate(eps):
            for j, k in enumerate(sheet_columns(len(frames), splice[e], 7)):
                x, y = sheet_tile_origin(e, j, H, W, left)
                np.testing.assert_array_equal(img[y:y + H, x:x + W], frames[k], err_msg=f"row {e} col {j}")
        # blank rows (all near-white) from the top until the first frame's pixels: only the title and a caption
        blank = img.min(axis=(1, 2)) > 240
        first_frame_row = sheet_tile_origin(0, 0, H, W, left)[1]
        assert _longest_blank_run(blank[:first_frame_row]) < SHEET_TITLE_PX, (n_rows, first_frame_row)
        assert not blank[:SHEET_TITLE_PX].all()  # the title is drawn
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sheet2.png", "sheet8.png"]  # no temporary left


def test_contact_sheet_refuses_frames_of_another_size(tmp_path):
    eps = [np.zeros((5, 32, 32, 3), np.uint8), np.zeros((5, 32, 40, 3), np.uint8)]
    with pytest.raises(AugmentError, match=r"row 1 \(ep 1\) frame 0 has shape \(32, 40, 3\)"):
        contact_sheet(eps, tmp_path / "bad.png")
    assert not any(tmp_path.iterdir())  # nothing written
