"""ag2gs-features (python/features/) with randomly initialised models of the
real architectures (SAM vit_b, CLIP ViT-B-32; nothing downloaded): the
layout's files, shapes, dtypes and ids; the crop geometry; the tokenizer and
text path against open_clip's; what ag2gs's reader, `train` and `query` make
of the output; and the errors for bad inputs, raised before any work.

Run by CTest (features) with the venv of scripts/install_features.sh,
PYTHONPATH=python/features and AG2GS_BINARY=the program."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

SRC = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
sys.path.insert(0, os.path.join(SRC, "python", "features"))
BINARY = os.environ.get("AG2GS_BINARY", os.path.join(SRC, "build", "ag2gs"))

from ag2gs_features.crops import mask_bbox, mask_crop  # noqa: E402
from ag2gs_features.layout import build_layout, id_map, level_order  # noqa: E402

SEED = 1
CLIP_ARCH = "ViT-B-32"
WIDTH, HEIGHT, VIEWS = 64, 48, 2
PHRASES = ["green box", "purple ball", "a photo of a cat", "the mug's handle", "café table"]
# Cheap settings: the smallest SAM, a 4 x 4 prompt grid, score filters off
# (--random-weights), masks of 4 pixels and more.
RANDOM_MODELS = ["--random-weights", str(SEED), "--sam-model", "vit_b", "--clip-model", CLIP_ARCH,
                 "--points-per-side", "4", "--min-mask-area", "4", "--device", "cpu"]


def tool(*args):
    env = dict(os.environ, PYTHONPATH=os.path.join(SRC, "python", "features"))
    return subprocess.run([sys.executable, "-m", "ag2gs_features", *map(str, args)], capture_output=True, text=True,
                          env=env)


def ag2gs(*args):
    r = subprocess.run([BINARY, *map(str, args)], capture_output=True, text=True)
    assert r.returncode == 0, f"ag2gs {' '.join(map(str, args))}:\n{r.stdout}\n{r.stderr}"
    return r


def make_scene(path):
    """A synthetic scene with its images and COLMAP model but no semantic inputs."""
    ag2gs("synth", path, "--views", VIEWS, "--seed", 1, "--width", WIDTH, "--height", HEIGHT, "--points", 500)
    for extra in ("language_features", "masks"):
        shutil.rmtree(os.path.join(path, extra))
    os.remove(os.path.join(path, "vocab.json"))
    return path


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The tool run once on a 2-view scene, masks, features and vocabulary."""
    scene = make_scene(str(tmp_path_factory.mktemp("features") / "scene"))
    phrases = os.path.join(os.path.dirname(scene), "phrases.txt")
    with open(phrases, "w", encoding="utf-8") as f:
        f.write("# test phrases\n" + "\n".join(PHRASES) + "\n\n")
    r = tool(scene, *RANDOM_MODELS, "--vocab", phrases)
    assert r.returncode == 0, r.stderr
    return {"scene": scene, "stderr": r.stderr, "lf": os.path.join(scene, "language_features")}


def stems(scene):
    return sorted(os.path.splitext(n)[0] for n in os.listdir(os.path.join(scene, "images")))


def load_pair(lf, stem):
    return np.load(os.path.join(lf, stem + "_s.npy")), np.load(os.path.join(lf, stem + "_f.npy"))


def test_every_view_gets_a_pair_of_the_layouts_shapes_and_dtypes(run):
    assert sorted(os.listdir(run["lf"])) == sorted(f"{s}_{k}.npy" for s in stems(run["scene"]) for k in "sf")
    for stem in stems(run["scene"]):
        s, f = load_pair(run["lf"], stem)
        assert s.dtype == np.float32 and s.shape == (4, HEIGHT, WIDTH)
        assert f.dtype == np.float32 and f.ndim == 2 and f.shape[1] == 512 and len(f) > 0
        assert np.all(np.isfinite(f))
        np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1, atol=1e-5)


def test_ids_are_integers_in_range_and_cumulative_across_levels(run):
    for stem in stems(run["scene"]):
        s, f = load_pair(run["lf"], stem)
        assert np.all(s == np.floor(s)) and s.min() >= -1 and s.max() < len(f)
        previous_max = -1
        for level in range(4):
            ids = np.unique(s[level][s[level] >= 0])
            assert len(ids) > 0, f"{stem}: level {level} has no mask"
            assert ids.min() > previous_max, f"{stem}: level {level}'s ids do not follow the previous level's"
            previous_max = ids.max()


def test_progress_line_per_image_with_eta(run):
    lines = [ln for ln in run["stderr"].splitlines() if "ETA" in ln]
    assert [ln.split("]")[0].split("[")[-1] for ln in lines] == [f"{i}/{VIEWS}" for i in range(1, VIEWS + 1)]
    assert "masks default/small/medium/large" in lines[0]
    assert "random-weights" in run["stderr"]


def test_ag2gs_reads_the_output(run):
    info = ag2gs("info", run["scene"]).stdout + ag2gs("info", run["scene"]).stderr
    assert "semantics: language_features" in info
    assert "feature dimension: 512" in info
    for level in range(4):
        r = ag2gs("info", run["scene"], "--sam-level", level)
        assert "masks per view" in r.stdout + r.stderr


def test_three_stage_training_and_text_query_on_the_output(run, tmp_path):
    model = tmp_path / "model"
    # With random features stage 3 needs lenient settings to form clusters at all.
    r = ag2gs("train", run["scene"], "-o", model, "--iters", 30, "--stages", "1,2,3", "--log-every", 0,
              "--min-cluster-size", 1, "--match-score", -1, "--cluster-distance", 1)
    stage3 = [ln for ln in (r.stdout + r.stderr).splitlines() if "stage 3:" in ln and "clusters" in ln]
    assert stage3 and " 0 with a language feature" not in stage3[0], r.stdout + r.stderr
    vocab = os.path.join(run["scene"], "vocab.json")
    ag2gs("query", model, "--scene", run["scene"], "-o", tmp_path / "q", "--text", PHRASES[0], "--vocab", vocab)
    with open(tmp_path / "q" / "selection.json") as f:
        assert json.load(f)


def test_crop_is_the_masked_box_padded_to_a_centred_square():
    rgb = np.arange(10 * 12 * 3, dtype=np.uint8).reshape(10, 12, 3) + 1  # no zero pixels
    mask = np.zeros((10, 12), dtype=bool)
    mask[2:5, 3:10] = True  # a 3 x 7 box ...
    mask[3, 5] = False  # ... with a hole
    mask[5, 9] = True  # and a tail: the box is rows 2..5, columns 3..9 (4 x 7)
    assert mask_bbox(mask) == (3, 2, 10, 6)
    crop = mask_crop(rgb, mask)
    assert crop.shape == (7, 7, 3) and crop.dtype == np.uint8
    # 4 rows in a 7-row square: 1 row of padding above, 2 below.
    assert np.all(crop[0] == 0) and np.all(crop[5:] == 0)
    box = crop[1:5]
    inside = mask[2:6, 3:10]
    np.testing.assert_array_equal(box[inside], rgb[2:6, 3:10][inside])
    assert np.all(box[~inside] == 0)  # background and the hole are black
    tall = np.zeros((10, 12), dtype=bool)
    tall[0:10, 11] = True  # a 10 x 1 column at the right edge
    c = mask_crop(rgb, tall)
    assert c.shape == (10, 10, 3)
    np.testing.assert_array_equal(c[:, 4], rgb[:, 11])
    assert np.all(np.delete(c, 4, axis=1) == 0)


def test_masks_of_large_images_are_made_at_most_max_side_long():
    from ag2gs_features.scene_images import working_size

    assert working_size(64, 48, 1024) == (64, 48)
    assert working_size(1024, 700, 1024) == (1024, 700)
    assert working_size(4000, 3000, 1024) == (1024, 768)
    assert working_size(3000, 4000, 1024) == (768, 1024)
    assert working_size(5000, 10, 1024) == (1024, 2)


def test_levels_paint_smaller_masks_over_larger_and_offset_ids():
    big = np.zeros((4, 4), dtype=bool)
    big[:, :] = True
    small = np.zeros((4, 4), dtype=bool)
    small[1:3, 1:3] = True
    masks = np.stack([small, big])
    order = level_order(masks)
    assert list(order) == [1, 0]
    ids = id_map(masks[order])
    assert ids[0, 0] == 0 and ids[1, 1] == 1  # the small mask stays visible
    levels = [masks[order], masks[order][:1], np.zeros((0, 4, 4), bool), masks[order][1:]]
    feats = [np.eye(3, dtype=np.float32)[[0, 1]], np.eye(3, dtype=np.float32)[[2]], np.zeros((0, 3), np.float32),
             np.eye(3, dtype=np.float32)[[0]]]
    s, f = build_layout(levels, feats)
    assert s.shape == (4, 4, 4) and f.shape == (4, 3)
    assert set(np.unique(s[1])) == {2} and set(np.unique(s[2])) == {-1} and set(np.unique(s[3])) == {-1, 3}


@pytest.fixture(scope="module")
def clip():
    import torch

    from ag2gs_features.clip_features import load_clip

    return load_clip(CLIP_ARCH, None, torch.device("cpu"), SEED)


def test_tokenizer_ids_are_open_clips(clip):
    import open_clip

    from ag2gs_features.clip_features import tokenize

    ours = tokenize(clip, PHRASES)
    theirs = open_clip.get_tokenizer(CLIP_ARCH)(PHRASES)
    assert ours.dtype == theirs.dtype and ours.shape == theirs.shape == (len(PHRASES), 77)
    assert bool((ours == theirs).all())
    # OpenAI's CLIP BPE: <start_of_text> a photo of a cat <end_of_text>, then zeros.
    assert ours[2, :8].tolist() == [49406, 320, 1125, 539, 320, 2368, 49407, 0]


def test_vocabulary_is_the_text_towers_normalised_output(run, clip):
    import open_clip
    import torch

    with open(os.path.join(run["scene"], "vocab.json"), encoding="utf-8") as f:
        vocab = json.load(f)
    assert list(vocab) == PHRASES
    with torch.inference_mode():
        ref = clip.model.encode_text(open_clip.get_tokenizer(CLIP_ARCH)(PHRASES)).numpy().astype(np.float64)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(np.array([vocab[p] for p in PHRASES]), ref, atol=1e-5)


def test_a_second_run_is_refused_without_force(run):
    before = {n: os.path.getmtime(os.path.join(run["lf"], n)) for n in os.listdir(run["lf"])}
    r = tool(run["scene"], *RANDOM_MODELS)
    assert r.returncode == 2 and "--force" in r.stderr
    assert {n: os.path.getmtime(os.path.join(run["lf"], n)) for n in os.listdir(run["lf"])} == before


def bad(*args):
    r = tool(*args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ag2gs-features: error: "), r.stderr
    return lines[0]


@pytest.fixture
def scene_copy(run, tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(os.path.join(run["scene"], "images"), dst / "images")
    return dst


def test_missing_weights_file_names_the_flag_and_file(scene_copy):
    missing = scene_copy / "sam_vit_b_01ec64.pth"
    line = bad(scene_copy, "--sam-model", "vit_b", "--sam-checkpoint", missing, "--clip-model", CLIP_ARCH,
               "--clip-checkpoint", "laion2b_s34b_b79k")
    assert f"--sam-checkpoint {missing}: no such file" in line
    line = bad(scene_copy, "--sam-model", "vit_b", "--sam-checkpoint", missing)
    assert "--clip-checkpoint is required" in line
    clip_file = scene_copy / "open_clip_model.safetensors"
    line = bad("--vocab", scene_copy / "none.txt", "-o", scene_copy / "v.json", "--clip-checkpoint", clip_file)
    assert f"--clip-checkpoint {clip_file}: no such file" in line
    assert not (scene_copy / "language_features").exists()


def test_a_file_that_is_not_a_checkpoint_is_named(scene_copy):
    junk = scene_copy / "sam.pth"
    junk.write_bytes(b"not a checkpoint")
    line = bad(scene_copy, "--sam-model", "vit_b", "--sam-checkpoint", junk, "--clip-model", CLIP_ARCH,
               "--clip-checkpoint", "laion2b_s34b_b79k", "--device", "cpu")
    assert f"--sam-checkpoint {junk}: not a PyTorch checkpoint" in line
    import torch

    other = scene_copy / "other.pth"  # a state dict of some other model
    torch.save({"image_encoder.other": torch.zeros(3)}, other)
    line = bad(scene_copy, "--sam-model", "vit_b", "--sam-checkpoint", other, "--clip-model", CLIP_ARCH,
               "--clip-checkpoint", "laion2b_s34b_b79k", "--device", "cpu")
    assert f"--sam-checkpoint {other} does not fit --sam-model vit_b" in line and "vit_h" in line
    (scene_copy / "p.txt").write_text("mug\n")
    line = bad("--vocab", scene_copy / "p.txt", "-o", scene_copy / "v.json", "--clip-model", CLIP_ARCH, "--clip-checkpoint",
               other, "--device", "cpu")
    assert f"--clip-checkpoint {other} cannot be loaded as --clip-model {CLIP_ARCH}" in line
    assert not (scene_copy / "language_features").exists() and not (scene_copy / "v.json").exists()


def test_unknown_architectures_list_the_valid_names(scene_copy):
    line = bad(scene_copy, "--random-weights", 1, "--sam-model", "vit_x", "--clip-model", CLIP_ARCH)
    assert "--sam-model vit_x" in line and "vit_b, vit_l, vit_h" in line
    line = bad(scene_copy, "--random-weights", 1, "--sam-model", "vit_b", "--clip-model", "ViT-B/32")
    assert "--clip-model ViT-B/32" in line and "ViT-B-32" in line
    line = bad(scene_copy, "--sam-model", "vit_b", "--sam-checkpoint", __file__, "--clip-model", CLIP_ARCH,
               "--clip-checkpoint", "no_such_tag")
    assert "--clip-checkpoint no_such_tag" in line and "laion2b_s34b_b79k" in line
    assert not (scene_copy / "language_features").exists()


def test_images_of_mixed_sizes_name_two_files_and_sizes(scene_copy):
    from PIL import Image

    odd = scene_copy / "images" / "view_zzz.png"
    Image.new("RGB", (WIDTH + 1, HEIGHT)).save(odd)
    line = bad(scene_copy, *RANDOM_MODELS)
    assert "mixed sizes" in line and f"{WIDTH}x{HEIGHT}" in line and f"{odd} is {WIDTH + 1}x{HEIGHT}" in line
    assert "view_000.png" in line
    assert not (scene_copy / "language_features").exists()


def test_two_images_with_one_stem_are_named(scene_copy):
    (scene_copy / "images" / "sub").mkdir()
    shutil.copy(scene_copy / "images" / "view_000.png", scene_copy / "images" / "sub" / "view_000.jpg")
    line = bad(scene_copy, *RANDOM_MODELS)
    assert "same stem 'view_000'" in line and "sub/view_000.jpg" in line


def test_no_images_and_no_scene(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "notes.txt").write_text("x")
    line = bad(tmp_path, *RANDOM_MODELS)
    assert "no images" in line and str(tmp_path / "images") in line
    line = bad(tmp_path / "nowhere", *RANDOM_MODELS)
    assert "no such folder" in line
    assert "nothing to do" in bad("--random-weights", 1)
