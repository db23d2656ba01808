"""Rendering through Python against the program's batch render, side by side:
the same model, views and outputs, on the same device, in one run.

    PYTHONPATH=build/python python3 bench/python_render_benchmark.py MODEL_DIR SCENE_DIR

Renders every view of SCENE_DIR (make one of 100 views with `ag2gs synth
DIR --views 100`) once each way and prints the seconds and their ratio. The
program's time is its whole batch render as a user runs it (start, model
load, PNG files); Python's is Model.load and the renders into arrays, in an
interpreter already started."""

import argparse
import os
import subprocess
import tempfile
import time

import numpy as np

import ag2gs

SRC = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("model")
    p.add_argument("scene")
    p.add_argument("--binary", default=os.path.join(SRC, "build", "ag2gs"))
    a = p.parse_args()
    scene = ag2gs.Scene(a.scene)
    n = len(scene.views)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run([a.binary, "render", a.model, "--scene", a.scene, "-o", os.path.join(tmp, "r"), "-q"],
                       check=True)
        cli_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = ag2gs.Model.load(a.model)
    frames = [model.render(v.camera)["rgb"] for v in scene.views]
    py_s = time.perf_counter() - t0
    assert len(frames) == n
    print(f"{n} views: program {cli_s:.2f} s ({n / cli_s:.1f} views/s, PNG files), Python {py_s:.2f} s "
          f"({n / py_s:.1f} views/s, arrays); Python / program = {py_s / cli_s:.3f}")


if __name__ == "__main__":
    main()
