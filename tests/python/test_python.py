"""The Python module against the program: same bytes, same arrays, same
selections; callbacks; errors; determinism across thread counts.

Run by CTest (python_module) with PYTHONPATH=BUILD/python and the viewer
fixture's models in BUILD/test_view (tests/viewer/make_models.sh)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import ag2gs

SRC = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
SAMPLE = os.path.join(SRC, "data_samples", "synth_small")
BUILD = os.environ.get("AG2GS_BUILD_DIR", os.path.join(SRC, "build"))
BINARY = os.environ.get("AG2GS_BINARY", os.path.join(BUILD, "ag2gs"))
FIXTURE = os.path.join(BUILD, "test_view")


def cli(*args):
    r = subprocess.run([BINARY, *map(str, args)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r


@pytest.fixture(scope="module")
def scene():
    return ag2gs.Scene(SAMPLE, eval=True)


@pytest.fixture(scope="module")
def model():
    return ag2gs.Model.load(os.path.join(FIXTURE, "model"))


def test_devices_lists_the_programs_devices():
    devs = ag2gs.devices()
    assert devs and {"index", "name", "platform", "type"} <= set(devs[0])
    listed = cli("devices").stdout + cli("devices").stderr
    assert devs[0]["name"] in listed


def test_scene_views_images_and_cameras(scene):
    assert len(scene.views) > 0
    v = scene.views[0]
    img = v.image
    assert img.dtype == np.uint8 and img.shape == (v.camera.height, v.camera.width, 3)
    assert v.camera.K.shape == (3, 3) and v.camera.R.shape == (3, 3) and v.camera.t.shape == (3,)
    # R is a rotation (world to camera).
    assert np.allclose(v.camera.R @ v.camera.R.T, np.eye(3), atol=1e-9)
    assert scene.test_views and all(not t.test for t in scene.train_views)


def test_training_through_python_gives_the_programs_bytes(tmp_path):
    settings = dict(iters=40, stages=(1,), seed=3)
    ag2gs.train(ag2gs.Scene(SAMPLE, eval=True), tmp_path / "py", quiet=True, **settings)
    cli("train", SAMPLE, "-o", tmp_path / "cli", "--eval", "--iters", 40, "--stages", 1, "--seed", 3, "--quiet")
    for f in ("model.ag2gs", "point_cloud.ply"):
        assert (tmp_path / "py" / f).read_bytes() == (tmp_path / "cli" / f).read_bytes(), f


def test_callback_sees_every_iteration_and_can_stop(tmp_path):
    seen = []

    def cb(it, m):
        seen.append((it, m))
        return it < 5

    with pytest.raises(ag2gs.Stopped):
        ag2gs.train(SAMPLE, tmp_path / "m", callback=cb, iters=30, stages=(1,), seed=1, quiet=True)
    assert [it for it, _ in seen] == [1, 2, 3, 4, 5]
    for field in ("iteration", "iterations", "stage", "loss", "psnr", "l1", "ssim", "anchors", "gaussians", "eta_s"):
        assert field in seen[0][1], field
    assert seen[0][1]["iterations"] == 30
    # Stopped as Ctrl-C stops: the checkpoint is there and the run continues from it.
    assert (tmp_path / "m" / "checkpoint.ag2gs").exists()
    resumed = []
    ag2gs.train(SAMPLE, tmp_path / "m", resume=True, quiet=True, callback=lambda it, m: resumed.append(it))
    assert resumed[0] == 6 and resumed[-1] == 30
    assert (tmp_path / "m" / "model.ag2gs").exists()


def test_a_callback_that_raises_stops_the_run_and_reraises(tmp_path):
    def cb(it, m):
        raise KeyError("from the callback")

    with pytest.raises(KeyError, match="from the callback"):
        ag2gs.train(SAMPLE, tmp_path / "m", callback=cb, iters=20, stages=(1,), seed=1, quiet=True)


def test_render_arrays_equal_the_programs_files(tmp_path, scene, model):
    cam = scene.views[0].camera
    out = model.render(cam, outputs=("rgb", "depth", "alpha", "feature", "instance"))
    h, w = cam.height, cam.width
    assert out["rgb"].shape == (h, w, 3) and out["rgb"].dtype == np.float32
    assert out["depth"].shape == (h, w) and out["instance"].dtype == np.int32
    cli("render", os.path.join(FIXTURE, "model"), "--scene", SAMPLE, "-o", tmp_path / "r", "--views",
        scene.views[0].name, "--outputs", "rgb,depth,alpha,feature,instance", "-r", 1)
    stem = scene.views[0].stem
    for o in ("depth", "alpha", "feature", "instance"):
        ref = np.load(tmp_path / "r" / o / f"{stem}.npy")
        assert np.array_equal(ref, out[o].astype(ref.dtype)), o
    # rgb: the program writes 8-bit PNGs of the same floats.
    png = ag2gs.read_image(tmp_path / "r" / "rgb" / f"{stem}.png")
    assert np.array_equal(png, ag2gs.to_uint8(out["rgb"]))


def test_render_is_repeatable_and_honours_the_background(scene, model):
    cam = scene.views[1].camera
    a = model.render(cam)["rgb"]
    b = model.render(cam)["rgb"]
    assert np.array_equal(a, b)
    black = model.render(cam, outputs=("rgb", "alpha"), background=(0, 0, 0))
    white = model.render(cam, background=(1, 1, 1))["rgb"]
    # Over a background the colour gains T * background, T = 1 - alpha.
    assert np.allclose(white - black["rgb"], (1 - black["alpha"])[..., None], atol=1e-5)


def test_queries_select_the_programs_anchors(model, scene):
    text = model.query(text="blue mug", vocab=os.path.join(SAMPLE, "vocab.json"), scene=scene)
    with open(os.path.join(FIXTURE, "query_text", "selection.json")) as f:
        assert text.anchors.tolist() == sorted(json.load(f)["anchors"])
    click = model.query(click=("view_000", 70, 62))
    with open(os.path.join(FIXTURE, "query_click", "selection.json")) as f:
        ref = json.load(f)
    assert click.anchors.tolist() == sorted(ref["anchors"])
    # The mask of the selection equals the program's masks/view_000.png in its pixel count.
    v0 = scene.view("view_000")
    m = click.mask(v0.camera)
    assert m.dtype == np.bool_ and m.shape == (v0.camera.height, v0.camera.width)
    pixels = [x["pixels"] for x in ref["masks"] if x["view"] == v0.name][0]
    assert int(m.sum()) == pixels


def test_remove_and_simulate_write_what_the_program_writes(tmp_path, model, scene):
    sel = model.query(click=("view_000", 70, 62), scene=scene)
    saved = sel.save(tmp_path / "selection.json")
    with open(saved) as f:
        assert json.load(f)["anchors"] == sel.anchors.tolist()
    assert os.listdir(tmp_path) == ["selection.json"]  # no temporary file left beside it
    removed = model.remove(sel, scene, tmp_path / "removed")
    assert os.path.exists(os.path.join(removed.path, "model.ag2gs"))
    out = model.simulate(sel, scene, tmp_path / "sim", frames=2, fps=50)
    assert os.listdir(out)


def test_bad_inputs_raise_with_the_programs_messages(tmp_path, model, scene):
    with pytest.raises(FileNotFoundError, match="no such scene directory"):
        ag2gs.Scene(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="no such model folder"):
        ag2gs.Model.load(tmp_path / "missing")
    with pytest.raises(ValueError, match="unknown output 'normals'"):
        model.render(scene.views[0].camera, outputs=("rgb", "normals"))
    bad = scene.views[0].camera
    bad = ag2gs.Camera(0, bad.height, bad.fx, bad.fy, bad.cx, bad.cy, bad.R, bad.t, bad.name)
    with pytest.raises(ValueError):
        model.render(bad)
    c = scene.views[0].camera
    with pytest.raises(ValueError, match="not a rotation"):
        model.render(ag2gs.Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, 2 * c.R, c.t, c.name))
    with pytest.raises(ValueError, match="--text needs --vocab"):
        model.query(text="blue mug", scene=scene)
    with pytest.raises(ValueError, match="--iters"):
        ag2gs.train(SAMPLE, tmp_path / "m", iters=-5)
    model.query(click=("view_000", 70, 62), scene=scene)  # the scene for masks
    with pytest.raises(ValueError, match="is not one of the model's"):
        ag2gs.Selection(model, [10 ** 7]).mask(scene.views[0].camera)
    with pytest.raises(IndexError):
        scene._core.image(len(scene.views))
    with pytest.raises(ValueError, match="resolution must be >= 1"):
        ag2gs.Scene(SAMPLE, resolution=0)


def test_training_is_deterministic_across_thread_counts(tmp_path):
    code = ("import ag2gs, sys; ag2gs.train(sys.argv[1], sys.argv[2], iters=20, stages=(1,), seed=7, quiet=True)")
    for threads in (1, 2):
        env = dict(os.environ, POCL_MAX_PTHREAD_COUNT=str(threads), OMP_NUM_THREADS=str(threads))
        r = subprocess.run([sys.executable, "-c", code, SAMPLE, str(tmp_path / f"t{threads}")], env=env,
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    assert (tmp_path / "t1" / "model.ag2gs").read_bytes() == (tmp_path / "t2" / "model.ag2gs").read_bytes()


def test_docstrings_carry_the_programs_help():
    assert "--iters" in ag2gs.train.__doc__ and "--seed" in ag2gs.train.__doc__
    assert "--material" in ag2gs.Model.simulate.__doc__ or "--frames" in ag2gs.Model.simulate.__doc__
    assert "--selection" in ag2gs.Model.remove.__doc__


def test_cameras_scale_as_the_program_scales_them(model):
    full = ag2gs.Scene(SAMPLE).views[3].camera
    half = ag2gs.Scene(SAMPLE, resolution=2).views[3].camera
    mine = full.scaled(2)
    for f in ("width", "height", "fx", "fy", "cx", "cy", "name"):
        assert getattr(mine, f) == getattr(half, f), f
    assert np.array_equal(mine.R, half.R) and np.array_equal(mine.t, half.t)
    big = full.resized(2 * full.width, 2 * full.height)
    assert model.render(big)["rgb"].shape == (2 * full.height, 2 * full.width, 3)
    with pytest.raises(ValueError, match="vanishes"):
        full.scaled(10000)


def test_a_stop_asked_at_the_last_iteration_ends_a_finished_run(tmp_path):
    model = ag2gs.train(SAMPLE, tmp_path / "m", callback=lambda it, m: it < m["iterations"], iters=10, stages=(1,),
                        seed=1, quiet=True)
    assert (tmp_path / "m" / "model.ag2gs").exists() and model.metrics["iterations"] == 10


def test_keywords_become_the_programs_flags(capfd):
    flags = ag2gs._settings({"far_shell": False, "init_children_at_points": True, "iters": 300, "stages": (1, 2),
                             "eval": True, "seed": None})
    assert flags == ["--far-shell=false", "--init-children-at-points=true", "--iters", "300", "--stages", "1,2",
                     "--eval=true"]
    capfd.readouterr()
    assert ag2gs.run("train", SAMPLE, "-o", "/nonexistent/m", *flags, "--print-config") == 0
    config = json.loads(capfd.readouterr().out)
    assert config["far_shell"] is False and config["anchors"]["init_children_at_points"] is True
    assert config["iterations"] == 300
