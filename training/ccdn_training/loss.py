"""The paper's loss (eq. 4-5): clipped output, class-balanced cross entropy, L2 on all parameters."""

from __future__ import annotations

import torch
from torch import nn

EPS = 1e-6


def ccdn_loss(score: torch.Tensor, target: torch.Tensor, model: nn.Module, weight_decay: float = 0.01) -> torch.Tensor:
    """score: (B, 1, H, W) network output; target: same shape, 1 corner, 0 not, -1 ignored.

    Positive and negative terms are each normalised by their own count over the batch, so the few
    corner pixels weigh as much as the many background ones; lambda/2 * ||p||^2 regularises.
    """
    pos, neg = target == 1, target == 0
    a_pos = score[pos].clamp(EPS, 1.0)
    a_neg = score[neg].clamp(0.0, 1.0 - EPS)
    loss_pos = -torch.log(a_pos).sum() / pos.sum().clamp(min=1)
    loss_neg = -torch.log1p(-a_neg).sum() / neg.sum().clamp(min=1)
    l2 = sum((p * p).sum() for p in model.parameters())
    return loss_pos + loss_neg + 0.5 * weight_decay * l2
