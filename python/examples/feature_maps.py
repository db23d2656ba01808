"""Renders the feature maps of every test view into one array and computes a
metric of your own on them: here, how far the features of an object found by
a text query lie from the rest of each view (over their spread inside the
object), next to the test PSNR.

    python3 python/examples/feature_maps.py MODEL_DIR SCENE_DIR
"""

import json
import os
import sys

import numpy as np

import ag2gs


def main(model_dir: str, scene_dir: str) -> None:
    model = ag2gs.Model.load(model_dir)
    scene = ag2gs.Scene(scene_dir, resolution=int(model.metrics.get("resolution", 1)), eval=True)
    views = scene.test_views or scene.views
    # One [V, H, W, 3] array of features and one of colours.
    frames = [model.render(v.camera, outputs=("rgb", "feature", "alpha")) for v in views]
    features = np.stack([f["feature"] for f in frames])
    rgb = np.stack([f["rgb"] for f in frames])
    images = np.stack([v.image for v in views]).astype(np.float32) / 255
    mse = float(np.mean((rgb - images) ** 2))
    print(f"{len(views)} test views, features {features.shape}, PSNR {10 * np.log10(1 / max(mse, 1e-12)):.2f} dB")

    # The user's metric: how far the rendered features of one object (found
    # by a text query, when the scene has a vocabulary) lie from the rest of
    # the view, over their spread inside the object.
    vocab = os.path.join(scene_dir, "vocab.json")
    if not os.path.exists(vocab) or not model.metrics.get("stages", {}).get("clusters"):
        return
    with open(vocab) as fp:
        phrase = next(iter(json.load(fp)))
    sel = model.query(text=phrase, vocab=vocab, scene=scene)
    ratios = []
    for v, f, fr in zip(views, features, frames):
        inside = sel.mask(v.camera) & (fr["alpha"] > 0.5)
        outside = ~sel.mask(v.camera) & (fr["alpha"] > 0.5)
        if inside.sum() < 10 or outside.sum() < 10:
            continue
        gap = np.linalg.norm(f[inside].mean(0) - f[outside].mean(0))
        ratios.append(gap / max(float(f[inside].std(0).mean()), 1e-6))
    print(f"'{phrase}': {len(sel)} anchors; feature gap / spread inside: "
          f"{np.mean(ratios) if ratios else float('nan'):.2f} over {len(ratios)} views")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
