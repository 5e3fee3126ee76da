"""The training losses, one home: the layout losses every run uses (`layout_loss`, weighted pixel
cross-entropy; `layout_iou_loss`, soft IoU), the distillation loss (`--teacher`) and the
least-squares GAN losses of the patch discriminators (RackLay-D-disc). The struct decoder's
direct loss on its structure is `racklay.structure.structure_loss` (it reads the structure's
own fields). Layout tensors are (N, R, 3, S, S) logits and (N, R, S, S) class ids.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .layout import NUM_CLASSES


def layout_loss(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Per-shelf weighted pixel cross-entropy. logits (N, R, 3, S, S), target (N, R, S, S) class ids
    (any integer type: the datasets give uint8)."""
    return F.cross_entropy(logits.float().transpose(1, 2), target.long(), weight=weight)


def layout_iou_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU (Jaccard) of the softmax probabilities with the truth, per foreground class
    (shelf, box) over every pixel of the batch (as the dataset-level IoU counts them), averaged over
    the two classes. Weighted cross-entropy alone calls a pixel shelf or box as soon as it is
    somewhat likely, so footprints come out too large when the rack's size is uncertain; this term
    rewards the footprint that maximises the overlap instead."""
    probs = logits.float().softmax(2)
    loss = 0.0
    for c in range(1, NUM_CLASSES):
        p, g = probs[:, :, c], (target == c).float()
        inter = (p * g).sum()
        loss = loss + 1 - (inter + 1.0) / (p.sum() + g.sum() - inter + 1.0)
    return loss / (NUM_CLASSES - 1)


def distill_loss(logits: torch.Tensor, teacher_logits: torch.Tensor) -> torch.Tensor:
    """Knowledge distillation: KL(teacher || model) of the per-pixel class distributions, summed
    over the 3 classes and averaged over shelves and pixels (0 when the model's layout
    probabilities equal the teacher's). logits, teacher_logits (N, R, 3, S, S)."""
    t = teacher_logits.float().log_softmax(2)
    return F.kl_div(logits.float().log_softmax(2), t, log_target=True, reduction="none").sum(2).mean()


def one_hot_layouts(target: torch.Tensor) -> torch.Tensor:
    """(N, R, S, S) class ids -> (N, R, 3, S, S) float one-hot (the discriminator's "real")."""
    return F.one_hot(target.long(), NUM_CLASSES).permute(0, 1, 4, 2, 3).float()


def lsgan_generator_loss(d_fake: torch.Tensor) -> torch.Tensor:
    """L_adv = E[(D(T̂) - 1)^2]."""
    return ((d_fake - 1) ** 2).mean()


def lsgan_discriminator_loss(d_real: torch.Tensor, d_fake: torch.Tensor) -> torch.Tensor:
    """L_discr = E[(D(T) - 1)^2] + E[D(T̂)^2]."""
    return ((d_real - 1) ** 2).mean() + (d_fake ** 2).mean()


__all__ = ["layout_loss", "layout_iou_loss", "distill_loss", "one_hot_layouts", "lsgan_generator_loss",
           "lsgan_discriminator_loss"]
