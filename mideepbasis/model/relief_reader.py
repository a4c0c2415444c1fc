"""The relief reader: a network of its own that reads the relief finer than the capture network's
resolution from a flash photo at up to ``READ_SIZE`` px.

The capture network sees the photo at 128 px; its normal unit, trained there, reads a 1024 px
photo's fine relief with a slope that correlates about 0.5 with the truth's (``benchmarks/
README.md``, detail). The reader is trained for that band alone (``train.relief_reader``): on
procedural materials generated and photographed at 1024 px as a phone takes them (noise, tone
curve, JPEG, the flash's cone), glittering, foiled and grained surfaces among them, it learns the
slope above the band by least squares. So where a photo's fine contrast does not tell relief
(glints, an albedo's texture) its answer shrinks toward none, rather than reading it as bumps.

What it reads (``reader_inputs``), per pixel of the photo at its working size:

- the fine contrast ``(I - L(I)) / L(I)`` of red, green, blue and their mean, ``L`` the photo
  area-averaged to the network's size and upsampled bilinearly (the band the capture network
  answers is taken out), clipped to +-``CONTRAST_LIMIT`` (4 channels);
- the smooth shading ``log(L(lum) / falloff)``, the flash's falloff over a white Lambertian
  divided out, less its mean: where the highlight lies (1);
- the smooth level ``log(L(lum))`` scaled to about [-1, 1]: how noisy the pixel is (1);
- the unit vector from the pixel's point towards the flash (3);
- with ``ReliefReaderConfig.unit_inputs``, the normal unit's own inputs too (``inputs.relief_inputs``,
  7): a reader of the unit's architecture can then start from the shipped unit's weights
  (``from_normal_unit``) and learn the band from there.

Shapes: photo (B, 3, H, W) linear; light (B, 3) [patch half-widths]; slope (B, 2, H, W), the x and
y of the normal to add above the band.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch
from torch import nn

from .. import constants, geometry
from ..errors import InputError
from ..resampling import downsample, upsample_bilinear
from .inputs import RELIEF_CHANNELS, flash_falloff, relief_inputs
from .nafnet import NAFNet

#: Channels of ``reader_inputs`` without the normal unit's.
READER_CHANNELS = 9

#: The x and y channels of the vectors among ``reader_inputs`` (the direction to the flash; with
#: the unit's inputs, its 3 l_x and 3 l_y too): they change sign with the image's mirrorings.
VECTOR_CHANNELS = ((6, 7), (READER_CHANNELS + 5, READER_CHANNELS + 6))

#: Largest side the reader reads at [pixels]: a larger photo is area-averaged to it first.
READ_SIZE = 1024

#: Bound of the fine contrast it reads (a glint's contrast runs to hundreds).
CONTRAST_LIMIT = 2.0

#: Darkest level a contrast is taken against, and the floor of the logs [linear].
DARKEST = 1e-3

#: Format tag of a reader's weights file.
FORMAT = "mideepbasis-relief-reader"


@dataclass(frozen=True)
class ReliefReaderConfig:
    """The reader's architecture: a NAFNet U-Net."""

    width: int = 16
    """Channels of its first level, doubled at every level down."""
    encoder_blocks: tuple[int, ...] = (1, 1, 1, 2)
    """NAF blocks per encoder level (one level per entry; the decoder mirrors them)."""
    middle_blocks: int = 2
    """NAF blocks at the bottom."""
    unit_inputs: bool = False
    """Read the normal unit's inputs beside its own (``reader_inputs``)."""
    bounded: bool = False
    """Bound the slope by a tanh, as the normal unit does."""

    @property
    def in_channels(self) -> int:
        """Channels of its inputs."""
        return READER_CHANNELS + (RELIEF_CHANNELS if self.unit_inputs else 0)

    @property
    def multiple(self) -> int:
        """The sides it reads must be multiples of this [pixels]."""
        return 2 ** len(self.encoder_blocks)


class ReliefReader(nn.Module):
    """``reader_inputs`` (B, config.in_channels, H, W) -> the slope above the band (B, 2, H, W)."""

    def __init__(self, config: ReliefReaderConfig = ReliefReaderConfig()):
        super().__init__()
        self.config = config
        blocks = tuple(config.encoder_blocks)
        self.net = NAFNet(config.in_channels, 2, config.width, blocks, config.middle_blocks, tuple(reversed(blocks)), 3)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        slope = self.net(inputs)
        return torch.tanh(slope) if self.config.bounded else slope


def from_normal_unit(model) -> ReliefReader:
    """A reader of the normal unit's architecture that reads as the shipped network's ``model``
    unit reads (one octave, before the band is taken out): its weights copied, its own inputs' first
    weights 0."""
    unit = model.normal_unit
    config = model.config
    reader = ReliefReader(ReliefReaderConfig(width=config.normal_unit_width, encoder_blocks=tuple(config.normal_unit_blocks),
                                             middle_blocks=config.normal_unit_middle_blocks, unit_inputs=True,
                                             bounded=True))
    state = {name: value.clone() for name, value in unit.state_dict().items()}
    intro = torch.zeros_like(reader.net.intro.weight)
    intro[:, READER_CHANNELS:] = state["intro.weight"]
    state["intro.weight"] = intro
    reader.net.load_state_dict(state)
    return reader


def reader_inputs(photo: torch.Tensor, light: torch.Tensor, low_size: tuple[int, int], fov: float,
                  convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0,
                  unit_inputs: bool = False) -> torch.Tensor:
    """What the reader reads of ``photo`` (B, 3, H, W) taken with the flash at ``light`` (B, 3) or
    (3,): (B, READER_CHANNELS, H, W) (module docstring), with ``unit_inputs`` the normal unit's
    inputs after them; ``low_size`` the capture network's (h, w)."""
    batch, _, height, width = photo.shape
    photo = photo.float().clamp(0.0, 1.0)
    light = light.float().reshape(-1, 3).expand(batch, 3).to(photo.device)
    guides = torch.cat([photo, photo.mean(dim=1, keepdim=True)], dim=1)
    smooth = upsample_bilinear(downsample(guides, low_size), height, width).clamp(min=DARKEST)
    contrast = ((guides - smooth) / smooth).clamp(-CONTRAST_LIMIT, CONTRAST_LIMIT)
    falloff = flash_falloff(light.cpu(), height, width, fov, convention, extent).to(photo)
    shading = torch.log(smooth[:, 3:]) - torch.log(falloff.clamp(min=DARKEST))
    shading = shading - shading.mean(dim=(2, 3), keepdim=True)
    level = 1.0 + 2.0 * torch.log(smooth[:, 3:]) / -math.log(DARKEST)
    points = geometry.pixel_points(height, width, device=photo.device, dtype=photo.dtype)[None] * extent
    towards = light.view(batch, 3, 1, 1) - points
    direction = towards / geometry.vector_length(towards, dim=1, keepdim=True)
    own = torch.cat([contrast, 0.5 * shading, level, direction], dim=1)
    if not unit_inputs:
        return own
    return torch.cat([own, relief_inputs(photo, light, fov, convention, extent)], dim=1)


def read_size(size: tuple[int, int], max_size: int, multiple: int) -> tuple[int, int]:
    """The (h, w) a photo of ``size`` is read at: scaled down to at most ``max_size`` on its longer
    side, each side then down to a multiple of ``multiple`` (at least one)."""
    scale = max(1.0, max(size) / max_size)
    return tuple(max(multiple, int(side / scale) // multiple * multiple) for side in size)


def read_relief(reader: ReliefReader, photo: torch.Tensor, light: torch.Tensor, fov: float,
                low_size: tuple[int, int], max_size: int = READ_SIZE,
                convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> torch.Tensor:
    """The relief finer than ``low_size`` as the reader reads it from ``photo`` (B, 3, H, W).

    The photo is area-averaged to at most ``max_size`` px, a multiple of the reader's
    ``multiple``; what the slope holds at and below ``low_size`` is taken out (the capture
    network's answer stays there).

    Returns:
        (B, 2, H', W') the x and y slope to add to the normals, H' and W' at most ``max_size``.
    """
    size = read_size(tuple(photo.shape[-2:]), max_size, reader.config.multiple)
    small = photo.float() if size == tuple(photo.shape[-2:]) else downsample(photo.float(), size)
    device = next(reader.parameters()).device
    with torch.no_grad():
        inputs = reader_inputs(small, light, low_size, fov, convention, extent, reader.config.unit_inputs)
        slope = reader(inputs.to(device)).float().cpu()
    return slope - upsample_bilinear(downsample(slope, low_size), *size)


def save_reader(path: str | os.PathLike, reader: ReliefReader, metadata: dict | None = None,
                extra_tensors: dict[str, torch.Tensor] | None = None) -> Path:
    """Write the reader's weights, its configuration and ``metadata`` atomically (a temporary file,
    then renamed); ``extra_tensors`` (optimiser state) are stored beside the weights."""
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {"reader." + name: value.detach().contiguous().cpu() for name, value in reader.state_dict().items()}
    tensors.update({name: value.detach().contiguous().cpu() for name, value in (extra_tensors or {}).items()})
    broken = [name for name, value in tensors.items() if value.is_floating_point() and not bool(torch.isfinite(value).all())]
    if broken:
        raise InputError(f"{path}: not written: {broken[0]} holds NaN or infinite values")
    document = {"format": FORMAT, "config": asdict(reader.config), **(metadata or {})}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        save_file(tensors, str(temporary), metadata={"mideepbasis": json.dumps(document)})
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def load_reader(path: str | os.PathLike) -> tuple[ReliefReader, dict, dict[str, torch.Tensor]]:
    """The reader stored at ``path`` (``save_reader``), its metadata and the other tensors stored
    with it; a file that is not a reader's is refused in one line that names it."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such relief reader file")
    try:
        with safe_open(str(path), framework="pt") as handle:
            document = json.loads((handle.metadata() or {}).get("mideepbasis", "{}"))
            tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    except (SafetensorError, OSError, ValueError) as error:
        raise InputError(f"{path}: not a safetensors file ({' '.join(str(error).split())})") from None
    if document.get("format") != FORMAT:
        raise InputError(f"{path}: not a relief reader's weights (format {document.get('format')!r})")
    known = {field.name for field in fields(ReliefReaderConfig)}
    values = {key: tuple(value) if isinstance(value, list) else value
              for key, value in document.get("config", {}).items() if key in known}
    reader = ReliefReader(ReliefReaderConfig(**values))
    prefix = "reader."
    reader.load_state_dict({name[len(prefix):]: value for name, value in tensors.items() if name.startswith(prefix)})
    reader.eval()
    others = {name: value for name, value in tensors.items() if not name.startswith(prefix)}
    return reader, document, others
