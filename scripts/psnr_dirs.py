#!/usr/bin/env python3
"""PSNR between the PNG images of the same name in two folders (Python's
standard library only: 8-bit greyscale, RGB or RGBA PNGs as ag2gs render
writes them). Prints one line per image and the mean; exits 1 when a folder
has no PNG, an image is missing from the other folder, or sizes differ.

    scripts/psnr_dirs.py DIR_A DIR_B
"""
import math
import os
import struct
import sys
import zlib


def read_png(path):
    with open(path, "rb") as f:
        data = f.read()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG file")
    pos, idat, width = 8, [], None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if depth != 8 or interlace != 0 or colour not in (0, 2, 6):
                raise ValueError(f"{path}: only 8-bit, non-interlaced grey/RGB/RGBA PNGs are read")
            channels = {0: 1, 2: 3, 6: 4}[colour]
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if width is None:
        raise ValueError(f"{path}: no IHDR chunk")
    raw = zlib.decompress(b"".join(idat))
    stride = width * channels
    rows, prev = [], bytearray(stride)
    for y in range(height):
        ftype = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - channels] if i >= channels else 0
            b = prev[i]
            c = prev[i - channels] if i >= channels else 0
            if ftype == 1:
                line[i] = (line[i] + a) & 255
            elif ftype == 2:
                line[i] = (line[i] + b) & 255
            elif ftype == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif ftype == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return width, height, channels, b"".join(rows)


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    a_dir, b_dir = sys.argv[1], sys.argv[2]
    names = sorted(n for n in os.listdir(a_dir) if n.endswith(".png"))
    if not names:
        print(f"psnr_dirs: no .png in {a_dir}", file=sys.stderr)
        sys.exit(1)
    values = []
    for name in names:
        other = os.path.join(b_dir, name)
        if not os.path.exists(other):
            print(f"psnr_dirs: {other} is missing", file=sys.stderr)
            sys.exit(1)
        wa, ha, ca, pa = read_png(os.path.join(a_dir, name))
        wb, hb, cb, pb = read_png(other)
        if (wa, ha, ca) != (wb, hb, cb):
            print(f"psnr_dirs: {name}: {wa}x{ha}x{ca} against {wb}x{hb}x{cb}", file=sys.stderr)
            sys.exit(1)
        mse = sum((x - y) ** 2 for x, y in zip(pa, pb)) / len(pa)
        psnr = math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)
        values.append(psnr)
        print(f"{name}: PSNR {psnr:.2f} dB")
    finite = [v for v in values if math.isfinite(v)]
    mean = sum(finite) / len(finite) if finite else math.inf
    print(f"mean PSNR over {len(values)} images: {mean:.2f} dB ({len(values) - len(finite)} identical)")


if __name__ == "__main__":
    main()
