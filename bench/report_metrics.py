#!/usr/bin/env python3
"""Speed against error from one or more training runs.

Reads the metrics.json that `ag2gs train --eval` (or `ag2gs baseline --eval`)
writes into its model folder and prints a Markdown table of test PSNR/SSIM,
training time and model size at each evaluation; with --svg, also draws test
PSNR against training time, one line per run. Standard library only.

  bench/report_metrics.py RUN_DIR_OR_METRICS [...] [--svg plot.svg] [--md table.md]
"""
import argparse
import json
import os
import sys


def load(path):
    if os.path.isdir(path):
        path = os.path.join(path, "metrics.json")
    try:
        with open(path) as f:
            m = json.load(f)
    except OSError as e:
        sys.exit(f"report_metrics: cannot read {path}: {e.strerror}. Train with --eval first.")
    except json.JSONDecodeError as e:
        sys.exit(f"report_metrics: {path} is not valid JSON ({e}); was the run interrupted while writing it?")
    if not m.get("test"):
        sys.exit(f"report_metrics: {path} has no test evaluations; train with --eval (and --test-every N).")
    return path, m


def label_of(path, m):
    name = m.get("method") or "anchors"
    return f"{name} ({os.path.basename(os.path.dirname(os.path.abspath(path)))})"


def rows(m):
    seen = set()
    for e in m["test"]:
        it = e["iteration"]
        if it in seen:  # the final evaluation may repeat the last interval's
            continue
        seen.add(it)
        yield e


def fmt(v, spec):
    return format(v, spec) if isinstance(v, (int, float)) else "-"


def table(runs):
    out = ["| run | iteration | train s | ms/it | test PSNR dB | test SSIM | anchors | Gaussians |",
           "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for path, m in runs:
        lab = label_of(path, m)
        for e in rows(m):
            s = e.get("train_seconds")
            ms = 1000 * s / e["iteration"] if isinstance(s, (int, float)) and e["iteration"] > 0 else None
            out.append(f"| {lab} | {e['iteration']} | {fmt(s, '.1f')} | {fmt(ms, '.1f')} | {e['psnr']:.2f} | "
                       f"{e['ssim']:.4f} | {fmt(e.get('anchors'), 'd')} | {fmt(e.get('gaussians'), 'd')} |")
    for path, m in runs:
        extra = []
        if "peak_rss_mb" in m:
            extra.append(f"peak RSS {m['peak_rss_mb']:.0f} MB")
        if "device" in m:
            extra.append(f"device {m['device']}")
        if extra:
            out.append(f"\n{label_of(path, m)}: " + ", ".join(extra))
    return "\n".join(out) + "\n"


def svg(runs, width=640, height=400):
    pts = []
    for path, m in runs:
        line = [(e["train_seconds"], e["psnr"]) for e in rows(m) if isinstance(e.get("train_seconds"), (int, float))]
        pts.append((label_of(path, m), line))
    xs = [x for _, l in pts for x, _ in l]
    ys = [y for _, l in pts for _, y in l]
    if not xs:
        sys.exit("report_metrics: no evaluation carries train_seconds; cannot plot.")
    x0, x1 = 0.0, max(xs) * 1.05 or 1.0
    y0, y1 = min(ys) - 0.5, max(ys) + 0.5
    L, R, T, B = 60, 20, 20, 50
    sx = lambda x: L + (x - x0) / (x1 - x0) * (width - L - R)
    sy = lambda y: height - B - (y - y0) / (y1 - y0) * (height - T - B)
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]
    s = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
         f'font-size="12"><rect width="100%" height="100%" fill="white"/>',
         f'<line x1="{L}" y1="{height-B}" x2="{width-R}" y2="{height-B}" stroke="black"/>',
         f'<line x1="{L}" y1="{T}" x2="{L}" y2="{height-B}" stroke="black"/>',
         f'<text x="{(width+L-R)/2}" y="{height-12}" text-anchor="middle">training time (s)</text>',
         f'<text x="14" y="{(height-B+T)/2}" transform="rotate(-90 14 {(height-B+T)/2})" '
         f'text-anchor="middle">test PSNR (dB)</text>']
    for k in range(6):
        xv = x0 + (x1 - x0) * k / 5
        yv = y0 + (y1 - y0) * k / 5
        s.append(f'<text x="{sx(xv):.1f}" y="{height-B+16}" text-anchor="middle">{xv:.0f}</text>')
        s.append(f'<text x="{L-6}" y="{sy(yv)+4:.1f}" text-anchor="end">{yv:.1f}</text>')
    for i, (lab, line) in enumerate(pts):
        c = colours[i % len(colours)]
        s.append('<polyline fill="none" stroke="%s" stroke-width="2" points="%s"/>' %
                 (c, " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in line)))
        for x, y in line:
            s.append(f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="3" fill="{c}"/>')
        s.append(f'<text x="{L+10}" y="{T+14+16*i}" fill="{c}">{lab}</text>')
    s.append("</svg>")
    return "\n".join(s) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="model folders or metrics.json files")
    ap.add_argument("--svg", help="write test PSNR against training time here")
    ap.add_argument("--md", help="write the table here as well as to stdout")
    a = ap.parse_args()
    runs = [load(p) for p in a.runs]
    t = table(runs)
    sys.stdout.write(t)
    if a.md:
        with open(a.md, "w") as f:
            f.write(t)
    if a.svg:
        with open(a.svg, "w") as f:
            f.write(svg(runs))


if __name__ == "__main__":
    main()
