"""The lighting search: where was the flash of a hand-held shot?

Starting from the candidate below the photo's brightest spot (where a flash beside the camera
lights and mirrors most), each pass predicts the material with the current light (one network
pass) and then, holding that material fixed, renders it under every candidate light within
delta = 16.33 deg (in one kernel of the Mitsuba plugin) and moves to the candidate whose rendering
matches the photo best; it stops when that candidate is within a grid step of the current light.
A final local search on a finer grid around it needs no network pass.

Shapes: photo (3, H, W) linear; offsets (K, 2) [patch half-widths]; maps (1, 10, h, w).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, Protocol

import torch

from .. import constants, geometry
from ..configs import positive_int
from ..resampling import downsample, downsample_maps, gaussian_blur


class Predicted(Protocol):
    """What the search reads of a prediction (a ``DeepBasisOutput`` or a ``capture.Prediction``)."""

    maps: torch.Tensor
    """(B, 10, H, W) the maps at the photo's size."""


#: A prediction: photos (B, 3, H, W) and flash positions (B, 3) to the network's output.
Predictor = Callable[[torch.Tensor, torch.Tensor], Predicted]


@dataclass(frozen=True)
class SearchConfig:
    """How the flash of a hand-held shot is searched for."""

    grid: int = field(default=15, metadata={"parse": positive_int})
    """Candidates per side of the square grid over the offsets within delta. A coarser grid makes
    each pass's move longer, so the passes reach the flash in fewer of them; the fine grid around
    the last candidate then places it. On 300 held-out procedural searches (benchmarks/search_prior.py
    --materials 100 --grids 11 13 15 17 21) 15 against 21 gave mean / median /
    90th percentile error 4.67 / 3.76 / 9.72 against 4.68 / 3.89 / 9.99 deg, with 2.19 instead of
    2.67 network passes and 0.29 instead of 0.39 s a search; 11 and 13 were quicker still, with
    worse medians (4.08, 3.99 deg)."""

    resolution: int = field(default=128, metadata={"parse": positive_int})
    """Resolution of the candidate renders [pixels]."""

    network_resolution: int = field(default=256, metadata={"parse": positive_int})
    """Largest resolution of the search's network passes [pixels]: a larger photo is searched on
    a downsampled copy (the flash position shows at any scale), then predicted in full."""

    passes: int = field(default=6, metadata={"parse": positive_int})
    """Most network passes."""

    settle_steps: float = 1.0
    """The passes stop when the best candidate is within this many grid steps (per axis) of the
    current light, the fine grid then searching around it with the last pass's material; 0: only
    when the light does not move. Each pass is a network pass and a render of every candidate.
    From the centre, 1 had halved the passes but moved error to the typical photo (the passes'
    stopping rule, benchmarks/README.md); from the highlight (``start``) it is better throughout."""

    relaxation: float = 1.0
    """How far a pass moves the light toward the best candidate: 1 to it, 2 twice as far (snapped
    to the nearest candidate). The material is predicted for the current light, so the best
    candidate lies between the current light and the true one; a model whose material follows the
    light makes the passes walk a grid step or so at a time. Tried on held-out procedural materials
    (benchmarks/search_prior.py --relaxations, 120 searches; benchmarks/README.md names the model):
    mean error 4.84 / 4.86 / 4.94 deg at 1 / 1.5 / 2, 2.74 / 2.52 / 2.87 network passes: kept at 1."""

    prior: float = 0.02
    """Weight of the squared offset [patch half-widths^2] added to the objective (mean L1), a pull
    toward the centre where the photo does not decide; 0: none. On held-out procedural materials
    (not the test set) 0.02 lowered the mean angular error from 4.72 to 4.07 deg
    (benchmarks/search_prior.py)."""

    max_offset_deg: float = constants.MAX_OFFSET_DEG
    """Largest hand-held offset searched [deg] (delta)."""

    start: str = field(default="highlight", metadata={"choices": ("centre", "highlight")})
    """Where the passes start: at the candidate nearest the photo's brightest spot
    (``highlight_offset``), or at the centred flash. On 300 held-out procedural searches
    (benchmarks/search_prior.py --materials 100 --starts highlight --settle-steps 0 1; the
    brightest spot alone is 4.88 deg off on average) the highlight with
    ``settle_steps`` 1 gave mean / median / 90th percentile error 3.98 / 3.47 / 7.95 deg in 1.28
    network passes and 0.17 s a search, against 4.67 / 3.76 / 9.72 deg, 2.19 passes and 0.29 s from
    the centre with ``settle_steps`` 0; better in every roughness group."""

    normal_unit: bool = False
    """Whether the search's network passes run the normal unit (``DeepBasisNet``'s
    ``with_normal_unit``). Without it a pass costs less (the bundled photo at 128 px: 65 against
    111 ms) and the candidates are rendered with the bases' normals alone, which found the flash
    better on held-out procedural materials (benchmarks/search_prior.py --normal-unit on off, 120
    searches; benchmarks/README.md names the weights): mean error 4.84 -> 4.37 deg, 2.74 -> 2.59
    passes. On the shared test set (``evaluate --lighting``) it was 0.06 deg worse: 3.03 -> 3.09 deg."""


@dataclass(frozen=True, eq=False)
class SearchResult:
    """What the search found."""

    offset: tuple[float, float]
    """The flash offset (tx, ty) [patch half-widths]."""

    history: list[dict]
    """The passes: offset [patch half-widths] and objective (mean L1) each."""

    last_pass: Callable[[], Predicted] = field(repr=False)
    """Gives the last pass's prediction (``output``)."""

    @functools.cached_property
    def output(self) -> Predicted:
        """The last pass's prediction (its maps at the search's network resolution). A search that
        went round a cycle predicts it again only when this is read: ``capture`` does not read it."""
        return self.last_pass()


def candidate_offsets(fov: float, max_offset_deg: float, grid: int, centre=(0.0, 0.0), span: float | None = None) -> torch.Tensor:
    """A square grid of ``grid`` x ``grid`` offsets around ``centre`` over +-``span`` [patch half-widths]
    (default: the whole reachable range), kept where the offset angle is within ``max_offset_deg``. (K, 2)."""
    limit = geometry.max_offset(fov, max_offset_deg)
    span = limit if span is None else span
    axis = torch.linspace(-span, span, grid)
    offsets = torch.stack(torch.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2) + torch.tensor(centre)
    return offsets[torch.linalg.vector_norm(offsets, dim=-1) <= limit + 1e-6]


def nearest_candidate(candidates: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """The row of ``candidates`` (K, 2) nearest ``point`` (2,), (2,)."""
    return candidates[int(torch.argmin((candidates - point).square().sum(dim=-1)))]


#: Size the photo's brightness is averaged to before its brightest spot is taken [pixels], and
#: the blur over it (a Gaussian's sigma [pixels at that size]): texture smaller than a few
#: sixteenths of the sample does not move the spot.
HIGHLIGHT_GRID = 32
HIGHLIGHT_BLUR = 1.5


def highlight_offset(photo: torch.Tensor) -> torch.Tensor:
    """The plane point (x, y) under the photo's brightest spot [patch half-widths], (2,).

    A flash beside the camera lights the point below it most (the falloff and the cosine peak
    there) and, on a flat sample, mirrors into the camera there too: that point's offset is the
    flash's. The luminance of ``photo`` (3, H, W), linear, is averaged to ``HIGHLIGHT_GRID`` pixels
    a side and blurred, so that the spot is the shading's and not a bright fleck of the texture.
    """
    luminance = (photo * torch.tensor(constants.LUMINANCE_WEIGHTS).view(3, 1, 1)).sum(dim=0)
    small = downsample(luminance[None, None], HIGHLIGHT_GRID)[0, 0]
    blurred = gaussian_blur(small[None, None], HIGHLIGHT_BLUR, padding="replicate",
                            radius=math.ceil(3 * HIGHLIGHT_BLUR))[0, 0]
    height, width = blurred.shape
    row, col = divmod(int(torch.argmax(blurred)), width)
    return torch.tensor([(2 * col + 1) / width - 1, 1 - (2 * row + 1) / height])


def light_objective(maps: torch.Tensor, photo: torch.Tensor, offsets: torch.Tensor, fov: float, convention: str,
                    extent: float = 1.0) -> torch.Tensor:
    """Mean L1 between the photo and the clipped rendering of ``maps`` under each candidate, (K,):
    ``render.flash_l1``, whose plugin kernel reduces each candidate's image as it renders it.

    Args:
        maps: (1, 10, h, w) the material held fixed; photo: (1, 3, h, w); offsets: (K, 2).
    """
    from ..render import flash_l1

    return flash_l1(maps, photo, geometry.light_positions(offsets, fov), fov=fov, convention=convention, extent=extent)


def search_light(predict: Predictor, photo: torch.Tensor, fov: float, convention: str, extent: float = 1.0,
                 config: SearchConfig = SearchConfig()) -> SearchResult:
    """Find the flash offset of ``photo`` (3, H, W), predicting with ``predict`` (photos, lights) and
    rendering under the shading ``convention`` over a sample of half-width ``extent``."""
    if photo.shape[-1] > config.network_resolution:
        photo = downsample(photo[None], config.network_resolution)[0]
    small_photo = downsample(photo[None], config.resolution)
    candidates = candidate_offsets(fov, config.max_offset_deg, config.grid)
    current = torch.zeros(2)
    if config.start == "highlight":
        current = nearest_candidate(candidates, highlight_offset(photo))
    history = []
    output = None

    def objective(maps: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        errors = light_objective(maps, small_photo, offsets, fov, convention, extent=extent)
        return errors + config.prior * offsets.square().sum(dim=-1)

    step = 2 * geometry.max_offset(fov, config.max_offset_deg) / max(1, config.grid - 1)
    passes = []  # (light, material at the objective's resolution) of each pass; the latest prediction alone
    last_pass = None  # where a cycle ends the passes on another pass than the latest: its prediction, when asked
    for index in range(config.passes):
        output = predict(photo[None], geometry.light_positions(current[None], fov))
        small_maps = downsample_maps(output.maps.cpu(), config.resolution)
        errors = objective(small_maps, candidates)
        best = candidates[int(torch.argmin(errors))]
        history.append({"pass": index + 1, "offset": current.tolist(), "best_candidate": best.tolist(),
                        "objective": float(errors.min())})
        passes.append((current, small_maps))
        if float((best - current).abs().max()) <= config.settle_steps * step + 1e-6:
            current = best
            break
        seen = next((j for j, (light, _) in enumerate(passes) if torch.allclose(best, light, atol=1e-6)), None)
        if seen is not None:
            # The passes are deterministic: from pass ``seen`` on they go round a cycle of lights (of
            # two, nearly always) until the last pass. End where that last pass would have ended.
            period = len(passes) - seen
            last = seen + (config.passes - 1 - seen) % period
            light, small_maps = passes[last]
            if last != len(passes) - 1:  # its prediction again if asked for, rather than every pass's held (60 MB at 256 px)
                last_pass = functools.partial(predict, photo[None], geometry.light_positions(light[None], fov))
            current = passes[seen + (last + 1 - seen) % period][0]
            break
        # Toward the best candidate (relaxation 1: to it), snapped to the grid.
        target = current + config.relaxation * (best - current)
        current = nearest_candidate(candidates, target)
    # A finer grid around the last candidate, with the material of the last pass.
    fine = candidate_offsets(fov, config.max_offset_deg, 9, centre=tuple(current.tolist()), span=step)
    errors = objective(small_maps, fine)
    current = fine[int(torch.argmin(errors))]
    history.append({"pass": "fine", "offset": current.tolist(), "objective": float(errors.min())})
    return SearchResult(offset=(float(current[0]), float(current[1])), history=history,
                        last_pass=last_pass or (lambda: output))
