"""The capture engine: a ``Capturer`` holds a model and a ``CaptureConfig`` and runs the stages.

    capturer = Capturer()                      # the shipped model, default settings
    photo = capturer.load("flash_photo.jpg")   # a Photo: linear pixels, field of view, notes
    found = capturer.search(photo)             # the flash offset (SearchResult)
    prediction = capturer.predict(photo, found.offset)   # a Prediction: .maps at the photo's size
    refined, losses = capturer.refine(prediction, photo, found.offset)
    result = capturer.capture("flash_photo.jpg")   # all of it: a CaptureResult

Evaluation and the benchmarks call these stages; every default lives once, in its config
(``CaptureConfig``, ``SearchConfig``, ``RefineConfig``).
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from .. import constants, geometry
from ..configs import non_negative, unit_share
from ..material import Material
from ..model.inputs import encode_inputs
from ..model.network import DeepBasisNet, DeepBasisOutput
from ..model.symmetry import check_symmetries, parse_symmetries
from .detail import (FINE_RELIEF_STRENGTH, FINE_RELIEF_SYMMETRIES, fine_relief, matte_share, photo_relief_gain,
                     relief_test_reads)
from .photo import load_photo, parse_resolution
from .refine import RefineConfig, refine_global_bases
from .search import SearchConfig, SearchResult, search_light


@dataclass(frozen=True)
class CaptureConfig:
    """How a photo becomes a material."""

    fov: float | None = None
    """Field of view of the photo's width [deg]; None: from EXIF, else the model's, else 45."""

    light: tuple[float, float] | None = field(default=None, metadata={"metavar": "TX,TY"})
    """Known flash offset (tx, ty) [patch half-widths]; None: search for it."""

    resolution: int | str = field(default=constants.DEFAULT_RESOLUTION,
                                  metadata={"parse": parse_resolution, "metavar": "N|native"})
    """Working resolution [pixels], or ``native`` (the photo's own, up to 4096)."""

    network_resolution: int | None = None
    """Largest resolution the network runs at [pixels]; a larger photo is predicted on a
    downsampled copy and the weights and deviations upsampled. None: the resolution the model was
    trained at (from its checkpoint); 0: no limit."""

    symmetries: int = field(default=constants.DEFAULT_SYMMETRIES,
                            metadata={"parse": parse_symmetries, "metavar": "{1,2,4,8}"})
    """The network's answer averaged over this many turns and mirrorings of the photo (1, 2, 4 or
    8; ``DeepBasisNet.symmetrised``): 8 costs a pass of eight photos instead of one. The lighting
    search's passes take one."""

    search: SearchConfig = SearchConfig()
    """The lighting search (when ``light`` is None)."""

    refine: RefineConfig = RefineConfig()
    """The refinement of the global bases (``refine.steps`` 0: none)."""

    detail: bool = True
    """Above the network's resolution, give the maps the photo's finer detail where their own
    variation follows the photo's (``capturing.detail``); False: the network's answer upsampled."""

    relief_test: bool = True
    """Scale the detail step's finer relief by how much of the photo's fine contrast is shading
    (``detail.photo_relief_gain``, from 4 times the network's resolution on): an albedo's texture
    (veined marble, grained wood) then adds no relief, the diffuse takes the contrast read as
    albedo as albedo, and the network's normals lose the relief they made up from it
    (``detail.add_detail``'s ``albedo_share``). False: the normals and the diffuse keep the gains
    fitted against the network's maps, whatever the photo."""

    fine_relief: bool = True
    """From 4 times the network's resolution on, read the normals' detail above it with the
    network's normal unit run on the photo itself and its half turn (``detail.fine_relief``, at up
    to 1024 px; the mean of the two readings, weighted by where they agree, by each pixel's
    diffuse share and by the relief test's gain but where it reads steep relief, which that test
    reads as albedo) instead of the photo's contrast times the normals' gains, which a metal keeps by
    its metallic share (it has no diffuse shading to read). The normal and re-rendering errors of
    held-out procedural relief, phone-like scenes and card-blue at 1024 px are lower than with the
    gains alone, and flat textured materials that the relief test reads as partly relief get less
    made-up relief than the upsampled answer has (benchmarks/README.md, detail: the fine relief).
    Each reading takes about 3 s on two cores at 1024 px and above; ``symmetries`` 1 reads the
    photo alone. False: the photo's contrast times the normals' gains."""

    fine_relief_strength: float = field(default=FINE_RELIEF_STRENGTH, metadata={"parse": non_negative})
    """With ``fine_relief``, the factor of the relief it reads (``detail.fine_relief``): 1, the
    default (``detail.FINE_RELIEF_STRENGTH``), the normal unit's own reading as its mirror images
    agree on it. Higher gives the normals more of the fine energy the truth has, and flat textured
    materials and card-blue's foil more made-up relief (benchmarks/README.md, detail: the fine
    relief's strength). A value other than the default without ``fine_relief`` is refused: it would
    change nothing."""

    relief_reader: str | None = field(default=None, metadata={"metavar": "FILE"})
    """With ``fine_relief``, a relief reader's weights (``model.relief_reader``, trained by
    ``scripts/train_relief_reader.py``): a network of its own, trained for the relief above the
    network's band, reads the normals' detail in place of the normal unit (weighted and scaled as
    the unit's reading is). None: the normal unit. The readers trained so far read about half of
    what the unit reads (benchmarks/README.md, detail: the relief reader)."""

    denoise_detail: bool = False
    """Take the photo's noise out of the detail step's fine contrast first (``detail.denoise_contrast``,
    the noise measured from the photo itself by its level, ``detail.photo_noise``): a noisy photo's
    noise at 1024 px and above otherwise goes into the diffuse as speckle. On phone-like procedural
    scenes at 1024 px the diffuse error falls 0.0788 -> 0.0747; off by default because a texture as
    fine as the pixels reads as noise too, and a noise-free photo's finest texture goes with it
    (benchmarks/README.md, detail: the photo's noise)."""

    colour_test: bool = False
    """With ``fine_relief`` off, from 4 times the network's resolution on, give the normals' gains
    the photo's fine luminance contrast less the part a change of hue explains
    (``detail.shading_contrast``):
    shading moves a pixel's chroma only along its own colour's, so the edges of a printed or inlaid
    colour texture are the albedo's, not relief. False: the whole luminance contrast. Off by
    default: card-blue re-renders a little better with it from its photo 00 and the same from each
    photo in turn, but where relief and colour change together (a tile's recessed, coloured grout)
    it takes the shading out with the hue, and procedural relief and phone-like scenes re-render a
    little worse (benchmarks/README.md, detail: the colour test)."""

    keep_lobe_peak: bool = True
    """From 4 times the network's resolution on, where the detail step gives the normals finer
    relief, narrow the refined roughness so that each network pixel's specular peak, averaged over
    it, stays as the refinement fitted it without that relief (``detail.lobe_peak_factors``): fine
    normals spread the lobe, and the highlights would dim under other lights. The network's own
    roughness, unrefined, is left as it is: it was trained to be the surface's, not to make up for
    relief the normals lack. At capture's default 256 px (one octave of detail) it is not applied:
    there phone-like procedural scenes re-rendered a little worse with it (benchmarks/README.md,
    detail: the lobe's peak)."""

    grey_specular: bool = False
    """Keep the specular's colour only in proportion to each pixel's metallic share (``Material.to_pbr``'s
    split, as the exports make it) and make it grey of the same luminance otherwise: a dielectric's
    F0 has no colour. A photo's colour otherwise leaks into the specular map (a green specular on
    real photos)."""

    normal_strength: float = constants.NORMAL_STRENGTH
    """The factor of the normals' slopes (``geometry.scaled_slopes``): 1 the network's relief, 0
    flat. The refinement renders the normals at this strength; it scales the detail step's finer
    relief too, whose gains follow the network's relief."""

    specular_floor: float = constants.SPECULAR_FLOOR
    """Lowest specular F0 of the captured maps [linear reflectance]; 0: as the network and the
    refinement left it. Water's 0.02 is below every real surface's; under it, a refinement that
    lowers a dark specular leaves it tinted by the one channel the others were clipped below.
    The refinement itself fits without it."""

    lobe_variation: float = field(default=constants.LOBE_VARIATION, metadata={"parse": unit_share})
    """The share of the network's per-pixel variation of each basis's roughness and specular that
    the capture keeps (``DeepBasisOutput.with_shrunk_deviations``): 1 all of it, 0 one roughness
    and specular per basis. One flash photo shows the specular lobe only near its highlight, and
    the local unit's lobe deviations follow where the highlight fell more than the surface."""

    tileable: bool = False
    """Make the captured maps wrap around their edges without a seam (``tiling.make_tileable``)."""

    crop: tuple[int, int, int, int] | None = field(default=None, metadata={"metavar": "X,Y,W,H"})
    """Part of the photo that holds the sample: (x, y, width, height) [pixels of the photo as
    shown, EXIF orientation applied]; its centre square is used. None: the whole photo."""

    def __post_init__(self):
        check_symmetries(self.symmetries)  # now, not at the first prediction
        # The command line's checks, for callers of the Python API.
        for name, check in (("lobe_variation", unit_share), ("fine_relief_strength", non_negative)):
            try:
                check(getattr(self, name))
            except ValueError as error:
                raise ValueError(f"{name} {error}") from None
        if self.fine_relief_strength != FINE_RELIEF_STRENGTH and not self.fine_relief:
            # Else the strength would be dropped without a word.
            raise ValueError(f"fine_relief_strength {self.fine_relief_strength:g} applies only with fine_relief "
                             "(not with --no-fine-relief)")
        if self.colour_test and self.fine_relief:
            # The test chooses the contrast the normals' gains multiply, which the fine relief replaces.
            raise ValueError("colour_test applies only without fine_relief (with --no-fine-relief)")
        if self.relief_reader is not None and not self.fine_relief:
            raise ValueError(f"relief_reader {self.relief_reader} applies only with fine_relief "
                             "(not with --no-fine-relief)")

    @property
    def fine_relief_symmetries(self) -> int:
        """How many mirror images ``fine_relief`` reads (``detail.fine_relief``'s ``symmetries``):
        no more than ``symmetries``, at most ``detail.FINE_RELIEF_SYMMETRIES``."""
        return min(self.symmetries, FINE_RELIEF_SYMMETRIES)


@dataclass(frozen=True)
class Photo:
    """A photo ready for capture."""

    pixels: torch.Tensor
    """(3, R, R) linear, in [0, 1]."""

    fov: float
    """Field of view across it [deg]."""

    fov_source: str
    """Where the field of view came from: ``exif``, ``argument`` or ``default``."""

    notes: list[str] = field(default_factory=list)
    """What the user should know (a crop, the field of view's source, ...)."""

    default_reading: torch.Tensor | None = None
    """(3, r, r) linear: the photo file as a capture at the default working resolution
    (``constants.DEFAULT_RESOLUTION``) reads it, where the working resolution is larger. The
    search, the network (where it runs at that size or below) and the refinement read this one,
    so that their answer is the default capture's at every working resolution and only the detail
    above the network's comes from ``pixels``: a large file is read with its 8-bit codes averaged
    (``load_photo``), and the network given linear means of a noisy photo instead made the
    diffuse worse (benchmarks/README.md, detail: the answer below the network's resolution).
    None: they read ``pixels``."""

    @property
    def coarse_pixels(self) -> torch.Tensor:
        """(3, r, r) the photo the search, the network and the refinement read."""
        return self.pixels if self.default_reading is None else self.default_reading


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
    """The network's prediction (weights, bases, ...) at the network's resolution, refined global
    bases included (``Prediction.output``)."""

    @property
    def offset_angle_deg(self) -> float:
        """Angle of the flash offset seen from the sample centre [deg]."""
        return float(geometry.offset_angle_deg(torch.tensor(self.offset), self.fov))

    @property
    def light_position(self) -> torch.Tensor:
        """(3,) the flash position [patch half-widths]."""
        return flash_position(self.offset, self.fov)


# --- prediction -------------------------------------------------------------------------------------


def network_resolution_limit(model: DeepBasisNet, requested: int | None = None) -> int | None:
    """The largest resolution [pixels] ``predict`` runs ``model`` at: ``requested``, or when it is
    None the model's training resolution; None (or 0) means no limit."""
    return model.info.training_size if requested is None else requested or None


@dataclass(frozen=True, eq=False)
class Prediction:
    """The network's prediction for a photo: its output at the network's resolution, shown at the
    photo's size. Nothing per-basis is held at the photo's size: ``maps`` are blended one basis
    at a time (``DeepBasisOutput.maps_at``) when first asked for."""

    output: DeepBasisOutput
    """What the network gave, at the resolution it ran at."""

    size: tuple[int, int]
    """The photo's (height, width) [pixels]."""

    detail_from: torch.Tensor | None = None
    """(B, 3, H, W) the photo whose detail above the network's resolution the maps are given
    (``detail.add_detail``); None: the network's answer upsampled."""

    grey_specular: bool = False
    """Make the maps' specular grey but for each pixel's metallic share (``CaptureConfig.grey_specular``)."""

    specular_floor: float = 0.0
    """Lowest specular of the maps [linear reflectance] (``CaptureConfig.specular_floor``)."""

    normal_strength: float = 1.0
    """The factor of the normals' slopes (``CaptureConfig.normal_strength``)."""

    normal_detail: float = 1.0
    """The share of the normals' detail above the network's resolution kept
    (``detail.relief_gain``): 0 where the photo's fine contrast reads as albedo alone. The rest is
    the share the diffuse takes as albedo (``detail.add_detail``'s ``albedo_share``)."""

    fine_slope: torch.Tensor | None = None
    """(B, 2, H', W') the normals' detail read by the normal unit (``detail.fine_relief``,
    ``CaptureConfig.fine_relief``), in place of the photo's contrast times their gains but for
    the maps' metallic share (``detail.add_detail``); None: the photo's contrast times their gains."""

    denoise_detail: bool = False
    """Whether the photo's fine contrast is denoised before it is added (``CaptureConfig.denoise_detail``)."""

    colour_test: bool = False
    """Whether the normals' detail leaves out the contrast a change of hue explains
    (``CaptureConfig.colour_test``, where the relief test reads and the fine relief is not read)."""

    keep_lobe_peak: bool = False
    """Whether the roughness is narrowed under the normals' detail (``CaptureConfig.keep_lobe_peak``;
    set by ``Capturer.refine``: the refined lobe is)."""

    relief_test_read: bool = False
    """Whether the relief test read the photo (``detail.relief_test_reads``; ``normal_detail`` is
    1 where it did not)."""

    @functools.cached_property
    def maps(self) -> torch.Tensor:
        """(B, 10, H, W) the maps at the photo's size."""
        maps = self.output.maps_at(*self.size)
        if self.detail_from is not None and maps.shape[-2] > self.output.maps.shape[-2]:
            from .detail import add_detail

            maps = add_detail(maps.clone() if maps is self.output.maps else maps, self.detail_from, self.output.maps,
                              normal_gain=self.normal_detail, albedo_share=1.0 - self.normal_detail,
                              fine_slope=self.fine_slope, denoise=self.denoise_detail,
                              keep_lobe_peak=self.keep_lobe_peak, slope_scale=self.normal_strength,
                              colour_test=self.colour_test)
        finishing = self.grey_specular or self.normal_strength != 1.0 or self.specular_floor > 0.0
        if finishing and maps is self.output.maps:
            maps = maps.clone()  # the output's own maps stay as the network gave them
        if self.grey_specular:
            from ..material import grey_dielectric_specular

            for index in range(maps.shape[0]):
                maps[index, constants.SPECULAR] = grey_dielectric_specular(
                    maps[index, constants.DIFFUSE], maps[index, constants.SPECULAR], constants.EXPORT_METAL_F0)
        if self.normal_strength != 1.0:
            maps[:, constants.NORMAL] = geometry.scaled_slopes(maps[:, constants.NORMAL], self.normal_strength, dim=1)
        if self.specular_floor > 0.0:
            maps[:, constants.SPECULAR] = maps[:, constants.SPECULAR].clamp(min=self.specular_floor)
        return maps

    def compose(self, global_bases: torch.Tensor) -> Prediction:
        """This prediction with other (say, refined) global bases."""
        return replace(self, output=self.output.compose(global_bases))


def predict_small(model: DeepBasisNet, photos: torch.Tensor, lights: torch.Tensor,
                  fov: float = constants.DEFAULT_FOV_DEG, network_resolution: int | None = None,
                  symmetries: int = 1, with_normal_unit: bool = True) -> Prediction:
    """``predict``, its output left at the network's resolution (a ``Prediction``). ``symmetries``
    is 1 here (a single pass, as the search's), not ``CaptureConfig``'s default;
    ``with_normal_unit`` False leaves the normal unit out (``DeepBasisNet.forward``)."""
    limit = network_resolution_limit(model, network_resolution)
    height, width = photos.shape[-2:]
    if limit and max(height, width) > limit:
        scale = limit / max(height, width)
        photos = F.interpolate(photos, size=(max(1, round(height * scale)), max(1, round(width * scale))), mode="area")
    return Prediction(_network_pass(model, photos, lights, fov, symmetries, with_normal_unit), (height, width))


def predict(model: DeepBasisNet, photos: torch.Tensor, lights: torch.Tensor,
            fov: float = constants.DEFAULT_FOV_DEG, network_resolution: int | None = None,
            symmetries: int = 1) -> DeepBasisOutput:
    """The material seen in ``photos`` (B, 3, H, W) taken with flashes at ``lights`` (B, 3).

    The network runs at most at ``network_resolution`` [pixels] (None: the resolution the model was
    trained at, when its checkpoint says; 0: no limit). A larger photo is predicted on an
    area-downsampled copy, and its blending weights and local deviations are upsampled to the
    photo's size, so the maps, the refinement and everything after work at full resolution. A
    fully convolutional network run at a larger scale than it was trained at sees every feature
    bigger than in training; on the shared test set the shipped model (trained at 128 px) gave
    lower errors at 128 px upsampled than run at 256 px (benchmarks/model_quality.py).
    ``symmetries``: the answer averaged over that many turns and mirrorings of the photo
    (``DeepBasisNet.symmetrised``); 1 here, where ``CaptureConfig`` (and so ``Capturer.predict``)
    defaults to ``constants.DEFAULT_SYMMETRIES``.
    """
    prediction = predict_small(model, photos, lights, fov, network_resolution, symmetries)
    output = prediction.output
    return output if tuple(output.maps.shape[-2:]) == prediction.size else output.upsample(*prediction.size)


def _network_pass(model: DeepBasisNet, photos: torch.Tensor, lights: torch.Tensor, fov: float,
                  symmetries: int = 1, with_normal_unit: bool = True) -> DeepBasisOutput:
    """One network pass at the photos' own size; a size that is not a multiple of the network's
    stride is padded by reflection and the prediction cropped back (the padding, on the bottom
    and right, then turns with the photo: the symmetries are not exact there). A non-square photo
    is averaged over the 4 mirrorings where 8 symmetries are asked for."""
    device = next(model.parameters()).device
    height, width = photos.shape[-2:]
    stride = model.config.stride
    pad_h, pad_w = (-height) % stride, (-width) % stride
    inputs = encode_inputs(photos, lights, fov, model.config.convention, model.config.plane_extent,
                           model.config.extra_inputs)
    if symmetries == 8 and height != width:  # the photo's own shape: its padding may make it square
        symmetries = 4
    if pad_h or pad_w:
        inputs = F.pad(inputs, (0, pad_w, 0, pad_h), mode="reflect")
    # A single pass names no options unless it leaves out a normal unit the model has: any model
    # with DeepBasisNet's call serves (tests' oracles).
    options = {"symmetries": symmetries} if symmetries > 1 else {}
    if not with_normal_unit and hasattr(model, "normal_unit"):
        options["with_normal_unit"] = False
    with torch.no_grad():
        output = model(inputs.to(device), lights.to(device), fov=fov, **options)
    return output.crop(height, width) if pad_h or pad_w else output


# --- the engine -------------------------------------------------------------------------------------


def flash_position(offset: tuple[float, float] | torch.Tensor, fov: float) -> torch.Tensor:
    """(3,) the flash position of an offset (tx, ty) [patch half-widths]: float32 from numbers, a
    tensor's own precision from a tensor (the evaluation's offsets are float64)."""
    offset = offset if isinstance(offset, torch.Tensor) else torch.tensor(offset, dtype=torch.float32)
    return geometry.light_positions(offset, fov)


@functools.cache
def loaded_reader(path: str):
    """The relief reader stored at ``path`` (``model.relief_reader.load_reader``), loaded once."""
    from ..model.relief_reader import load_reader

    return load_reader(path)[0]


class Capturer:
    """A model and the settings of its captures; its stages are what ``capture`` runs.

    Args:
        model: a DeepBasisNet, a checkpoint path, or None for the shipped model (loaded once).
        config: the capture settings.
    """

    def __init__(self, model: DeepBasisNet | str | Path | None = None, config: CaptureConfig = CaptureConfig()):
        if not isinstance(model, DeepBasisNet):
            from ..model.checkpoint import load_model

            model = load_model(model)
        self.model, self.config = model, config

    def with_config(self, **overrides) -> Capturer:
        """This model with some ``CaptureConfig`` fields replaced (no reload)."""
        return Capturer(self.model, replace(self.config, **overrides))

    @property
    def convention(self) -> str:
        return self.model.info.convention

    @property
    def requested_fov(self) -> float | None:
        """The field of view asked for [deg]: the config's, else the one the model was trained for."""
        return self.config.fov if self.config.fov is not None else self.model.info.fov_deg

    def load(self, path: str | Path) -> Photo:
        """Read a photo file (``capture.photo.load_photo``) with the model's photo decoding and the
        field of view of the config, else of the photo's EXIF, else of the model, else 45 deg."""
        pixels, fov, source, notes = load_photo(path, self.config.fov, self.config.resolution,
                                                decoding=self.model.info.photo_decoding, crop=self.config.crop)
        if source == "default" and self.model.info.fov_deg:
            fov, source = self.model.info.fov_deg, "model"
            notes = [note for note in notes if not note.startswith("no EXIF focal length")]
        default_reading = None
        if pixels.shape[-1] > constants.DEFAULT_RESOLUTION:
            with warnings.catch_warnings():  # the first reading warned of a dark or clipped photo
                warnings.simplefilter("ignore")
                default_reading = load_photo(path, self.config.fov, constants.DEFAULT_RESOLUTION,
                                             decoding=self.model.info.photo_decoding, crop=self.config.crop)[0]
        return Photo(pixels, fov, source, self._fov_notes(fov, notes), default_reading)

    def photo_from_tensor(self, pixels: torch.Tensor) -> Photo:
        """A (3, H, W) linear tensor as a photo (the config's field of view, else the model's, else 45 deg)."""
        requested = self.requested_fov
        fov, source = (requested, "argument") if requested else (constants.DEFAULT_FOV_DEG, "default")
        return Photo(pixels.float().clamp(0, 1), fov, source, self._fov_notes(fov, []))

    def _fov_notes(self, fov: float, notes: list[str]) -> list[str]:
        trained = self.model.info.fov_deg
        if trained and abs(fov - trained) > 1.0:
            notes = notes + [f"this model was trained for a {trained:g} deg field of view, the photo has {fov:.1f} deg"]
        return notes

    def predict(self, photo: Photo, offset: tuple[float, float] | torch.Tensor) -> Prediction:
        """The network's prediction for the photo taken with the flash at ``offset`` [patch half-widths]."""
        light = flash_position(offset, photo.fov)
        limit = network_resolution_limit(self.model, self.config.network_resolution)
        # The default reading serves a network that runs at its size or below; one without a
        # limit reads the working photo itself.
        seen = photo.coarse_pixels if limit and limit <= photo.coarse_pixels.shape[-1] else photo.pixels
        prediction = predict_small(self.model, seen[None], light[None], photo.fov, self.config.network_resolution,
                                   self.config.symmetries)
        prediction = replace(prediction, size=tuple(photo.pixels.shape[-2:]))
        output = prediction.output
        if self.config.lobe_variation < 1.0 and self.config.refine.unclamped_moves:
            # The shrink cuts the lobe's deviations to the signed space. An unclamped refinement (the
            # default) cuts every reflectance channel's, the maps the same: so are they all cut here.
            # A clamped one keeps the diffuse's pixels the local unit pushed past a bound.
            output = output.unsaturated()
        output = output.with_shrunk_deviations(constants.LOBE, self.config.lobe_variation)
        detailed = self.config.detail and prediction.size[0] > output.maps.shape[-2]
        low_size = tuple(output.maps.shape[-2:])
        wide = detailed and relief_test_reads(tuple(photo.pixels.shape[-2:]), low_size)
        tested = wide and self.config.relief_test
        fine_wanted = wide and self.config.fine_relief and hasattr(self.model, "normal_unit")
        extent = self.model.config.plane_extent
        matte = (matte_share(output.maps[:1].detach().cpu(), light.cpu(), photo.fov, self.convention, extent)
                 if tested or fine_wanted else None)
        normal_detail = (photo_relief_gain(photo.pixels, light, output.maps, photo.fov, self.convention, extent,
                                           matte=matte) if tested else 1.0)
        # The unit's slope is scaled by the relief test's gain: where that is 0 it would add nothing.
        fine = None
        if fine_wanted and normal_detail > 0.0:
            reader = loaded_reader(self.config.relief_reader) if self.config.relief_reader else None
            fine = fine_relief(self.model, photo.pixels[None], light, photo.fov, low_size, matte=matte,
                               strength=self.config.fine_relief_strength, reader=reader, convention=self.convention,
                               extent=extent, symmetries=self.config.fine_relief_symmetries, gain=normal_detail)
        return replace(prediction, output=output, detail_from=photo.pixels[None] if detailed else None,
                       fine_slope=fine, denoise_detail=self.config.denoise_detail,
                       colour_test=wide and self.config.colour_test,
                       grey_specular=self.config.grey_specular, specular_floor=self.config.specular_floor,
                       normal_strength=self.config.normal_strength, relief_test_read=tested,
                       normal_detail=normal_detail)

    def search(self, photo: Photo) -> SearchResult:
        """The flash offset of a hand-held photo (``capture.search.search_light``)."""
        def predictor(photos: torch.Tensor, lights: torch.Tensor) -> Prediction:
            # The search reads the maps alone: ``Prediction.maps`` builds them basis by basis, the
            # upsampled output's to the bit in half its time (25 against 60 ms at 256 px).
            return predict_small(self.model, photos, lights, photo.fov, self.config.network_resolution,
                                 with_normal_unit=self.config.search.normal_unit)

        return search_light(predictor, photo.coarse_pixels, photo.fov, self.convention, self.model.config.plane_extent,
                            self.config.search)

    def refine(self, prediction: Prediction, photo: Photo, offset: tuple[float, float] | torch.Tensor,
               progress: bool = False) -> tuple[Prediction, list[float]]:
        """The prediction with its global bases refined against the photo, and the loss at every step;
        the prediction as it is when there is nothing to refine (no steps, or no bases)."""
        if self.config.refine.steps <= 0 or prediction.output.weights is None:
            return prediction, []
        light = flash_position(offset, photo.fov)
        if self.config.refine.unclamped_moves:
            prediction = replace(prediction, output=prediction.output.unsaturated())
        refined, losses = refine_global_bases(prediction.output, photo.coarse_pixels, light, photo.fov, self.convention,
                                              self.model.config.plane_extent, self.config.refine, progress,
                                              size=prediction.size, normal_strength=prediction.normal_strength)
        # The refined lobe was fitted without the normals' detail: it is narrowed under it, where the
        # detail holds two octaves above the network's resolution or more.
        low_size = tuple(prediction.output.maps.shape[-2:])
        keep = self.config.keep_lobe_peak and relief_test_reads(prediction.size, low_size)
        return replace(prediction.compose(refined), keep_lobe_peak=keep), losses

    def capture(self, image: str | Path | torch.Tensor, progress: bool = False) -> CaptureResult:
        """Capture a material from one flash photo: a file, or a (3, H, W) linear tensor."""
        config, timings = self.config, {}
        start = time.perf_counter()
        photo = self.photo_from_tensor(image) if isinstance(image, torch.Tensor) else self.load(image)
        timings["photo"] = time.perf_counter() - start

        start = time.perf_counter()
        history = []
        if config.light is None:
            found = self.search(photo)
            offset, history = found.offset, found.history
            timings["search"] = time.perf_counter() - start
            start = time.perf_counter()
        else:
            offset = (float(config.light[0]), float(config.light[1]))
        prediction = self.predict(photo, offset)
        timings["predict"] = time.perf_counter() - start

        start = time.perf_counter()
        prediction, losses = self.refine(prediction, photo, offset, progress)
        if losses:
            timings["refine"] = time.perf_counter() - start
        start = time.perf_counter()
        maps = prediction.maps.cpu()
        timings["blend"] = time.perf_counter() - start
        if config.tileable:
            from ..tiling import make_tileable

            # In place: the maps are the prediction's, not used again (0.7 GB at 4096 px).
            maps = make_tileable(maps[0], source="photo" if isinstance(image, torch.Tensor) else str(image),
                                 in_place=True)[None]
        material = Material.from_tensor(maps[0], convention=self.convention,
                                        provenance={"capture": {"offset": list(offset), "fov": photo.fov,
                                                                "fov_source": photo.fov_source,
                                                                "searched": config.light is None,
                                                                "refine_steps": config.refine.steps,
                                                                "tileable": config.tileable,
                                                                "network_size": list(prediction.output.maps.shape[-2:]),
                                                                "detail_added": prediction.detail_from is not None,
                                                                "relief_test_read": prediction.relief_test_read,
                                                                "fine_relief": prediction.fine_slope is not None,
                                                                "fine_relief_strength": config.fine_relief_strength,
                                                                "fine_relief_symmetries": (
                                                                    config.fine_relief_symmetries
                                                                    if prediction.fine_slope is not None else None),
                                                                "relief_reader": (Path(config.relief_reader).name
                                                                                  if prediction.fine_slope is not None
                                                                                  and config.relief_reader else None),
                                                                "detail_denoised": (prediction.detail_from is not None
                                                                                    and prediction.denoise_detail),
                                                                "lobe_peak_kept": (prediction.detail_from is not None
                                                                                   and prediction.keep_lobe_peak),
                                                                "colour_tested": (prediction.detail_from is not None
                                                                                  and prediction.colour_test),
                                                                "normal_detail": prediction.normal_detail}})
        return CaptureResult(material=material, photo=photo.pixels, offset=offset, fov=photo.fov,
                             fov_source=photo.fov_source, searched=config.light is None, search_history=history,
                             refinement_losses=losses, timings=timings, notes=photo.notes, output=prediction.output)


def capture(image: str | Path | torch.Tensor, model: DeepBasisNet | str | Path | None = None,
            config: CaptureConfig = CaptureConfig(), progress: bool = False, **overrides) -> CaptureResult:
    """Capture a material from one flash photo.

    Args:
        image: a photo file, or a (3, H, W) linear tensor (then ``config.fov`` or 45 deg applies).
        model: a DeepBasisNet, a checkpoint path, or None for the shipped model.
        config: the capture settings; keyword ``overrides`` replace its fields
            (``refine=RefineConfig(steps=0)``, ``light=(0.1, 0.0)``, ...).
        progress: show progress bars.

    Returns:
        the CaptureResult (material, light, timings, losses, notes).
    """
    config = replace(config, **overrides) if overrides else config
    start = time.perf_counter()
    capturer = Capturer(model, config)
    loaded = time.perf_counter() - start
    result = capturer.capture(image, progress)
    result.timings = {"model": loaded, **result.timings}
    return result
