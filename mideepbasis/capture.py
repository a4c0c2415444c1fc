"""Photo to material: load the photo, find the flash, predict the bases, refine the global bases.

    from mideepbasis import capture
    result = capture("flash_photo.jpg")                   # a CaptureResult
    result.material.save("out/")

Stages (DESIGN section 1):

1. **Photo.** JPEG, PNG (8/16-bit) or EXR; EXIF orientation applied; sRGB decoded to linear; the
   centre square cropped; resampled to the working resolution (256 by default, or the photo's
   own up to 2048 with ``resolution="native"``). The field of view comes from the EXIF
   35 mm-equivalent focal length when present, else ``fov``, else 45 degrees.
2. **Lighting search.** The flash position is unknown in a hand-held shot. Starting from the
   centred flash, each pass predicts the material with the current light (one network pass) and
   then, holding that material fixed, renders it under every candidate light within delta =
   16.33 deg (batched through the Mitsuba plugin) and moves to the candidate whose rendering
   matches the photo best; it stops when the light no longer moves. A final local search on a
   finer grid needs no network pass.
3. **Prediction** with the found light: weights, global bases, local deviations.
4. **Refinement.** Only the N global bases move: Adam on the L1 difference between the photo and
   the rendering of the blended material (rendered through the plugin, gradients through the
   bridge); weights and local deviations stay fixed. It runs on a downsampled copy (the global
   bases are a few numbers; the photo's large-scale appearance determines them).

Shapes: photos (B, 3, H, W) linear in [0, 1]; lights (B, 3) flash positions and offsets (B, 2)
[patch half-widths].
"""

from __future__ import annotations

import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import constants, geometry
from .data.synth import encode_inputs
from .errors import InputError
from .imageio import image_size, read_focal_length_35mm, read_image
from .material import Material
from .model.network import DeepBasisNet, DeepBasisOutput, blend, normalize_basis_normals, to_maps

#: Smallest photo side accepted [pixels].
MIN_PHOTO_SIZE = 64

#: Largest working resolution of ``resolution="native"`` [pixels].
MAX_NATIVE_RESOLUTION = 2048

#: Diagonal of a 35 mm film frame [mm]: EXIF 35 mm-equivalent focal lengths match its field of view.
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)


@dataclass(frozen=True)
class CaptureConfig:
    """How a photo becomes a material."""

    fov: float | None = None
    """Field of view of the photo's width [deg]; None: from EXIF, else 45."""

    light: tuple[float, float] | None = None
    """Known flash offset (tx, ty) [patch half-widths]; None: search for it."""

    resolution: int | str = constants.DEFAULT_RESOLUTION
    """Working resolution [pixels], or ``native`` (the photo's own, up to 2048)."""

    refine_steps: int = 125
    """Adam steps refining the global bases; 0 turns refinement off. (The paper: 500; with the
    normals kept, 125 did as well here: benchmarks/refinement.py.)"""

    refine_resolution: int = 64
    """Resolution of the refinement's renders [pixels]."""

    refine_lr: float = 0.01
    """Adam learning rate of the refinement [signed-space units per step]."""

    refine_normals: bool = False
    """Whether the refinement may turn the global bases' normals, as the paper's does. Off by
    default: fitting the one flash view by tilting the normals raised the normal and the
    re-rendering errors (benchmarks/refinement.py)."""

    refine_prior: float = 0.0
    """Weight of the L1 pull of the refined global bases toward the network's (0: none)."""

    network_resolution: int | None = None
    """Largest resolution the network runs at [pixels]; a larger photo is predicted on a
    downsampled copy and the weights and deviations upsampled. None: the resolution the model was
    trained at (from its checkpoint); 0: no limit."""

    search_grid: int = 21
    """Candidates per side of the lighting search's square grid over the offsets within delta."""

    search_resolution: int = 128
    """Resolution of the lighting search's candidate renders [pixels]."""

    search_network_resolution: int = 256
    """Largest resolution of the lighting search's network passes [pixels]: a larger photo is
    searched on a downsampled copy (the flash position shows at any scale), then predicted in full."""

    search_passes: int = 6
    """Most network passes of the lighting search."""

    search_prior: float = 0.02
    """Weight of the squared offset [patch half-widths^2] added to the search's objective (mean L1),
    a pull toward the centre where the photo does not decide; 0: none. On held-out procedural
    materials (not the test set) 0.02 lowered the mean angular error from 4.72 to 4.07 deg
    (benchmarks/search_prior.py)."""

    max_offset_deg: float = constants.MAX_OFFSET_DEG
    """Largest hand-held offset searched [deg] (delta)."""

    tileable: bool = False
    """Make the captured maps wrap around their edges without a seam (``tiling.make_tileable``)."""

    crop: tuple[int, int, int, int] | None = None
    """Part of the photo that holds the sample: (x, y, width, height) [pixels of the photo as
    shown, EXIF orientation applied]; its centre square is used. None: the whole photo."""


@dataclass
class CaptureResult:
    """A capture: the material and everything measured on the way."""

    material: Material
    """The captured maps."""

    photo: torch.Tensor
    """(3, H, W) the working photo, linear."""

    offset: tuple[float, float]
    """The flash offset (tx, ty) used [patch half-widths]."""

    fov: float
    """Field of view [deg]."""

    fov_source: str
    """Where the field of view came from: ``exif``, ``argument`` or ``default``."""

    searched: bool
    """Whether the offset was searched for (else it was given)."""

    search_history: list[dict] = field(default_factory=list)
    """The lighting search's passes: offset [patch half-widths] and objective (mean L1) each."""

    refinement_losses: list[float] = field(default_factory=list)
    """The refinement's loss at every step."""

    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage."""

    notes: list[str] = field(default_factory=list)
    """What the user should know (a crop, the field of view's source, a dark photo)."""

    output: DeepBasisOutput | None = None
    """The network's prediction (weights, bases, ...), refined global bases included."""

    @property
    def offset_angle_deg(self) -> float:
        """Angle of the flash offset seen from the sample centre [deg]."""
        return float(geometry.offset_angle_deg(torch.tensor(self.offset), self.fov))

    @property
    def light_position(self) -> torch.Tensor:
        """(3,) the flash position [patch half-widths]."""
        return geometry.light_positions(torch.tensor(self.offset, dtype=torch.float32), self.fov)


# --- the photo ------------------------------------------------------------------------------------


def field_of_view_from_focal(focal_35mm: float, width: int, height: int, square: int | None = None) -> float:
    """Field of view across the centre square of a width x height photo [deg], from its
    35 mm-equivalent focal length [mm] (which matches the field of view of the frame's diagonal);
    or across a square of ``square`` pixels of it (a crop)."""
    half_diagonal = math.atan(FILM_DIAGONAL_MM / 2.0 / focal_35mm)
    side = (square or min(width, height)) / math.hypot(width, height)
    return math.degrees(2.0 * math.atan(math.tan(half_diagonal) * side))


def load_photo(path: str | Path, fov: float | None = None, resolution: int | str = constants.DEFAULT_RESOLUTION,
               decoding: str = "srgb", crop: tuple[int, int, int, int] | None = None
               ) -> tuple[torch.Tensor, float, str, list[str]]:
    """Read a flash photo for capture.

    ``decoding`` turns 8/16-bit values into linear ones: ``srgb`` (the IEC curve) or ``gamma2.2``
    (the authors' networks were given x^2.2). EXR photos are linear already. ``crop`` (x, y,
    width, height) [pixels of the photo as shown] keeps that part of it (then its centre square).
    A photo much larger than the working resolution is decoded at a reduced size (``read_image``'s
    ``reduce``), at least twice the working resolution, so that 48 MP photos fit in little memory.

    Returns:
        (photo (3, R, R) linear, field of view [deg] of the square used, its source, notes).

    Raises:
        InputError: unreadable, not an image, smaller than 64 pixels, a crop outside the photo.
    """
    path = Path(path)
    full_width, full_height = image_size(path)
    box = (0, 0, full_width, full_height) if crop is None else _checked_crop(path, crop, full_width, full_height)
    side = min(box[2], box[3])
    if side < MIN_PHOTO_SIZE:
        what = "the crop" if crop else "the photo"
        raise InputError(f"'{path}': {what} is {box[2]}x{box[3]} pixels, smaller than the {MIN_PHOTO_SIZE} pixels "
                         "a capture needs")
    needed = 2 * _working_resolution(side, resolution)
    reduce = max(1, side // needed) if resolution != "native" else 1
    image = read_image(path, decode_srgb=decoding == "srgb", reduce=reduce)
    if decoding == "gamma2.2" and path.suffix.lower() != ".exr":
        image = image**2.2
    notes = []
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    x, y, w, h = (v // reduce for v in box)
    image = image[y:y + h, x:x + w]
    height, width = image.shape[:2]
    focal, note = (None, None) if path.suffix.lower() == ".exr" else read_focal_length_35mm(path)
    if note:
        notes.append(note)
    if focal:
        # The lens saw the whole frame; the square used (its centre square, or a crop's) is part of it.
        used_fov, source = field_of_view_from_focal(focal, full_width, full_height, side), "exif"
        notes.append(f"field of view {used_fov:.1f} deg from the EXIF 35 mm-equivalent focal length {focal:g} mm")
    elif fov is not None:
        used_fov, source = float(fov), "argument"
    else:
        used_fov, source = constants.DEFAULT_FOV_DEG, "default"
        notes.append(f"no EXIF focal length: field of view {used_fov:g} deg assumed (set it with --fov)")
    if crop is not None:
        notes.append(f"cropped to {box[2]}x{box[3]} pixels at ({box[0]}, {box[1]}) of the {full_width}x{full_height} photo")
    if width != height:
        side = min(width, height)
        top, left = (height - side) // 2, (width - side) // 2
        image = image[top:top + side, left:left + side]
        notes.append(f"the {'crop' if crop is not None else 'photo'} is {width}x{height}: "
                     f"its centre {side}x{side} square was used")
    photo = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float()
    target = _working_resolution(photo.shape[-1], resolution)
    if target != photo.shape[-1]:
        photo = F.interpolate(photo[None], size=(target, target), mode="area" if target < photo.shape[-1] else "bilinear",
                              align_corners=None if target < photo.shape[-1] else False)[0]
    photo = photo.clamp(0.0, 1.0)
    mean = float(photo.mean())
    if mean < 0.01:
        warnings.warn(f"'{path.name}' is nearly black (mean {mean:.4f}): the capture will be poor")
    if float((photo >= 0.999).float().mean()) > 0.25:
        warnings.warn(f"'{path.name}' is clipped over a quarter of its pixels: the capture will be poor")
    return photo, used_fov, source, notes


def _checked_crop(path: Path, crop, width: int, height: int) -> tuple[int, int, int, int]:
    """The crop (x, y, w, h) as integers, or a one-line InputError when it leaves the photo."""
    x, y, w, h = (int(v) for v in crop)
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise InputError(f"'{path}': the crop {x},{y},{w},{h} (x, y, width, height) does not lie inside the "
                         f"{width}x{height} photo")
    return x, y, w, h


def _working_resolution(side: int, resolution: int | str) -> int:
    if resolution == "native":
        return min(side, MAX_NATIVE_RESOLUTION)
    return int(resolution)


# --- prediction -------------------------------------------------------------------------------------


def trained_resolution(model: DeepBasisNet) -> int | None:
    """The resolution [pixels] ``model`` was trained at, as its checkpoint records it (None: unknown)."""
    document = getattr(model, "checkpoint", None) or {}
    size = (document.get("training") or {}).get("config", {}).get("size")
    return int(size) if size else None


def network_resolution_limit(model: DeepBasisNet, requested: int | None = None) -> int | None:
    """The largest resolution [pixels] ``predict`` runs ``model`` at: ``requested``, or when it is
    None the model's training resolution; None (or 0) means no limit."""
    return trained_resolution(model) if requested is None else requested or None


def predict(model: DeepBasisNet, photos: torch.Tensor, lights: torch.Tensor,
            fov: float = constants.DEFAULT_FOV_DEG, network_resolution: int | None = None) -> DeepBasisOutput:
    """The material seen in ``photos`` (B, 3, H, W) taken with flashes at ``lights`` (B, 3).

    The network runs at most at ``network_resolution`` [pixels] (None: the resolution the model was
    trained at, when its checkpoint says; 0: no limit). A larger photo is predicted on an
    area-downsampled copy, and its blending weights and local deviations are upsampled to the
    photo's size, so the maps, the refinement and everything after work at full resolution. A
    fully convolutional network run at a larger scale than it was trained at sees every feature
    bigger than in training; on the shared test set the shipped model (trained at 128 px) gave
    lower errors at 128 px upsampled than run at 256 px (benchmarks/model_quality.py).
    """
    limit = network_resolution_limit(model, network_resolution)
    height, width = photos.shape[-2:]
    if not limit or max(height, width) <= limit:
        return _network_pass(model, photos, lights, fov)
    scale = limit / max(height, width)
    small = F.interpolate(photos, size=(max(1, round(height * scale)), max(1, round(width * scale))), mode="area")
    return _upsample_output(_network_pass(model, small, lights, fov), height, width)


def _network_pass(model: DeepBasisNet, photos: torch.Tensor, lights: torch.Tensor, fov: float) -> DeepBasisOutput:
    """One network pass at the photos' own size; a size that is not a multiple of the network's
    stride is padded by reflection and the prediction cropped back."""
    device = next(model.parameters()).device
    height, width = photos.shape[-2:]
    stride = model.config.stride
    pad_h, pad_w = (-height) % stride, (-width) % stride
    inputs = encode_inputs(photos, lights, fov, model.config.convention, model.config.plane_extent,
                           model.config.extra_inputs)
    if pad_h or pad_w:
        inputs = F.pad(inputs, (0, pad_w, 0, pad_h), mode="reflect")
    with torch.no_grad():
        output = model(inputs.to(device), lights.to(device), fov=fov)
    if pad_h or pad_w:
        output = _crop_output(output, height, width)
    return output


def _upsample_output(output: DeepBasisOutput, height: int, width: int) -> DeepBasisOutput:
    """The prediction at height x width: weights and local deviations (or, without bases, the
    maps) upsampled bilinearly, and the maps rebuilt from them."""
    def upsample(value):
        flat = value.reshape(value.shape[0], -1, *value.shape[-2:])
        big = F.interpolate(flat, size=(height, width), mode="bilinear", align_corners=False)
        return big.reshape(*value.shape[:-2], height, width)

    if output.weights is None:
        signed = upsample(output.signed_maps)
        return DeepBasisOutput(maps=to_maps(signed), extras={"signed_maps": signed})
    # Bilinear interpolation keeps the weights non-negative and summing to one.
    result = DeepBasisOutput(maps=None, weights=upsample(output.weights), global_bases=output.global_bases,
                             deviations=upsample(output.deviations) if output.deviations is not None else None,
                             error=upsample(output.error) if output.error is not None else None)
    result.maps = maps_from_bases(result, output.global_bases)
    return result


def _crop_output(output: DeepBasisOutput, height: int, width: int) -> DeepBasisOutput:
    def crop(value):
        return value[..., :height, :width] if isinstance(value, torch.Tensor) and value.ndim >= 4 else value

    return DeepBasisOutput(maps=crop(output.maps), weights=crop(output.weights), global_bases=output.global_bases,
                           bases=crop(output.bases), deviations=crop(output.deviations), error=crop(output.error),
                           extras={k: crop(v) for k, v in output.extras.items()})


def _downsample(image: torch.Tensor, size: int) -> torch.Tensor:
    """Area-average (..., C, H, W) to size x size (no-op when already there)."""
    if image.shape[-1] == size and image.shape[-2] == size:
        return image
    shape = image.shape
    flat = image.reshape(-1, *shape[-3:])
    return F.interpolate(flat, size=(size, size), mode="area").reshape(*shape[:-2], size, size)


def _downsample_maps(maps: torch.Tensor, size: int) -> torch.Tensor:
    small = _downsample(maps, size)
    return torch.cat([F.normalize(small[:, :3], dim=1), small[:, 3:]], dim=1)


# --- the lighting search -------------------------------------------------------------------------------


def candidate_offsets(fov: float, max_offset_deg: float, grid: int, centre=(0.0, 0.0), span: float | None = None) -> torch.Tensor:
    """A square grid of ``grid`` x ``grid`` offsets around ``centre`` over +-``span`` [patch half-widths]
    (default: the whole reachable range), kept where the offset angle is within ``max_offset_deg``. (K, 2)."""
    limit = geometry.max_offset(fov, max_offset_deg)
    span = limit if span is None else span
    axis = torch.linspace(-span, span, grid)
    offsets = torch.stack(torch.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2) + torch.tensor(centre)
    return offsets[torch.linalg.vector_norm(offsets, dim=-1) <= limit + 1e-6]


def light_objective(maps: torch.Tensor, photo: torch.Tensor, offsets: torch.Tensor, fov: float, convention: str,
                    batch: int = 64, extent: float = 1.0) -> torch.Tensor:
    """Mean L1 between the photo and the clipped rendering of ``maps`` under each candidate, (K,).

    Args:
        maps: (1, 10, h, w) the material held fixed; photo: (1, 3, h, w); offsets: (K, 2).
    """
    from .render import render_flash

    lights = geometry.light_positions(offsets, fov)
    errors = []
    with torch.no_grad():
        for first in range(0, len(lights), batch):
            chunk = lights[first:first + batch].unsqueeze(0)
            rendered = render_flash(maps, chunk, fov=fov, convention=convention, extent=extent)[0].clamp(0.0, 1.0)
            errors.append((rendered - photo).abs().mean(dim=(1, 2, 3)))
    return torch.cat(errors)


def search_light(model: DeepBasisNet, photo: torch.Tensor, fov: float, config: CaptureConfig = CaptureConfig()
                 ) -> tuple[tuple[float, float], list[dict], DeepBasisOutput]:
    """Find the flash offset of ``photo`` (3, H, W); returns (offset, history, last prediction)."""
    convention = model.config.convention
    if photo.shape[-1] > config.search_network_resolution:
        photo = _downsample(photo[None], config.search_network_resolution)[0]
    small_photo = _downsample(photo[None], config.search_resolution)
    candidates = candidate_offsets(fov, config.max_offset_deg, config.search_grid)
    current = torch.zeros(2)
    history = []
    output = None

    def objective(maps: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        errors = light_objective(maps, small_photo, offsets, fov, convention, extent=model.config.plane_extent)
        return errors + config.search_prior * offsets.square().sum(dim=-1)

    for index in range(config.search_passes):
        output = predict(model, photo[None], geometry.light_positions(current[None], fov), fov,
                         config.network_resolution)
        small_maps = _downsample_maps(output.maps.cpu(), config.search_resolution)
        errors = objective(small_maps, candidates)
        best = candidates[int(torch.argmin(errors))]
        history.append({"pass": index + 1, "offset": current.tolist(), "best_candidate": best.tolist(),
                        "objective": float(errors.min())})
        if torch.allclose(best, current, atol=1e-6):
            break
        current = best
    # A finer grid around the last candidate, with the material of the last pass.
    step = 2 * geometry.max_offset(fov, config.max_offset_deg) / max(1, config.search_grid - 1)
    fine = candidate_offsets(fov, config.max_offset_deg, 9, centre=tuple(current.tolist()), span=step)
    errors = objective(small_maps, fine)
    current = fine[int(torch.argmin(errors))]
    history.append({"pass": "fine", "offset": current.tolist(), "objective": float(errors.min())})
    return (float(current[0]), float(current[1])), history, output


# --- refinement of the global bases ---------------------------------------------------------------------


class SmallAdam:
    """Adam (Kingma and Ba 2015) for one small tensor, the update of ``torch.optim.Adam``'s
    single-tensor path written out, so that its results are the same to the bit.

    ``torch.optim.Adam`` imports ``torch._dynamo`` (with sympy) when it is first built: 1.5 - 2.6 s
    of a capture's start-up, for a (1, N, 10) parameter.
    """

    def __init__(self, parameter: torch.Tensor, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        self.parameter, self.lr, self.betas, self.eps = parameter, lr, betas, eps
        self.exp_avg = torch.zeros_like(parameter)
        self.exp_avg_sq = torch.zeros_like(parameter)
        self.steps = 0

    @torch.no_grad()
    def step(self) -> None:
        """One update from ``parameter.grad``."""
        grad, (beta1, beta2) = self.parameter.grad, self.betas
        self.steps += 1
        self.exp_avg.lerp_(grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        bias_correction1 = 1 - beta1**self.steps
        bias_correction2_sqrt = (1 - beta2**self.steps) ** 0.5
        denominator = (self.exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
        self.parameter.addcdiv_(self.exp_avg, denominator, value=-self.lr / bias_correction1)


def refine_global_bases(output: DeepBasisOutput, photo: torch.Tensor, light: torch.Tensor, fov: float,
                        convention: str, steps: int = 500, resolution: int = 64, lr: float = 0.01,
                        progress: bool = False, extent: float = 1.0, refine_normals: bool = True,
                        prior: float = 0.0) -> tuple[torch.Tensor, list[float]]:
    """Optimise the global bases so the rendering matches the photo; weights and deviations stay fixed.

    The loss is the mean L1 between the rendering and the photo, plus ``prior`` times the mean L1
    between the bases and the network's.

    Args:
        output: the prediction (weights, global bases, deviations) of one photo.
        photo: (3, H, W) the photo, linear; light: (3,) the flash position.
        steps, resolution, lr: Adam steps, render resolution [pixels], learning rate.
        refine_normals: False keeps the bases' normals as predicted (one view constrains them poorly).
        prior: weight of the pull toward the network's bases.

    Returns:
        ((1, N, 10) refined global bases, signed space; the loss at every step).
    """
    from tqdm import tqdm

    from .render import render_flash

    weights = _downsample(output.weights.detach().cpu(), resolution)
    weights = weights / weights.sum(dim=1, keepdim=True).clamp(min=1e-6)
    deviations = _downsample(_deviations(output).detach().cpu(), resolution)
    target = _downsample(photo[None], resolution)
    lights = light.view(1, 1, 3)
    predicted = output.global_bases.detach().cpu()
    global_bases = predicted.clone().requires_grad_(True)
    # Zero where the refinement may not move a channel: the normals when refine_normals is False.
    movable = torch.ones(constants.BASIS_CHANNELS)
    if not refine_normals:
        movable[:3] = 0.0

    def masked(free: torch.Tensor) -> torch.Tensor:
        return predicted + (free - predicted) * movable

    optimizer = SmallAdam(global_bases, lr=lr)
    losses = []
    # The tensors here are small: waking torch's worker threads for every op costs more than it saves.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for _ in tqdm(range(steps), desc="refining", unit="step", disable=not progress):
            current = masked(global_bases)
            bases = normalize_basis_normals(current[..., None, None] + deviations, dim=2).clamp(-1.0, 1.0)
            maps = to_maps(blend(weights, bases))
            rendered = render_flash(maps, lights, fov=fov, convention=convention, extent=extent)[:, 0].clamp(0.0, 1.0)
            loss = (rendered - target).abs().mean()
            if prior:
                loss = loss + prior * (current - predicted).abs().mean()
            global_bases.grad = None
            loss.backward()
            optimizer.step()
            with torch.no_grad():  # keep the bases inside the signed space the network predicts in
                global_bases.clamp_(-1.0, 1.0)
            losses.append(loss.item())
    finally:
        torch.set_num_threads(threads)
    return masked(global_bases.detach()), losses


def _deviations(output: DeepBasisOutput) -> torch.Tensor:
    """The local deviations, or zeros for a network without local bases."""
    if output.deviations is not None:
        return output.deviations
    batch, n = output.global_bases.shape[:2]
    return output.global_bases.new_zeros(batch, n, constants.BASIS_CHANNELS, 1, 1).expand(
        -1, -1, -1, *output.weights.shape[-2:])


def maps_from_bases(output: DeepBasisOutput, global_bases: torch.Tensor) -> torch.Tensor:
    """Full-resolution maps (1, 10, H, W) from (refined) global bases and the predicted weights and deviations."""
    deviations = _deviations(output)
    bases = normalize_basis_normals(global_bases.to(deviations)[..., None, None] + deviations, dim=2)
    return to_maps(blend(output.weights, bases.clamp(-1.0, 1.0)))


# --- the whole capture ----------------------------------------------------------------------------------


def capture(image: str | Path | torch.Tensor, model: DeepBasisNet | str | Path | None = None,
            config: CaptureConfig = CaptureConfig(), progress: bool = False, **overrides) -> CaptureResult:
    """Capture a material from one flash photo.

    Args:
        image: a photo file, or a (3, H, W) linear tensor (then ``config.fov`` or 45 deg applies).
        model: a DeepBasisNet, a checkpoint path, or None for the shipped model.
        config: the capture settings; keyword ``overrides`` replace its fields.
        progress: show progress bars.

    Returns:
        the CaptureResult (material, light, timings, losses, notes).
    """
    from dataclasses import replace

    from .model.checkpoint import load_model

    config = replace(config, **overrides) if overrides else config
    timings = {}
    start = time.perf_counter()
    if not isinstance(model, DeepBasisNet):
        model = load_model(model)
    timings["model"] = time.perf_counter() - start

    start = time.perf_counter()
    document = getattr(model, "checkpoint", {}) or {}
    trained_fov = document.get("fov_deg")
    requested_fov = config.fov if config.fov is not None else trained_fov
    if isinstance(image, torch.Tensor):
        photo = image.float().clamp(0, 1)
        fov, source, notes = ((requested_fov, "argument", []) if requested_fov else (constants.DEFAULT_FOV_DEG, "default", []))
    else:
        photo, fov, source, notes = load_photo(image, requested_fov, config.resolution,
                                               decoding=document.get("photo_decoding", "srgb"), crop=config.crop)
    if trained_fov and abs(fov - trained_fov) > 1.0:
        notes.append(f"this model was trained for a {trained_fov:g} deg field of view, the photo has {fov:.1f} deg")
    timings["photo"] = time.perf_counter() - start

    start = time.perf_counter()
    history = []
    if config.light is None:
        offset, history, output = search_light(model, photo, fov, config)
        timings["search"] = time.perf_counter() - start
        start = time.perf_counter()
    else:
        offset = (float(config.light[0]), float(config.light[1]))
    light = geometry.light_positions(torch.tensor(offset, dtype=torch.float32), fov)
    output = predict(model, photo[None], light[None], fov, config.network_resolution)
    timings["predict"] = time.perf_counter() - start

    losses = []
    maps = output.maps.cpu()
    if config.refine_steps > 0 and output.weights is not None:
        start = time.perf_counter()
        refined, losses = refine_global_bases(output, photo, light, fov, model.config.convention, config.refine_steps,
                                              config.refine_resolution, config.refine_lr, progress,
                                              extent=model.config.plane_extent, refine_normals=config.refine_normals,
                                              prior=config.refine_prior)
        output.global_bases = refined.to(output.global_bases)
        maps = maps_from_bases(output, refined).cpu()
        timings["refine"] = time.perf_counter() - start
    if config.tileable:
        from .tiling import make_tileable

        maps = make_tileable(maps[0], source="photo" if isinstance(image, torch.Tensor) else str(image))[None]
    material = Material.from_tensor(maps[0], convention=model.config.convention,
                                    provenance={"capture": {"offset": list(offset), "fov": fov, "fov_source": source,
                                                            "searched": config.light is None,
                                                            "refine_steps": config.refine_steps,
                                                            "tileable": config.tileable}})
    return CaptureResult(material=material, photo=photo, offset=offset, fov=fov, fov_source=source,
                         searched=config.light is None, search_history=history, refinement_losses=losses,
                         timings=timings, notes=notes, output=output)


class _CallableModule(type(sys.modules[__name__])):
    """This module, callable as its ``capture`` function: DESIGN section 4 promises
    ``from mideepbasis import capture; capture("photo.jpg")``, and once imported the submodule
    ``mideepbasis.capture`` is what that name is bound to."""

    def __call__(self, *args, **kwargs) -> CaptureResult:
        return capture(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
