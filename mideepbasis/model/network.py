"""DeepBasisNet: joint prediction of global and local basis materials and their blending weights.

docs/ARCHITECTURE.md section 7. From the 9-channel input (photo, log-compressed photo, lighting mark):

- a shared encoder (strided 4x4 convolutions, instance norm, and a global feature track that
  is fed back into every level, after Deschaintre et al. 2018) down to a bottleneck;
- a weight decoder (nearest upsampling, two 3x3 convolutions per level, skip connections, the
  same global track) to N weight maps, non-negative and summing to 1 at every pixel;
- a global unit (an MLP on the pooled bottleneck) to N global bases of 10 parameters;
- a local unit (a NAFNet) to per-pixel deviations of every basis, from the input, the weights,
  the global bases and the error map between the photo and a rendering of the globally-blended
  material under the same light (through the renderer interface, differentiably).

Bases live in the network's *signed* space, where every parameter is in [-1, 1]:
``[n (3), 2 d - 1 (3), 2 r - 1, 2 s - 1 (3)]``. ``to_maps`` and ``to_signed`` convert to and
from the maps of docs/ARCHITECTURE.md section 5. Shapes: inputs (B, 9, H, W); lights (B, 3); weights
(B, N, H, W); global bases (B, N, 10); bases (B, N, 10, H, W); maps (B, 10, H, W).

Two presets: ``paper`` (the published sizes, laid out so that the authors' weights can be
mapped onto it) and ``compact`` (for a CPU). Ablation switches: no local bases, no global
bases, no bases at all (the same encoder-decoder predicting the maps directly), and N.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch
import torch.nn.functional as F
from torch import nn

from .. import constants, geometry
from ..resampling import exact_in_bands, upsample_bilinear, upsampled_rows
from .inputs import EXTRA_INPUTS, RELIEF_CHANNELS, ModelInfo, decode_photo, input_channels, octave_relief_inputs
from .nafnet import NAFNet


#: The local unit's error maps (``NetworkConfig.error_map``).
ERROR_MAPS = ("clipped", "log_ratio")

#: Floor added to the render and the photo before their log ratio (``log_ratio_error``) [linear]:
#: about the noise of a phone photo's darkest values, so that black pixels do not dominate.
LOG_RATIO_FLOOR = 0.01

#: Bound of the log ratio's magnitude (``log_ratio_error``): a render 55 times the photo's value.
LOG_RATIO_LIMIT = 4.0

#: Linear photo values at or above this are clipped: a render above one tells nothing there.
PHOTO_CLIPPED = 0.98


@dataclass(frozen=True)
class NetworkConfig:
    """Sizes and switches of DeepBasisNet."""

    encoder_channels: tuple[int, ...] = (64, 128, 256, 512, 512, 512, 512, 512)
    """Output channels of the encoder levels; each level halves the resolution."""

    decoder_channels: tuple[int, ...] = (512, 512, 512, 512, 256, 128, 64)
    """Output channels of the decoder levels but the last (which outputs the N weights); one level
    per encoder level."""

    mlp_width: int = 512
    """Width of the hidden layers of the global unit."""

    mlp_hidden_layers: int = 3
    """Hidden layers of the global unit (plus the output layer: the paper's 5-layer MLP counts the
    input and output too)."""

    local_width: int = 16
    """Channels of the first NAFNet level."""

    local_encoder_blocks: tuple[int, ...] = (2, 2, 4, 8)
    """NAF blocks per NAFNet encoder level."""

    local_middle_blocks: int = 12
    """NAF blocks at the bottom of the NAFNet."""

    local_decoder_blocks: tuple[int, ...] = (2, 2, 2, 2)
    """NAF blocks per NAFNet decoder level."""

    local_ending_kernel: int = 3
    """Kernel size of the NAFNet's last convolution (to N x 10 channels at full resolution)."""

    num_bases: int = constants.NUM_BASES
    """Number N of basis materials."""

    use_global: bool = True
    """Predict global bases (else the local unit predicts the whole bases per pixel)."""

    use_local: bool = True
    """Predict local deviations (else the bases are the global ones)."""

    use_bases: bool = True
    """Use the basis model at all (else the encoder-decoder predicts the 10 map channels directly)."""

    convention: str = field(default=constants.DEFAULT_CONVENTION, metadata={"choices": constants.CONVENTIONS})
    """Shading convention of the error-map render (and of the training renders)."""

    extra_inputs: tuple[str, ...] = ()
    """Optional input channels that make the shading explicit, after the 9 of docs/ARCHITECTURE.md section 7:
    ``shading`` and/or ``highpass`` (``model.inputs.EXTRA_INPUTS``)."""

    plane_extent: float = 1.0
    """Half-width of the sample the camera frames [patch half-widths] for the error map's render:
    1 in this project; 384 / 383 for the authors' networks, whose pixels sit 3 / 383 apart."""

    normal_unit_width: int = 0
    """Channels of the first level of the normal unit (0: none; not in the paper): a NAFNet that reads
    the photo's shading beside the flash direction (``model.inputs.relief_inputs``) and predicts a
    per-pixel slope of the normal, added to the normal deviation of every basis. It needs the local
    unit. (A separately trained 1.6M-parameter unit beat the flat normal on the shared test set
    where the whole network, trained for its maps, had stayed flat: MODEL.md.)"""

    normal_unit_blocks: tuple[int, ...] = (1, 1, 1, 1)
    """NAF blocks per level of the normal unit, in its encoder and decoder alike (one level per
    entry, from the full resolution down, each halving it). A block starts as the identity (its residual scales are
    zero), so a checkpoint's unit deepened here computes what it did until trained."""

    normal_unit_middle_blocks: int = 2
    """NAF blocks at the bottom of the normal unit (1/16 of the resolution with four levels), where
    it sees the broad relief."""

    normal_unit_octaves: tuple[float, ...] = (1.0,)
    """Weights of the normal unit's slope by octave: the unit also runs on the photo area-averaged
    to 1/2, 1/4, ... of the network's resolution (one entry each after the first), and the slopes,
    upsampled back (bilinear), are summed with these weights. At half the resolution the unit's
    receptive field covers twice the sample, so it sees broad relief that the full-resolution
    pass misses. (1.0,): the full resolution alone."""

    normal_slope_scaled: bool = False
    """Add the normal unit's slope to each basis's normal made unit (the slope scaled by the length
    of global plus deviation before the sum is made unit), so that it tilts every basis as it tilts
    a flat unit normal: as the normal pool trains the unit (``train.losses.normals_over_flat``). False
    (also for a checkpoint that does not store it): added to the sum as it is, whose length the
    shipped local unit makes about 1.7 (its deviations' z saturates at +1), which weakens the unit's
    relief by as much."""

    error_map: str = field(default="clipped", metadata={"choices": ERROR_MAPS})
    """What the local unit's error map holds (``DeepBasisNet.error_map``): ``clipped``, the global
    blend's render clipped to [0, 1] minus the photo (the paper's); ``log_ratio``, the log of the
    unclipped render over the photo (``log_ratio_error``). Clipped, the render of a highlight the
    global lobe overshoots reads 1 minus the photo whatever the overshoot: the unit cannot tell a
    lobe's miss from a diffuse one, and takes it out of the diffuse. The ratio also makes a
    diffuse's miss one value across the flash's falloff."""

    def __post_init__(self):
        if self.error_map not in ERROR_MAPS:
            raise ValueError(f"unknown error map {self.error_map!r}; expected one of {list(ERROR_MAPS)}")
        unknown = sorted(set(self.extra_inputs) - set(EXTRA_INPUTS))
        if unknown:
            raise ValueError(f"unknown extra inputs {unknown}; expected some of {list(EXTRA_INPUTS)}")
        if self.normal_unit_width and not (self.use_bases and self.use_local):
            raise ValueError("the normal unit adds to the local deviations: it needs use_bases and use_local")
        if self.normal_unit_width and len(self.normal_unit_blocks) > len(self.encoder_channels):
            raise ValueError(f"the normal unit's {len(self.normal_unit_blocks)} levels need inputs in multiples "
                             f"of 2^{len(self.normal_unit_blocks)}: at most the encoder's {len(self.encoder_channels)}")
        if not any(self.normal_unit_octaves):
            raise ValueError("normal_unit_octaves needs a weight other than 0")
        if self.normal_unit_width and self.normal_unit_stride > self.stride:
            raise ValueError(f"the normal unit's {len(self.normal_unit_octaves)} octaves of {len(self.normal_unit_blocks)} "
                             f"levels each need inputs in multiples of {self.normal_unit_stride}: "
                             f"more than the encoder's {self.stride}")

    @property
    def input_channels(self) -> int:
        """Channels of the network input: 9, plus 3 per entry of ``extra_inputs``."""
        return input_channels(self.extra_inputs)

    @property
    def stride(self) -> int:
        """Input sizes must be multiples of this [pixels]."""
        return 2 ** len(self.encoder_channels)

    @property
    def normal_unit_stride(self) -> int:
        """The normal unit's inputs must be multiples of this [pixels]: each of its levels halves
        them, and each octave after the first is the photo at half the size before."""
        return 2 ** (len(self.normal_unit_blocks) + len(self.normal_unit_octaves) - 1)


PRESETS = {
    "paper": NetworkConfig(),
    "compact": NetworkConfig(encoder_channels=(32, 64, 96, 128, 160, 192), decoder_channels=(160, 128, 96, 64, 32),
                             mlp_width=256, mlp_hidden_layers=3, local_width=8, local_encoder_blocks=(1, 1, 1, 1),
                             local_middle_blocks=2, local_decoder_blocks=(1, 1, 1, 1), local_ending_kernel=1),
    "tiny": NetworkConfig(encoder_channels=(8, 16, 16, 16), decoder_channels=(16, 16, 8), mlp_width=32,
                          mlp_hidden_layers=1, local_width=4, local_encoder_blocks=(1, 1), local_middle_blocks=1,
                          local_decoder_blocks=(1, 1), local_ending_kernel=1),
}


def preset(name: str, **overrides) -> NetworkConfig:
    """A named configuration (``paper``, ``compact``, ``tiny`` for tests) with fields overridden."""
    if name not in PRESETS:
        raise ValueError(f"unknown network preset {name!r}; expected one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)


# --- spaces ---------------------------------------------------------------------------------------


def to_signed(maps: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Maps [n, d, r, s] to the signed space [n, 2d - 1, 2r - 1, 2s - 1] along ``dim``."""
    normal, rest = maps.split(constants.NORMAL_AND_REFLECTANCE, dim=dim)
    return torch.cat([normal, rest * 2.0 - 1.0], dim=dim)


def to_maps(signed: torch.Tensor, dim: int = 1, upper_hemisphere: bool = True) -> torch.Tensor:
    """Signed parameters to maps along ``dim``: unit normals (with z >= 0 unless
    ``upper_hemisphere`` is False), others clipped to [0, 1]."""
    normal, rest = signed.split(constants.NORMAL_AND_REFLECTANCE, dim=dim)
    if upper_hemisphere:
        x, y, z = normal.split(1, dim=dim)
        normal = torch.cat([x, y, z.clamp(min=0.0)], dim=dim)
    normal = normal / (normal * normal).sum(dim=dim, keepdim=True).clamp(min=1e-12).sqrt()
    return torch.cat([normal, (rest * 0.5 + 0.5).clamp(0.0, 1.0)], dim=dim)


def normalize_basis_normals(signed: torch.Tensor, dim: int) -> torch.Tensor:
    """Unit-length normal part (the first 3 entries along ``dim``) of signed bases."""
    normal, rest = signed.split(constants.NORMAL_AND_REFLECTANCE, dim=dim)
    normal = normal / (geometry.vector_length(normal, dim, keepdim=True) + 1e-12)
    return torch.cat([normal, rest], dim=dim)


def normalize_weights(raw: torch.Tensor) -> torch.Tensor:
    """(B, N, H, W) decoder output in [-1, 1] to non-negative weights summing to 1 per pixel."""
    positive = raw * 0.5 + 0.5
    return positive / (positive.sum(dim=1, keepdim=True) + 1e-6)


def blend(weights: torch.Tensor, bases: torch.Tensor) -> torch.Tensor:
    """sum_i w_i b_i: weights (B, N, H, W) and bases (B, N, 10) or (B, N, 10, H, W) -> (B, 10, H, W)."""
    if bases.ndim == 3:
        return torch.einsum("bnhw,bnc->bchw", weights, bases)
    # unbind (not indexing) so that the backward pass stacks the gradients once instead of
    # zero-filling N full tensors.
    return weighted_sum(weights.unbind(1), bases.unbind(1))


def weighted_sum(weights, bases) -> torch.Tensor:
    """sum_i w_i b_i over per-basis weights (B, H, W) and bases (B, 10, H, W), taken one basis at a
    time (``bases`` may be a generator), so no (B, N, 10, H, W) product is materialised."""
    total = None
    for weight, basis in zip(weights, bases):
        term = weight.unsqueeze(1) * basis
        total = term if total is None else total + term
    return total


# --- the shared encoder and the weight decoder ---------------------------------------------------------


class Encoder(nn.Module):
    """Strided 4x4 convolutions with a global feature track (mean of each level, fed back in)."""

    def __init__(self, in_channels: int, channels: tuple[int, ...]):
        super().__init__()
        ins = (in_channels,) + channels[:-1]
        # The global track after level i has as many features as level i + 1 has channels.
        global_sizes = channels[1:] + channels[-1:]
        self.convs = nn.ModuleList(nn.Conv2d(i, o, 4, stride=2, padding=1) for i, o in zip(ins, channels))
        self.norms = nn.ModuleList(nn.InstanceNorm2d(c, affine=True) for c in channels[1:-1])
        self.global_fcs = nn.ModuleList([nn.Linear(in_channels, global_sizes[0])] + [
            nn.Linear(c + g, gs) for c, g, gs in zip(channels[1:], global_sizes[:-1], global_sizes[1:])])
        self.global_to_maps = nn.ModuleList(nn.Linear(g, c, bias=False) for g, c in zip(global_sizes[:-1], channels[1:]))
        self.global_size = global_sizes[-1]

    def forward(self, x: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """Returns the outputs of every level and the final global features (B, global_size).

        Every level but the bottleneck is returned after the leaky ReLU that the next level
        applies to it, so the decoder's skip connections see activated features (as in the
        published network, whose in-place activation does this); the bottleneck is returned raw.
        """
        levels = []
        global_features = F.selu(self.global_fcs[0](x.mean(dim=(2, 3))))
        last = len(self.convs) - 1
        for index, conv in enumerate(self.convs):
            x = conv(x)
            if index > 0:
                mean = torch.cat([global_features, x.mean(dim=(2, 3))], dim=1)
                if index < last:
                    x = self.norms[index - 1](x)
                x = x + self.global_to_maps[index - 1](global_features)[:, :, None, None]
                global_features = F.selu(self.global_fcs[index](mean))
            if index < last:
                x = F.leaky_relu(x, 0.2)
            levels.append(x)
        return levels, global_features


#: Smallest side [pixels] of a decoder level's input whose upsampling the first convolution folds
#: in (``upsampled_conv``): below it the four small convolutions cost more than they save. The
#: decoder at 128 px on two cores, batch of 4 / 1: 58 / 15 ms upsampling everywhere, 43 / 18 ms
#: folding everywhere, 34 / 14 ms folding from 16 px on.
PHASE_CONVOLUTION_MIN_SIZE = 16


def _phase_taps(kernel: torch.Tensor, parity: int, dim: int) -> torch.Tensor:
    """A 3-tap kernel axis ``dim`` folded to the 2 taps that an output of ``parity`` sees in the
    image before a nearest x2 upsampling: even outputs see pixel i - 1 once and pixel i twice, odd
    ones pixel i twice and pixel i + 1 once."""
    first, middle, last = kernel.unbind(dim)
    return torch.stack([first, middle + last] if parity == 0 else [first + middle, last], dim)


def upsampled_conv(x: torch.Tensor, conv: nn.Conv2d) -> torch.Tensor:
    """``conv`` (3x3, padding 1) of ``x`` (B, C, H, W) upsampled x2 by nearest neighbours, (B, O, 2H, 2W),
    without making the upsampled copy: each of the four output phases (row and column parity) is
    a 2x2 convolution of ``x`` with the kernel's taps summed over the pixels they see twice. The
    same to float rounding (3e-6) in 2.25 times fewer operations: 21 -> 7 ms for the decoder's last
    level (64 -> 10 channels, 64 -> 128 px, a batch of 4) on two cores."""
    batch, _, height, width = x.shape
    padded = F.pad(x, (1, 1, 1, 1))
    phases = []
    for row_parity in (0, 1):
        rows = _phase_taps(conv.weight, row_parity, 2)
        for column_parity in (0, 1):
            window = padded[:, :, row_parity:row_parity + height + 1, column_parity:column_parity + width + 1]
            phases.append(F.conv2d(window, _phase_taps(rows, column_parity, 3), conv.bias))
    out = torch.stack(phases, 2).view(batch, -1, 2, 2, height, width)  # (B, O, row parity, column parity, H, W)
    return out.permute(0, 1, 4, 2, 5, 3).reshape(batch, -1, 2 * height, 2 * width)


class WeightDecoder(nn.Module):
    """Nearest upsampling and two 3x3 convolutions per level, U-Net skips and the global track."""

    def __init__(self, encoder_channels: tuple[int, ...], channels: tuple[int, ...], out_channels: int,
                 global_size: int):
        super().__init__()
        outs = channels + (out_channels,)
        ins = (encoder_channels[-1],) + tuple(2 * c for c in outs[:-1])
        if len(outs) != len(encoder_channels):
            raise ValueError("the decoder needs one level per encoder level")
        self.convs = nn.ModuleList(nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.Conv2d(o, o, 3, padding=1))
                                   for i, o in zip(ins, outs))
        self.norms = nn.ModuleList(nn.InstanceNorm2d(o, affine=True) for o in outs[:-1])
        globals_in = (global_size,) + outs[:-2]
        self.global_fcs = nn.ModuleList(nn.Linear(o + g, o) for o, g in zip(outs[:-1], globals_in))
        self.global_to_maps = nn.ModuleList(nn.Linear(g, o, bias=False) for g, o in zip(globals_in + outs[-2:-1], outs))

    def forward(self, levels: list[torch.Tensor], global_features: torch.Tensor) -> torch.Tensor:
        x = levels[-1]
        for index, convs in enumerate(self.convs):
            if index > 0:
                x = torch.cat([x, levels[-(index + 1)]], dim=1)
            # The activation commutes with the nearest upsampling, which the first convolution
            # folds in where that is quicker.
            first, second = convs
            x = F.leaky_relu(x, 0.2)
            if min(x.shape[-2:]) >= PHASE_CONVOLUTION_MIN_SIZE:
                x = upsampled_conv(x, first)
            else:
                x = first(F.interpolate(x, scale_factor=2, mode="nearest"))
            x = second(x)
            last = index == len(self.convs) - 1
            if not last:
                mean = torch.cat([global_features, x.mean(dim=(2, 3))], dim=1)
                x = self.norms[index](x)
            x = x + self.global_to_maps[index](global_features)[:, :, None, None]
            if not last:
                global_features = F.selu(self.global_fcs[index](mean))
        return x


def mlp(in_features: int, width: int, hidden_layers: int, out_features: int) -> nn.Sequential:
    """Linear layers with leaky ReLUs between them and a tanh on the output ([-1, 1])."""
    layers, size = [], in_features
    for _ in range(hidden_layers):
        layers += [nn.Linear(size, width), nn.LeakyReLU(0.2)]
        size = width
    return nn.Sequential(*layers, nn.Linear(size, out_features), nn.Tanh())


# --- the network -------------------------------------------------------------------------------------


def compose_bases(weights: torch.Tensor, global_bases: torch.Tensor, deviations: torch.Tensor | None = None,
                  keep_bases: bool = True) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The two-level basis model: bases = unit-normal(global + deviation), blended by the weights.

    Args:
        weights: (B, N, H, W); global_bases: (B, N, 10) signed space; deviations: (B, N, 10, H, W)
            signed space, or None for the global bases alone.
        keep_bases: return the per-pixel bases (training needs them); False builds one basis at a
            time (the same arithmetic, so the same blend) and never holds all N: at 1024 x 1024 that
            is 400 MB fewer.

    Returns:
        (bases (B, N, 10, H, W) or, without deviations, (B, N, 10), or None when not kept; the blend
        (B, 10, H, W), signed space).
    """
    if deviations is None:
        return global_bases, blend(weights, global_bases)
    global_bases = global_bases.to(device=deviations.device)
    if not keep_bases:
        return None, streamed_blend(weights, global_bases, deviations.unbind(1))
    bases = normalize_basis_normals(global_bases[..., None, None] + deviations, dim=2).clamp(-1.0, 1.0)
    return bases, blend(weights, bases)


def streamed_blend(weights: torch.Tensor, global_bases: torch.Tensor, deviations) -> torch.Tensor:
    """The blend of ``compose_bases`` built one basis at a time: weights (B, N, H, W), global bases
    (B, N, 10) and the N deviations (B, 10, H, W) as an iterable (a generator may make each one
    when it is needed), so at most one basis is held. Returns (B, 10, H, W), signed space."""
    bases = (normalize_basis_normals(base[..., None, None] + deviation, dim=1).clamp(-1.0, 1.0)
             for base, deviation in zip(global_bases.unbind(1), deviations))
    return weighted_sum(weights.unbind(1), bases)


#: Output pixels ``maps_at`` builds at a time, in bands of whole rows, when it can: a band of
#: every basis stays in the cache instead of ten full-size passes through memory each. On this
#: machine (medians of 5): 1024 px 0.55 -> 0.30 s, 2048 px 2.3 -> 1.2 s; a quarter of this band
#: or twice it was slower at 2048 px.
BAND_PIXELS = 262144


@dataclass(frozen=True, eq=False)
class DeepBasisOutput:
    """What DeepBasisNet predicts (see the module docstring for shapes and spaces). Immutable: the
    operations below return new outputs."""

    maps: torch.Tensor
    """(B, 10, H, W) blended maps: unit normals, d, r, s in [0, 1]."""

    weights: torch.Tensor | None = None
    """(B, N, H, W) blending weights, non-negative, summing to 1."""

    global_bases: torch.Tensor | None = None
    """(B, N, 10) global bases, signed space."""

    bases: torch.Tensor | None = None
    """(B, N, 10, H, W) global plus local bases, signed space."""

    deviations: torch.Tensor | None = None
    """(B, N, 10, H, W) local deviations, signed space."""

    error: torch.Tensor | None = None
    """(B, 3, H, W) rendering of the globally-blended material minus the photo."""

    signed: torch.Tensor | None = None
    """(B, 10, H, W) the blend in signed space, before normalisation and clipping; None: from ``maps``."""

    extras: dict = field(default_factory=dict)
    """More tensors by name (``decoder_raw``: the weight decoder's output before its tanh)."""

    @property
    def signed_maps(self) -> torch.Tensor:
        """The blend in signed space, before normalisation and clipping (what the loss compares)."""
        return self.signed if self.signed is not None else to_signed(self.maps)

    @classmethod
    def from_bases(cls, weights: torch.Tensor, global_bases: torch.Tensor, deviations: torch.Tensor | None = None,
                   keep_bases: bool = True, **fields) -> DeepBasisOutput:
        """The output of the basis model with these weights, global bases and local deviations
        (``keep_bases``: also the per-pixel bases, which only training uses)."""
        bases, signed = compose_bases(weights, global_bases, deviations, keep_bases)
        return cls(maps=to_maps(signed), weights=weights, global_bases=global_bases,
                   bases=bases if deviations is not None else None, deviations=deviations, signed=signed, **fields)

    def compose(self, global_bases: torch.Tensor) -> DeepBasisOutput:
        """This prediction with other (say, refined) global bases: the maps rebuilt with the same
        weights and local deviations."""
        if self.weights is None:
            raise ValueError("an output without bases (a direct network's) has no global bases to replace")
        if self.deviations is None:  # no local unit: the bases are the global ones, kept unit-normal
            global_bases = normalize_basis_normals(global_bases, dim=2).clamp(-1.0, 1.0)
        return DeepBasisOutput.from_bases(self.weights, global_bases.to(self.weights), self.deviations,
                                          keep_bases=False, error=self.error, extras=self.extras)

    def unsaturated(self, channels: slice = constants.REFLECTANCE) -> DeepBasisOutput:
        """This output with each basis's deviations of ``channels`` (default: the reflectance) cut
        to what its global basis leaves inside the signed space, deviation' = clamp(global +
        deviation, -1, 1) - global: the same maps, in which a change of a global basis moves every
        pixel where that basis weighs. The local unit often pushes a basis past a bound (its
        deviations saturate near +-1); there a change of the global basis moves nothing, so a
        refinement that may move only some of a basis's channels tints the specular
        (``RefineConfig.unclamped_moves``)."""
        if self.deviations is None or self.global_bases is None:
            return self
        start = self.global_bases[:, :, channels, None, None].to(self.deviations)
        deviations = self.deviations.clone()
        deviations[:, :, channels] = (start + self.deviations[:, :, channels]).clamp(-1.0, 1.0) - start
        return replace(self, deviations=deviations)

    def with_shrunk_deviations(self, channels: slice, share: float) -> DeepBasisOutput:
        """This output with each basis's local deviations of ``channels`` pulled toward their mean
        over the pixels where the basis weighs: ``mean + share (deviation - mean)``, the mean
        weighted by the basis's blending weights. 1 keeps them, 0 leaves each basis one value
        there, its global basis plus that mean. The deviations of ``channels`` are first cut to what
        their global basis leaves inside the signed space (``unsaturated``), so the mean is of what
        the maps show; the other channels' stay as they are (a clamped refinement keeps them)."""
        if share == 1.0 or self.deviations is None or self.weights is None:
            return self
        output = self.unsaturated(channels)
        deviations = output.deviations.clone()
        part = deviations[:, :, channels]  # (B, N, C, H, W)
        weights = self.weights.to(part)[:, :, None]
        mean = (part * weights).sum(dim=(-2, -1), keepdim=True) / weights.sum(dim=(-2, -1), keepdim=True).clamp(min=1e-6)
        deviations[:, :, channels] = mean + share * (part - mean)
        return DeepBasisOutput.from_bases(self.weights, self.global_bases, deviations, keep_bases=False,
                                          error=self.error, extras=self.extras)

    def crop(self, height: int, width: int) -> DeepBasisOutput:
        """The top-left height x width pixels of every per-pixel tensor."""
        def crop(value):
            return value[..., :height, :width] if isinstance(value, torch.Tensor) and value.ndim >= 4 else value

        return self._map(crop)

    def upsample(self, height: int, width: int) -> DeepBasisOutput:
        """The prediction at height x width: the weights and local deviations (or, without bases,
        the signed maps) upsampled bilinearly and the maps rebuilt from them. Bilinear
        interpolation keeps the weights non-negative and summing to one."""
        if self.weights is None:
            signed = upsample_bilinear(self.signed_maps, height, width)
            return DeepBasisOutput(maps=to_maps(signed), signed=signed)
        deviations = None
        if self.deviations is not None:  # basis by basis, as maps_at does: the same values to the bit
            deviations = torch.stack([upsample_bilinear(deviation, height, width)
                                      for deviation in self.deviations.unbind(1)], dim=1)
        error = upsample_bilinear(self.error, height, width) if self.error is not None else None
        return DeepBasisOutput.from_bases(upsample_bilinear(self.weights, height, width), self.global_bases,
                                          deviations, keep_bases=False, error=error)

    def maps_at(self, height: int, width: int) -> torch.Tensor:
        """The maps (B, 10, height, width) of ``upsample(height, width)`` without its upsampled
        deviations: each basis's is made, blended and freed in turn (at 2048 x 2048 the N
        deviations together take 1.6 GB), in bands of rows above ``BAND_PIXELS`` (then equal to
        float rounding; up to it, as at 256 px, to the bit)."""
        if tuple(self.maps.shape[-2:]) == (height, width):
            return self.maps
        if self.weights is None or self.deviations is None:
            return self.upsample(height, width).maps
        with torch.no_grad():
            if not exact_in_bands(self.weights.shape[-2], height):
                return self._blend_upsampled(lambda value: upsample_bilinear(value, height, width))
            # Band by band (tested against the whole): half the time at 2048 px.
            maps = self.weights.new_empty(self.weights.shape[0], constants.BASIS_CHANNELS, height, width)
            band = max(1, BAND_PIXELS // width)
            for start in range(0, height, band):
                stop = min(height, start + band)
                maps[:, :, start:stop] = self._blend_upsampled(
                    lambda value, start=start, stop=stop: upsampled_rows(value, height, width, start, stop))
            return maps

    def _blend_upsampled(self, upsampled) -> torch.Tensor:
        """The maps of the weights and deviations upsampled by ``upsampled`` (a tensor's (..., h, w)
        to (..., rows, columns)), each basis's made, blended and freed in turn."""
        weights = upsampled(self.weights)
        total = None
        for weight, base, deviation in zip(weights.unbind(1), self.global_bases.to(weights.device).unbind(1),
                                           self.deviations.unbind(1)):
            # streamed_blend's arithmetic, in place on the one upsampled basis: four buffers
            # live at a time instead of eight.
            basis = upsampled(deviation).add_(base[..., None, None])
            normal = basis[:, constants.NORMAL]
            normal.div_(normal.square().sum(dim=1, keepdim=True).sqrt_().add_(1e-12))
            term = basis.clamp_(-1.0, 1.0).mul_(weight.unsqueeze(1))
            total = term if total is None else total.add_(term)
            del basis, normal, term
        return to_maps(total)

    def split(self, batch: int) -> tuple[DeepBasisOutput, DeepBasisOutput]:
        """The first ``batch`` items and the rest, as two outputs."""
        return self._map(lambda value: value[:batch]), self._map(lambda value: value[batch:])

    def _map(self, function) -> DeepBasisOutput:
        """Every tensor (extras included) through ``function``."""
        def apply(value):
            return function(value) if isinstance(value, torch.Tensor) else value

        values = {f.name: apply(getattr(self, f.name)) for f in fields(self) if f.name != "extras"}
        return DeepBasisOutput(**values, extras={key: apply(value) for key, value in self.extras.items()})


class DeepBasisNet(nn.Module):
    """The DeepBasis network (see the module docstring)."""

    def __init__(self, config: NetworkConfig = PRESETS["compact"]):
        super().__init__()
        self.config = config
        if len(config.decoder_channels) != len(config.encoder_channels) - 1:
            raise ValueError("decoder_channels needs one entry fewer than encoder_channels (the last level outputs the weights)")
        # How the network must be run; ``load_model`` replaces it with what its checkpoint records.
        self.info = ModelInfo(convention=config.convention, plane_extent=config.plane_extent)
        n = config.num_bases
        out_channels = n if config.use_bases else constants.BASIS_CHANNELS
        self.encoder = Encoder(config.input_channels, config.encoder_channels)
        self.weight_decoder = WeightDecoder(config.encoder_channels, config.decoder_channels, out_channels,
                                            self.encoder.global_size)
        if config.use_bases and config.use_global:
            self.global_unit = mlp(config.encoder_channels[-1], config.mlp_width, config.mlp_hidden_layers,
                                   n * constants.BASIS_CHANNELS)
        if config.use_bases and (config.use_local or not config.use_global):
            local_in = config.input_channels + 3 + n + n * constants.BASIS_CHANNELS
            self.local_unit = NAFNet(local_in, n * constants.BASIS_CHANNELS, config.local_width,
                                     config.local_encoder_blocks, config.local_middle_blocks, config.local_decoder_blocks,
                                     config.local_ending_kernel)
        if config.normal_unit_width:  # the relief inputs to the normal's x and y slope, before their tanh
            blocks = tuple(config.normal_unit_blocks)
            self.normal_unit = NAFNet(RELIEF_CHANNELS, 2, config.normal_unit_width, blocks,
                                      config.normal_unit_middle_blocks, tuple(reversed(blocks)), 3)

    def forward(self, inputs: torch.Tensor, lights: torch.Tensor | None = None,
                fov: float = constants.DEFAULT_FOV_DEG, with_normal_unit: bool = True,
                symmetries: int = 1) -> DeepBasisOutput:
        """Predict the material seen in ``inputs`` (B, 9, H, W) taken under flashes at ``lights`` (B, 3).
        ``with_normal_unit`` False leaves the normal unit out (its slope, the normal's only change, is
        not added): everything but the normal is the same, for less work. ``symmetries`` above 1
        averages the answers for the photo turned and mirrored that many ways (``symmetrised``)."""
        if symmetries > 1:
            return self.symmetrised(inputs, lights, fov, with_normal_unit, symmetries)
        stage = self.basis_stage(inputs, lights, fov)
        if isinstance(stage, DeepBasisOutput):
            return stage
        deviations = self.local_deviations(stage.local_inputs, stage.weights, stage.global_bases)
        if with_normal_unit and hasattr(self, "normal_unit"):
            deviations = add_slope(stage.global_bases, deviations, self.normal_slope(stage, lights, fov),
                                   self.config.normal_slope_scaled)
        return DeepBasisOutput.from_bases(stage.weights, stage.global_bases, deviations, error=stage.error,
                                          extras=stage.extras)

    def symmetrised(self, inputs: torch.Tensor, lights: torch.Tensor | None, fov: float = constants.DEFAULT_FOV_DEG,
                    with_normal_unit: bool = True, symmetries: int = 8) -> DeepBasisOutput:
        """``forward`` averaged over ``symmetries`` turns and mirrorings of the square sample:
        ``model.symmetry.symmetrised_prediction`` (8 needs square inputs)."""
        from .symmetry import symmetrised_prediction

        return symmetrised_prediction(self, inputs, lights, fov, with_normal_unit, symmetries)

    def basis_stage(self, inputs: torch.Tensor, lights: torch.Tensor | None,
                    fov: float = constants.DEFAULT_FOV_DEG) -> BasisStage | DeepBasisOutput:
        """Everything before the local unit: the weights, the global bases and the local unit's
        inputs (a ``BasisStage``); for a network without a local unit, its whole output."""
        config = self.config
        height, width = inputs.shape[-2:]
        if height % config.stride or width % config.stride:
            raise ValueError(f"input size {height}x{width} is not a multiple of the network's stride {config.stride}")
        levels, global_features = self.encoder(inputs)
        raw = self.weight_decoder(levels, global_features)
        decoded = torch.tanh(raw)
        if not config.use_bases:
            return DeepBasisOutput(maps=to_maps(decoded), signed=decoded, extras={"decoder_raw": raw})

        batch, n = inputs.shape[0], config.num_bases
        weights = normalize_weights(decoded)
        if config.use_global:
            pooled = levels[-1].mean(dim=(2, 3))
            global_bases = normalize_basis_normals(self.global_unit(pooled).view(batch, n, constants.BASIS_CHANNELS), dim=2)
        else:
            global_bases = inputs.new_zeros(batch, n, constants.BASIS_CHANNELS)
        extras = {"decoder_raw": raw}
        if not hasattr(self, "local_unit"):
            return DeepBasisOutput.from_bases(weights, global_bases, extras=extras)

        if lights is None:
            raise ValueError("the local unit needs the flash positions (lights) for its error map")
        photo = decode_photo(inputs)
        error = self.error_map(weights, global_bases, photo, lights, fov)
        return BasisStage(weights=weights, global_bases=global_bases, local_inputs=local_unit_inputs(inputs, error, weights),
                          photo=photo, error=error, extras=extras)

    def error_map(self, weights: torch.Tensor, global_bases: torch.Tensor, photo: torch.Tensor, lights: torch.Tensor,
                  fov: float = constants.DEFAULT_FOV_DEG) -> torch.Tensor:
        """(B, 3, H, W) the local unit's error map: the globally-blended material (weights (B, N, H, W),
        global bases (B, N, 10) signed space) rendered under the flashes at ``lights`` (B, 3), clipped
        to [0, 1], minus the linear photo (B, 3, H, W)."""
        from ..render import render_flash

        # The renderer takes the blended normal as it is (a normal below the surface renders black).
        global_maps = to_maps(compose_bases(weights, global_bases)[1], upper_hemisphere=False)
        # The render runs in float32 even under mixed-precision autocast: the GGX peak of smooth
        # bases does not survive bfloat16.
        with torch.autocast(photo.device.type, enabled=False):
            rendered = render_flash(global_maps.float(), lights.view(photo.shape[0], 1, 3).float(), fov=fov,
                                    convention=self.config.convention, extent=self.config.plane_extent)[:, 0]
        if self.config.error_map == "log_ratio":
            return log_ratio_error(rendered, photo.float())
        return rendered.clamp(0.0, 1.0) - photo.float()

    def local_deviations(self, local_inputs: torch.Tensor, weights: torch.Tensor,
                         global_bases: torch.Tensor) -> torch.Tensor:
        """The local unit's deviations of every basis, (B, N, 10, H, W) signed space, from a
        ``BasisStage``'s local inputs, weights (B, N, H, W) and global bases (B, N, 10)."""
        batch, n = weights.shape[:2]
        height, width = weights.shape[-2:]
        # The global bases enter as constant planes (N x 10 channels) without being built.
        deviations = torch.tanh(self.local_unit(local_inputs, planes=global_bases.reshape(batch, -1)))
        return deviations.view(batch, n, constants.BASIS_CHANNELS, height, width)

    def normal_slope(self, stage: BasisStage, lights: torch.Tensor,
                     fov: float = constants.DEFAULT_FOV_DEG) -> torch.Tensor:
        """The normal unit's slope, (B, 2, H, W): the x and y it adds to every basis's normal
        (``slope_change``), summed over its octaves (``NetworkConfig.normal_unit_octaves``)."""
        reliefs = self.relief_inputs(stage.photo, lights.view(stage.photo.shape[0], 3), fov)
        return self.octave_slope([relief.to(stage.local_inputs.dtype) for relief in reliefs])

    def relief_inputs(self, photo: torch.Tensor, lights: torch.Tensor, fov: float) -> list[torch.Tensor]:
        """The normal unit's inputs at each of its octaves (``octave_relief_inputs`` with this
        network's octaves, convention and plane extent), made in float32 whatever the autocast."""
        config = self.config
        return octave_relief_inputs(photo.float(), lights.float(), len(config.normal_unit_octaves), fov,
                                    config.convention, config.plane_extent)

    def octave_slope(self, reliefs: list[torch.Tensor]) -> torch.Tensor:
        """The normal unit's slope (B, 2, H, W) from its relief inputs at each octave
        (``NetworkConfig.normal_unit_octaves``; the k-th (B, C, H / 2^k, W / 2^k),
        ``octave_relief_inputs``): each octave's slope, upsampled to the first's size, times its
        weight, summed; the unit does not run where the weight is 0."""
        height, width = reliefs[0].shape[-2:]
        total = None
        for octave, (relief, weight) in enumerate(zip(reliefs, self.config.normal_unit_octaves, strict=True)):
            if weight == 0:
                continue
            slope = torch.tanh(self.normal_unit(relief))
            slope = weight * (upsample_bilinear(slope, height, width) if octave else slope)
            total = slope if total is None else total + slope
        return total


def log_ratio_error(rendered: torch.Tensor, photo: torch.Tensor) -> torch.Tensor:
    """The ``log_ratio`` error map: log((render + f) / (photo + f)), f = ``LOG_RATIO_FLOOR``, bounded
    by +-``LOG_RATIO_LIMIT``; where the photo clipped (``PHOTO_CLIPPED``) a brighter render counts
    as the photo's value (0). Render and photo (B, 3, H, W) linear; the render unclipped."""
    rendered = rendered.clamp(min=0.0)
    rendered = torch.where(photo >= PHOTO_CLIPPED, torch.minimum(rendered, photo), rendered)
    ratio = torch.log(rendered + LOG_RATIO_FLOOR) - torch.log(photo.clamp(min=0.0) + LOG_RATIO_FLOOR)
    return ratio.clamp(-LOG_RATIO_LIMIT, LOG_RATIO_LIMIT)


def local_unit_inputs(inputs: torch.Tensor, error: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(B, input channels + 3 + N, H, W) what the local unit reads: the network's inputs, the error
    map (B, 3, H, W, ``DeepBasisNet.error_map``) and the weights (B, N, H, W), in that order."""
    return torch.cat([inputs, error, weights], dim=1)


def slope_change(slope: torch.Tensor) -> torch.Tensor:
    """The normal unit's slope (B, 2, H, W) as a change of a basis, (B, 10, H, W) signed space: the
    normal's x and y, zero elsewhere."""
    batch, _, height, width = slope.shape
    return torch.cat([slope, slope.new_zeros(batch, constants.BASIS_CHANNELS - 2, height, width)], dim=1)


def add_slope(global_bases: torch.Tensor, deviations: torch.Tensor, slope: torch.Tensor,
              scaled: bool = False) -> torch.Tensor:
    """The deviations (B, N, 10, H, W) with the normal unit's slope (B, 2, H, W) added to every
    basis's normal x and y (``slope_change``), global bases (B, N, 10) signed space; ``scaled``:
    the slope times the length of each basis's normal sum, global plus deviation
    (``NetworkConfig.normal_slope_scaled``), so that unit-normal(sum + slope) is
    unit-normal(unit sum + slope)."""
    change = slope_change(slope)[:, None]
    if scaled:
        sums = global_bases[:, :, constants.NORMAL, None, None].to(deviations) + deviations[:, :, constants.NORMAL]
        change = change * geometry.vector_length(sums, dim=2, keepdim=True)
    return deviations + change


@dataclass
class BasisStage:
    """What ``DeepBasisNet.basis_stage`` passes on to the local unit (signed space)."""

    weights: torch.Tensor
    """(B, N, H, W) blending weights."""

    global_bases: torch.Tensor
    """(B, N, 10) global bases."""

    local_inputs: torch.Tensor
    """(B, input channels + 3 + N, H, W): the inputs, the error map, the weights."""

    photo: torch.Tensor
    """(B, 3, H, W) the decoded photo [linear]."""

    error: torch.Tensor
    """(B, 3, H, W) the global bases' render minus the photo."""

    extras: dict = field(default_factory=dict)
    """What the output keeps for the losses (``decoder_raw``)."""


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
