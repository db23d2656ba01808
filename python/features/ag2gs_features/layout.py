"""The LangSplat layout ag2gs reads (docs/formats.md section 3):
<stem>_s.npy float32 [4, H, W] mask ids per level (default, small, medium,
large; -1 none), ids cumulative across levels, indexing the rows of
<stem>_f.npy float32 [masks, D]."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def level_order(masks: np.ndarray) -> np.ndarray:
    """Mask indices by decreasing area (ties keep their order): painted in this
    order, a smaller mask lying on a larger one keeps its pixels."""
    area = masks.reshape(len(masks), -1).sum(axis=1)
    return np.argsort(-area, kind="stable")


def id_map(masks: np.ndarray) -> np.ndarray:
    """[H, W] float32: for masks [N, H, W] bool already in painting order, the
    index of the last mask covering each pixel, -1 where none does."""
    out = np.full(masks.shape[1:], -1, dtype=np.float32)
    for i, m in enumerate(masks):
        out[m] = i
    return out


def build_layout(levels: list[np.ndarray], features: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """levels: four [N_k, H, W] bool arrays, each in painting order; features:
    their [N_k, D] rows. Returns (s [4, H, W] float32, f [sum N_k, D] float32)
    with level k's ids offset by the masks of the levels before it."""
    maps, offset = [], 0
    for masks in levels:
        m = id_map(masks)
        m[m >= 0] += offset
        offset += len(masks)
        maps.append(m)
    return np.stack(maps).astype(np.float32), np.concatenate(features).astype(np.float32)


def _atomic_target(path: Path) -> Path:
    return path.with_name(f"{path.name}.tmp.{os.getpid()}")


def _write_npy(path: Path, array: np.ndarray) -> Path:
    tmp = _atomic_target(path)
    with open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())
    return tmp


def write_pair(out_dir: Path, stem: str, s: np.ndarray, f: np.ndarray) -> None:
    """Writes both files under temporary names, then renames them into place
    (features first, so a reader never finds mask ids without their rows for
    longer than one rename)."""
    tmp_s = _write_npy(out_dir / f"{stem}_s.npy", s)
    tmp_f = _write_npy(out_dir / f"{stem}_f.npy", f)
    os.replace(tmp_f, out_dir / f"{stem}_f.npy")
    os.replace(tmp_s, out_dir / f"{stem}_s.npy")


def write_vocabulary(path: Path, phrases: list[str], embeddings: np.ndarray) -> None:
    """vocab.json: {"phrase": [D floats], ...}, as ag2gs's read_vocabulary reads it."""
    vocab = {p: [float(x) for x in e] for p, e in zip(phrases, embeddings)}
    tmp = _atomic_target(path)
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(vocab, f, ensure_ascii=False)
        f.write("\n")
    os.replace(tmp, path)
