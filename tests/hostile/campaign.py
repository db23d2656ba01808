#!/usr/bin/env python3
"""A hostile-input campaign against the ag2gs program.

Generated cases over every subcommand and input kind: damaged and crafted
input files (models with recomputed checksums included), flags at NaN, Inf,
huge, zero and negative values, outputs over inputs, reruns into existing
outputs, and kill -9 / SIGTERM at seeded random moments of every writing
subcommand. Each case is run on its own copy of the inputs and classed:

  crash          the process died of a signal it did not ask for
  hang           it ran past the time limit
  data loss      a file that existed before the run changed or vanished
                 (inputs, or the results of an earlier run without --force)
  leftover       a temporary file or folder (*.tmp.PID, *.partial.PID) left
                 after the run, or after a rerun following a kill
  silent accept  exit 0 where the input is invalid
  unclear        refused with a message that names an internal (a C++
                 exception, a JSON library code) or neither the file nor the
                 flag
  broken         after a kill, a final-named file that does not load
  mixed set      after a kill of a run replacing earlier results with
                 --force, some of the old files replaced and some not

  tests/hostile/campaign.py [--size small|full] [--seed N] [--keep]

The small size (CTest) runs every case but the flag matrix, of which it
samples a tenth (and every NaN), and kills each writer twice instead of twelve times;
full runs all of it. Exit 1 when
any case is in one of the classes above. The program is $AG2GS_BINARY (else
BUILD/ag2gs); the trained model comes from the viewer tests' fixture
(BUILD/test_view/model) when present, else it is trained here.
"""

import argparse
import hashlib
import json
import os
import random
import re
import shutil
import signal
import struct
import subprocess
import sys
import time

SRC = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BUILD = os.environ.get("AG2GS_BUILD_DIR", os.path.join(SRC, "build"))
BIN = os.environ.get("AG2GS_BINARY", os.path.join(BUILD, "ag2gs"))
SAMPLE = os.path.join(SRC, "data_samples", "synth_small")

# Signs of a message written for the program's authors, not its users.
INTERNAL = re.compile(
    r"json\.exception|std::|basic_(?:i|o)?f?stream|basic_filebuf|bad_alloc|filesystem error|terminate called|"
    r"Assertion|vector::|basic_string|stoi|stod|what\(\)|Segmentation|core dumped|CL_[A-Z_]+ \(-\d+\)")
TEMP = re.compile(r"\.tmp\.\d+|\.partial\.\d+")
LIMIT_S = 120


# ----------------------------------------------------------------------------
# Files


def snapshot(root):
    """{relative path: sha1} of every file under root (root may be a file)."""
    out = {}
    if os.path.isfile(root):
        with open(root, "rb") as f:
            return {"": hashlib.sha1(f.read()).hexdigest()}
    for d, _, names in os.walk(root):
        for n in names:
            p = os.path.join(d, n)
            try:
                with open(p, "rb") as f:
                    out[os.path.relpath(p, root)] = hashlib.sha1(f.read()).hexdigest()
            except OSError:
                out[os.path.relpath(p, root)] = "unreadable"
    return out


def leftovers(root):
    found = []
    for d, dirs, names in os.walk(root):
        for n in dirs + names:
            if TEMP.search(n):
                found.append(os.path.relpath(os.path.join(d, n), root))
    return found


def fnv1a64(data):
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


class Container:
    """model.ag2gs / checkpoint.ag2gs (docs/formats.md, section 5)."""

    def __init__(self, path):
        b = open(path, "rb").read()
        (length,) = struct.unpack("<Q", b[16:24])
        self.prefix = b[:16]
        self.header = json.loads(b[24:24 + length])
        start = 24 + length + 8
        start += (-start) % 8
        self.data = bytearray(b[start:])

    def array(self, name):
        for a in self.header["arrays"]:
            if a["name"] == name:
                return a
        raise KeyError(name)

    def put(self, name, index, value, fmt):
        """Writes one element (struct format fmt) and fixes the checksum."""
        a = self.array(name)
        size = struct.calcsize(fmt)
        at = a["offset"] + index * size
        self.data[at:at + size] = struct.pack(fmt, value)
        a["fnv1a64"] = str(fnv1a64(bytes(self.data[a["offset"]:a["offset"] + a["bytes"]])))

    def save(self, path, header_text=None):
        text = (header_text if header_text is not None else json.dumps(self.header)).encode()
        head = self.prefix + struct.pack("<Q", len(text)) + text + struct.pack("<Q", fnv1a64(text))
        head += b"\0" * ((-len(head)) % 8)
        with open(path, "wb") as f:
            f.write(head + bytes(self.data))


def deep_json(levels):
    return "[" * levels + "]" * levels


def loads_ok(path):
    """A final-named output file is whole: it parses as its kind."""
    name = os.path.basename(path)
    try:
        if name.endswith(".json"):
            json.load(open(path))
        elif name.endswith(".png"):
            b = open(path, "rb").read()
            return b.startswith(b"\x89PNG") and b.rstrip(b"\0").endswith(b"IEND\xaeB`\x82")
        elif name.endswith(".ag2gs") or name.endswith(".ply"):
            r = subprocess.run([BIN, "-q", "info", path], capture_output=True, timeout=LIMIT_S)
            return r.returncode == 0
        elif name.endswith(".npy"):
            return open(path, "rb").read(6) == b"\x93NUMPY"
        return True
    except Exception:
        return False


# ----------------------------------------------------------------------------
# Cases


class Case:
    """One run: argv (with {W} for the case folder), what the inputs are,
    what it must do (refuse / any) and what the refusal must name."""

    def __init__(self, kind, argv, expect="any", names=None, setup=None, inputs=("scene", "big", "sel"),
                 before=None, kill=None):
        self.kind, self.argv, self.expect, self.names = kind, argv, expect, names
        self.setup, self.inputs, self.before, self.kill = setup, inputs, before, kill

    def label(self):
        return self.kind + ": " + " ".join(self.argv)


def run(argv, cwd, timeout=LIMIT_S, kill_after=None, sig=signal.SIGKILL, repeat_sig=False):
    p = subprocess.Popen([BIN] + argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         start_new_session=True)
    if kill_after is not None:
        try:
            p.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            p.send_signal(sig)
            if repeat_sig:  # as `timeout` does: the process and its group
                os.killpg(p.pid, sig)
    try:
        out, err = p.communicate(timeout=timeout)
        return p.returncode, out.decode(errors="replace"), err.decode(errors="replace"), False
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        return None, out.decode(errors="replace"), err.decode(errors="replace"), True


class Campaign:
    def __init__(self, work, seed, size):
        self.work, self.rng, self.size = work, random.Random(seed), size
        self.cases, self.results = [], []

    # --- fixtures -----------------------------------------------------------
    def prepare(self):
        shutil.rmtree(self.work, ignore_errors=True)
        os.makedirs(self.work)
        self.base = os.path.join(self.work, "base")
        os.makedirs(self.base)
        shutil.copytree(SAMPLE, os.path.join(self.base, "scene"))
        fixture = os.path.join(BUILD, "test_view", "model")
        big = os.path.join(self.base, "big")
        if os.path.isfile(os.path.join(fixture, "model.ag2gs")):
            shutil.copytree(fixture, big)
        else:
            subprocess.run([BIN, "-q", "train", "scene", "-o", "big", "--iters", "300", "--eval", "--seed", "1"],
                           cwd=self.base, check=True)
        subprocess.run([BIN, "-q", "query", "big", "--scene", "scene", "--view", "view_000", "--click", "70,62",
                        "--views", "view_000", "-o", "sel"], cwd=self.base, check=True, stdout=subprocess.DEVNULL)
        self.model_header = Container(os.path.join(big, "model.ag2gs")).header

    def case_dir(self, i):
        d = os.path.join(self.work, "c%04d" % i)
        shutil.copytree(self.base, d, symlinks=True)
        return d

    # --- generation ---------------------------------------------------------
    def add(self, *a, **k):
        self.cases.append(Case(*a, **k))

    def generate(self):
        S = ["--scene", "scene"]
        click = ["--view", "view_000", "--click", "70,62"]
        EV = ["--labels", "scene/label", "--vocab", "scene/vocab.json", "--clicks", "scene/clicks.json"]
        quick_train = ["--iters", "3", "--stages", "1", "-r", "4", "--seed", "1"]
        # The consumers of each input: commands that read it, all fast.
        consumers = {
            "scene/sparse/0/cameras.bin": [["train", "scene", "-o", "out"] + quick_train,
                                           ["render", "big"] + S + ["-o", "out", "--views", "view_000"]],
            "scene/sparse/0/images.bin": [["train", "scene", "-o", "out"] + quick_train,
                                          ["render", "big"] + S + ["-o", "out", "--views", "view_000"]],
            "scene/sparse/0/points3D.bin": [["train", "scene", "-o", "out"] + quick_train],
            "scene/images/view_003.png": [["train", "scene", "-o", "out"] + quick_train],
            "scene/masks/view_003.png": [["train", "scene", "-o", "out"] + quick_train],
            "scene/language_features/view_003_f.npy": [["train", "scene", "-o", "out"] + quick_train],
            "scene/language_features/view_003_s.npy": [["train", "scene", "-o", "out"] + quick_train],
            "scene/label/view_000.json": [["eval", "big"] + S + EV + ["-o", "out/eval.json"]],
            "scene/clicks.json": [["eval", "big"] + S + EV + ["-o", "out/eval.json"]],
            "scene/vocab.json": [["query", "big"] + S + ["--text", "blue mug", "--vocab", "scene/vocab.json",
                                                        "-o", "out", "--views", "view_000"]],
            "big/model.ag2gs": [["info", "big"], ["render", "big"] + S + ["-o", "out", "--views", "view_000"],
                                ["query", "big"] + S + click + ["-o", "out", "--views", "view_000"],
                                ["remove", "big"] + S + ["--selection", "sel/selection.json", "-o", "out",
                                                         "--dilate", "0"],
                                ["simulate", "big"] + S + ["--selection", "sel/selection.json", "-o", "out",
                                                           "--frames", "1", "--views", "view_000"]],
            "big/point_cloud.ply": [["info", "big/point_cloud.ply"],
                                    ["render", "--ply", "big/point_cloud.ply"] + S + ["-o", "out", "--views",
                                                                                      "view_000"],
                                    ["render", "big"] + S + ["-o", "out", "--views", "view_000"]],
            "sel/selection.json": [["remove", "big"] + S + ["--selection", "sel/selection.json", "-o", "out"],
                                   ["simulate", "big"] + S + ["--selection", "sel/selection.json", "-o", "out",
                                                              "--frames", "1"]],
        }
        # Damage that no reader may accept, and damage it may (a flipped byte
        # in a pixel is still a picture): no crash, hang or loss either way.
        for path, commands in consumers.items():
            for how in ("empty", "half", "folder", "flip", "garbage", "deep"):
                if how == "deep" and not path.endswith((".json", ".ag2gs")):
                    continue
                refuse = how in ("empty", "half", "folder", "deep")
                if path.endswith(".png") and how == "half":
                    refuse = True
                if path in ("scene/clicks.json", "scene/label/view_000.json") and how == "empty":
                    refuse = True
                for argv in commands:
                    self.add("damaged " + how + " " + path, argv, "refuse" if refuse else "any",
                             names=os.path.basename(path), setup=("damage", path, how))
        # Models crafted past their checksums: non-finite numbers, indices
        # out of range, impossible records.
        A = self.model_header["meta"]["anchors"]["count"]
        crafted = [("anchors/pos", 5, float("nan"), "<f"), ("anchors/offset", 7, float("inf"), "<f"),
                   ("anchors/opacity_logit", 3, float("-inf"), "<f"), ("anchors/scale_logit", 0, float("nan"), "<f"),
                   ("anchors/quat", 4, float("nan"), "<f"), ("anchors/feature", 2, float("inf"), "<f"),
                   ("anchors/sh", 11, float("nan"), "<f"), ("anchors/voxel", 1, float("nan"), "<f"),
                   ("anchors/layer", 9, 99, "<i"), ("anchors/layer", 9, -1, "<i"),
                   ("graph/neighbours", 17, A + 5, "<i"), ("graph/neighbours", 3, -2, "<i"),
                   ("graph/row_offsets", 10, 10 ** 9, "<i"), ("clusters/anchor_cluster", 0, 999, "<i"),
                   ("clusters/anchor_cluster", 5, -7, "<i"), ("clusters/size", 1, -3, "<i"),
                   ("clusters/language", 6, float("nan"), "<f")]
        metas = [("train.resolution", 0), ("train.resolution", -3), ("anchors.config.children", 99),
                 ("train.active_sh_degree", 9), ("anchors.count", A + 1), ("anchors.config.sh_degree", 7)]
        model_cmds = consumers["big/model.ag2gs"] + [["train", "scene", "-o", "big", "--stages", "3", "--seed", "1"]]
        for craft in crafted + [("meta",) + m for m in metas] + [("header_deep",)]:
            for argv in model_cmds:
                self.add("crafted model " + "/".join(str(x) for x in craft[:3]), argv, "refuse",
                         names="model.ag2gs", setup=("craft",) + craft)
        # Flags: NaN and Inf are never a setting; huge, zero and negative
        # values are refused or run, never crash.
        bases = {
            "train": ["train", "scene", "-o", "out"] + quick_train,
            "render": ["render", "big"] + S + ["-o", "out", "--views", "view_000"],
            "query": ["query", "big"] + S + click + ["-o", "out", "--views", "view_000"],
            "remove": ["remove", "big"] + S + ["--selection", "sel/selection.json", "-o", "out", "--iters", "2"],
            "simulate": ["simulate", "big"] + S + ["--selection", "sel/selection.json", "-o", "out", "--frames", "1",
                         "--views", "view_000"],
            "eval": ["eval", "big"] + S + EV + ["-o", "out/eval.json"],
            "baseline": ["baseline", "scene", "-o", "out", "--iters", "3", "-r", "4"],
            "synth": ["synth", "out", "--views", "4", "--width", "32", "--height", "24"],
        }
        for cmd, base in bases.items():
            for flag, kind in self.numeric_flags(cmd):
                if flag in base or flag in ("--device",):
                    continue
                values = ["nan", "inf", "-inf", "1e300", "-1", "0"] if kind == "FLOAT" else \
                    ["-1", "0", "99999999999", "nan"]
                for v in values:
                    refuse = v in ("nan", "inf", "-inf")
                    extra = [flag, v]
                    if flag == "--gravity" or flag == "--force" or flag == "--up":
                        extra = [flag, ",".join([v] * 3)]
                    self.add("flag " + cmd, base + extra, "refuse" if refuse else "any", names=flag)
        # Outputs over inputs.
        over = ["scene", "scene/images", "scene/sparse/0/cameras.bin", "scene/masks/view_000.png", "big/model.ag2gs",
                "sel/selection.json", "."]
        for cmd, base in bases.items():
            for o in over:
                argv = list(base)
                if cmd == "synth":
                    argv[1] = o
                else:
                    i = argv.index("-o")
                    argv[i + 1] = o if cmd != "eval" or o.endswith((".bin", ".png", ".ag2gs", ".json")) else o + "/x.json"
                # "." holds the inputs but is none of them: writing there is fine.
                self.add("output over input " + o, argv, "any" if o == "." else "refuse",
                         names="-o" if cmd != "synth" else o)
        # Reruns with other settings into earlier results, without --force.
        reruns = {
            "train": (bases["train"], ["--seed", "2"]),
            "baseline": (bases["baseline"], ["--seed", "2"]),
            "render": (bases["render"], ["--bg", "1,1,1"]),
            "query": (bases["query"], ["--click-by", "support"]),
            "eval": (bases["eval"], ["--tau", "0.1"]),
            "remove": (bases["remove"], ["--dilate", "1"]),
            "simulate": (bases["simulate"], ["--material", "sand"]),
            "synth": (bases["synth"], ["--seed", "3"]),
        }
        for cmd, (base, change) in reruns.items():
            self.add("rerun without --force", base + change, "refuse", names="--force", before=base)
        # Interruptions: kill -9 (and a doubled SIGTERM) at random moments.
        writers = dict(bases)
        writers["train"] = ["train", "scene", "-o", "out", "--iters", "60", "-r", "4", "--seed", "1", "--save-every",
                            "10", "--prop-iters", "5"]
        writers["render"] = ["render", "big"] + S + ["-o", "out"]
        writers["query"] = ["query", "big"] + S + click + ["-o", "out", "--views", "all"]
        writers["simulate"] = ["simulate", "big"] + S + ["--selection", "sel/selection.json", "-o", "out", "--frames",
                                                          "3", "--views", "view_000,view_003"]
        kills = 6 if self.size == "full" else 1
        for cmd, argv in writers.items():
            for k in range(kills):
                for sig in ("KILL", "TERM2"):
                    self.add("interrupted (" + sig + ")", argv, "any", kill=(sig, self.rng.uniform(0.1, 2.5)))
                    self.add("interrupted (" + sig + ") then --force", argv, "any",
                             kill=(sig, self.rng.uniform(0.1, 2.5), "force"))

        # --force over earlier results, killed: the folder holds the old set
        # until the new one is complete (render, query: host/io/output_set.h).
        over_results = {"render": (["render", "big"] + S + ["-o", "out", "--outputs", "rgb,depth,alpha,feature"],
                                   ["--bg", "1,1,1"]),
                        "query": (writers["query"], ["--click-by", "support"])}
        for cmd, (argv, change) in over_results.items():
            for k in range(kills * 2):
                sig = ("KILL", "TERM2")[k % 2]
                self.add("interrupted (" + sig + ") over results", argv + change + ["--force"], "any", before=argv,
                         kill=(sig, self.rng.uniform(0.02, 0.5), "force", "old or new"))

    def numeric_flags(self, cmd):
        r = subprocess.run([BIN, cmd, "--help"], capture_output=True, text=True)
        flags = []
        for line in r.stdout.splitlines():
            m = re.match(r"\s+((?:-\w,)?--[\w-]+)\s+(FLOAT|INT|UINT)", line)
            if m:
                flags.append((m.group(1).split(",")[-1], "FLOAT" if m.group(2) == "FLOAT" else "INT"))
        return flags

    # --- running ------------------------------------------------------------
    def apply(self, d, setup):
        if setup[0] == "damage":
            _, path, how = setup
            p = os.path.join(d, path)
            if path.startswith("scene/masks/"):  # masks/ is read when there is no language_features/
                shutil.rmtree(os.path.join(d, "scene", "language_features"))
            b = open(p, "rb").read()
            if how == "folder":
                os.remove(p)
                os.makedirs(p)
                return
            if how == "empty":
                b = b""
            elif how == "half":
                b = b[:len(b) // 2]
            elif how == "flip":
                b = bytearray(b)
                for _ in range(16):
                    b[self.rng.randrange(len(b))] ^= 1 << self.rng.randrange(8)
                b = bytes(b)
            elif how == "garbage":
                b = bytes(self.rng.randrange(256) for _ in range(1024))
            elif how == "deep":
                if path.endswith(".ag2gs"):
                    return self.apply(d, ("craft", "header_deep"))
                b = deep_json(100000).encode()
            open(p, "wb").write(b)
        elif setup[0] == "craft":
            p = os.path.join(d, "big", "model.ag2gs")
            c = Container(p)
            if setup[1] == "header_deep":
                c.save(p, header_text='{"meta": ' + deep_json(200000) + ', "arrays": []}')
            elif setup[1] == "meta":
                keys, value = setup[2].split("."), setup[3]
                node = c.header["meta"]
                for k in keys[:-1]:
                    node = node[k]
                node[keys[-1]] = value
                c.save(p)
            else:
                _, name, index, value, fmt = setup
                c.put(name, index, value, fmt)
                c.save(p)

    def run_case(self, i, case):
        d = self.case_dir(i)
        if case.setup:
            self.apply(d, case.setup)
        argv = [a.replace("{W}", d) for a in case.argv]
        findings = []
        if case.before:
            rc, _, err, hung = run(case.before, d)
            if rc != 0:
                return self.record(case, ["setup failed: " + err.strip()[-200:]], d, keep=True)
        protect = snapshot(d)
        if case.kill:
            sig, after = case.kill[0], case.kill[1]
            rc, out, err, hung = run(argv, d, kill_after=after,
                                     sig=signal.SIGKILL if sig == "KILL" else signal.SIGTERM,
                                     repeat_sig=(sig == "TERM2"))
            if hung:
                findings.append("hang")
            elif rc is not None and rc < 0 and -rc != (signal.SIGKILL if sig == "KILL" else signal.SIGTERM):
                findings.append("crash (signal %d)" % -rc)
            outdir = os.path.join(d, "out")
            if len(case.kill) > 3 and rc != 0 and not hung:
                old = {p: h for p, h in protect.items() if p.startswith("out" + os.sep)}
                now = {os.path.join("out", p): h for p, h in snapshot(outdir).items() if not TEMP.search(p)}
                journal = any(".ag2gs-commit." in p for p in now)
                now = {p: h for p, h in now.items() if ".ag2gs-commit." not in p}
                if now != old and not journal:
                    findings.append("mixed set: %d of %d earlier files changed by a run that did not finish" %
                                    (sum(1 for p in old if now.get(p) != old[p]), len(old)))
            # Every final-named file of the output loads.
            for root, _, names in os.walk(outdir):
                for n in names:
                    if not TEMP.search(n) and not TEMP.search(root) and not loads_ok(os.path.join(root, n)):
                        findings.append("broken: " + os.path.relpath(os.path.join(root, n), d))
            if len(case.kill) > 2 and not hung:
                # remove and simulate have no --force (their -o must be new or
                # empty): the rerun goes into the same folder as it is.
                finished = rc == 0
                rerun = argv if argv[0] in ("remove", "simulate") else argv + ["--force"]
                rc2, _, err2, hung2 = run(rerun, d)
                if hung2:
                    findings.append("hang (rerun)")
                elif rc2 is not None and rc2 < 0:
                    findings.append("crash (rerun, signal %d)" % -rc2)
                elif rc2 != 0 and "resume" not in err2 and not (finished and rerun is argv):
                    findings.append("rerun with --force failed: " + err2.strip()[-200:])
                left = leftovers(d)
                if left:
                    findings.append("leftover after rerun: " + ", ".join(left[:3]))
            changed = [p for p, h in protect.items()
                       if not p.startswith("out") and snapshot(os.path.join(d, p)).get("", None) != h]
            changed = [p for p in changed if os.path.exists(os.path.join(d, p)) or not p.startswith("out")]
            if changed:
                findings.append("data loss: " + ", ".join(changed[:3]))
            return self.record(case, findings, d, rc=rc, err=err)
        rc, out, err, hung = run(argv, d)
        if hung:
            findings.append("hang")
        elif rc < 0:
            findings.append("crash (signal %d)" % -rc)
        else:
            if case.expect == "refuse" and rc == 0:
                findings.append("silent accept")
            if rc != 0:
                msg = err.strip()
                if INTERNAL.search(msg) or not msg:
                    findings.append("unclear: " + (msg.splitlines()[-1][:160] if msg else "(no message)"))
                elif case.names and case.names.lower() not in msg.lower() and case.kind.startswith(("damaged", "flag")):
                    findings.append("unclear (does not name %s): %s" % (case.names, msg.splitlines()[-1][:160]))
        changed = []
        for p, h in protect.items():
            full = os.path.join(d, p)
            now = snapshot(full).get("", None) if os.path.isfile(full) else None
            if now != h and (not p.startswith("out" + os.sep) or case.before):
                changed.append(p)
        if case.setup and case.setup[0] == "damage" and case.setup[2] == "folder":
            changed = [p for p in changed if p != case.setup[1]]
        if changed:
            findings.append("data loss: " + ", ".join(changed[:3]) + (" (+%d)" % (len(changed) - 3)
                                                                     if len(changed) > 3 else ""))
        left = leftovers(d)
        if left:
            findings.append("leftover: " + ", ".join(left[:3]))
        return self.record(case, findings, d, rc=rc, err=err)

    def record(self, case, findings, d, rc=None, err="", keep=False):
        self.results.append((case, findings, rc, err))
        if not findings and not keep and not self.keep:
            shutil.rmtree(d, ignore_errors=True)
        return findings


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", action="store_true", help="keep every case folder (failing ones are always kept)")
    ap.add_argument("--only", default="", help="run only cases whose label contains this text")
    ap.add_argument("--work", default=os.path.join(BUILD, "test_hostile"))
    args = ap.parse_args()
    c = Campaign(args.work, args.seed, args.size)
    c.keep = args.keep
    c.prepare()
    c.generate()
    cases = [x for x in c.cases if args.only in x.label()]
    if args.size == "small":
        # Every case but the flag matrix, of which a seeded tenth (each
        # flag's NaN among them): about 570 runs, 2-3 minutes.
        flags = [x for x in cases if x.kind.startswith("flag")]
        keep = set(id(x) for x in random.Random(args.seed).sample(flags, len(flags) // 10))
        keep |= set(id(x) for x in flags if x.argv[-1] == "nan")
        cases = [x for x in cases if not x.kind.startswith("flag") or id(x) in keep]
    t0 = time.time()
    classes = {}
    for i, case in enumerate(cases):
        findings = c.run_case(i, case)
        for f in findings:
            key = f.split(":")[0].split(" (")[0]
            classes[key] = classes.get(key, 0) + 1
            print("FAIL c%04d %s\n     %s\n     %s" % (i, case.label(), f, (c.results[-1][3].strip().splitlines()
                                                                           or [""])[-1][:200]), flush=True)
        if (i + 1) % 25 == 0:
            el = time.time() - t0
            print("%d/%d cases, %.0f s, ETA %.0f s" % (i + 1, len(cases), el, el / (i + 1) * (len(cases) - i - 1)),
                  flush=True)
    refused = sum(1 for _, f, rc, _ in c.results if rc not in (0, None))
    print("campaign: %d cases in %.0f s, %d refused, %d accepted" % (len(cases), time.time() - t0, refused,
                                                                   len(cases) - refused))
    for k in ("crash", "hang", "data loss", "leftover", "leftover after rerun", "mixed set", "silent accept", "unclear",
              "broken",
              "rerun with --force failed", "setup failed"):
        print("  %-24s %d" % (k, classes.get(k, 0)))
    return 1 if classes else 0


if __name__ == "__main__":
    sys.exit(main())
