#!/usr/bin/python3
"""`ag2gs view`'s page in a real browser: headless Chromium driven by
WebDriver (Debian chromium, chromium-driver, python3-selenium).

The page loads without console errors, a drag changes the picture, a click on
an object's pixel highlights that object (the highlighted pixels are the
pixels of /api/mask), a text query selects the named object (against the
generated scene's exact object ids), keys move between views. A screenshot is
kept at BUILD/test_view/viewer.png.

Needs the models of tests/viewer/make_models.sh (the CTest fixture view_models).
"""
import math
import os
import re
import shutil
import signal
import time
import unittest

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.support.ui import Select

from viewer_util import SCENE, VOCAB, Viewer, read_png_grey, test_dir

MODEL = os.path.join(test_dir(), "model")

# In the page: compares the displayed picture with the rgb render of the same
# view and with the selection's mask (both at the displayed picture's size); the pixels that the highlight changed
# (summed channel difference above 90 of 765) against the mask's pixels. JPEG
# blurs colour over 2x2 blocks and rings at edges, so the IoU leaves out a
# band of 2 pixels on either side of the mask's outline ("iou"; "iou_all"
# counts every pixel).
HIGHLIGHT_JS = """
const [view, done] = arguments;
const load = (src) => new Promise((ok, bad) => { const i = new Image(); i.onload = () => ok(i); i.onerror = bad; i.src = src; });
const pixels = (img) => { const c = document.createElement("canvas"); c.width = img.naturalWidth; c.height = img.naturalHeight;
  const g = c.getContext("2d"); g.drawImage(img, 0, 0); return g.getImageData(0, 0, c.width, c.height).data; };
(async () => {
  const shown = pixels(document.getElementById("frame"));
  const w = document.getElementById("frame").naturalWidth, h0 = document.getElementById("frame").naturalHeight;
  const plain = pixels(await load(`/api/render?view=${view}&mode=rgb&quality=88&w=${w}&h=${h0}`));
  const mask = pixels(await load(`/api/mask?view=${view}&w=${w}&h=${h0}`));
  const n = mask.length / 4, m = (i) => mask[4 * i] > 127;
  let both = 0, either = 0, bothAll = 0, eitherAll = 0, inMask = 0, changed = 0;
  for (let i = 0; i < n; i++) {
    const p = 4 * i, x = i % w, y = (i - x) / w, h = n / w;
    const d = Math.abs(shown[p] - plain[p]) + Math.abs(shown[p+1] - plain[p+1]) + Math.abs(shown[p+2] - plain[p+2]);
    const hi = d > 90;
    let band = false;
    for (let dy = -2; dy <= 2 && !band; dy++) for (let dx = -2; dx <= 2; dx++) {
      const xx = x + dx, yy = y + dy;
      if (xx >= 0 && yy >= 0 && xx < w && yy < h && m(yy * w + xx) !== m(i)) { band = true; break; }
    }
    inMask += m(i); changed += hi; bothAll += m(i) && hi; eitherAll += m(i) || hi;
    if (!band) { both += m(i) && hi; either += m(i) || hi; }
  }
  done({ iou: both / Math.max(either, 1), iou_all: bothAll / Math.max(eitherAll, 1), mask: inMask, changed });
})().catch((e) => done({ error: String(e) }));
"""

def chromium():
    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1100,760",
                "--force-device-scale-factor=1"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver_path = shutil.which("chromedriver") or "/usr/bin/chromedriver"
    return webdriver.Chrome(service=Service(driver_path), options=opts)


class ViewBrowser(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.v = Viewer(MODEL, "--scene", SCENE, "--vocab", VOCAB)
        cls.d = chromium()
        cls.d.set_script_timeout(60)

    @classmethod
    def tearDownClass(cls):
        cls.d.quit()
        cls.v.stop()

    def state(self, key):
        return self.d.execute_script("return window.ag2gs[arguments[0]];", key)

    def wait_for(self, what, predicate, timeout=60):
        deadline = time.time() + timeout
        while time.time() < deadline:
            value = predicate()
            if value:
                return value
            time.sleep(0.05)
        self.fail("timed out waiting for %s (last error: %s)\n%s" % (what, self.state("lastError"), self.v.output[-2000:]))

    def settled(self, frames_before):
        """Waits for a full-quality frame after frames_before and nothing in flight."""
        self.wait_for("a settled frame", lambda: self.d.execute_script(
            "const s = window.ag2gs; return s.frames > arguments[0] && !s.inFlight && !s.pending && !s.moving "
            "&& s.shown && !s.shown.includes('quality=40');", frames_before))

    def picture(self):
        return self.d.execute_script(
            "const i = document.getElementById('frame'), c = document.createElement('canvas');"
            "c.width = i.naturalWidth; c.height = i.naturalHeight; c.getContext('2d').drawImage(i, 0, 0);"
            "return c.toDataURL('image/png');")

    def console_errors(self):
        return [e for e in self.d.get_log("browser") if e["level"] == "SEVERE"]

    def click_view_pixel(self, x, y):
        """Clicks the displayed picture at a pixel of the served render (its centre)."""
        frame = self.d.find_element(By.ID, "frame")
        size = frame.size
        w, h = self.d.execute_script("return [window.ag2gs.w, window.ag2gs.h];")
        dx = (x + 0.5) * size["width"] / w - size["width"] / 2
        dy = (y + 0.5) * size["height"] / h - size["height"] / 2
        ActionChains(self.d).move_to_element_with_offset(frame, dx, dy).click().perform()

    def test_orbit_keeps_the_horizon_level(self):
        # The generated scene's up is +z; the page orbits about the up the
        # server finds (the floor's normal), so the horizon does not roll,
        # and yaw keeps the camera's height above the target.
        d = self.d
        d.get(self.v.base + "/")
        self.wait_for("the first frame", lambda: self.state("frames") >= 1)
        up = self.v.json("/api/info")[1]["up"]
        self.assertGreater(up[2], 0.99, up)
        dot = lambda a, b: sum(x * y for x, y in zip(a, b))

        def roll_and_height():
            R, C, target = self.state("R"), self.state("C"), self.state("target")
            return (abs(math.degrees(math.asin(max(-1.0, min(1.0, dot(R[0:3], up)))))),
                    dot([c - t for c, t in zip(C, target)], up))

        _, height0 = roll_and_height()
        body = d.find_element(By.TAG_NAME, "body")
        for keys in ([Keys.ARROW_LEFT] * 39, [Keys.ARROW_UP] * 3, [Keys.ARROW_RIGHT] * 7, [Keys.ARROW_DOWN] * 5):
            for k in keys:
                body.send_keys(k)
            roll, height = roll_and_height()
            self.assertLess(roll, 0.5, "horizon roll after %d presses" % len(keys))
        # 39 presses of the left arrow: the same height (the camera stays above the floor).
        for k in [Keys.ARROW_LEFT] * 39:
            body.send_keys(k)
        frame = d.find_element(By.ID, "frame")
        chain = ActionChains(d).move_to_element(frame).click_and_hold()
        for _ in range(10):
            chain.move_by_offset(15, 0)
        chain.release().perform()
        roll, height = roll_and_height()
        self.assertLess(roll, 0.5)
        print("orbit: horizon roll %.3f degrees, height above the target %.3f (first %.3f)" % (roll, height, height0))
        self.assertGreater(height, 0.0)

    def test_touch_pinch_and_a_phone_sized_window(self):
        # A phone's width: the picture keeps the width and most of the height
        # (the panel goes below it); two fingers moving apart zoom in without
        # turning the camera or clicking, and moving together pan.
        d = self.d
        d.set_window_size(390, 844)
        try:
            d.get(self.v.base + "/")
            self.wait_for("the first frame", lambda: self.state("frames") >= 1)
            stage = d.execute_script("const r = document.getElementById('stage').getBoundingClientRect();"
                                     "return [r.width, r.height, window.innerWidth, window.innerHeight];")
            print("phone-sized window: picture area %dx%d of %dx%d" % tuple(stage))
            self.assertGreaterEqual(stage[0], stage[2] - 2)
            self.assertGreater(stage[1], 0.55 * stage[3])
            before = d.execute_script("const s = window.ag2gs; return [s.R, s.C, s.target, s.selected || 0];")
            queries = len(self.v.output)
            touch = """
                const st = document.getElementById('stage'), r = st.getBoundingClientRect();
                const ev = (type, id, x, y) => st.dispatchEvent(new PointerEvent(type, {pointerId: id,
                    pointerType: 'touch', isPrimary: id === 11, clientX: r.left + x, clientY: r.top + y,
                    bubbles: true, cancelable: true, button: 0}));
                ev('pointerdown', 11, 150, 200); ev('pointerdown', 12, 250, 200);
                for (let k = 1; k <= 8; ++k) ev('pointermove', 12, 250 + 10 * k, 200);   // apart: 100 -> 180 px
                ev('pointermove', 11, 160, 230); ev('pointermove', 12, 340, 230);       // both 10 px right, 30 down
                ev('pointerup', 12, 340, 230); ev('pointerup', 11, 160, 230);
                const s = window.ag2gs; return [s.R, s.C, s.target];"""
            R, C, target = d.execute_script(touch)
            dist = lambda a, b: math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b)))
            ratio = dist(C, target) / dist(before[1], before[2])
            turn = max(abs(x - y) for x, y in zip(R, before[0]))
            moved = dist(target, before[2])
            print("pinch: distance to the target x%.3f (fingers 100 -> 180 px), rotation change %.2g, pan %.3g"
                  % (ratio, turn, moved))
            self.assertAlmostEqual(ratio, 100.0 / 180.0, places=3)
            self.assertLess(turn, 1e-9)
            self.assertGreater(moved, 0.0)
            time.sleep(0.3)
            self.assertEqual(self.state("selected") or 0, before[3], "a pinch must not click")
            self.assertNotIn("query ", self.v.output[queries:], "a pinch must not click")
        finally:
            d.set_window_size(1100, 760)

    def test_sharp_picture_link_and_screenshot(self):
        d = self.d
        d.get(self.v.base + "/")
        self.wait_for("the first frame", lambda: self.state("frames") >= 1)
        self.settled(0)
        # The picture is rendered at its size on the screen, not the view's
        # 160x120 stretched.
        natural = d.execute_script("const i = document.getElementById('frame'); return [i.naturalWidth, "
                                   "i.naturalHeight, i.getBoundingClientRect().width, "
                                   "i.getBoundingClientRect().height];")
        print("picture: %dx%d rendered, %.0fx%.0f on the screen" % tuple(natural))
        self.assertGreater(natural[0], 2 * 160)
        self.assertLess(abs(natural[0] - natural[2]), 3)
        self.assertLess(abs(natural[1] - natural[3]), 3)
        # The views' size on request.
        frames = self.state("frames")
        Select(d.find_element(By.ID, "res")).select_by_value("0")
        self.settled(frames)
        self.assertEqual(d.execute_script("return document.getElementById('frame').naturalWidth;"), 160)
        Select(d.find_element(By.ID, "res")).select_by_value("1")
        # A moved camera goes into the address; opening it shows that camera.
        frames = self.state("frames")
        body = d.find_element(By.TAG_NAME, "body")
        for k in [Keys.ARROW_LEFT] * 5 + [Keys.ARROW_UP] * 2:
            body.send_keys(k)
        self.settled(frames)
        url = d.current_url
        self.assertIn("#cam=", url)
        R, C = self.state("R"), self.state("C")
        d.get("about:blank")
        d.get(url)
        self.wait_for("the linked frame", lambda: self.state("frames") >= 1)
        self.assertFalse(self.state("atView"))
        for a, b in zip(R + C, self.state("R") + self.state("C")):
            self.assertAlmostEqual(a, b, places=5)
        # The screenshot: a PNG of the picture's size, rendered again.
        size = d.execute_async_script(
            "const done = arguments[0]; const [w, h] = frameSize(false);"
            "fetch(renderUrl(false, [w, h], '&format=png')).then(async (r) => {"
            "  const b = await r.blob(); const i = await createImageBitmap(b);"
            "  done([w, h, i.width, i.height, r.headers.get('Content-Type')]); });")
        self.assertEqual(size[0:2], size[2:4])
        self.assertEqual(size[4], "image/png")

    def test_the_page(self):
        d = self.d
        d.get(self.v.base + "/")
        self.wait_for("the first frame", lambda: self.state("frames") >= 1)
        self.settled(0)
        self.assertIn("view_000", self.state("shown"))
        self.assertIn("anchors", d.find_element(By.ID, "stats").text)
        self.assertEqual(len(d.find_elements(By.CSS_SELECTOR, "#views option")), 16)

        # A drag orbits: the picture changes and comes back at full quality.
        before = self.picture()
        frames = self.state("frames")
        frame = d.find_element(By.ID, "frame")
        chain = ActionChains(d).move_to_element(frame).click_and_hold()
        for _ in range(8):
            chain.move_by_offset(12, 3)
        chain.release().perform()
        self.settled(frames)
        print("after a drag: the full-size frame %.0f ms after the release" % self.state("refineMs"))
        self.assertIn("pose=", self.state("shown"))
        self.assertFalse(self.state("atView"))
        self.assertNotEqual(self.picture(), before, "a drag must change the picture")
        self.assertIsNone(self.state("lastQuery"), "a drag is not a click")

        # R goes back to the view; the picture is the view's again.
        frames = self.state("frames")
        d.find_element(By.TAG_NAME, "body").send_keys("r")
        self.settled(frames)
        self.assertTrue(self.state("atView"))
        self.assertIn("view=view_000", self.state("shown"))

        # A click on the blue mug in view_000 (the scene's click list: 70, 62)
        # selects it, and the highlight covers the pixels of /api/mask.
        frames = self.state("frames")
        self.click_view_pixel(70, 62)
        self.wait_for("the click's selection", lambda: self.state("lastQuery"))
        self.settled(frames)
        self.assertIn("mode=selection", self.state("shown"))
        q = self.state("lastQuery")
        self.assertEqual(q["query"]["pixel"], [70, 62])
        expected = self.v.json("/api/info")[1]["selection"]["anchors"]
        self.assertEqual(q["anchors"], expected)
        r = d.execute_async_script(HIGHLIGHT_JS, "view_000")
        self.assertNotIn("error", r)
        print("click highlight: IoU %.3f with /api/mask away from its outline, %.3f over every pixel (%d mask pixels, "
              "%d changed)" % (r["iou"], r["iou_all"], r["mask"], r["changed"]))
        self.assertGreater(r["mask"], 50)
        self.assertGreater(r["iou"], 0.97)
        self.assertGreater(r["iou_all"], 0.7)
        d.save_screenshot(os.path.join(test_dir(), "viewer.png"))

        # A text query selects the named object: its mask against the
        # generated scene's exact object ids (gt/<view>.png; the blue mug is 3).
        d.find_element(By.ID, "clear").click()
        self.wait_for("the clear", lambda: self.v.json("/api/info")[1]["selection"]["anchors"] == 0)
        self.wait_for("download disabled", lambda: not d.find_element(By.ID, "download").is_enabled())
        box = d.find_element(By.ID, "query")
        box.send_keys("blue mug", Keys.ENTER)
        self.wait_for("the text query", lambda: (self.state("lastQuery") or {}).get("query", {}).get("type") == "text")
        self.assertTrue(d.find_element(By.ID, "download").is_enabled())
        status, _, png = self.v.request("/api/mask?view=view_003")
        self.assertEqual(status, 200)
        w, h, mask = read_png_grey(png)
        gw, gh, gt = read_png_grey(os.path.join(SCENE, "gt", "view_003.png"))
        self.assertEqual((w, h), (gw, gh))
        both = sum(m > 127 and g == 3 for mr, gr in zip(mask, gt) for m, g in zip(mr, gr))
        either = sum(m > 127 or g == 3 for mr, gr in zip(mask, gt) for m, g in zip(mr, gr))
        r = {"iou": both / max(either, 1)}
        print("text query 'blue mug': IoU %.3f with the object's true pixels in view_003" % r["iou"])
        self.assertGreater(r["iou"], 0.7)

        # Keys: ] is the next view, H hides the selection.
        frames = self.state("frames")
        d.find_element(By.TAG_NAME, "body").send_keys("]")
        self.settled(frames)
        self.assertIn("view=view_001", self.state("shown"))
        d.find_element(By.TAG_NAME, "body").send_keys("h")
        self.wait_for("hide", lambda: self.v.json("/api/info")[1]["visibility"] == "hide")
        self.assertIn("on", d.find_element(By.ID, "hide").get_attribute("class"))
        d.find_element(By.ID, "show").click()
        self.wait_for("show", lambda: self.v.json("/api/info")[1]["visibility"] == "show")

        # Frames per second while the camera moves (previews sized to arrive
        # about 16 ms apart, quality 40, two requests in flight), for the
        # record: the page orbits a little every animation frame for 3 s.
        r = d.execute_async_script("""
          const done = arguments[0], s = window.ag2gs, f0 = s.frames, t0 = performance.now();
          s.moving = true;
          const step = () => {
            if (performance.now() - t0 < 3000) { s.moving = true; orbit(0.01, 0); requestAnimationFrame(step); }
            else done({ frames: s.frames - f0, seconds: (performance.now() - t0) / 1000,
                        w: +/[?&]w=(\d+)/.exec(s.shown)[1], h: +/[?&]h=(\d+)/.exec(s.shown)[1] });
          };
          requestAnimationFrame(step);""")
        print("while moving: %d preview frames in %.1f s (%.1f frames/s), the last %dx%d" % (
            r["frames"], r["seconds"], r["frames"] / r["seconds"], r["w"], r["h"]))
        self.assertGreater(r["frames"], 3)
        self.settled(self.state("frames") - 1)

        self.assertEqual(self.console_errors(), [])
        self.assertIsNone(self.state("lastError"))


class LiveBrowser(unittest.TestCase):
    """The page of `ag2gs train ... --view`: progress advancing, new pictures, pause, then the final model."""

    def test_the_page_follows_training(self):
        import tempfile
        out = tempfile.mkdtemp(prefix="ag2gs_live_page_")
        v = Viewer(SCENE, "-o", os.path.join(out, "m"), "--iters", "400", "--seed", "1", "--view", "--log-every", "0",
                   command="train")
        d = chromium()
        try:
            d.get(v.base + "/")
            text = lambda: d.find_element(By.ID, "trainstat").text

            def iteration():
                m = re.search(r"iteration (\d+)/", text())
                return int(m.group(1)) if m else None

            deadline = time.time() + 120
            while iteration() is None and time.time() < deadline:
                time.sleep(0.05)
            first, frames = iteration(), d.execute_script("return window.ag2gs.frames;")
            self.assertIsNotNone(first, text())
            self.assertTrue(d.find_element(By.ID, "query").get_attribute("disabled"))
            while (iteration() or 0) < first + 30 and time.time() < deadline:
                time.sleep(0.05)
            self.assertGreater(iteration(), first, text())
            self.assertGreater(d.execute_script("return window.ag2gs.frames;"), frames, "no new picture")
            d.find_element(By.ID, "pause").click()
            deadline = time.time() + 10
            while "paused" not in text() and time.time() < deadline:
                time.sleep(0.05)
            self.assertIn("paused", text())
            self.assertEqual(d.find_element(By.ID, "pause").text, "Resume")
            d.find_element(By.ID, "pause").click()
            deadline = time.time() + 300
            while "trained" not in text() and time.time() < deadline:
                time.sleep(0.1)
            self.assertIn("trained: 466 iterations", text())
            # The final model: clicking selects again (no --vocab, so no text queries).
            deadline = time.time() + 30
            while "click an object" not in d.find_element(By.ID, "status").text and time.time() < deadline:
                time.sleep(0.05)
            self.assertIn("click an object", d.find_element(By.ID, "status").text)
            self.assertIsNone(d.execute_script("return window.ag2gs.lastError;"))
        finally:
            d.quit()
            v.stop(signal.SIGINT)
            shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    unittest.main(verbosity=2)
