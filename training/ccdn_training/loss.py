"""The paper's loss (eq. 4-5): clipped output, class-balanced cross entropy, L2 on all parameters."""

from __future__ import annotations

import torch
from torch import nn

EPS = 1e-6


def ccdn_loss(z: torch.Tensor, target: torch.Tensor, model: nn.Module, weight_decay: float = 0.01) -> torch.Tensor:
    """z: (B, 1, H, W) last conv output BEFORE its ReLU; target: same shape, 1 corner, 0 not, -1 ignored.

    Positive and negative terms are each normalised by their own count over the batch, so the few
    corner pixels weigh as much as the many background ones; lambda/2 * ||p||^2 regularises.
    The value equals eq. 4-5 on relu(z) wherever a positive's output is alive (z >= 1e-6). Below
    that, eq. 5's clip (and the ReLU) give a zero gradient, and a network whose output ReLU starts
    dead never recovers; there we add the linear penalty (1e-6 - z), which pulls z back up.
    """
    pos, neg = target == 1, target == 0
    z_pos = z[pos]
    a_pos = z_pos.clamp(EPS, 1.0)
    a_neg = z[neg].clamp(0.0, 1.0 - EPS)  # relu then clip: the same for negatives
    revive = (EPS - z_pos).clamp(min=0.0)
    loss_pos = (-torch.log(a_pos) + revive).sum() / pos.sum().clamp(min=1)
    loss_neg = -torch.log1p(-a_neg).sum() / neg.sum().clamp(min=1)
    l2 = sum((p * p).sum() for p in model.parameters())
    return loss_pos + loss_neg + 0.5 * weight_decay * l2
