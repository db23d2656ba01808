"""Starting `ag2gs view` from a test and talking to it (standard library only)."""
import json
import os
import re
import signal
import subprocess
import threading
import urllib.error
import urllib.request

SOURCE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(SOURCE, "data_samples", "synth_small")
VOCAB = os.path.join(SCENE, "vocab.json")


def build_dir():
    return os.environ.get("AG2GS_BUILD_DIR", os.path.join(SOURCE, "build"))


def binary():
    return os.environ.get("AG2GS_BINARY", os.path.join(build_dir(), "ag2gs"))


def test_dir():
    return os.path.join(build_dir(), "test_view")


class Viewer:
    """`ag2gs view ARGS --port 0` (or `ag2gs COMMAND ARGS --port 0`: `train ... --view`), until stop(); base is
    http://127.0.0.1:PORT."""

    def __init__(self, *args, timeout=120, command="view"):
        self.proc = subprocess.Popen([binary(), command, *args, "--port", "0"], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines = []
        self.port = None
        ready = threading.Event()

        def drain():  # reads everything it prints, so its pipe never fills
            for line in self.proc.stdout:
                self.lines.append(line)
                m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
                if m and self.port is None:
                    self.port = int(m.group(1))
                    ready.set()
            ready.set()

        self.reader = threading.Thread(target=drain, daemon=True)
        self.reader.start()
        ready.wait(timeout)
        if self.port is None:
            self.proc.kill()
            self.reader.join(5)
            raise RuntimeError("ag2gs view did not print its URL:\n" + self.output)
        self.base = "http://127.0.0.1:%d" % self.port

    @property
    def output(self):
        return "".join(self.lines)

    def request(self, path, body=None, method=None, raw=None, timeout=60):
        """(status, content type, bytes); body: a JSON value, raw: bytes as they are."""
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        req = urllib.request.Request(self.base + path, data=data, method=method or ("POST" if data is not None else "GET"))
        if data is not None:
            req.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, r.headers.get("Content-Type", ""), r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.headers.get("Content-Type", ""), e.read()

    def json(self, path, body=None, method=None):
        status, ctype, data = self.request(path, body, method)
        return status, json.loads(data)

    def stop(self, sig=signal.SIGTERM, timeout=20):
        """Sends the signal; returns the exit status (None if it had to be killed)."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                return None
        self.reader.join(10)
        self.proc.stdout.close()
        return self.proc.returncode


def read(path):
    with open(path, "rb") as f:
        return f.read()


def read_png_grey(source):
    """A non-interlaced greyscale PNG of 8 or 16 bits (a path or its bytes) as (width, height, rows of ints),
    standard library only (the generator's gt/<view>.png object ids are 16-bit, which browsers reduce to 8)."""
    import struct
    import zlib
    data = source if isinstance(source, bytes) else read(source)
    path = "the PNG" if isinstance(source, bytes) else source
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(path + ": not a PNG")
    pos, idat, width = 8, b"", None
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        chunk = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", chunk)
            if colour != 0 or depth not in (8, 16) or interlace:
                raise ValueError(path + ": only non-interlaced 8/16-bit greyscale is read here")
        elif kind == b"IDAT":
            idat += chunk
        pos += 12 + n
    raw, bpp = zlib.decompress(idat), depth // 8
    stride = width * bpp
    rows, prev = [], bytearray(stride)
    for y in range(height):
        f, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b, c = prev[i], prev[i - bpp] if i >= bpp else 0
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append([int.from_bytes(line[x * bpp:(x + 1) * bpp], "big") for x in range(width)])
        prev = line
    return width, height, rows
