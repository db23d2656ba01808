"""What CLIP sees of a mask: its bounding box, the pixels outside the mask
black, padded with black to a square around the box's centre (LangSplat's
crop), so the model's resize to its input size keeps the object's shape."""

from __future__ import annotations

import numpy as np


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of a non-empty [H, W] bool mask, x1 and y1 exclusive."""
    ys = np.flatnonzero(mask.any(axis=1))
    xs = np.flatnonzero(mask.any(axis=0))
    if len(xs) == 0:
        raise ValueError("empty mask has no bounding box")
    return int(xs[0]), int(ys[0]), int(xs[-1]) + 1, int(ys[-1]) + 1


def mask_crop(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[S, S, 3] uint8: the box of mask cut from rgb [H, W, 3], pixels outside
    the mask 0, centred in a black square of side S = max(box width, height);
    the odd pixel of padding goes after the box (right, bottom)."""
    x0, y0, x1, y1 = mask_bbox(mask)
    box = rgb[y0:y1, x0:x1] * mask[y0:y1, x0:x1, None]
    bh, bw = box.shape[:2]
    side = max(bh, bw)
    out = np.zeros((side, side, 3), dtype=np.uint8)
    top, left = (side - bh) // 2, (side - bw) // 2
    out[top:top + bh, left:left + bw] = box
    return out
