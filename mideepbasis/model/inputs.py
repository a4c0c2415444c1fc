"""The network's inference contract: how a photo and its flash become the network's input.

Training (``data.synth``) and capture both build the input here, and the network reads its
photo back with ``decode_photo``; nothing else assumes the layout. The input of photos
(B, 3, H, W) taken under flashes at lights (B, 3) is (B, C, H, W), every channel in [-1, 1]:

======================  ============  ==========================================================
channels                name          content
======================  ============  ==========================================================
``PHOTO`` 0:3           photo         the linear photo, clipped to [0, 1]
``LOG_PHOTO`` 3:6       log photo     ``log_compress`` of it (shadows stretched)
``LIGHTING_MARK`` 6:9   lighting mark a fixed reference material rendered under the same flash
9 : 9 + 3 k             extras        the network's ``extra_inputs`` (``EXTRA_INPUTS``), 3 each
======================  ============  ==========================================================

(docs/ARCHITECTURE.md section 7.) Shapes: photos (B, 3, H, W) linear; lights (B, 3) [patch half-widths].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .. import constants, geometry
from ..errors import InputError
from ..resampling import gaussian_blur

#: Constant of the log compression of the network input (the DeepBasis value).
LOG_EPS = 0.01

#: Channels of the input every network has: the photo, the log photo and the lighting mark.
PHOTO = slice(0, 3)
LOG_PHOTO = slice(3, 6)
LIGHTING_MARK = slice(6, 9)
BASE_CHANNELS = 9

#: Channels each optional input adds.
CHANNELS_PER_EXTRA = 3


def input_channels(extra_inputs: tuple[str, ...] = ()) -> int:
    """Channels of the network input with the optional inputs ``extra_inputs``."""
    return BASE_CHANNELS + CHANNELS_PER_EXTRA * len(extra_inputs)


def decode_photo(inputs: torch.Tensor) -> torch.Tensor:
    """The linear photo (B, 3, H, W) in [0, 1] back from a network input (B, C, H, W): the
    inverse of ``network_input`` on its ``PHOTO`` channels."""
    return inputs[:, PHOTO] * 0.5 + 0.5


#: Photo decodings a checkpoint may ask for: how 8/16-bit photo values become linear ones.
PHOTO_DECODINGS = ("srgb", "gamma2.2")


@dataclass(frozen=True)
class ModelInfo:
    """How a model must be run, as its checkpoint records it: the inference contract that capture
    reads (``load_model`` attaches it to the network as ``model.info``)."""

    convention: str
    """Shading convention the network was trained with (``physical`` or ``deepbasis``)."""

    fov_deg: float | None = None
    """Field of view the weights were trained for [deg]; None: not recorded (any)."""

    plane_extent: float = 1.0
    """Half-width of the sample the camera frames [patch half-widths]."""

    photo_decoding: str = "srgb"
    """How 8/16-bit photo values become linear: ``srgb`` (the IEC curve) or ``gamma2.2`` (x^2.2)."""

    training_size: int | None = None
    """Resolution the network was trained at [pixels]; None: not recorded."""

    @classmethod
    def from_document(cls, document: dict, config, source: str = "checkpoint") -> ModelInfo:
        """The record of a checkpoint's JSON document and its network's ``NetworkConfig`` (a key
        the document lacks takes its default)."""
        decoding = document.get("photo_decoding", "srgb")
        if decoding not in PHOTO_DECODINGS:
            raise InputError(f"{source}: unknown photo decoding {decoding!r}; expected one of {list(PHOTO_DECODINGS)}")
        size = ((document.get("training") or {}).get("config") or {}).get("size")
        fov = document.get("fov_deg")
        return cls(convention=config.convention, fov_deg=float(fov) if fov else None,
                   plane_extent=float(config.plane_extent), photo_decoding=decoding,
                   training_size=int(size) if size else None)


def log_compress(photo: torch.Tensor, eps: float = LOG_EPS) -> torch.Tensor:
    """(log(x + eps) - log(eps)) / (log(1 + eps) - log(eps)): [0, 1] to [0, 1], shadows stretched."""
    return (torch.log(photo + eps) - math.log(eps)) / (math.log(1.0 + eps) - math.log(eps))


def _reference_render(material: torch.Tensor, lights: torch.Tensor, fov: float, convention: str,
                      extent: float) -> torch.Tensor:
    """A fixed reference material (1, 10, H, W) rendered under each co-located flash of ``lights``
    (B, 3), without gradients: (B, 3, H, W) linear."""
    from ..render import render_flash

    batch = material.to(lights).expand(lights.shape[0], -1, -1, -1)
    with torch.no_grad():
        return render_flash(batch, lights.view(-1, 1, 3), fov=fov, convention=convention, extent=extent)[:, 0]


def lighting_mark(lights: torch.Tensor, height: int, width: int, fov: float = constants.DEFAULT_FOV_DEG,
                  convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> torch.Tensor:
    """The lighting-mark image: the fixed reference material rendered under each light, clipped to [0, 1].

    Args:
        lights: (B, 3) flash positions [patch half-widths].

    Returns:
        (B, 3, H, W).
    """
    return _reference_render(geometry.lighting_mark_material(height, width), lights, fov, convention,
                             extent).clamp(0.0, 1.0)


#: Optional input channels (three each) that make the shading explicit (``NetworkConfig.extra_inputs``):
#: ``shading``: the photo divided by the flash's own falloff (a white Lambertian rendered under the
#: same flash), log-compressed: what is left is albedo times relative shading, plus the highlight;
#: ``highpass``: the log photo minus its Gaussian blur (sigma 1/64 of the width): local shading
#: and texture, the flash's slow falloff removed; ``view``: the camera's geometry, which the lighting
#: mark shows only through a clipped highlight: 2 cos - 1 and 2 cos^3 - 1 of each pixel's angle to
#: the co-located flash and camera (the falloff's shape), and the field of view as a constant
#: (``VIEW_FOV_RANGE`` to [-1, 1]); all three turn with the image, as the symmetries need.
EXTRA_INPUTS = ("shading", "highpass", "view")

#: Fields of view the ``view`` input's constant channel maps to -1 and 1 [deg].
VIEW_FOV_RANGE = (20.0, 75.0)


def view_channels(lights: torch.Tensor, height: int, width: int, fov: float = constants.DEFAULT_FOV_DEG,
                  extent: float = 1.0) -> torch.Tensor:
    """The ``view`` input channels (``EXTRA_INPUTS``) of flashes at ``lights`` (B, 3) [patch
    half-widths], (B, 3, H, W) in [-1, 1]."""
    points = geometry.pixel_points(height, width, device=lights.device, dtype=lights.dtype)[None] * extent
    towards = lights.view(-1, 3, 1, 1) - points
    cosine = (towards[:, 2:3] / geometry.vector_length(towards, dim=1, keepdim=True)).clamp(0.0, 1.0)
    low, high = VIEW_FOV_RANGE
    code = max(-1.0, min(1.0, 2.0 * (fov - low) / (high - low) - 1.0))
    return torch.cat([2.0 * cosine - 1.0, torch.full_like(cosine, code), 2.0 * cosine**3 - 1.0], dim=1)

#: Largest ratio of photo to falloff the ``shading`` channels represent (highlights saturate there).
MAX_SHADING_RATIO = 4.0


def flash_falloff(lights: torch.Tensor, height: int, width: int, fov: float = constants.DEFAULT_FOV_DEG,
                  convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> torch.Tensor:
    """A flat white Lambertian (specular 0) rendered under each co-located flash, (B, 1, H, W): the
    flash's falloff and the cosine at every pixel (``physical``: (H / d)^3 for a flash at height H
    and distance d; a co-located flash sees no Fresnel reflection from specular 0)."""
    white = torch.zeros(1, constants.BASIS_CHANNELS, height, width)
    white[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    white[:, constants.DIFFUSE], white[:, constants.ROUGHNESS] = 1.0, 1.0
    return _reference_render(white, lights, fov, convention, extent)[:, :1]


def extra_input_channels(photo: torch.Tensor, names: tuple[str, ...], falloff: torch.Tensor | None = None,
                         view: torch.Tensor | None = None) -> torch.Tensor:
    """The optional input channels ``names`` (``EXTRA_INPUTS``) of photos (B, 3, H, W) in [0, 1], each in
    [-1, 1], (B, 3 len(names), H, W). ``shading`` needs the flash's ``falloff`` (B, 1, H, W),
    ``view`` its ``view_channels`` (B, 3, H, W)."""
    channels = []
    for name in names:
        if name == "view":
            if view is None:
                raise ValueError("the view input needs the view channels")
            channels.append(view.to(photo))
            continue
        if name == "shading":
            if falloff is None:
                raise ValueError("the shading input needs the flash falloff")
            ratio = (photo / falloff.clamp(min=1e-4)).clamp(0.0, MAX_SHADING_RATIO)
            channels.append(log_compress(ratio / MAX_SHADING_RATIO) * 2.0 - 1.0)
        elif name == "highpass":
            logarithm = torch.log(photo + LOG_EPS)
            sigma = max(0.5, photo.shape[-1] / 64.0)
            channels.append((0.5 * (logarithm - gaussian_blur(logarithm, sigma))).clamp(-1.0, 1.0))
        else:
            raise ValueError(f"unknown extra input {name!r}; expected some of {EXTRA_INPUTS}")
    return torch.cat(channels, dim=1) if channels else photo.new_zeros(photo.shape[0], 0, *photo.shape[-2:])


#: Channels of ``relief_inputs``: log photo (3), shading (1), its high-pass (1), flash direction (2).
RELIEF_CHANNELS = 7
#: The relief inputs' first channel of the flash direction's x and y (they turn with the image).
RELIEF_DIRECTION_CHANNEL = 5


def relief_inputs(photo: torch.Tensor, lights: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG,
                  convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> torch.Tensor:
    """The input of the normal unit (``NetworkConfig.normal_unit_width``): what a relief changes in a
    flash photo, made explicit. A small tilt t of the normal changes the shading by about
    t . l_xy, the flash direction's component in the sample plane, so the unit gets:

    - the log-compressed photo, in [-1, 1] (3 channels);
    - the shading: 0.3 log(luminance / falloff), the falloff a white Lambertian under the same
      flash (``flash_falloff``), so the flash's own gradient is gone (1);
    - its high-pass, minus a Gaussian blur of sigma 1/64 of the width (1);
    - 3 l_x and 3 l_y, the unit vector from each pixel's point towards the flash (2).

    Args:
        photo: (B, 3, H, W) linear, clipped to [0, 1]; lights: (B, 3) flash positions [patch half-widths].

    Returns:
        (B, RELIEF_CHANNELS, H, W).
    """
    batch, _, height, width = photo.shape
    photo = photo.clamp(0.0, 1.0)
    falloff = flash_falloff(lights, height, width, fov, convention, extent).to(photo)
    shading = torch.log(photo.mean(dim=1, keepdim=True) + LOG_EPS) - torch.log(falloff + LOG_EPS)
    highpass = shading - gaussian_blur(shading, max(0.5, width / 64.0))
    points = geometry.pixel_points(height, width, device=photo.device, dtype=photo.dtype)[None] * extent
    towards = lights.to(photo).view(batch, 3, 1, 1) - points
    direction = towards / geometry.vector_length(towards, dim=1, keepdim=True)
    return torch.cat([log_compress(photo) * 2.0 - 1.0, 0.3 * shading, highpass, 3.0 * direction[:, :2]], dim=1)


def octave_relief_inputs(photo: torch.Tensor, lights: torch.Tensor, octaves: int,
                         fov: float = constants.DEFAULT_FOV_DEG, convention: str = constants.DEFAULT_CONVENTION,
                         extent: float = 1.0) -> list[torch.Tensor]:
    """``relief_inputs`` of the photo (B, 3, H, W) and of the photo area-averaged to 1/2, 1/4, ...
    of its size, ``octaves`` in all (``NetworkConfig.normal_unit_octaves``). The k-th is
    (B, RELIEF_CHANNELS, H / 2^k, W / 2^k)."""
    return [relief_inputs(torch.nn.functional.avg_pool2d(photo, 2**octave) if octave else photo, lights, fov,
                          convention, extent)
            for octave in range(octaves)]


def network_input(photo: torch.Tensor, mark: torch.Tensor, extra_inputs: tuple[str, ...] = (),
                  falloff: torch.Tensor | None = None, view: torch.Tensor | None = None) -> torch.Tensor:
    """The network input: [photo, log-compressed photo, lighting mark] (9 channels), each in [-1, 1],
    then the ``extra_inputs`` channels (``extra_input_channels``).

    Args:
        photo: (B, 3, H, W) linear photo; clipped to [0, 1].
        mark: (B, 3, H, W) lighting-mark image in [0, 1].
        extra_inputs: names of optional channels (the network's ``config.extra_inputs``).
        falloff: (B, 1, H, W) the flash's falloff (``flash_falloff``), for ``shading``.
        view: (B, 3, H, W) ``view_channels``, for ``view``.

    Returns:
        (B, 9 + 3 len(extra_inputs), H, W).
    """
    photo = photo.clamp(0.0, 1.0)
    base = torch.cat([photo, log_compress(photo), mark], dim=1) * 2.0 - 1.0
    if not extra_inputs:
        return base
    return torch.cat([base, extra_input_channels(photo, tuple(extra_inputs), falloff, view)], dim=1)


def encode_inputs(photos: torch.Tensor, lights: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG,
                  convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0,
                  extra_inputs: tuple[str, ...] = ()) -> torch.Tensor:
    """The network input of photos (B, 3, H, W) taken under flashes at ``lights`` (B, 3): their
    lighting marks (and flash falloffs, for ``shading``) rendered and ``network_input`` built.
    Training and capture both call this."""
    height, width = photos.shape[-2:]
    mark = lighting_mark(lights, height, width, fov, convention, extent)
    falloff = flash_falloff(lights, height, width, fov, convention, extent) if "shading" in extra_inputs else None
    view = view_channels(lights.float(), height, width, fov, extent) if "view" in extra_inputs else None
    return network_input(photos, mark, tuple(extra_inputs), falloff, view)
