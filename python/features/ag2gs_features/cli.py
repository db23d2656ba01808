"""ag2gs-features: the command line.

Every input is checked before any model runs: a missing or unreadable
weights file, an unknown architecture, a scene without images or with images
of mixed sizes, an output that would be overwritten without --force. Each is
one line on stderr naming the file or flag and the fix, and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from .errors import InputError

PROG = "ag2gs-features"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Write SAM masks at three levels and the CLIP features of each masked crop as SCENE_DIR/"
        "language_features/<stem>_s.npy and <stem>_f.npy (the LangSplat layout `ag2gs train` reads), and/or CLIP "
        "text embeddings of a phrase list as a vocabulary JSON (`ag2gs query --vocab`).",
        epilog="Example: ag2gs-features scenes/room --sam-model vit_h --sam-checkpoint sam_vit_h_4b8939.pth "
        "--clip-model ViT-B-16 --clip-checkpoint open_clip_vit_b16_laion2b.bin --vocab phrases.txt")
    p.add_argument("scene_dir", nargs="?", type=Path,
                   help="scene folder: reads images/ (every image, recursively), writes language_features/; "
                   "leave out to write only the vocabulary")
    p.add_argument("--sam-model", default="vit_h", help="SAM architecture of --sam-checkpoint: vit_b, vit_l or vit_h "
                   "(default vit_h, LangSplat's)")
    p.add_argument("--sam-checkpoint", metavar="FILE", help="SAM weights, e.g. sam_vit_h_4b8939.pth")
    p.add_argument("--clip-model", default="ViT-B-16", metavar="ARCH",
                   help="open_clip architecture (default ViT-B-16, LangSplat's)")
    p.add_argument("--clip-checkpoint", metavar="FILE|TAG",
                   help="open_clip weights: a file, or a pretrained tag of ARCH (e.g. laion2b_s34b_b88k, fetched "
                   "by open_clip into its cache)")
    p.add_argument("--device", default="auto", help="torch device: cpu, cuda, cuda:1, mps, ... (default: cuda when "
                   "available, else cpu)")
    p.add_argument("--vocab", metavar="PHRASES", type=Path,
                   help="also embed these phrases: a .txt file (one per line, # comments) or a .json list of "
                   "strings or object whose keys are the phrases")
    p.add_argument("-o", "--vocab-out", metavar="FILE", type=Path,
                   help="vocabulary to write (default SCENE_DIR/vocab.json; required without SCENE_DIR)")
    p.add_argument("--points-per-side", type=int, default=32, metavar="N",
                   help="SAM prompt grid N x N per image (default 32; cost grows with N^2)")
    p.add_argument("--points-per-batch", type=int, default=64, metavar="N",
                   help="prompts decoded at once (default 64; lower it if memory runs out on large images)")
    p.add_argument("--pred-iou-thresh", type=float, default=0.7, help="keep masks SAM scores above this (default 0.7)")
    p.add_argument("--stability-thresh", type=float, default=0.85,
                   help="keep masks whose stability score is above this (default 0.85)")
    p.add_argument("--box-nms-thresh", type=float, default=0.7,
                   help="of two masks of a level whose boxes overlap by more than this IoU, keep the better scored "
                   "(default 0.7; 1 = keep all)")
    p.add_argument("--min-mask-area", type=int, default=100, metavar="PIXELS",
                   help="drop masks smaller than this (default 100)")
    p.add_argument("--max-side", type=int, default=1024, metavar="PIXELS",
                   help="make masks at the image size, or with the longer side this long for larger images "
                   "(default 1024, SAM's input; ag2gs rescales masks to its views)")
    p.add_argument("--clip-batch", type=int, default=32, metavar="N", help="crops per CLIP batch (default 32)")
    p.add_argument("--force", action="store_true",
                   help="replace existing <stem>_s.npy/_f.npy pairs in language_features/ and an existing "
                   "vocabulary file (default: refused)")
    p.add_argument("--random-weights", type=int, metavar="SEED",
                   help="FOR TESTS ONLY: build both models with random weights from SEED instead of loading "
                   "checkpoints, and keep every mask (score filters off); the features mean nothing")
    return p


def read_phrases(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise InputError(f"--vocab {path}: cannot be read ({e.strerror}); give a .txt or .json phrase list")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"--vocab {path}: not valid JSON ({e}); give a list of strings")
        if isinstance(data, dict):
            data = list(data)
        if not isinstance(data, list) or not all(isinstance(x, str) for x in data):
            raise InputError(f"--vocab {path}: a JSON phrase list is a list of strings or an object keyed by phrase")
        phrases = [x.strip() for x in data]
    else:
        phrases = [ln.strip() for ln in text.splitlines()]
        phrases = [ln for ln in phrases if ln and not ln.startswith("#")]
    phrases = [x for x in phrases if x]
    if not phrases:
        raise InputError(f"--vocab {path}: holds no phrases")
    if len(set(phrases)) != len(phrases):
        dup = next(x for x in phrases if phrases.count(x) > 1)
        raise InputError(f"--vocab {path}: phrase '{dup}' appears twice; vocabulary keys must be unique")
    return phrases


def check_readable(flag: str, path: str) -> None:
    if not os.path.exists(path):
        raise InputError(f"{flag} {path}: no such file; download the weights and give their path")
    if not os.path.isfile(path):
        raise InputError(f"{flag} {path}: not a file; give the weights file itself")
    try:
        with open(path, "rb") as f:
            f.read(1)
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot be read ({e.strerror}); check its permissions")


def check_arguments(args: argparse.Namespace) -> dict:
    """Everything that can be checked without a model. Returns the plan."""
    plan: dict = {}
    if args.scene_dir is None and args.vocab is None:
        raise InputError("nothing to do: give SCENE_DIR (masks and features) and/or --vocab PHRASES (text embeddings)")
    for flag, value, low in (("--points-per-side", args.points_per_side, 1),
                             ("--points-per-batch", args.points_per_batch, 1),
                             ("--clip-batch", args.clip_batch, 1), ("--min-mask-area", args.min_mask_area, 0),
                             ("--max-side", args.max_side, 8)):
        if value < low:
            raise InputError(f"{flag} {value}: must be at least {low}")
    if args.random_weights is not None:
        for flag, value in (("--sam-checkpoint", args.sam_checkpoint), ("--clip-checkpoint", args.clip_checkpoint)):
            if value is not None:
                raise InputError(f"{flag} and --random-weights exclude each other; --random-weights is for tests")
    else:
        if args.clip_checkpoint is None:
            raise InputError("--clip-checkpoint is required: the open_clip weights file (or a pretrained tag) for "
                             f"--clip-model {args.clip_model}")
        if os.sep in args.clip_checkpoint or os.path.splitext(args.clip_checkpoint)[1]:
            check_readable("--clip-checkpoint", args.clip_checkpoint)
        if args.scene_dir is not None:
            if args.sam_checkpoint is None:
                raise InputError("--sam-checkpoint is required: the SAM weights file (e.g. sam_vit_h_4b8939.pth) "
                                 f"for --sam-model {args.sam_model}")
            check_readable("--sam-checkpoint", args.sam_checkpoint)
    if args.scene_dir is not None:
        from .architectures import SAM_MODELS
        from .scene_images import list_scene_images

        if args.sam_model not in SAM_MODELS:
            raise InputError(f"--sam-model {args.sam_model}: unknown SAM architecture; use one of "
                             f"{', '.join(SAM_MODELS)} (the one the --sam-checkpoint file was trained as)")
        if not args.scene_dir.is_dir():
            raise InputError(f"{args.scene_dir}: no such folder; SCENE_DIR is a scene with images/")
        plan["images"] = list_scene_images(args.scene_dir)
        out = args.scene_dir / "language_features"
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: exists and is not a folder; move it away")
        existing = sorted(out.glob("*.npy")) if out.is_dir() else []
        if existing and not args.force:
            raise InputError(f"{out}: already holds {len(existing)} .npy files (e.g. {existing[0].name}); pass "
                             "--force to replace them, or move the folder away")
        plan["out_dir"] = out
    if args.vocab is not None:
        plan["phrases"] = read_phrases(args.vocab)
        vocab_out = args.vocab_out
        if vocab_out is None:
            if args.scene_dir is None:
                raise InputError("-o/--vocab-out FILE is required when no SCENE_DIR is given")
            vocab_out = args.scene_dir / "vocab.json"
        if vocab_out.exists() and not args.force:
            raise InputError(f"-o {vocab_out}: exists; pass --force to replace it")
        if not vocab_out.parent.is_dir():
            raise InputError(f"-o {vocab_out}: the folder {vocab_out.parent} does not exist")
        plan["vocab_out"] = vocab_out
    elif args.vocab_out is not None:
        raise InputError("-o/--vocab-out needs --vocab PHRASES")
    return plan


def choose_device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise InputError(f"--device {name}: not a torch device ({e}); use cpu, cuda, cuda:N, mps, ...")
    available = {"cuda": torch.cuda.is_available,
                 "mps": lambda: hasattr(torch.backends, "mps") and torch.backends.mps.is_available()}
    if device.type in available and not available[device.type]():
        raise InputError(f"--device {name}: this PyTorch build or machine has no {device.type.upper()} device; "
                         "use --device cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise InputError(f"--device {name}: there are {torch.cuda.device_count()} CUDA devices")
    return device


def format_duration(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def log(message: str) -> None:
    print(f"{PROG}: {message}", file=sys.stderr, flush=True)


def features_of_levels(clip, rgb, levels, batch):
    """CLIP features of every mask of every level; a mask that appears in
    several levels (the default level repeats the others) is encoded once."""
    import numpy as np

    from .clip_features import encode_crops
    from .crops import mask_crop

    unique: dict[bytes, int] = {}
    crops, rows = [], []
    for masks in levels:
        level_rows = []
        for m in masks:
            key = np.packbits(m).tobytes()
            if key not in unique:
                unique[key] = len(crops)
                crops.append(mask_crop(rgb, m))
            level_rows.append(unique[key])
        rows.append(level_rows)
    encoded = encode_crops(clip, crops, batch)
    return [encoded[r] for r in rows], len(crops)


def run_scene(args, plan, sam, clip) -> None:
    import numpy as np

    from .layout import build_layout, level_order, write_pair
    from .sam_levels import MaskSettings, generate_levels
    from .scene_images import load_rgb, working_size

    settings = MaskSettings(args.points_per_side, args.points_per_batch, args.pred_iou_thresh,
                            args.stability_thresh, 1.0, args.box_nms_thresh, args.min_mask_area)
    if args.random_weights is not None:
        settings.pred_iou_thresh = -math.inf
        settings.stability_thresh = -math.inf
    images = plan["images"]
    out_dir: Path = plan["out_dir"]
    out_dir.mkdir(exist_ok=True)
    size = working_size(images[0].width, images[0].height, args.max_side)
    log(f"{len(images)} image{'s' if len(images) != 1 else ''} of {images[0].width}x{images[0].height} in {args.scene_dir / 'images'} -> {out_dir}, "
        f"masks at {size[0]}x{size[1]} (SAM {args.sam_model}, {settings.points_per_side}x{settings.points_per_side} "
        f"points; CLIP {args.clip_model}, {clip.dim}-d)")
    start = time.monotonic()
    total_masks = 0
    for i, image in enumerate(images):
        t0 = time.monotonic()
        rgb = load_rgb(image, size)
        levels = [m.numpy() for m in generate_levels(sam, rgb, settings)]
        levels = [m[level_order(m)] for m in levels]
        features, encoded = features_of_levels(clip, rgb, levels, args.clip_batch)
        s, f = build_layout(levels, features)
        if len(f) == 0:
            f = np.zeros((0, clip.dim), dtype=np.float32)
        write_pair(out_dir, image.stem, s, f)
        total_masks += len(f)
        done = i + 1
        elapsed = time.monotonic() - start
        eta = elapsed / done * (len(images) - done)
        counts = "/".join(str(len(m)) for m in levels)
        log(f"[{done}/{len(images)}] {image.name}: masks default/small/medium/large {counts}, {encoded} crops "
            f"encoded, {time.monotonic() - t0:.1f} s; elapsed {format_duration(elapsed)}, "
            f"ETA {format_duration(eta)}")
    log(f"wrote {2 * len(images)} files, {total_masks} masks, in {format_duration(time.monotonic() - start)}")


def run_vocab(plan, clip) -> None:
    from .clip_features import embed_phrases
    from .layout import write_vocabulary

    phrases = plan["phrases"]
    write_vocabulary(plan["vocab_out"], phrases, embed_phrases(clip, phrases))
    log(f"wrote {plan['vocab_out']}: {len(phrases)} phrase{'s' if len(phrases) != 1 else ''}, {clip.dim}-d")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        plan = check_arguments(args)
        device = choose_device(args.device)
        from .clip_features import check_clip_names, load_clip

        check_clip_names(args.clip_model, args.clip_checkpoint)
        if args.random_weights is not None:
            log(f"--random-weights {args.random_weights}: untrained models, for tests only; the features mean "
                "nothing")
        sam = None
        if args.scene_dir is not None:
            from .sam_levels import load_sam

            sam = load_sam(args.sam_model, args.sam_checkpoint, device, args.random_weights)
        clip = load_clip(args.clip_model, args.clip_checkpoint, device, args.random_weights)
        if sam is not None:
            run_scene(args, plan, sam, clip)
        if args.vocab is not None:
            run_vocab(plan, clip)
    except InputError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; the images finished so far are written", file=sys.stderr)
        return 130
    return 0
