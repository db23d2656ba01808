#!/usr/bin/env python3
"""Generates the tiny synthetic scene in data_samples/ (Python 3, standard library only).

Run from anywhere:  python3 data_samples/make_samples.py
Output (next to this script, deterministic: a rerun reproduces the same bytes):

  tiny_scene/gaussians.ply         300 Gaussians in five coloured blobs around the
                                   origin, standard 3DGS point_cloud.ply layout
                                   (binary little-endian floats x y z nx ny nz
                                   f_dc_0..2 f_rest_0..8 opacity scale_0..2
                                   rot_0..3 feat_0..2), SH degree 1; opacity as
                                   logit, scale as log, rot = (w, x, y, z),
                                   f_rest channel-major; feat_0..2 is the blob's
                                   semantic feature (one unit vector per blob).
  tiny_scene/sparse/0/*.txt        COLMAP text model: 2 PINHOLE cameras, 4 images
                                   of 160x120 looking at the origin from distance
                                   4, 60 sparse points (every 5th Gaussian centre)
                                   with tracks and matching 2D observations.
  tiny_scene/images/               empty (.gitkeep); ground-truth renders go here.
  tiny_scene_bin/sparse/0/*.bin    the same COLMAP model in binary format; every
                                   number equals its text counterpart exactly.

World frame: z up. Cameras follow COLMAP: X_cam = R X_world + t, x right,
y down, z forward. Image ids are deliberately not in name order, and views
000/001 use camera 1 while 002/003 use camera 2, so readers must sort by name
and look cameras up by id.
"""

import math
import os
import random
import struct

HERE = os.path.dirname(os.path.abspath(__file__))
SH_C0 = 0.28209479177387814
WIDTH, HEIGHT = 160, 120
DISTANCE = 4.0

# (centre, colour in [0,1], semantic feature): one entry per blob.
BLOBS = [
    ((-0.45, -0.30, 0.00), (0.90, 0.15, 0.10), (1.0, 0.0, 0.0)),
    ((0.45, -0.30, 0.10), (0.15, 0.80, 0.20), (0.0, 1.0, 0.0)),
    ((0.00, 0.45, -0.10), (0.15, 0.25, 0.90), (0.0, 0.0, 1.0)),
    ((0.00, 0.00, 0.45), (0.95, 0.85, 0.15), (0.7071067811865476, 0.7071067811865476, 0.0)),
    ((0.05, 0.05, -0.40), (0.85, 0.85, 0.85), (0.0, 0.7071067811865476, 0.7071067811865476)),
]
PER_BLOB = 60

# camera_id -> (fx, fy, cx, cy)
CAMERAS = {1: (160.0, 160.0, 80.0, 60.0), 2: (170.0, 170.0, 79.5, 60.5)}
# (image_id, name, camera_id, azimuth deg, elevation deg)
VIEWS = [
    (1, "view_002.png", 2, 225.0, 20.0),
    (2, "view_000.png", 1, 45.0, 25.0),
    (3, "view_003.png", 2, 315.0, 30.0),
    (4, "view_001.png", 1, 135.0, 15.0),
]


def f32(x):
    """x rounded to float32, as a Python float."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def normalize(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def matvec(m, v):
    return tuple(sum(m[r][c] * v[c] for c in range(3)) for r in range(3))


def rotmat_to_quat(m):
    """(w, x, y, z) with w >= 0 for a rotation matrix (rows)."""
    trace = m[0][0] + m[1][1] + m[2][2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = (0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s)
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = ((m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s)
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = ((m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = ((m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s)
    if q[0] < 0:
        q = tuple(-c for c in q)
    return normalize(q)


def quat_to_rotmat(q):
    w, x, y, z = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )


def look_at_origin(azimuth_deg, elevation_deg):
    """COLMAP pose (q, t) of a camera at DISTANCE looking at the origin, z up."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    centre = (DISTANCE * math.cos(el) * math.cos(az), DISTANCE * math.cos(el) * math.sin(az),
              DISTANCE * math.sin(el))
    forward = normalize(tuple(-c for c in centre))
    right = normalize(cross(forward, (0.0, 0.0, 1.0)))
    down = cross(forward, right)
    q = rotmat_to_quat((right, down, forward))
    r = quat_to_rotmat(q)  # the rotation readers will rebuild from q
    # Rounded to 1e-12 so the files show 0.0 rather than 2e-16; harmless for the pose.
    t = tuple(round(-c, 12) + 0.0 for c in matvec(r, centre))
    return q, t, r


def make_gaussians(rng):
    """Rows of raw PLY values (pre-activation) and the blob index of each."""
    rows, blob_of = [], []
    for b, (centre, colour, feat) in enumerate(BLOBS):
        for _ in range(PER_BLOB):
            xyz = [centre[i] + rng.gauss(0.0, 0.14) for i in range(3)]
            f_dc = [(min(max(colour[c] + rng.gauss(0.0, 0.04), 0.0), 1.0) - 0.5) / SH_C0
                    for c in range(3)]
            f_rest = [rng.uniform(-0.05, 0.05) for _ in range(9)]  # channel-major, K-1 = 3
            opacity = rng.uniform(0.55, 0.95)
            base = math.log(0.05) + rng.gauss(0.0, 0.2)
            log_scale = [base + rng.gauss(0.0, 0.25) for _ in range(3)]
            rot = normalize([rng.gauss(0.0, 1.0) for _ in range(4)])
            if rot[0] < 0:
                rot = tuple(-c for c in rot)
            logit = math.log(opacity / (1.0 - opacity))
            rows.append(xyz + [0.0, 0.0, 0.0] + f_dc + f_rest + [logit] + log_scale + list(rot) +
                        list(feat))
            blob_of.append(b)
    return rows, blob_of


def write_ply(path, rows):
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] +
             ["f_rest_%d" % i for i in range(9)] +
             ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"] +
             ["feat_0", "feat_1", "feat_2"])
    assert all(len(r) == len(names) for r in rows)
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % len(rows)
    header += "".join("property float %s\n" % n for n in names) + "end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for r in rows:
            f.write(struct.pack("<%df" % len(r), *r))


def project(cam, r, t, p):
    fx, fy, cx, cy = cam
    pc = [a + b for a, b in zip(matvec(r, p), t)]
    if pc[2] <= 0.1:
        return None
    u, v = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy
    if 0 <= u < WIDTH and 0 <= v < HEIGHT:
        return u, v
    return None


def build_model(rows, blob_of):
    """COLMAP records; every float is one the text files print exactly (repr or rounded)."""
    images = []
    for image_id, name, cam_id, az, el in VIEWS:
        q, t, r = look_at_origin(az, el)
        images.append({"id": image_id, "name": name, "camera": cam_id, "q": q, "t": t, "r": r,
                       "points2d": []})
    points = []
    for i in range(0, len(rows), 5):
        pid = 10 + 3 * (i // 5)  # sparse, increasing ids
        xyz = tuple(f32(c) for c in rows[i][0:3])
        colour = BLOBS[blob_of[i]][1]
        rgb = tuple(int(round(255 * c)) for c in colour)
        track = []
        for im in images:
            uv = project(CAMERAS[im["camera"]], im["r"], im["t"], xyz)
            if uv is None:
                continue
            uv = (float("%.2f" % uv[0]), float("%.2f" % uv[1]))
            track.append((im["id"], len(im["points2d"])))
            im["points2d"].append((uv[0], uv[1], pid))
        points.append({"id": pid, "xyz": xyz, "rgb": rgb, "error": 0.5, "track": track})
    return images, points


def write_text_model(folder, images, points):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "cameras.txt"), "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write("# Number of cameras: %d\n" % len(CAMERAS))
        for cid, params in sorted(CAMERAS.items()):
            f.write("%d PINHOLE %d %d %s\n" % (cid, WIDTH, HEIGHT, " ".join(repr(p) for p in params)))
    n_obs = sum(len(im["points2d"]) for im in images)
    with open(os.path.join(folder, "images.txt"), "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write("# Number of images: %d, mean observations per image: %g\n" %
                (len(images), n_obs / len(images)))
        for im in images:
            f.write("%d %s %s %d %s\n" % (im["id"], " ".join(repr(c) for c in im["q"]),
                                          " ".join(repr(c) for c in im["t"]), im["camera"], im["name"]))
            f.write(" ".join("%.2f %.2f %d" % p for p in im["points2d"]) + "\n")
    with open(os.path.join(folder, "points3D.txt"), "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write("# Number of points: %d\n" % len(points))
        for p in points:
            f.write("%d %s %d %d %d %s %s\n" % (p["id"], " ".join(repr(c) for c in p["xyz"]),
                                              p["rgb"][0], p["rgb"][1], p["rgb"][2], repr(p["error"]),
                                              " ".join("%d %d" % tr for tr in p["track"])))


def write_binary_model(folder, images, points):
    """Layout of COLMAP's scripts/python/read_write_model.py (little endian)."""
    os.makedirs(folder, exist_ok=True)
    pinhole_model_id = 1
    with open(os.path.join(folder, "cameras.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(CAMERAS)))
        for cid, params in sorted(CAMERAS.items()):
            f.write(struct.pack("<iiQQ", cid, pinhole_model_id, WIDTH, HEIGHT))
            f.write(struct.pack("<4d", *params))
    with open(os.path.join(folder, "images.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for im in images:
            f.write(struct.pack("<i4d3di", im["id"], *im["q"], *im["t"], im["camera"]))
            f.write(im["name"].encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", len(im["points2d"])))
            for x, y, pid in im["points2d"]:
                f.write(struct.pack("<ddq", x, y, pid))
    with open(os.path.join(folder, "points3D.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for p in points:
            f.write(struct.pack("<Q3d3Bd", p["id"], *p["xyz"], *p["rgb"], p["error"]))
            f.write(struct.pack("<Q", len(p["track"])))
            for image_id, idx in p["track"]:
                f.write(struct.pack("<ii", image_id, idx))


def main():
    rng = random.Random(20240611)
    rows, blob_of = make_gaussians(rng)
    images, points = build_model(rows, blob_of)

    scene = os.path.join(HERE, "tiny_scene")
    os.makedirs(os.path.join(scene, "images"), exist_ok=True)
    open(os.path.join(scene, "images", ".gitkeep"), "w").close()
    write_ply(os.path.join(scene, "gaussians.ply"), rows)
    write_text_model(os.path.join(scene, "sparse", "0"), images, points)
    write_binary_model(os.path.join(HERE, "tiny_scene_bin", "sparse", "0"), images, points)

    for im in images:
        print("%s: camera %d, %d points visible" % (im["name"], im["camera"], len(im["points2d"])))
    print("%d Gaussians, %d sparse points" % (len(rows), len(points)))


if __name__ == "__main__":
    main()
