"""The CCDN network of the paper's section 2.1 (6 convs, 16301 parameters)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class CCDN(nn.Module):
    """Fully convolutional corner scorer: (B, 1, H, W) gray -> (B, 1, H, W) non-negative score.

    conv 9x9 1->20, pool, three conv 3x3 20->20, pool, conv 3x3 20->20, conv 3x3 20->1, ReLU after
    every conv. Both 2x2 max-pools have stride 1; the first pads bottom/right (its output at pixel p
    covers p..p+1, a +1/2 px shift) and the second pads top/left (covers p-1..p, -1/2 px), so the
    shifts cancel and a score peak sits on the corner's own pixel. Zero padding of a ReLU output
    equals -inf padding, which is what ONNX MaxPool's own pads attribute means.
    """

    def __init__(self, channels: int = 20) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(1, channels, 9, padding=4)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv3 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv4 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv5 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv6 = nn.Conv2d(channels, 1, 3, padding=1)

    def reset_parameters_paper(self) -> None:
        """The paper's initialisation: weights ~ N(0, 0.1), biases = 0.1."""
        for conv in self.convs():
            nn.init.normal_(conv.weight, 0.0, 0.1)
            nn.init.constant_(conv.bias, 0.1)

    def convs(self) -> list[nn.Conv2d]:
        return [self.conv1, self.conv2, self.conv3, self.conv4, self.conv5, self.conv6]

    def forward(self, x: torch.Tensor, pre_activation: bool = False) -> torch.Tensor:
        """Scores; with pre_activation=True, the last conv's output before its ReLU (for the loss)."""
        x = F.relu(self.conv1(x))
        x = F.max_pool2d(F.pad(x, (0, 1, 0, 1)), 2, stride=1)
        x = F.relu(self.conv2(x))
        x = F.relu(self.conv3(x))
        x = F.relu(self.conv4(x))
        x = F.max_pool2d(F.pad(x, (1, 0, 1, 0)), 2, stride=1)
        x = F.relu(self.conv5(x))
        z = self.conv6(x)
        return z if pre_activation else F.relu(z)


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
