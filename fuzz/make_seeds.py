#!/usr/bin/env python3
"""Writes the seed corpora of the fuzz targets (Python 3, standard library only).

Usage: python3 fuzz/make_seeds.py OUT_DIR
Creates OUT_DIR/<target>/<seed> for fuzz_npy, fuzz_ply, fuzz_colmap_bin and
fuzz_colmap_txt from the sample scene, plus fuzz_model and fuzz_json seeds in data_samples/ (tiny_scene: PLY and
text COLMAP model; tiny_scene_bin: binary model), kept small so the fuzzers
run fast. Deterministic: a rerun writes the same bytes.
"""

import os
import struct
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAMPLES = os.path.join(ROOT, "data_samples")


def read(rel):
    with open(os.path.join(SAMPLES, rel), "rb") as f:
        return f.read()


def put(out_dir, target, name, data):
    d = os.path.join(out_dir, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


# ------------------------------------------------------------------ npy

def npy(descr, shape, payload, fortran=False, major=1, align=64):
    """A .npy file laid out as numpy.save writes it."""
    shape_text = "(" + ", ".join(str(d) for d in shape) + ("," if len(shape) == 1 else "") + ")"
    header = "{'descr': '%s', 'fortran_order': %s, 'shape': %s, }" % (descr, "True" if fortran else "False", shape_text)
    len_bytes = 2 if major == 1 else 4
    pad = (align - (8 + len_bytes + len(header) + 1) % align) % align
    header = (header + " " * pad + "\n").encode("latin1")
    length = struct.pack("<H" if major == 1 else "<I", len(header))
    return b"\x93NUMPY" + bytes([major, 0]) + length + header + payload


def sample_points():
    """(id, xyz, rgb) of the sample's sparse points, from points3D.txt."""
    points = []
    for line in read("tiny_scene/sparse/0/points3D.txt").decode().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        tok = line.split()
        points.append((int(tok[0]), [float(v) for v in tok[1:4]], [int(v) for v in tok[4:7]]))
    return points


def npy_seeds(out):
    pts = sample_points()[:16]
    xyz = [v for _, p, _ in pts for v in p]
    rgb = [v for _, _, c in pts for v in c]
    ids = [i for i, _, _ in pts]
    n = len(pts)
    put(out, "fuzz_npy", "xyz_f4", npy("<f4", (n, 3), struct.pack("<%df" % len(xyz), *xyz)))
    put(out, "fuzz_npy", "xyz_f8_big_fortran",
        npy(">f8", (n, 3), struct.pack(">%dd" % len(xyz), *[xyz[r * 3 + c] for c in range(3) for r in range(n)]),
            fortran=True))
    put(out, "fuzz_npy", "xyz_f2", npy("<f2", (n, 3), struct.pack("<%de" % len(xyz), *xyz)))
    put(out, "fuzz_npy", "rgb_u1", npy("|u1", (n, 3), bytes(rgb)))
    put(out, "fuzz_npy", "ids_i8_v2", npy("<i8", (n,), struct.pack("<%dq" % n, *ids), major=2))
    put(out, "fuzz_npy", "ids_u2_big_v3", npy(">u2", (2, n // 2), struct.pack(">%dH" % n, *ids), major=3))
    put(out, "fuzz_npy", "mask_b1_3d", npy("|b1", (2, 2, 4), bytes([c % 2 for c in rgb[:16]])))
    put(out, "fuzz_npy", "scalar_i4", npy("<i4", (), struct.pack("<i", -7)))
    put(out, "fuzz_npy", "empty_f4", npy("<f4", (0, 512), b""))
    put(out, "fuzz_npy", "align16_i2", npy(">i2", (4,), struct.pack(">4h", -1, 2, -3, 4), align=16))


# ------------------------------------------------------------------ ply

def ply_seeds(out):
    full = read("tiny_scene/gaussians.ply")
    end = full.index(b"end_header\n") + len(b"end_header\n")
    header = full[:end].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    stride = 4 * len(props)
    count = 4
    cut_header = header.replace("element vertex 300", "element vertex %d" % count).encode()
    put(out, "fuzz_ply", "sample_4_vertices", cut_header + full[end:end + count * stride])

    # The same vertices as ascii, after a face element with a list property.
    rows = []
    for v in range(2):
        values = struct.unpack("<%df" % len(props), full[end + v * stride:end + (v + 1) * stride])
        rows.append(" ".join(repr(x) for x in values))
    ascii_header = header.replace("binary_little_endian", "ascii").replace("element vertex 300",
                                                                          "element face 1\nproperty list uchar int "
                                                                          "vertex_indices\nelement vertex 2")
    put(out, "fuzz_ply", "sample_ascii_with_face", (ascii_header + "3 0 1 1\n" + "\n".join(rows) + "\n").encode())

    # SH degree 0, doubles, no normals or features, a comment.
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    h = "ply\nformat binary_little_endian 1.0\ncomment degree 0\nelement vertex 2\n"
    h += "".join("property double %s\n" % n for n in names) + "end_header\n"
    body = struct.pack("<%dd" % (2 * len(names)), *[0.25 * i for i in range(2 * len(names))])
    put(out, "fuzz_ply", "degree0_double", h.encode() + body)


# ------------------------------------------------------------------ COLMAP

def three(cameras, images, points):
    """The targets' input layout: two uint32 lengths, cameras, images, points3D."""
    return struct.pack("<II", len(cameras), len(images)) + cameras + images + points


def colmap_bin_seeds(out):
    d = "tiny_scene_bin/sparse/0/"
    cams, imgs, pts = read(d + "cameras.bin"), read(d + "images.bin"), read(d + "points3D.bin")
    put(out, "fuzz_colmap_bin", "sample", three(cams, imgs, pts))

    # One SIMPLE_PINHOLE camera, one image without 2D points, one point with a track of 1.
    cam = struct.pack("<Q", 1) + struct.pack("<iiQQ3d", 1, 0, 64, 48, 50.0, 32.0, 24.0)
    img = struct.pack("<Q", 1) + struct.pack("<i7di", 1, 1, 0, 0, 0, 0, 0, 3, 1) + b"a.png\0" + struct.pack("<Q", 0)
    pt = struct.pack("<Q", 1) + struct.pack("<Q3d3Bd", 5, 0.5, -0.5, 1.0, 1, 2, 3, 0.1) + struct.pack("<Qii", 1, 1, 0)
    put(out, "fuzz_colmap_bin", "simple_pinhole", three(cam, img, pt))

    # A distorted camera (OPENCV, model id 4) used by the image.
    cam = struct.pack("<Q", 1) + struct.pack("<iiQQ8d", 1, 4, 64, 48, 50, 50, 32, 24, 0.1, 0, 0, 0)
    put(out, "fuzz_colmap_bin", "opencv", three(cam, img, pt))


def colmap_txt_seeds(out):
    d = "tiny_scene/sparse/0/"
    cams, imgs, pts = read(d + "cameras.txt"), read(d + "images.txt"), read(d + "points3D.txt")
    # Two images with their 2D points keep the seed small.
    img_lines = imgs.decode().splitlines(keepends=True)
    first = [l for l in img_lines if l.startswith("#")]
    data = [l for l in img_lines if not l.startswith("#")]
    imgs_small = "".join(first + data[:4]).encode()
    pts_small = b"".join(pts.splitlines(keepends=True)[:12])
    put(out, "fuzz_colmap_txt", "sample", three(cams, imgs_small, pts_small))

    cams = b"# cameras\n1 SIMPLE_PINHOLE 640 480 500.5 320 240.25\n2 OPENCV 64 48 50 50 32 24 0.1 0 0 0\n"
    imgs = b"1 1 0 0 0 0.5 -1 3 1 frame 001.jpg\n10.5 20.25 -1\n2 0.7 0.7 0 0 0 0 1 2 b.png\n\n"
    pts = b"1 0 0 1 255 0 0 0.5 1 0\n2 1e-3 -2.5e2 nan 0 128 255 0\n"
    put(out, "fuzz_colmap_txt", "models_and_names", three(cams, imgs, pts))


# ------------------------------------------------------------------ model archive

def fnv1a64(data):
    h = 0xcbf29ce484222325
    for b in data:
        h ^= b
        h = (h * 0x100000001b3) & 0xFFFFFFFFFFFFFFFF
    return h


def archive(meta, arrays):
    """A model.ag2gs file laid out as host/io/model_io.cpp writes it."""
    import json
    entries, blobs, offset = [], b"", 0
    for name, dtype, shape, payload in arrays:
        entries.append({"name": name, "dtype": dtype, "shape": shape, "offset": offset, "bytes": len(payload),
                        "fnv1a64": str(fnv1a64(payload))})
        padded = payload + b"\0" * ((8 - len(payload) % 8) % 8)
        blobs += padded
        offset += len(padded)
    header = json.dumps({"meta": meta, "arrays": entries}, separators=(",", ":")).encode()
    head = b"AG2GSMDL" + struct.pack("<IIQ", 1, 0, len(header)) + header + struct.pack("<Q", fnv1a64(header))
    head += b"\0" * ((8 - len(head) % 8) % 8)
    return head + blobs


def model_seeds(out):
    put(out, "fuzz_model", "empty", archive({}, []))
    put(out, "fuzz_model", "arrays", archive(
        {"iteration": 7, "config": {"lr": 0.001}},
        [("anchors/pos", "f32", [2, 3], struct.pack("<6f", 0, 1, 2, 3, 4, 5)),
         ("anchors/layer", "i32", [2], struct.pack("<2i", 0, 1)),
         ("rng", "u64", [1], struct.pack("<Q", 123)),
         ("flags", "u8", [3], b"\1\0\1")]))


# ------------------------------------------------------------------ JSON

def json_seeds(out):
    put(out, "fuzz_json", "vocab", b"\0" + b'{"red mug": [1, 0, 0.5], "ball": [0, 1, -2e-3]}')
    put(out, "fuzz_json", "label", b"\1" + b'{"info": {"width": 16, "height": 12, "name": "f.jpg"}, "objects": '
        b'[{"category": "cup", "segmentation": [[2, 2], [9, 2.5], [9, 9], [2, 9]], "bbox": [2, 2, 9, 9]}]}')
    put(out, "fuzz_json", "clicks", b"\2" + b'[{"frame": "view_000", "x": 10.5, "y": 3, "category": "mug"}]')
    for name in ("vocab.json", "clicks.json"):
        path = os.path.join("synth_small", name)
        if os.path.exists(os.path.join(SAMPLES, path)) and name == "clicks.json":
            put(out, "fuzz_json", "sample_clicks", b"\2" + read(path))


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: make_seeds.py OUT_DIR")
    out = sys.argv[1]
    npy_seeds(out)
    ply_seeds(out)
    colmap_bin_seeds(out)
    colmap_txt_seeds(out)
    model_seeds(out)
    json_seeds(out)


if __name__ == "__main__":
    main()
