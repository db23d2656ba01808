"""SAM's automatic masks, sorted into the four levels of the LangSplat layout.

A grid of points prompts SAM; for each point SAM's decoder proposes three
nested masks (multimask output). Ordered by pixel area they are the point's
small, medium and large mask, whatever order the decoder gave them in. Each
level keeps the proposals whose predicted IoU and stability score pass the
thresholds and that cover at least min_area pixels, then removes near
duplicates by box non-maximum suppression (highest predicted IoU wins). The
default level is all three levels pooled and suppressed again, which is what
SAM's automatic mask generator returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torchvision.ops import nms

from .architectures import SAM_MODELS  # noqa: F401 (re-exported)
from .errors import InputError

LEVEL_NAMES = ("default", "small", "medium", "large")


@dataclass
class MaskSettings:
    points_per_side: int = 32  # the prompt grid is points_per_side^2 points
    points_per_batch: int = 64  # prompts decoded at once (memory: 3 x H x W floats each)
    pred_iou_thresh: float = 0.7  # LangSplat's setting (SAM's default is 0.88)
    stability_thresh: float = 0.85  # LangSplat's setting (SAM's default is 0.95)
    stability_offset: float = 1.0  # logit offset of the stability score
    box_nms_thresh: float = 0.7  # box IoU above which the lower-scored mask is dropped
    min_area: int = 100  # pixels


def load_sam(model_name: str, checkpoint: str | None, device: torch.device, seed: int | None):
    """A SamPredictor; checkpoint None builds the architecture with random
    weights from seed (tests only)."""
    from segment_anything import SamPredictor, sam_model_registry

    if model_name not in SAM_MODELS:
        raise InputError(f"--sam-model {model_name}: unknown SAM architecture; use one of {', '.join(SAM_MODELS)} "
                         "(the one the --sam-checkpoint file was trained as)")
    if checkpoint is None:
        torch.manual_seed(seed)
        sam = sam_model_registry[model_name](checkpoint=None)
    else:
        sam = sam_model_registry[model_name](checkpoint=None)
        try:
            state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        except Exception as e:
            raise InputError(f"--sam-checkpoint {checkpoint}: not a PyTorch checkpoint ({str(e).splitlines()[0]}); "
                             "download sam_vit_b_01ec64.pth, sam_vit_l_0b3195.pth or sam_vit_h_4b8939.pth again")
        try:
            sam.load_state_dict(state)
        except Exception as e:
            detail = " ".join(str(e).split())  # torch lists every missing key: keep the start
            raise InputError(f"--sam-checkpoint {checkpoint} does not fit --sam-model {model_name} "
                             f"({detail[:160]}...); give the architecture the file was trained as "
                             "(sam_vit_b_* is vit_b, sam_vit_l_* vit_l, sam_vit_h_* vit_h)")
    sam.to(device).eval()
    return SamPredictor(sam)


def point_grid(points_per_side: int, width: int, height: int) -> np.ndarray:
    """[n*n, 2] (x, y) pixel coordinates: the centres of an n x n grid of cells."""
    g = (np.arange(points_per_side) + 0.5) / points_per_side
    xs, ys = np.meshgrid(g * width, g * height)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def stability_score(logits: torch.Tensor, offset: float) -> torch.Tensor:
    """IoU of the masks thresholded at +offset and at -offset (the first lies
    inside the second, so the IoU is the ratio of their areas). [..., H, W] -> [...]"""
    inner = (logits > offset).sum(dim=(-1, -2), dtype=torch.int64)
    outer = (logits > -offset).sum(dim=(-1, -2), dtype=torch.int64)
    return inner.float() / outer.clamp(min=1).float()


def mask_boxes(masks: torch.Tensor) -> torch.Tensor:
    """[N, H, W] bool -> [N, 4] float (x0, y0, x1, y1), x1 and y1 exclusive."""
    n, h, w = masks.shape
    if n == 0:
        return torch.zeros((0, 4))
    cols = masks.any(dim=1)  # [N, W]
    rows = masks.any(dim=2)  # [N, H]
    xi = torch.arange(w)
    yi = torch.arange(h)
    x0 = torch.where(cols, xi, w).min(dim=1).values
    x1 = torch.where(cols, xi, -1).max(dim=1).values + 1
    y0 = torch.where(rows, yi, h).min(dim=1).values
    y1 = torch.where(rows, yi, -1).max(dim=1).values + 1
    return torch.stack([x0, y0, x1, y1], dim=1).float()


def suppress(masks: torch.Tensor, scores: torch.Tensor, iou: float) -> tuple[torch.Tensor, torch.Tensor]:
    if len(masks) == 0 or iou >= 1:
        return masks, scores
    keep = nms(mask_boxes(masks), scores, iou)
    return masks[keep], scores[keep]


def _decode(predictor, points: np.ndarray, image_hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Three mask logits per point at the image's size, and their predicted IoU:
    [B, 3, H, W], [B, 3]. The decoder's 256 x 256 output is cropped to the
    image's part and resized straight to the image (SAM's own predictor goes
    through 1024 x 1024 first, which costs more and changes nothing visible)."""
    sam = predictor.model
    device = predictor.device
    coords = torch.as_tensor(predictor.transform.apply_coords(points, image_hw), dtype=torch.float32, device=device)
    labels = torch.ones((len(points), 1), dtype=torch.int64, device=device)
    sparse, dense = sam.prompt_encoder(points=(coords[:, None, :], labels), boxes=None, masks=None)
    low_res, iou = sam.mask_decoder(image_embeddings=predictor.features, image_pe=sam.prompt_encoder.get_dense_pe(),
                                    sparse_prompt_embeddings=sparse, dense_prompt_embeddings=dense,
                                    multimask_output=True)
    scale = low_res.shape[-1] / sam.image_encoder.img_size
    h_in, w_in = predictor.input_size
    low_res = low_res[..., :math.ceil(h_in * scale), :math.ceil(w_in * scale)]
    return F.interpolate(low_res, image_hw, mode="bilinear", align_corners=False), iou


@torch.inference_mode()
def generate_levels(predictor, rgb: np.ndarray, settings: MaskSettings) -> list[torch.Tensor]:
    """The masks of one image by level (default, small, medium, large): four
    [N_k, H, W] bool tensors on the CPU, each in the order of decreasing
    predicted IoU."""
    h, w = rgb.shape[:2]
    predictor.set_image(rgb)
    points = point_grid(settings.points_per_side, w, h)
    kept: list[list[tuple[torch.Tensor, torch.Tensor]]] = [[], [], []]
    for start in range(0, len(points), settings.points_per_batch):
        logits, iou = _decode(predictor, points[start:start + settings.points_per_batch], (h, w))
        area = (logits > 0).sum(dim=(2, 3))
        order = area.argsort(dim=1, stable=True)  # the point's three masks, smallest first
        logits = logits.gather(1, order[:, :, None, None].expand_as(logits))
        iou = iou.gather(1, order)
        stability = stability_score(logits, settings.stability_offset)
        for k in range(3):
            ok = (iou[:, k] > settings.pred_iou_thresh) & (stability[:, k] > settings.stability_thresh)
            masks = logits[ok, k] > 0
            big = masks.sum(dim=(1, 2)) >= settings.min_area
            kept[k].append((masks[big].cpu(), iou[ok, k][big].float().cpu()))
        del logits
    predictor.reset_image()
    levels = []
    pooled_masks, pooled_scores = [], []
    for k in range(3):
        masks = torch.cat([m for m, _ in kept[k]]) if kept[k] else torch.zeros((0, h, w), dtype=torch.bool)
        scores = torch.cat([s for _, s in kept[k]]) if kept[k] else torch.zeros(0)
        masks, scores = suppress(masks, scores, settings.box_nms_thresh)
        order = scores.argsort(descending=True, stable=True)
        levels.append(masks[order])
        pooled_masks.append(masks[order])
        pooled_scores.append(scores[order])
    default, _ = suppress(torch.cat(pooled_masks), torch.cat(pooled_scores), settings.box_nms_thresh)
    return [default] + levels
