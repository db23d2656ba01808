"""OpenCLIP: image features of mask crops and text embeddings of phrases, both
L2-normalised, from one model so they can be compared (ag2gs's relevancy)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from .errors import InputError


@dataclass
class Clip:
    model: torch.nn.Module
    preprocess: object  # PIL image -> [3, S, S] tensor, the model's own resize and normalisation
    tokenizer: object  # open_clip's tokenizer for the architecture: list[str] -> [P, context] int64
    device: torch.device
    dim: int


def check_clip_names(arch: str, checkpoint: str | None) -> None:
    """Errors for an unknown architecture, or a checkpoint that is neither a
    file nor one of open_clip's pretrained tags for it."""
    import open_clip

    models = open_clip.list_models()
    if arch not in models:
        close = [m for m in models if arch.lower().replace("/", "-") in m.lower()][:8]
        hint = f" (close: {', '.join(close)})" if close else ""
        raise InputError(f"--clip-model {arch}: not an open_clip architecture{hint}; "
                         f"the names are listed by `python -c 'import open_clip; print(open_clip.list_models())'`, "
                         f"e.g. ViT-B-16 (LangSplat's), ViT-B-32, ViT-L-14")
    if checkpoint is None or os.path.isfile(checkpoint):
        return
    tags = open_clip.list_pretrained_tags_by_model(arch)
    if checkpoint not in tags:
        known = f"; its pretrained tags are {', '.join(tags)}" if tags else ""
        raise InputError(f"--clip-checkpoint {checkpoint}: no such file, and not a pretrained tag of {arch}{known}")


def load_clip(arch: str, checkpoint: str | None, device: torch.device, seed: int | None) -> Clip:
    """checkpoint: a file, or an open_clip pretrained tag (downloaded by
    open_clip into its cache); None builds the architecture with random
    weights from seed (tests only)."""
    import logging

    import open_clip

    check_clip_names(arch, checkpoint)
    if checkpoint is None:
        torch.manual_seed(seed)
        # open_clip logs a warning for an untrained model; the command says so itself.
        logging.getLogger().setLevel(logging.ERROR)
    try:
        model, _, preprocess = open_clip.create_model_and_transforms(arch, pretrained=checkpoint, device=device)
    except Exception as e:  # torch's RuntimeError for other shapes, pickle's and zipfile's for other files
        if checkpoint is None:
            raise
        detail = " ".join(str(e).split())
        raise InputError(f"--clip-checkpoint {checkpoint} cannot be loaded as --clip-model {arch} ({detail[:160]}...); "
                         "give the architecture the file was trained as, or download the file again")
    model.eval()
    tokenizer = open_clip.get_tokenizer(arch)
    with torch.inference_mode():
        dim = int(model.encode_text(tokenizer(["a"]).to(device)).shape[-1])
    return Clip(model, preprocess, tokenizer, device, dim)


def _normalised(x: torch.Tensor) -> np.ndarray:
    x = x.float()
    return (x / x.norm(dim=-1, keepdim=True).clamp(min=1e-12)).cpu().numpy().astype(np.float32)


@torch.inference_mode()
def encode_crops(clip: Clip, crops: list[np.ndarray], batch: int = 32) -> np.ndarray:
    """[N, D] float32 unit rows, one per [S, S, 3] uint8 crop."""
    out = [np.zeros((0, clip.dim), dtype=np.float32)]
    for start in range(0, len(crops), batch):
        x = torch.stack([clip.preprocess(Image.fromarray(c)) for c in crops[start:start + batch]]).to(clip.device)
        out.append(_normalised(clip.model.encode_image(x)))
    return np.concatenate(out)


def tokenize(clip: Clip, phrases: list[str]) -> torch.Tensor:
    """The ids the text tower reads: open_clip's tokenizer for the architecture."""
    return clip.tokenizer(phrases)


@torch.inference_mode()
def embed_phrases(clip: Clip, phrases: list[str], batch: int = 64) -> np.ndarray:
    """[P, D] float32 unit rows, the phrases as given (no prompt template)."""
    out = [np.zeros((0, clip.dim), dtype=np.float32)]
    for start in range(0, len(phrases), batch):
        ids = tokenize(clip, phrases[start:start + batch]).to(clip.device)
        out.append(_normalised(clip.model.encode_text(ids)))
    return np.concatenate(out)
