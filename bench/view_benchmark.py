#!/usr/bin/env python3
"""`ag2gs view`: speed against picture error, through the HTTP API as the page uses it.

    bench/view_benchmark.py MODEL_DIR --scene SCENE_DIR [--vocab V.json] [--view NAME]
                            [--click X,Y] [--text PHRASE] [--repeats 7]

Starts `ag2gs view` (build/ag2gs, or $AG2GS_BINARY) on a free port and reports
- frame latency (render + JPEG + transfer, median of --repeats) at 400x300 and
  800x600 for JPEG quality 40 (the page's preview), 70 and 88 (the page's still
  frame), with the bytes sent and the PSNR of the decoded JPEG against the
  quality-100 frame of the same camera (the error the compression adds);
- preview frames per second: back-to-back half-size, quality-40 frames of a
  camera orbiting the scene, as the page requests them while one drags;
- query latency through the API (a click in --view at --click, and --text).

Needs numpy and Pillow (Debian python3-numpy, python3-pil) to decode frames.
"""
import argparse
import io
import json
import math
import os
import statistics
import sys
import time

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "viewer"))
from viewer_util import Viewer  # noqa: E402


def decode(jpeg):
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), dtype=np.float64) / 255.0


def psnr(a, b):
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def pose_query(v, w, h, yaw=0.0, centre=None):
    """v's camera scaled to w x h, turned by `yaw` about the vertical through `centre`."""
    R = np.array(v["R"], dtype=np.float64).reshape(3, 3)
    t = np.array(v["t"], dtype=np.float64)
    if yaw:
        up = -R[1]  # the view's up
        k = up / np.linalg.norm(up)
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        Q = np.eye(3) + math.sin(yaw) * K + (1 - math.cos(yaw)) * K @ K
        C = -R.T @ t
        C = centre + Q @ (C - centre)
        R = R @ Q.T
        t = -R @ C
    sx, sy = w / v["width"], h / v["height"]
    pose = ",".join(repr(float(x)) for x in list(R.reshape(-1)) + list(t))
    return "pose=%s&fx=%r&fy=%r&cx=%r&cy=%r&w=%d&h=%d" % (pose, v["fx"] * sx, v["fy"] * sy, v["cx"] * sx,
                                                          v["cy"] * sy, w, h)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--vocab")
    ap.add_argument("--view", help="the view to measure from (default: the first)")
    ap.add_argument("--click", help="X,Y: a click query in --view (full-size pixels)")
    ap.add_argument("--text", help="a text query (needs --vocab)")
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()

    args = [a.model, "--scene", a.scene] + (["--vocab", a.vocab] if a.vocab else [])
    v = Viewer(*args)
    try:
        status, info = v.json("/api/info")
        assert status == 200, info
        view = next(x for x in info["views"] if not a.view or a.view in (x["name"], x["stem"]))
        centre = np.array(info["centre"])
        print("model %s: %d anchors, %d Gaussians; view %s (%dx%d)" % (a.model, info["anchors"], info["gaussians"],
                                                                     view["name"], view["width"], view["height"]))
        print("| size | JPEG quality | frame latency (ms, median) | KiB | PSNR vs quality 100 (dB) |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for w, h in ((400, 300), (800, 600)):
            q = pose_query(view, w, h)
            reference = decode(v.request("/api/render?%s&quality=100" % q)[2])
            for quality in (40, 70, 88):
                times = []
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    status, _, jpeg = v.request("/api/render?%s&quality=%d" % (q, quality))
                    times.append(1000 * (time.perf_counter() - t0))
                    assert status == 200, jpeg[:200]
                print("| %dx%d | %d | %.1f | %.1f | %.2f |" % (w, h, quality, statistics.median(times),
                                                              len(jpeg) / 1024, psnr(decode(jpeg), reference)))
        for w, h in ((400, 300), (800, 600)):
            frames, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < 3.0:
                status, _, _ = v.request("/api/render?%s&quality=40" % pose_query(view, w // 2, h // 2,
                                                                                  0.02 * frames, centre))
                frames += 1
            dt = time.perf_counter() - t0
            print("preview while moving, %dx%d shown (%dx%d rendered, quality 40): %.1f frames/s" % (
                w, h, w // 2, h // 2, frames / dt))
        queries = []
        if a.click:
            x, y = (float(s) for s in a.click.split(","))
            queries.append(("click %s (%g, %g)" % (view["name"], x, y), {"view": view["name"], "x": x, "y": y}))
        if a.text:
            queries.append(("text \"%s\"" % a.text, {"text": a.text}))
        for name, body in queries:
            times, engine = [], []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                status, r = v.json("/api/query", body)
                times.append(1000 * (time.perf_counter() - t0))
                assert status == 200, r
                engine.append(r["ms"])
            print("query %s: %.1f ms through the API (%.1f ms in the engine), %d anchors" % (
                name, statistics.median(times), statistics.median(engine), r["anchors"]))
    finally:
        v.stop()


if __name__ == "__main__":
    main()
