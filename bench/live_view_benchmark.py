#!/usr/bin/env python3
"""What watching training costs: `ag2gs train` with and without `--view`,
the viewed runs with a client that does what the page does (asks for the
progress every 500 ms and, when the iteration changed, a new picture of
the first training view at WxH). Runs alternate (plain, viewed, plain,
...) so a busy machine affects both alike; prints each run's training
seconds (metrics.json, evaluations excluded) and the ratio of the medians.

  bench/live_view_benchmark.py SCENE_DIR [--iters 2000] [-r 1] [--runs 2] [--size 640x480] [--binary build/ag2gs]
"""
import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def train(binary, scene, out, args, view, size):
    cmd = [binary, "train", scene, "-o", out, "--force", "--seed", "1", "--stages", "1", "--log-every", "0"] + args
    if not view:
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return json.load(open(os.path.join(out, "metrics.json")))["train_seconds"], 0
    p = subprocess.Popen(cmd + ["--view", "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    base, pictures = None, 0
    for line in p.stdout:
        m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        if m:
            base = "http://127.0.0.1:%s" % m.group(1)
            break
    threading.Thread(target=lambda: [None for _ in p.stdout], daemon=True).start()
    w, h = size.split("x")
    view = urllib.parse.quote(json.load(urllib.request.urlopen(base + "/api/info"))["views"][0]["name"])
    shown = -1
    while True:
        t = json.load(urllib.request.urlopen(base + "/api/train"))
        if t["iteration"] != shown:
            shown = t["iteration"]
            urllib.request.urlopen(base + "/api/render?view=%s&w=%s&h=%s&client=bench" % (view, w, h)).read()
            pictures += 1
        if t["finished"]:
            break
        time.sleep(0.5)
    p.send_signal(2)
    p.wait(60)
    return json.load(open(os.path.join(out, "metrics.json")))["train_seconds"], pictures


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--iters", default="2000")
    ap.add_argument("-r", default="1")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--binary", default=os.path.join(ROOT, "build", "ag2gs"))
    a = ap.parse_args()
    work = tempfile.mkdtemp(prefix="ag2gs_live_bench_")
    plain, viewed = [], []
    try:
        for run in range(a.runs):
            for is_view in (False, True):
                s, n = train(a.binary, a.scene, os.path.join(work, "m"), ["--iters", a.iters, "-r", a.r],
                             is_view, a.size)
                (viewed if is_view else plain).append(s)
                print("%s run %d: %.1f s%s" % ("--view" if is_view else "plain ", run + 1, s,
                                               " (%d pictures)" % n if is_view else ""), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print("median: plain %.1f s, --view with a client %.1f s: x%.3f" %
          (statistics.median(plain), statistics.median(viewed), statistics.median(viewed) / statistics.median(plain)))


if __name__ == "__main__":
    sys.exit(main())
