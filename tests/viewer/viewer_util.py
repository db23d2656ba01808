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
    """`ag2gs view ARGS --port 0`, until stop(); base is http://127.0.0.1:PORT."""

    def __init__(self, *args, timeout=120):
        self.proc = subprocess.Popen([binary(), "view", *args, "--port", "0"], stdout=subprocess.PIPE,
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
