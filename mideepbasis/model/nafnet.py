"""NAFNet (Chen et al., "Simple Baselines for Image Restoration", ECCV 2022): the local unit.

A U-Net of NAF blocks (layer norm, depth-wise convolution, simple gate, simplified channel
attention) with strided-convolution downsampling and pixel-shuffle upsampling. Fully
convolutional; inputs are padded to a multiple of 2^levels and the output cropped back.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class LayerNorm2d(nn.Module):
    """Layer norm over the channels of a (B, C, H, W) tensor, with a per-channel affine map."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # One fused kernel over the channels, which are the last dimension of a channels-last
        # tensor (``NAFNet`` runs in that layout): no copy, where mean, variance and affine map
        # written out took eight passes over the activations.
        normalised = F.layer_norm(x.permute(0, 2, 3, 1), (x.shape[1],), self.weight, self.bias, self.eps)
        return normalised.permute(0, 3, 1, 2)


class SimpleGate(nn.Module):
    """Split the channels in two halves and multiply them: a gate without a nonlinearity."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        first, second = x.chunk(2, dim=1)
        return first * second


class NAFBlock(nn.Module):
    """One NAF block on ``channels`` channels (expansion 2 in both the spatial and channel mixers)."""

    def __init__(self, channels: int, expansion: int = 2):
        super().__init__()
        hidden = channels * expansion
        self.conv1 = nn.Conv2d(channels, hidden, 1)
        self.conv2 = nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden)
        self.conv3 = nn.Conv2d(hidden // 2, channels, 1)
        self.sca = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(hidden // 2, hidden // 2, 1))
        self.sg = SimpleGate()
        self.conv4 = nn.Conv2d(channels, hidden, 1)
        self.conv5 = nn.Conv2d(hidden // 2, channels, 1)
        self.norm1 = LayerNorm2d(channels)
        self.norm2 = LayerNorm2d(channels)
        # Zero-initialised residual scales: every block starts as the identity.
        self.beta = nn.Parameter(torch.zeros(1, channels, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, channels, 1, 1))

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        x = self.sg(self.conv2(self.conv1(self.norm1(inputs))))
        x = self.conv3(x * self.sca(x))
        y = inputs + x * self.beta
        x = self.conv5(self.sg(self.conv4(self.norm2(y))))
        return y + x * self.gamma


class NAFNet(nn.Module):
    """The NAFNet U-Net.

    Args:
        in_channels, out_channels: channels of input and output.
        width: channels of the first level (doubled at every level down).
        encoder_blocks: NAF blocks per encoder level (one level per entry).
        middle_blocks: NAF blocks at the bottom.
        decoder_blocks: NAF blocks per decoder level (as many levels as the encoder).
        ending_kernel: size of the last convolution's kernel (3 in the published network).
    """

    def __init__(self, in_channels: int, out_channels: int, width: int = 16,
                 encoder_blocks: tuple[int, ...] = (2, 2, 4, 8), middle_blocks: int = 12,
                 decoder_blocks: tuple[int, ...] = (2, 2, 2, 2), ending_kernel: int = 3):
        super().__init__()
        if len(encoder_blocks) != len(decoder_blocks):
            raise ValueError("NAFNet needs as many decoder levels as encoder levels")
        self.intro = nn.Conv2d(in_channels, width, 3, padding=1)
        self.ending = nn.Conv2d(width, out_channels, ending_kernel, padding=ending_kernel // 2)
        self.encoders, self.downs = nn.ModuleList(), nn.ModuleList()
        self.decoders, self.ups = nn.ModuleList(), nn.ModuleList()
        channels = width
        for count in encoder_blocks:
            self.encoders.append(nn.Sequential(*[NAFBlock(channels) for _ in range(count)]))
            self.downs.append(nn.Conv2d(channels, 2 * channels, 2, stride=2))
            channels *= 2
        self.middle_blks = nn.Sequential(*[NAFBlock(channels) for _ in range(middle_blocks)])
        for count in decoder_blocks:
            self.ups.append(nn.Sequential(nn.Conv2d(channels, channels * 2, 1, bias=False), nn.PixelShuffle(2)))
            channels //= 2
            self.decoders.append(nn.Sequential(*[NAFBlock(channels) for _ in range(count)]))
        self.multiple = 2 ** len(encoder_blocks)

    def forward(self, x: torch.Tensor, planes: torch.Tensor | None = None) -> torch.Tensor:
        """(B, in_channels, H, W) -> (B, out_channels, H, W), any H and W.

        Args:
            x: the input; or its first channels when ``planes`` is given.
            planes: (B, P) values of the last P input channels, each constant over the image.
                They enter the first convolution as one per-sample kernel applied to an image of
                ones, which equals convolving the P constant planes (zero padding included)
                without ever building them: P is N x 10 = 100 channels for the local unit.
        """
        height, width = x.shape[-2:]
        # Channels last: oneDNN's depth-wise and 1x1 convolutions and the layer norms run on it
        # without reordering (at 128 px the normal unit's pass took 40 - 60 % less time).
        x = F.pad(x, (0, (-width) % self.multiple, 0, (-height) % self.multiple))
        x = x.contiguous(memory_format=torch.channels_last)
        if planes is None:
            x = self.intro(x)
        else:
            x = self._intro_with_planes(x, planes, height, width)
        skips = []
        for encoder, down in zip(self.encoders, self.downs):
            x = encoder(x)
            skips.append(x)
            x = down(x)
        x = self.middle_blks(x)
        for decoder, up, skip in zip(self.decoders, self.ups, reversed(skips)):
            x = decoder(up(x) + skip)
        # Back to the standard layout before the last convolution, on its few input channels
        # rather than its many output channels (100 for the local unit).
        return self.ending(x.contiguous())[..., :height, :width].contiguous()

    def _intro_with_planes(self, x: torch.Tensor, planes: torch.Tensor, height: int, width: int) -> torch.Tensor:
        batch, varying = x.shape[:2]
        weight = self.intro.weight
        out = F.conv2d(x, weight[:, :varying], self.intro.bias, padding=1)
        # Per-sample kernel sum_p planes[b, p] W[:, varying + p], applied to the (unpadded) image of ones.
        kernels = torch.einsum("bp,opij->boij", planes, weight[:, varying:]).reshape(-1, 1, 3, 3)
        ones = x.new_zeros(1, batch, *x.shape[-2:])
        ones[..., :height, :width] = 1.0
        constant = F.conv2d(ones.expand(1, batch, -1, -1), kernels, padding=1, groups=batch)
        return out + constant.view(batch, -1, *x.shape[-2:])
