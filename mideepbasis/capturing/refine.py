"""Refinement of the global bases by differentiable rendering.

Only the N global bases move: Adam on the L1 difference between the photo and the rendering of the
blended material (rendered through the plugin); the weights and local deviations stay fixed. It
runs on a downsampled copy: the global bases are a few numbers, and the photo's large-scale
appearance determines them. With the Mitsuba backend the loop runs on the drjit side, each step
one frozen drjit function (``render.fit``: 0.3 s for 125 steps where the torch loop,
crossing the bridge at every step, took 0.8 - 0.9 s; with the normals kept, as by default, the
steps blend and differentiate the other seven channels alone: 0.44 -> 0.28 s on two AVX2 cores);
with the torch backend, in torch (``_fit_torch``, also the reference of the drjit loop).

Shapes: photo (3, H, W) linear; light (3,) [patch half-widths]; global bases (1, N, 10) signed space.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from .. import constants
from ..configs import positive_int
from ..geometry import scaled_slopes
from ..imageio import linear_to_srgb
from ..model.network import DeepBasisOutput, blend, compose_bases, to_maps
from ..resampling import downsample


#: The refinement's learning-rate schedules (``RefineConfig.lr_schedule``, ``step_rates``).
LR_SCHEDULES = ("cosine", "constant")


@dataclass(frozen=True)
class RefineConfig:
    """How the global bases are refined."""

    steps: int = 250
    """Adam steps; 0 turns refinement off. (The paper: 500 at one rate; with the normals kept, 125 at
    one rate did as well here, and 250 along the cosine move the bases as far: benchmarks/refinement.py.)"""

    resolution: int = field(default=64, metadata={"parse": positive_int})
    """Resolution of the refinement's renders [pixels]."""

    lr: float = 0.01
    """Adam's learning rate at the first step [signed-space units per step]."""

    lr_schedule: str = field(default="cosine", metadata={"choices": LR_SCHEDULES})
    """How the rate changes over the steps (``step_rates``): ``cosine`` lowers it to 0 along half a
    cosine so that the bases settle, ``constant`` keeps it (its last steps still move the bases by
    about the rate: benchmarks/README.md, refinement)."""

    normals: bool = False
    """Whether the refinement may turn the global bases' normals, as the paper's does. Off by
    default: fitting the one flash view by tilting the normals raised the normal and the
    re-rendering errors (benchmarks/refinement.py)."""

    prior: float = 0.0
    """Weight of the L1 pull of the refined global bases toward the network's (0: none)."""

    moving_maps: tuple[str, ...] = ("diffuse", "roughness", "specular")
    """The maps (of ``diffuse``, ``roughness``, ``specular``) whose global bases move; the others
    stay as the network predicted them (the normals move where ``normals``)."""

    skip_clipped: bool = False
    """Leave the photo's clipped pixels (a channel at or above ``CLIPPED``, linear) out of the
    loss: they say only that the surface was at least that bright."""

    encoded_loss: bool = False
    """Compare the render and the photo sRGB-encoded (as the eye and the real-photo protocol do)
    instead of linear, where the few pixels of a highlight outweigh the rest of the photo."""

    achromatic_specular: bool = False
    """Move each basis's three specular channels together, by one shift, so that the refinement
    cannot tint a dielectric's highlight with the photo's colour processing; a basis the network
    made a metal's (its specular's channels spread over ``METAL_SPREAD``) moves them apart."""

    unclamped_moves: bool = True
    """Let a global basis's change move every pixel where that basis weighs
    (``DeepBasisOutput.unsaturated``). Off: pixels the local unit pushed past a bound of the signed
    space stay there, only a basis's other channels move, and real photos end with a green
    specular (``benchmarks/README.md``, refinement_real)."""

    def __post_init__(self):
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule: unknown schedule {self.lr_schedule!r}; expected one of "
                             f"{', '.join(LR_SCHEDULES)}")
        unknown = [name for name in self.moving_maps if name not in ("diffuse", "roughness", "specular")]
        if unknown:
            raise ValueError(f"moving_maps: unknown maps {unknown}; expected some of diffuse, roughness, specular "
                             "(the normals move with normals)")


def step_rates(lr: float, steps: int, schedule: str = "cosine") -> list[float]:
    """Adam's learning rate at each of ``steps`` steps: ``lr`` throughout (``constant``), or from
    ``lr`` down along half a cosine, ``lr (1 + cos(pi k / steps)) / 2`` at step k = 0, 1, ...
    (``cosine``: the last step's rate is about ``lr (pi / steps)^2 / 4``)."""
    if schedule == "constant":
        return [lr] * steps
    return [lr * 0.5 * (1.0 + math.cos(math.pi * k / steps)) for k in range(steps)]


#: Linear photo values at or above this are clipped (``RefineConfig.skip_clipped``).
CLIPPED = 0.98

#: Spread (largest minus smallest channel, [0, 1]) of a basis's specular above which it is a
#: metal's, whose colour the refinement may change (``RefineConfig.achromatic_specular``).
METAL_SPREAD = 0.08


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


@functools.lru_cache(maxsize=8)
def upsample_then_average(small: int, large: int, resolution: int) -> torch.Tensor:
    """(resolution, small): the matrix of ``upsample_bilinear`` from ``small`` to ``large`` pixels
    followed by ``downsample`` (area) to ``resolution``, along one axis: both ops applied to the
    columns of an identity, so it is what they compute, to float rounding."""
    identity = torch.eye(small, dtype=torch.float64).view(1, small, small, 1)  # one column per input pixel
    large_columns = F.interpolate(identity, size=(large, 1), mode="bilinear", align_corners=False)
    averaged = F.interpolate(large_columns, size=(resolution, 1), mode="area")
    return averaged[0, :, :, 0].T.float().contiguous()


def refinement_inputs(output: DeepBasisOutput, resolution: int, size: tuple[int, int] | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """The weights (1, N, r, r) and local deviations (1, N, 10, r, r) that the refinement renders
    at ``resolution`` r: those of the prediction shown at ``size`` (its own when None; a larger
    one upsamples them bilinearly first, as ``DeepBasisOutput.maps_at`` does), area-averaged to
    r. The upsampling and averaging are applied as one matrix per axis (``upsample_then_average``),
    so a 2048 px capture holds nothing at 2048 px here. Zeros for a network without local bases."""
    def resample(value: torch.Tensor) -> torch.Tensor:
        if size is None or tuple(value.shape[-2:]) == tuple(size):
            return downsample(value, resolution)
        # Both steps are linear and separable: one small matrix per axis, never the photo's size.
        rows = upsample_then_average(value.shape[-2], size[0], resolution)
        columns = upsample_then_average(value.shape[-1], size[1], resolution)
        return torch.einsum("rh,...hw,sw->...rs", rows, value, columns)

    weights = resample(output.weights.detach().cpu())
    weights = weights / weights.sum(dim=1, keepdim=True).clamp(min=1e-6)
    if output.deviations is None:
        batch, n = output.global_bases.shape[:2]
        return weights, weights.new_zeros(batch, n, constants.BASIS_CHANNELS, resolution, resolution)
    deviations = torch.stack([resample(deviation) for deviation in output.deviations.detach().cpu().unbind(1)], dim=1)
    return weights, deviations


def refine_global_bases(output: DeepBasisOutput, photo: torch.Tensor, light: torch.Tensor, fov: float,
                        convention: str, extent: float = 1.0, config: RefineConfig = RefineConfig(),
                        progress: bool = False, size: tuple[int, int] | None = None,
                        normal_strength: float = 1.0) -> tuple[torch.Tensor, list[float]]:
    """Optimise the global bases so the rendering matches the photo; weights and deviations stay fixed.

    The loss is the mean L1 between the rendering and the photo, plus ``config.prior`` times the
    mean L1 between the bases and the network's.

    Args:
        output: the prediction (weights, global bases, deviations) of one photo.
        photo: (3, H, W) the photo, linear; light: (3,) the flash position.
        fov, convention, extent: the camera's field of view [deg], the shading convention and the
            half-width of the sample [patch half-widths].
        config: steps, render resolution, learning rate, whether the normals move, the prior.
        size: the size (H, W) the prediction is shown at, when its tensors are smaller (the
            network's resolution): ``refinement_inputs``.
        normal_strength: the factor of the blended normals' slopes in the renders
            (``geometry.scaled_slopes``; ``CaptureConfig.normal_strength``).

    Returns:
        ((1, N, 10) refined global bases, signed space; the loss at every step).
    """
    from ..render import render_backend

    resolution = config.resolution
    weights, deviations = refinement_inputs(output, resolution, size)
    target = downsample(photo[None], resolution)
    predicted = output.global_bases.detach().cpu()
    # Zero where the refinement may not move a channel: the normals unless config.normals.
    movable = torch.zeros(constants.BASIS_CHANNELS)
    for name in config.moving_maps + (("normal",) if config.normals else ()):
        movable[constants.MAP_SLICES[name]] = 1.0
    fit = _fit_drjit if render_backend() == "mitsuba" else _fit_torch
    return fit(weights, deviations, predicted, movable, target, light, fov, convention, extent, config, progress,
               *loss_settings(photo, predicted, config), normal_strength=normal_strength)


def loss_settings(photo: torch.Tensor, predicted: torch.Tensor, config: RefineConfig
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(each pixel's weight in the loss (1, r, r), mean 1: 0 at clipped pixels with
    ``skip_clipped``; whether each basis's specular channels move together (N,) with
    ``achromatic_specular``) for the photo (3, H, W) and the predicted bases (1, N, 10)."""
    resolution = config.resolution
    pixel_weights = torch.ones(1, resolution, resolution)
    if config.skip_clipped:  # a refinement pixel with any clipped photo pixel in it is left out
        clipped = downsample((photo[None] >= CLIPPED).float(), resolution).amax(dim=1) > 0
        unclipped = (~clipped).float()
        pixel_weights = unclipped / unclipped.mean().clamp(min=1.0 / unclipped.numel())
    tied = (tied_speculars(predicted[0]) if config.achromatic_specular
            else torch.zeros(predicted.shape[1], dtype=torch.bool))
    return pixel_weights, tied


def encoded(linear: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded values of linear ones in [0, 1] (``imageio.linear_to_srgb``), floored at
    ``constants.REFINE_ENCODING_FLOOR``: what the refinement's ``encoded_loss`` compares
    (``render.fit`` computes the same)."""
    return linear_to_srgb(linear.clamp(min=constants.REFINE_ENCODING_FLOOR))


def basis_bound(config: RefineConfig) -> float:
    """The largest magnitude of a refined global basis value: the signed space's 1; 2 with
    ``unclamped_moves``, so that a basis at a bound whose deviations lift some pixels off it can
    still lower them (a global basis plus a deviation in [-1, 1] spans [-1, 1] from there)."""
    return 2.0 if config.unclamped_moves else 1.0


def tied_speculars(global_bases: torch.Tensor) -> torch.Tensor:
    """(N,) whether each of the global bases (N, 10) (signed space) keeps its specular's three
    channels moving together: those whose specular is not a metal's (``METAL_SPREAD``)."""
    specular = global_bases[:, constants.SPECULAR] * 0.5 + 0.5
    return (specular.amax(dim=1) - specular.amin(dim=1)) <= METAL_SPREAD


def tie_specular_gradient(gradient: torch.Tensor, tied: torch.Tensor) -> torch.Tensor:
    """The gradient (1, N, 10) with each tied basis's three specular entries replaced by their mean."""
    tied_mean = gradient[:, :, constants.SPECULAR].mean(dim=2, keepdim=True).expand(-1, -1, 3)
    specular = torch.where(tied.view(1, -1, 1), tied_mean, gradient[:, :, constants.SPECULAR])
    return torch.cat([gradient[:, :, :constants.SPECULAR.start], specular], dim=2)


def _fit_drjit(weights: torch.Tensor, deviations: torch.Tensor, predicted: torch.Tensor, movable: torch.Tensor,
               target: torch.Tensor, light: torch.Tensor, fov: float, convention: str, extent: float,
               config: RefineConfig, progress: bool, pixel_weights: torch.Tensor,
               tied: torch.Tensor, normal_strength: float = 1.0) -> tuple[torch.Tensor, list[float]]:
    """The refinement's loop as one frozen drjit step (``render.fit``): the Mitsuba backend's."""
    from tqdm import tqdm

    from .. import geometry
    from ..render.fit import fit_global_bases

    bar = (lambda steps: tqdm(steps, desc="refining", unit="step")) if progress else None
    refined, losses = fit_global_bases(weights[0].numpy(), deviations[0].numpy(), predicted[0].numpy(), movable.numpy(),
                                       target[0].numpy(), light.numpy(), geometry.flash_intensity(fov, convention),
                                       convention, extent, step_rates(config.lr, config.steps, config.lr_schedule),
                                       config.prior, progress=bar,
                                       pixel_weights=pixel_weights[0].numpy(), tied=tied.numpy(),
                                       encoded_loss=config.encoded_loss, bound=basis_bound(config),
                                       normal_strength=normal_strength)
    return torch.from_numpy(refined)[None], losses


def _fit_torch(weights: torch.Tensor, deviations: torch.Tensor, predicted: torch.Tensor, movable: torch.Tensor,
               target: torch.Tensor, light: torch.Tensor, fov: float, convention: str, extent: float,
               config: RefineConfig, progress: bool, pixel_weights: torch.Tensor,
               tied: torch.Tensor, normal_strength: float = 1.0) -> tuple[torch.Tensor, list[float]]:
    """The refinement's loop in torch, rendering through ``render_flash`` (the torch backend's;
    the reference of ``_fit_drjit``)."""
    from tqdm import tqdm

    from ..render import render_flash

    lights = light.view(1, 1, 3)
    global_bases = predicted.clone().requires_grad_(True)

    def masked(free: torch.Tensor) -> torch.Tensor:
        return predicted + (free - predicted) * movable

    if config.normals:
        def blended(current: torch.Tensor) -> torch.Tensor:
            return compose_bases(weights, current, deviations)[1]
    else:
        # The normals stay as predicted: blend them once; each step blends the other seven channels
        # only (channel by channel the same arithmetic as the whole blend, so the same result).
        normals = compose_bases(weights, predicted, deviations)[1][:, constants.NORMAL]
        reflectance = deviations[:, :, constants.REFLECTANCE]

        def blended(current: torch.Tensor) -> torch.Tensor:
            bases = (current[:, :, constants.REFLECTANCE, None, None] + reflectance).clamp(-1.0, 1.0)
            return torch.cat([normals, blend(weights, bases)], dim=1)

    rates = step_rates(config.lr, config.steps, config.lr_schedule)
    optimizer = SmallAdam(global_bases, lr=config.lr)
    bound = basis_bound(config)
    compared = encoded(target) if config.encoded_loss else target
    losses = []
    # The tensors here are small: waking torch's worker threads for every op costs more than it saves.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for step in tqdm(range(config.steps), desc="refining", unit="step", disable=not progress):
            optimizer.lr = rates[step]
            current = masked(global_bases)
            maps = to_maps(blended(current))
            if normal_strength != 1.0:
                maps = torch.cat([scaled_slopes(maps[:, constants.NORMAL], normal_strength, dim=1),
                                  maps[:, constants.REFLECTANCE]], dim=1)
            rendered = render_flash(maps, lights, fov=fov, convention=convention, extent=extent)[:, 0].clamp(0.0, 1.0)
            if config.encoded_loss:
                rendered = encoded(rendered)
            loss = ((rendered - compared) * pixel_weights).abs().mean()
            if config.prior:
                loss = loss + config.prior * (current - predicted).abs().mean()
            global_bases.grad = None
            loss.backward()
            if bool(tied.any()):
                global_bases.grad = tie_specular_gradient(global_bases.grad, tied)
            optimizer.step()
            with torch.no_grad():
                global_bases.clamp_(-bound, bound)
            losses.append(loss.item())
    finally:
        torch.set_num_threads(threads)
    return masked(global_bases.detach()), losses
