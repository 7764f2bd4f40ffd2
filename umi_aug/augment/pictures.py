"""Pictures of an augmented export: the contact sheet of original and new episodes (policy images).

PNG files written atomically (temporary file, then rename). The contact sheet is drawn with OpenCV; the figures of
other modules use matplotlib through :func:`pyplot` / :func:`save_figure`, headless (Agg) and imported only when a
picture is drawn.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from umi_aug.errors import AugmentError
from umi_aug.io_utils import atomic_path, atomic_write_bytes

__all__ = ["contact_sheet", "sheet_columns", "sheet_tile_origin", "pyplot", "save_figure"]


def pyplot():
    """matplotlib.pyplot on the headless Agg backend (imported on first use)."""
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy, start-up: matplotlib

    return plt


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically and close it."""
    plt = pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


#: The contact sheet's geometry, pixels: gap between tiles, caption band above each frame, title band.
SHEET_GAP_PX: int = 6
SHEET_CAPTION_PX: int = 18
SHEET_TITLE_PX: int = 26
#: OpenCV's Hershey font scales of the captions / row names and of the title (the title shrinks to fit).
SHEET_FONT_SCALE: float = 0.42
SHEET_TITLE_SCALE: float = 0.5


def sheet_columns(n_frames: int, last_new: int, n_cols: int) -> list[int]:
    """Frame indices of a contact-sheet row: ``n_cols - 1`` evenly spaced from 0 up to and including
    ``last_new`` (the splice), then the last frame."""
    return [int(k) for k in np.linspace(0, last_new, n_cols - 1).round().astype(int)] + [n_frames - 1]


def _text_width(text: str, scale: float) -> int:
    import cv2  # lazy, start-up: OpenCV

    return int(cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0])


def _put_text(img: np.ndarray, text: str, x: int, y_baseline: int, scale: float) -> None:
    import cv2  # lazy, start-up: OpenCV

    cv2.putText(img, text, (int(x), int(y_baseline)), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)


def contact_sheet(
    episodes: list[np.ndarray],  # E × [T_e, H, W, 3] uint8 RGB (episodes may differ in length)
    path: Path,
    n_cols: int = 7,
    splice_indices: list[int] | None = None,
    row_names: list[str] | None = None,
) -> Path:
    """Grid of frames: one row per episode, ``n_cols − 1`` frames evenly spaced in time up to and including the
    row's splice index (after it the frames are the original ones), then the row's last frame
    (:func:`sheet_columns`). Frames are shown at their own size (no resampling), each captioned ``t=<index>``
    (``splice`` / ``end`` marked), with the row's name on its left and a one-line title; drawn with OpenCV and
    written as one PNG (a matplotlib grid of the same frames took ~1 s of an export's ~60 s).

    The tile of row ``e``, column ``j`` starts at pixel ``(x, y) = (left + j·(W + gap), title + caption +
    e·(caption + H + gap))`` with ``left`` the row names' width: :func:`sheet_tile_origin`."""
    import cv2  # lazy, start-up: OpenCV

    n_ep = len(episodes)
    H, W = _frame_size(episodes)
    names = [row_names[e] if row_names else f"ep {e}" for e in range(n_ep)]
    left = _sheet_left(names)
    width = left + n_cols * (W + SHEET_GAP_PX)
    height = SHEET_TITLE_PX + n_ep * (SHEET_CAPTION_PX + H + SHEET_GAP_PX)
    sheet = np.full((height, width, 3), 255, dtype=np.uint8)
    title = (f"policy images ({H}x{W}, UMI layout): original demo and new episodes (new frames up to the splice, "
             "original frames after it)")
    fit = (width - 2 * SHEET_GAP_PX) / max(_text_width(title, SHEET_TITLE_SCALE), 1)
    scale = SHEET_TITLE_SCALE * min(1.0, fit)
    _put_text(sheet, title, (width - _text_width(title, scale)) // 2, SHEET_TITLE_PX - 9, scale)
    for e, frames in enumerate(episodes):
        n_t = len(frames)
        x0, y0 = sheet_tile_origin(e, 0, H, W, left)
        _put_text(sheet, names[e], SHEET_GAP_PX, y0 + H // 2, SHEET_FONT_SCALE)
        if n_t == 0:
            continue
        last_new = n_t - 1 if splice_indices is None else int(splice_indices[e])
        for j, k in enumerate(sheet_columns(n_t, last_new, n_cols)):
            x, y = sheet_tile_origin(e, j, H, W, left)
            frame = np.asarray(frames[k])
            if frame.shape[:2] != (H, W) or frame.ndim != 3 or frame.shape[2] < 3:
                raise AugmentError(f"contact_sheet {path}: row {e} ({names[e]}) frame {k} has shape {frame.shape}; "
                                 f"every frame must be [{H}, {W}, 3] like the first")
            sheet[y:y + H, x:x + W] = frame[..., :3]
            tag = " splice" if splice_indices is not None and k == last_new else (" end" if k == n_t - 1 else "")
            cap = f"t={k}{tag}"
            _put_text(sheet, cap, x + (W - _text_width(cap, SHEET_FONT_SCALE)) // 2, y - 5, SHEET_FONT_SCALE)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(sheet[..., ::-1]))
    if not ok:
        raise OSError(f"PNG encoding failed for {path}")
    return atomic_write_bytes(path, buf.tobytes())


def _frame_size(episodes: list[np.ndarray]) -> tuple[int, int]:
    for frames in episodes:
        if len(frames):
            f = np.asarray(frames[0])
            return int(f.shape[0]), int(f.shape[1])
    return 0, 0


def _sheet_left(names: list[str]) -> int:
    return 2 * SHEET_GAP_PX + max((_text_width(n, SHEET_FONT_SCALE) for n in names), default=0)


def sheet_tile_origin(row: int, col: int, H: int, W: int, left: int) -> tuple[int, int]:
    """Top-left pixel ``(x, y)`` of the frame of ``row``, ``col`` in a :func:`contact_sheet` of ``H x W`` frames
    whose row-name column is ``left`` pixels wide."""
    return (left + col * (W + SHEET_GAP_PX),
            SHEET_TITLE_PX + SHEET_CAPTION_PX + row * (SHEET_CAPTION_PX + H + SHEET_GAP_PX))
