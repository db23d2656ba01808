"""The views of a scene folder, named as ag2gs names them.

ag2gs names a view's semantic files by its stem: the image's file name without
folder or extension (host/scene/scene.cpp), so images/a/0001.png and
images/0001.png would collide; that is refused here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from .errors import InputError

# What OpenCV (ag2gs's decoder) and PIL both read.
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}

# EXIF orientations that swap width and height (OpenCV applies them on load).
_TRANSPOSING_ORIENTATIONS = {5, 6, 7, 8}


@dataclass
class SceneImage:
    path: Path  # the file
    name: str  # relative to images/, with '/' separators
    stem: str  # file name without folder or extension: <stem>_s.npy
    width: int  # after EXIF orientation, as ag2gs decodes it
    height: int


def _oriented_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            w, h = im.size
            orientation = im.getexif().get(0x0112, 1)
    except Exception as e:  # PIL raises several types for damaged files
        raise InputError(f"{path}: cannot be read as an image ({e}); remove it from images/ or replace it")
    return (h, w) if orientation in _TRANSPOSING_ORIENTATIONS else (w, h)


def list_scene_images(scene_dir: Path) -> list[SceneImage]:
    """Every image under SCENE/images/ (recursively), sorted by name, all of one size."""
    images_dir = scene_dir / "images"
    if not images_dir.is_dir():
        raise InputError(f"{images_dir}: no such folder; SCENE_DIR must hold the photos in images/")
    found: list[SceneImage] = []
    for root, dirs, files in os.walk(images_dir):
        dirs.sort()
        for f in sorted(files):
            p = Path(root) / f
            if p.suffix.lower() in IMAGE_SUFFIXES:
                found.append(SceneImage(p, p.relative_to(images_dir).as_posix(), p.stem, 0, 0))
    if not found:
        raise InputError(f"{images_dir}: no images ({', '.join(sorted(IMAGE_SUFFIXES))}); put the scene's photos there")
    found.sort(key=lambda s: s.name)
    by_stem: dict[str, SceneImage] = {}
    for s in found:
        if s.stem in by_stem:
            raise InputError(f"{by_stem[s.stem].path} and {s.path} have the same stem '{s.stem}', which names both "
                             "views' language_features files; rename one")
        by_stem[s.stem] = s
    for s in found:
        s.width, s.height = _oriented_size(s.path)
    first = found[0]
    for s in found[1:]:
        if (s.width, s.height) != (first.width, first.height):
            raise InputError(f"images of mixed sizes: {first.path} is {first.width}x{first.height} but {s.path} is "
                             f"{s.width}x{s.height}; SAM's masks must match the views, so give every view the same "
                             "size (undistort or resize them all the same way)")
    return found


def working_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """The size masks are made at: the image's, or scaled so its longer side
    is max_side. SAM's masks come from a 256 x 256 grid over its 1024 x 1024
    input, so a larger mask image holds no more detail; ag2gs rescales masks
    to its views (nearest neighbour)."""
    if max(width, height) <= max_side:
        return width, height
    scale = max_side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def load_rgb(image: SceneImage, size: tuple[int, int]) -> np.ndarray:
    """[H, W, 3] uint8 RGB at size (W, H), EXIF orientation applied as OpenCV
    does, reduced with an area filter."""
    with Image.open(image.path) as im:
        im = ImageOps.exif_transpose(im).convert("RGB")
        if im.size != (image.width, image.height):
            raise InputError(f"{image.path}: decoded as {im.size[0]}x{im.size[1]}, its header says "
                             f"{image.width}x{image.height}; the file is damaged")
        if im.size != size:
            im = im.resize(size, Image.Resampling.BOX)
        return np.asarray(im)
