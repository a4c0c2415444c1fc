"""The losses of training and what they need: the supervised and variation-consistency losses,
the decoder's saturation penalty, the re-rendering loss and its random lights and views, the
highlight weights of the diffuse loss, the specular lobe's loss, the specular colour's loss, the
global blend's loss, the normal pool's loss, and the learning-rate schedule."""

from __future__ import annotations

import math

import torch

from .. import constants, geometry
from ..data.synth import Variation
from ..imageio import linear_to_srgb
from ..model.network import DeepBasisOutput, blend, to_signed


def specular_lobe(maps: torch.Tensor, lights: torch.Tensor, fov: float, convention: str,
                  extent: float = 1.0) -> torch.Tensor:
    """The luminance (B, 1, H, W) of the maps' (B, 10, H, W) specular lobe alone (their diffuse
    set to zero) rendered under the flashes at ``lights`` (B, 3): where the highlight is."""
    with torch.no_grad():
        return lobe_luminance(maps, lights, fov, convention, extent)


def lobe_luminance(maps: torch.Tensor, lights: torch.Tensor, fov: float, convention: str,
                   extent: float = 1.0) -> torch.Tensor:
    """``specular_lobe`` with its gradient: the luminance (B, 1, H, W) of the maps' (B, 10, H, W)
    specular lobe alone under the flashes at ``lights`` (B, 3), rendered in float32."""
    from ..render import render_flash

    specular_only = torch.cat([maps[:, constants.NORMAL], torch.zeros_like(maps[:, constants.DIFFUSE]),
                               maps[:, constants.DIFFUSE.stop:]], dim=1).float()
    with torch.autocast(maps.device.type, enabled=False):
        rgb = render_flash(specular_only, lights.view(-1, 1, 3).float(), fov=fov, convention=convention,
                           extent=extent)[:, 0]
    return rgb_luminance(rgb)[:, None]


def rgb_luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) linear RGB -> (B, H, W) luminance (``constants.LUMINANCE_WEIGHTS``)."""
    return sum(weight * rgb[:, channel] for channel, weight in enumerate(constants.LUMINANCE_WEIGHTS))


#: Floor of the lobe loss's logs (``lobe_loss``) as a share of the true photo's peak (the
#: ``HIGHLIGHT_PEAK_QUANTILE`` of the truth rendered whole): a lobe fainter than this hardly shows.
LOBE_FLOOR = 0.01


def lobe_loss(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, fov: float, convention: str,
              extent: float = 1.0) -> torch.Tensor:
    """How far the predicted maps' specular lobe is from the truth's where the photo shows it:
    the mean over the pixels of |log(f + lobe(predicted)) - log(f + lobe(truth))| times how much
    of either lobe the pixel shows (the larger of the two over the photo's peak, at most 1), so
    that a lobe that covers few pixels or hardly shows costs little. The lobes are rendered alone
    under the photo's flashes at ``lights`` (B, 3) (``lobe_luminance``); the photo's peak is the
    ``HIGHLIGHT_PEAK_QUANTILE`` of the truth rendered whole, and f = ``LOBE_FLOOR`` times it.
    Maps (B, 10, H, W).

    In one flash photo the diffuse makes up what the lobe misses of the highlight (a weak lobe
    leaves a blob, a strong one a hole: ``benchmarks/highlight_leak.py``); this is the lobe's
    miss itself, in ratios: a lobe ten times too faint costs log 10 where the true lobe shows (one
    ten times too bright as much, and more where it shows beyond the true one).
    """
    from ..render import render_flash

    with torch.no_grad(), torch.autocast(truth.device.type, enabled=False):
        true_lobe = lobe_luminance(truth, lights, fov, convention, extent)
        photo = rgb_luminance(render_flash(truth.float(), lights.view(-1, 1, 3).float(), fov=fov,
                                           convention=convention, extent=extent)[:, 0])
        peak = torch.quantile(photo.flatten(1), HIGHLIGHT_PEAK_QUANTILE, dim=1).view(-1, 1, 1, 1).clamp_min(1e-6)
    predicted_lobe = lobe_luminance(predicted, lights, fov, convention, extent).clamp_min(0.0)
    floor = LOBE_FLOOR * peak
    miss = (torch.log(floor + predicted_lobe) - torch.log(floor + true_lobe)).abs()
    weights = (torch.maximum(true_lobe, predicted_lobe.detach()) / peak).clamp(max=1.0)
    return (miss * weights).mean()


#: Floor of the specular colour loss's logs (``specular_colour_loss``) [linear reflectance]: under
#: water's F0 (0.02) a channel's ratio to the others hardly shows in a render.
COLOUR_FLOOR = 0.01


def specular_colour_loss(predicted: torch.Tensor, truth: torch.Tensor, floor: float = COLOUR_FLOOR) -> torch.Tensor:
    """Mean |c(predicted) - c(truth)| over the pixels and channels, with c the log chromaticity of a
    specular map: log(f + s) minus its mean over the three channels (f = ``floor``). Maps
    (B, 10, H, W), linear.

    The supervised L1 weighs a tint by its size in reflectance, so on a dark dielectric (F0 about
    0.04) a specular one channel of which is twice another costs a few hundredths, as little as a
    small roughness error; in ratios it costs as much as on a bright one. A tinted specular is what
    a dark real photo's capture shows (``benchmarks/highlight_leak.py``'s tint)."""
    def chromaticity(maps: torch.Tensor) -> torch.Tensor:
        logs = torch.log(floor + maps[:, constants.SPECULAR].float().clamp_min(0.0))
        return logs - logs.mean(dim=1, keepdim=True)

    return (chromaticity(predicted) - chromaticity(truth)).abs().mean()


def global_blend_loss(output: DeepBasisOutput, maps: torch.Tensor) -> torch.Tensor:
    """L1 in signed space between the global blend alone (each pixel's blending weights times the
    global bases, no local deviations) and the truth ``maps`` (B, 10, H, W), over the reflectance
    channels (the relief is the local unit's and the normal unit's).

    The local unit reads the render of this blend against the photo (``DeepBasisNet.error_map``)
    and the refinement moves the global bases. Trained on the final maps alone, the shipped
    network's global blend is not the material: on the shared 84 its diffuse and specular RMSE
    are 0.36 and 0.29 against the final maps' 0.027 and 0.038 (``benchmarks/model_quality.py``),
    the local deviations pulling every pixel back."""
    global_blend = blend(output.weights, output.global_bases)[:, constants.REFLECTANCE]
    return (global_blend - to_signed(maps)[:, constants.REFLECTANCE]).abs().mean()


#: The lobe's brightness that weighs fully in ``highlight_weights``: its 99th percentile.
HIGHLIGHT_PEAK_QUANTILE = 0.99


def highlight_weights(maps: torch.Tensor, lights: torch.Tensor, weight: float, fov: float, convention: str,
                      extent: float = 1.0) -> torch.Tensor:
    """Per-pixel weights (B, 1, H, W) of the diffuse loss: 1 + ``weight`` * the specular lobe alone
    (the maps (B, 10, H, W) with their diffuse set to zero) rendered under the flashes at
    ``lights`` (B, 3), as luminance over its ``HIGHLIGHT_PEAK_QUANTILE`` (at most 1); then divided
    by their mean, so that the highlight moves the loss within a material, not its scale. A
    material without specular weighs 1 everywhere."""
    lobe = specular_lobe(maps, lights, fov, convention, extent)
    # A percentile rather than the maximum: the glints of a bumpy glossy sample would set the scale.
    peak = torch.quantile(lobe.flatten(1), HIGHLIGHT_PEAK_QUANTILE, dim=1).view(-1, 1, 1, 1)
    share = torch.where(peak > 0, lobe / peak.clamp_min(1e-12), torch.zeros_like(lobe)).clamp(max=1.0)
    weights = 1.0 + weight * share
    return weights / weights.mean(dim=(2, 3), keepdim=True)


def normals_over_flat(slope: torch.Tensor) -> torch.Tensor:
    """The normals (B, 3, H, W) that the normal unit's slope (B, 2, H, W) gives a flat material:
    unit-normal(slope, 1), as ``DeepBasisNet`` adds it to the bases."""
    return geometry.unit_vectors(torch.cat([slope, torch.ones_like(slope[:, :1])], dim=1), dim=1)


def normal_unit_loss(normals: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The normal pool's loss (``TrainConfig.normal_pool``): the mean squared error of unit normals
    (B, 3, H, W) against the true ones."""
    return ((normals - truth) ** 2).mean()


def vary_signed(variation: Variation, signed: torch.Tensor) -> torch.Tensor:
    """Apply xi to signed-space parameters (B, 10, ...) (maps or bases with channels at dim 1)."""
    normal, rest = signed.split(constants.NORMAL_AND_REFLECTANCE, dim=1)
    varied = variation.apply(torch.cat([normal, rest * 0.5 + 0.5], dim=1))
    return torch.cat([varied[:, constants.NORMAL], varied[:, constants.REFLECTANCE] * 2.0 - 1.0], dim=1)


def channel_weights(normal_weight: float, device=None) -> torch.Tensor:
    """(1, 10, 1, 1) weights of the map channels: ``normal_weight`` for the normal, 1 for the rest,
    scaled so that their mean is 1."""
    weights = torch.tensor([normal_weight] * 3 + [1.0] * 7, device=device)
    return (weights * 10 / weights.sum()).view(1, 10, 1, 1)


def supervised_loss(output: DeepBasisOutput, maps: torch.Tensor, normal_weight: float = 1.0,
                    signed_target: torch.Tensor | None = None,
                    diffuse_weights: torch.Tensor | None = None, diffuse_encoded: bool = False) -> torch.Tensor:
    """(Weighted) L1 between the predicted blend and the ground truth ``maps`` (or, given, the
    target already in signed space), in signed space; ``diffuse_weights`` (B, 1, H, W) weigh the
    diffuse channels' pixels (``highlight_weights``); ``diffuse_encoded``: the diffuse channels
    compared as sRGB-encoded albedos instead (``TrainConfig.diffuse_loss_encoded``)."""
    target = to_signed(maps) if signed_target is None else signed_target
    difference = (output.signed_maps - target).abs()
    if diffuse_encoded or diffuse_weights is not None:  # the diffuse channels' term, rebuilt once
        diffuse = difference[:, constants.DIFFUSE]
        if diffuse_encoded:
            def encoded(signed: torch.Tensor) -> torch.Tensor:  # signed space to sRGB-encoded albedo
                return linear_to_srgb((signed[:, constants.DIFFUSE] * 0.5 + 0.5).clamp(0.0, 1.0))

            diffuse = (encoded(output.signed_maps) - encoded(target)).abs()
        if diffuse_weights is not None:
            diffuse = diffuse * diffuse_weights
        difference = torch.cat([difference[:, :constants.DIFFUSE.start], diffuse,
                                difference[:, constants.DIFFUSE.stop:]], dim=1)
    return (difference * channel_weights(normal_weight, maps.device)).mean()


def saturation_penalty(raw: torch.Tensor, limit: float = 2.0) -> torch.Tensor:
    """mean(max(|raw| - limit, 0)^2) of pre-tanh outputs (B, C, H, W): zero where tanh still has slope."""
    return torch.relu(raw.abs() - limit).square().mean()


def variation_consistency_loss(original: DeepBasisOutput, varied: DeepBasisOutput, variation: Variation,
                               varied_maps: torch.Tensor, normal_weight: float = 1.0) -> torch.Tensor:
    """|xi(bases(M)) - bases(M + xi)|_1 + |maps(M + xi) - (M + xi)|_1 (DeepBasis's L_vc).

    Without bases (the direct ablation) the maps stand in for the bases.
    """
    if original.bases is not None:
        source, target = original.bases.transpose(1, 2), varied.bases.transpose(1, 2)  # (B, 10, N, H, W)
    elif original.global_bases is not None:
        source, target = original.global_bases.transpose(1, 2), varied.global_bases.transpose(1, 2)
    else:
        source, target = original.signed_maps, varied.signed_maps
    consistency = (vary_signed(variation, source) - target).abs().mean()
    return consistency + supervised_loss(varied, varied_maps, normal_weight)


def sample_render_geometry(batch: int, count: int, generator: torch.Generator,
                           distance: tuple[float, float] = (2.0, 5.0), min_cos: float = 0.15,
                           jitter: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Random light and view positions of the re-rendering loss.

    Every position is ``d * dir + (jx, jy, 0)``: ``dir`` on the upper hemisphere with its cosine
    to +z uniform in [min_cos, 1] (down to grazing, 81 deg by default), uniform azimuth, ``d``
    uniform in ``distance``, a lateral jitter uniform in [-jitter, jitter]. The first
    ``count - count // 2`` pairs draw light and view independently; the other ``count // 2`` are
    mirror pairs: the view is the light mirrored about the normal of a random point q of the
    sample (at its own distance), so a flat, smooth sample shows a highlight at q.

    Returns:
        lights, views: (B, K, 3) positions [patch half-widths].
    """
    def positions():
        """(B, K, 3) positions drawn as the docstring says."""
        n = batch * count
        cos = min_cos + (1 - min_cos) * torch.rand(n, generator=generator)
        sin = torch.sqrt(1 - cos**2)
        phi = 2 * math.pi * torch.rand(n, generator=generator)
        length = distance[0] + (distance[1] - distance[0]) * torch.rand(n, generator=generator)
        lateral = (2 * torch.rand(n, 2, generator=generator) - 1) * jitter
        direction = torch.stack([sin * torch.cos(phi), sin * torch.sin(phi), cos], dim=-1)
        return (length[:, None] * direction + torch.cat([lateral, torch.zeros(n, 1)], dim=-1)).view(batch, count, 3)

    mirrored = count // 2
    lights = positions()
    views = positions()
    if mirrored:
        target = torch.cat([(2 * torch.rand(batch, mirrored, 2, generator=generator) - 1) * 0.7,
                            torch.zeros(batch, mirrored, 1)], dim=-1)
        to_light = lights[:, -mirrored:] - target
        mirror = to_light * torch.tensor([-1.0, -1.0, 1.0])
        length = distance[0] + (distance[1] - distance[0]) * torch.rand(batch, mirrored, 1, generator=generator)
        views = torch.cat([views[:, :-mirrored], target + mirror / mirror.norm(dim=-1, keepdim=True) * length], dim=1)
    return lights, views


def rendering_loss(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor,
                   convention: str = constants.DEFAULT_CONVENTION) -> torch.Tensor:
    """Mean |log(1 + render(predicted)) - log(1 + render(truth))| over K lights and views.

    Args:
        predicted, truth: (B, 10, H, W) maps (unit normals, the rest in [0, 1]).
        lights, views: (B, K, 3) positions [patch half-widths] (``sample_render_geometry``).

    The render is the renderer interface's (its current backend), in float32, with the physical
    flash intensity of the default field of view.
    """
    from ..render import render_flash

    with torch.autocast(predicted.device.type, enabled=False):
        rendered = render_flash(predicted.float(), lights, views=views, convention=convention)
        with torch.no_grad():
            reference = render_flash(truth.float(), lights, views=views, convention=convention)
        return (torch.log1p(rendered.clamp(min=0.0)) - torch.log1p(reference.clamp(min=0.0))).abs().mean()



def learning_rate_factor(step: int, steps: int, final_fraction: float, warmup: int = 0) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay from 1 to ``final_fraction`` at the last step."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, steps - warmup - 1))
    return final_fraction + (1 - final_fraction) * 0.5 * (1 + math.cos(math.pi * progress))
