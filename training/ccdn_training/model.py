"""The networks: the paper's CCDN (section 2.1, 6 convs, 16301 parameters), FastCCDN, a cheaper
shape for the same job (shipped as the `fast` model), and FineCCDN, FastCCDN's shape at half
resolution instead of a quarter, for full-resolution passes (shipped as the `fine` model).

Each describes itself as a list of layers (`layers()`), which the ONNX exporter writes node by node.
"""

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

    def layers(self) -> list[tuple]:
        """The graph, for export: ("conv", module, relu) and ("maxpool", kernel, stride, pads t,l,b,r)."""
        c = self.convs()
        return ([("conv", c[0], True), ("maxpool", 2, 1, (0, 0, 1, 1))] + [("conv", m, True) for m in c[1:4]]
                + [("maxpool", 2, 1, (1, 1, 0, 0)), ("conv", c[4], True), ("conv", c[5], True)])

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


class FastCCDN(nn.Module):
    """The same job at about a seventh of the paper net's multiply-adds (0.75 vs 5.0 GMAC at 640x480).

    conv 5x5 1->16 at full resolution, 2x2 max-pool stride 2, two conv 3x3 16->16, 2x2 max-pool
    stride 2, conv 3x3 16->32 and 32->32 at a quarter resolution, then a 1x1 conv 32->16 whose 16
    channels are the 4x4 pixels of each quarter-resolution cell (depth-to-space, PyTorch's
    pixel_shuffle order = ONNX DepthToSpace CRD), so the score map is back at full H x W. ReLU after
    every conv and at the end. Channel counts are multiples of 16 (onnxruntime's blocked kernels);
    H and W must be multiples of 4 (the runtime pads frames). Receptive radius about 20 px.
    """

    stride = 4

    def __init__(self, channels: int = 16, wide: int = 32) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(1, channels, 5, padding=2)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv3 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv4 = nn.Conv2d(channels, wide, 3, padding=1)
        self.conv5 = nn.Conv2d(wide, wide, 3, padding=1)
        self.head = nn.Conv2d(wide, self.stride**2, 1)

    def reset_parameters_paper(self) -> None:
        """PyTorch's default init (He-like) with 0.1 biases: N(0, 0.1) is too wide for 32-channel inputs."""
        for conv in self.convs():
            conv.reset_parameters()
            nn.init.constant_(conv.bias, 0.1)

    def convs(self) -> list[nn.Conv2d]:
        return [self.conv1, self.conv2, self.conv3, self.conv4, self.conv5, self.head]

    def layers(self) -> list[tuple]:
        pool = ("maxpool", 2, 2, (0, 0, 0, 0))
        second_pool = [pool] if self.stride == 4 else []  # FineCCDN (stride 2) stays at half resolution
        return [("conv", self.conv1, True), pool, ("conv", self.conv2, True), ("conv", self.conv3, True),
                *second_pool, ("conv", self.conv4, True), ("conv", self.conv5, True), ("conv", self.head, False),
                ("depth_to_space", self.stride), ("relu",)]

    def forward(self, x: torch.Tensor, pre_activation: bool = False) -> torch.Tensor:
        x = F.max_pool2d(F.relu(self.conv1(x)), 2)
        x = F.relu(self.conv3(F.relu(self.conv2(x))))
        if self.stride == 4:  # as in layers()
            x = F.max_pool2d(x, 2)
        z = F.pixel_shuffle(self.head(F.relu(self.conv5(F.relu(self.conv4(x))))), self.stride)
        return z if pre_activation else F.relu(z)


class FineCCDN(FastCCDN):
    """FastCCDN with one pooling instead of two: its convs 2-5 run at half resolution and the head's
    4 channels are the 2x2 pixels of each half-resolution cell, so corners 2-3 px apart get cells of
    their own (FastCCDN's 4x4 cells merge corners closer than ~5 px: tiny or steep squares, which a
    full-resolution pass must see). 1.5 GMAC at 640x480, under a third of the paper net's 5.0;
    receptive radius 12 px. H and W must be multiples of 2.
    """

    stride = 2


ARCHITECTURES = {"paper": CCDN, "fast": FastCCDN, "fine": FineCCDN}


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
