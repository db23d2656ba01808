"""The viewer's page in headless Chromium, as a user meets it: preview frames
shown per second during a drag orbit of 60 steps, and the time from the
mouse's release to the full-size frame.

    /usr/bin/python3 bench/view_page_benchmark.py MODEL_DIR --scene SCENE_DIR [--runs 3]

Needs chromium, chromium-driver and python3-selenium (scripts/install_deps.sh
--test) and build/ag2gs (or $AG2GS_BINARY)."""

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests", "viewer"))

from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402

from test_view_browser import chromium  # noqa: E402
from viewer_util import Viewer  # noqa: E402


def wait(d, script, timeout=60):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if d.execute_script(script):
            return
        time.sleep(0.02)
    raise TimeoutError(script)


SETTLED = ("const s = window.ag2gs; return s.frames > 0 && !s.inFlight && !s.pending && !s.moving && s.shown "
           "&& !s.shown.includes('quality=40');")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("model")
    p.add_argument("--scene", required=True)
    p.add_argument("--runs", type=int, default=3)
    a = p.parse_args()
    v = Viewer(a.model, "--scene", a.scene)
    d = chromium()
    try:
        d.get(v.base + "/")
        wait(d, SETTLED)
        fps, moves, refine, orbit_fps, size = [], [], [], [], None
        for _ in range(a.runs):
            # A mouse drag of 60 steps (Chromium's input events, 16 ms apart).
            f0 = d.execute_script("return window.ag2gs.frames;")
            frame = d.find_element(By.ID, "frame")
            t0 = time.time()
            chain = ActionChains(d, duration=16).move_to_element(frame).click_and_hold()
            for _ in range(60):
                chain.move_by_offset(3, 0)
            chain.release().perform()
            drag_s = time.time() - t0
            wait(d, SETTLED)
            s = d.execute_script("const s = window.ag2gs; return [s.frames, s.refineMs];")
            fps.append((s[0] - f0 - 1) / drag_s)  # the last frame is the full-size one
            moves.append(60 / drag_s)
            refine.append(s[1])
            # The same orbit driven by the page every animation frame (60 steps):
            # what the pipeline delivers when input is not the limit.
            r = d.execute_async_script("""
              const done = arguments[0], s = window.ag2gs, f0 = s.frames, t0 = performance.now();
              let n = 0;
              const step = () => {
                if (n++ < 60) { s.moving = true; orbit(0.01, 0); requestAnimationFrame(step); }
                else done({ frames: s.frames - f0, seconds: (performance.now() - t0) / 1000,
                            w: +/[?&]w=(\\d+)/.exec(s.shown)[1], h: +/[?&]h=(\\d+)/.exec(s.shown)[1] });
              };
              requestAnimationFrame(step);""")
            orbit_fps.append(r["frames"] / r["seconds"])
            size = (r["w"], r["h"])
            wait(d, SETTLED)
        med = statistics.median
        print(f"mouse drag of 60 steps: {med(fps):.1f} preview frames/s for {med(moves):.1f} moves/s; full-size "
              f"frame {med(refine):.0f} ms after the release (runs: {', '.join(f'{x:.0f}' for x in refine)})")
        print(f"orbit of 60 animation frames: {med(orbit_fps):.1f} preview frames/s (runs: "
              f"{', '.join(f'{x:.1f}' for x in orbit_fps)}), the last preview {size[0]}x{size[1]}")
    finally:
        d.quit()
        v.stop()


if __name__ == "__main__":
    main()
