"""Metrics of predicted materials against ground truth, each a plain function.

Shapes: maps (B, 10, H, W) [normal 3, diffuse 3, roughness 1, specular 3], normals unit vectors;
images (N, C, H, W) sRGB-encoded in [0, 1]; lights and views (K, 3) [patch half-widths].

Map RMSE is computed on the maps in their stored encoding (normals as (n + 1) / 2, the other maps
as they are; training's validation figure, ``unit_normal_map_rmse``, on unit normals). The
re-rendering error compares renders of the prediction and of the truth under the same lights and
viewpoints, on clipped sRGB-encoded images; FLIP, SSIM and LPIPS compare the same renders.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import constants, geometry
from ..imageio import linear_to_srgb


def light_error_deg(estimate, truth, fov: float = constants.DEFAULT_FOV_DEG) -> float:
    """Angle between an estimated and a true flash position seen from the sample centre [deg].

    Args:
        estimate, truth: lateral offsets (tx, ty) [patch half-widths], or (..., 2) tensors.
    """
    a = geometry.light_positions(torch.as_tensor(estimate, dtype=torch.float64), fov)
    b = geometry.light_positions(torch.as_tensor(truth, dtype=torch.float64), fov)
    cosine = (a * b).sum(-1) / (torch.linalg.vector_norm(a, dim=-1) * torch.linalg.vector_norm(b, dim=-1))
    angle = torch.rad2deg(torch.arccos(cosine.clamp(-1.0, 1.0)))
    return float(angle) if angle.ndim == 0 else angle


def map_rmse(predicted: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-material RMSE of each map of ``predicted`` against ``truth`` (B, 10, H, W) in the
    stored encoding, (B,) each.

    Normals are compared as stored, (n + 1) / 2; the other maps as they are (linear, or the stored
    values of a dataset read as-is); roughness has one channel.
    """
    def rmse(a, b):
        return ((a - b) ** 2).mean(dim=(1, 2, 3)).sqrt()

    # Normals in the stored encoding (n + 1) / 2, the other maps as they are.
    stored_predicted = torch.cat([(predicted[:, constants.NORMAL] + 1) / 2, predicted[:, constants.REFLECTANCE]], dim=1)
    stored_truth = torch.cat([(truth[:, constants.NORMAL] + 1) / 2, truth[:, constants.REFLECTANCE]], dim=1)
    return {name: rmse(stored_predicted[:, channels], stored_truth[:, channels])
            for name, channels in constants.MAP_SLICES.items()}


def unit_normal_map_rmse(predicted: torch.Tensor, truth: torch.Tensor) -> dict:
    """RMSE of each map over a batch (B, 10, H, W), in the in-memory encoding (unit normals, so the
    normal's figure is twice ``map_rmse``'s, which is in the stored encoding): training's
    validation figure."""
    rmse = ((predicted - truth) ** 2).mean(dim=(0, 2, 3)).sqrt()
    return {name: rmse[channels].mean().item() for name, channels in constants.MAP_SLICES.items()}


#: The band of ``detail_ratio``: the resolution [pixels] the shipped network answers at.
DETAIL_BAND = 128


def above_band(values: torch.Tensor, band: int = DETAIL_BAND) -> torch.Tensor:
    """(B, C, H, W) minus its area average to ``band`` px upsampled bilinearly back to H x W: what
    ``values`` hold above the band."""
    from ..resampling import downsample, upsample_bilinear

    return values - upsample_bilinear(downsample(values, band), *values.shape[-2:])


def high_band_energy(maps: torch.Tensor, band: int = DETAIL_BAND) -> dict[str, torch.Tensor]:
    """Per-material energy of each map of (B, 10, H, W) above the ``band``-pixel band, (B,) each:
    the mean over pixels of the squared residual ``map - upsample_bilinear(downsample(map, band))``
    (area average, then bilinear back to H x W), summed over the map's channels.

    The filter is linear and applied to the maps as they are (unit normals, not renormalised), so
    the normal's figure is the same in the stored encoding but for a factor 1/4. A map at or
    below ``band`` pixels has none. Note the residual of a map that is itself a bilinear
    upsampling of a ``band``-pixel one is small but not 0: area-averaging a bilinear upsampling by
    an even factor blurs by [1/8, 3/4, 1/8] along each axis (away from the edges), so 1/8 of the
    band-size map's discrete Laplacian remains.
    """
    height, width = maps.shape[-2:]
    result = {}
    for name, channels in constants.MAP_SLICES.items():
        values = maps[:, channels]
        if min(height, width) <= band:
            result[name] = torch.zeros(maps.shape[0], dtype=maps.dtype, device=maps.device)
            continue
        result[name] = (above_band(values, band)**2).mean(dim=(2, 3)).sum(dim=1)
    return result


def detail_ratio(predicted: torch.Tensor, truth: torch.Tensor, band: int = DETAIL_BAND) -> dict[str, torch.Tensor]:
    """Per-material detail of each predicted map against the truth, (B,) each: the predicted
    map's energy above the ``band``-pixel band over the truth's (``high_band_energy``; energy,
    not amplitude: twice the truth's fine detail gives 4). 1 is right, 0 a map as blurred as a
    ``band``-pixel answer, above 1 detail the truth lacks; NaN where the truth has no energy there.

    Args:
        predicted, truth: (B, 10, H, W) maps of one size, normals unit vectors.
    """
    if predicted.shape[-2:] != truth.shape[-2:]:
        raise ValueError(f"predicted maps {tuple(predicted.shape[-2:])} and truth {tuple(truth.shape[-2:])} differ in size")
    found, expected = high_band_energy(predicted, band), high_band_energy(truth, band)
    return {name: torch.where(expected[name] > 0, found[name] / expected[name].clamp_min(1e-30),
                              torch.full_like(expected[name], float("nan")))
            for name in constants.MAP_SLICES}


def flat_normals(maps: torch.Tensor) -> torch.Tensor:
    """A copy of maps (B, 10, H, W) with flat normals (+z): the baseline of the normal's RMSE."""
    flat = maps.clone()
    flat[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0], dtype=maps.dtype).view(1, 3, 1, 1)
    return flat


def mean_tilt_deg(maps: torch.Tensor) -> float:
    """Mean angle between the normals of (B, 10, H, W) maps and +z [deg]: how much relief there is."""
    return torch.rad2deg(torch.acos(maps[:, constants.NORMAL][:, 2].clamp(-1.0, 1.0))).mean().item()


def rerender(maps: torch.Tensor, lights: torch.Tensor, views: torch.Tensor, convention: str,
             backend: str = "mitsuba") -> torch.Tensor:
    """Clipped, sRGB-encoded renders of (B, 10, H, W) maps under (K, 3) lights and views -> (B, K, 3, H, W).

    ``physical``: one intensity for all K lights, pi times the mean over the lights of their squared
    distance to the sample centre, so a white Lambertian facing a light renders to about 1.
    ``deepbasis``: their unit lamp without falloff.
    """
    from ..render import render_flash

    batch = maps.shape[0]
    intensity = math.pi * float((lights**2).sum(-1).mean()) if convention == "physical" else constants.DEEPBASIS_LAMP_INTENSITY
    with torch.no_grad():
        linear = render_flash(maps, lights.expand(batch, -1, -1), convention=convention, intensity=intensity,
                              backend=backend, views=views.expand(batch, -1, -1))
    return linear_to_srgb(linear.clamp(0.0, 1.0))


def rerender_rmse(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor,
                  convention: str, backend: str = "mitsuba") -> torch.Tensor:
    """Per-material RMSE between re-renderings (``rerender``) of prediction and truth
    (B, 10, H, W) under (K, 3) lights and views, (B,)."""
    difference = rerender(predicted, lights, views, convention, backend) - rerender(truth, lights, views, convention, backend)
    return (difference**2).mean(dim=(1, 2, 3, 4)).sqrt()


def trivial_baseline(materials: torch.Tensor) -> torch.Tensor:
    """The trivial prediction for a set (N, 10, H, W): a flat normal and the set's mean maps, (10, H, W)."""
    mean = materials.mean(dim=(0, 2, 3))
    baseline = mean.view(10, 1, 1).expand(10, *materials.shape[-2:]).clone()
    baseline[constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    return baseline


@dataclass
class Scores:
    """Per-material scores of one method on a set."""

    names: list[str]
    maps: dict[str, torch.Tensor] = field(default_factory=dict)
    render: torch.Tensor | None = None

    def summary(self) -> dict:
        result = {name: float(values.mean()) for name, values in self.maps.items()}
        if self.render is not None:
            result["render_rmse"] = float(self.render.mean())
        return result


# --- image metrics -------------------------------------------------------------------------------------


def ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel structural similarity of images in [0, 1] (Wang et al. 2004; Gaussian 11 x 11, sigma 1.5).

    Args:
        a, b: (N, C, H, W).

    Returns:
        (N, C, H - window + 1, W - window + 1): no padding, so the map covers the inner image.
    """
    coordinates = torch.arange(window, dtype=a.dtype) - (window - 1) / 2
    gauss = torch.exp(-(coordinates**2) / (2 * sigma**2))
    gauss = gauss / gauss.sum()
    kernel = (gauss[:, None] * gauss[None, :]).expand(a.shape[1], 1, window, window).contiguous()

    def blur(x):
        return torch.nn.functional.conv2d(x, kernel, groups=a.shape[1])

    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    covariance = blur(a * b) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * covariance + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean structural similarity of images (N, C, H, W) in [0, 1] over pixels and channels, (N,)."""
    return ssim_map(a, b, window, sigma).mean(dim=(1, 2, 3))


def flip(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean LDR FLIP error (NVIDIA's flip-evaluator) of sRGB-encoded images in [0, 1], (N, 3, H, W) -> (N,)."""
    import flip_evaluator

    values = []
    for reference, test in zip(a, b):
        _, mean, _ = flip_evaluator.evaluate(reference.permute(1, 2, 0).numpy().astype(np.float32),
                                             test.permute(1, 2, 0).numpy().astype(np.float32), "LDR",
                                             applyMagma=False)
        values.append(mean)
    return torch.tensor(values)


class LPIPS(torch.nn.Module):
    """LPIPS (Zhang et al. 2018), AlexNet variant, from weights already on this machine.

    Needs torchvision's AlexNet weights in the torch hub cache (``alexnet-owt-7be5be79.pth``) and
    the LPIPS linear layers (``alex.pth`` of the ``lpips`` package); ``available()`` says why not.
    Nothing is ever downloaded.
    """

    ALEXNET = "alexnet-owt-7be5be79.pth"
    CHANNELS = (64, 192, 384, 256, 256)

    @classmethod
    def weight_files(cls) -> tuple[Path | None, Path | None, str | None]:
        hub = Path(torch.hub.get_dir()) / "checkpoints" / cls.ALEXNET
        linear = None
        try:
            import importlib.util

            spec = importlib.util.find_spec("lpips")
            if spec and spec.origin:
                candidate = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
                linear = candidate if candidate.is_file() else None
        except (ImportError, ValueError):
            linear = None
        if not hub.is_file():
            return None, linear, f"LPIPS skipped: no AlexNet weights at {hub} (nothing is downloaded)"
        if linear is None:
            return hub, None, "LPIPS skipped: the LPIPS linear weights (package lpips) are not installed"
        return hub, linear, None

    def __init__(self, alexnet: Path, linear: Path):
        super().__init__()
        from torch import nn

        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2), nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
            nn.MaxPool2d(3, 2), nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(), nn.Conv2d(384, 256, 3, padding=1),
            nn.ReLU(), nn.Conv2d(256, 256, 3, padding=1), nn.ReLU())
        state = torch.load(alexnet, map_location="cpu", weights_only=True)
        self.features.load_state_dict({k[len("features."):]: v for k, v in state.items() if k.startswith("features.")})
        lins = torch.load(linear, map_location="cpu", weights_only=True)
        self.lins = [lins[f"lin{i}.model.1.weight"] for i in range(5)]
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.eval()

    def _taps(self, x):
        x = ((x * 2 - 1) - self.shift) / self.scale
        taps = []
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in (1, 4, 7, 9, 11):
                taps.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return taps

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) sRGB in [0, 1] -> (N,) LPIPS distance."""
        with torch.no_grad():
            distance = 0
            for lin, fa, fb in zip(self.lins, self._taps(a), self._taps(b)):
                distance = distance + (torch.nn.functional.conv2d((fa - fb) ** 2, lin)).mean(dim=(1, 2, 3))
        return distance


# --- the metrics of an evaluation row ----------------------------------------------------------------


def score(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor, convention: str,
          lpips: LPIPS | None = None, cross_check: bool = False, stored: torch.Tensor | None = None
          ) -> dict[str, torch.Tensor]:
    """Per-material metrics of predictions (N, 10, H, W) against the truth: map RMSE against the
    maps as ``stored`` (default: ``truth``), re-renderings against ``truth``."""
    result = {f"maps_{k}": v for k, v in map_rmse(predicted, truth if stored is None else stored).items()}
    rmse, flips, ssims, lpipses, torch_rmse = [], [], [], [], []
    for index in range(len(truth)):
        a = rerender(predicted[index:index + 1], lights, views, convention)[0]
        b = rerender(truth[index:index + 1], lights, views, convention)[0]
        rmse.append(((a - b) ** 2).mean().sqrt())
        flips.append(flip(a, b).mean())
        ssims.append(ssim(a, b).mean())
        if lpips is not None:
            lpipses.append(lpips(a, b).mean())
        if cross_check:
            ta = rerender(predicted[index:index + 1], lights, views, convention, backend="torch")[0]
            tb = rerender(truth[index:index + 1], lights, views, convention, backend="torch")[0]
            torch_rmse.append(((ta - tb) ** 2).mean().sqrt())
    result.update(render_rmse=torch.stack(rmse), render_flip=torch.stack(flips), render_ssim=torch.stack(ssims))
    if lpips is not None:
        result["render_lpips"] = torch.stack(lpipses)
    if cross_check:
        result["render_rmse_torch"] = torch.stack(torch_rmse)
    return result


def summary_scores(means: dict[str, float]) -> dict:
    """Means of ``score``'s metrics (flat keys ``maps_normal``, ``render_rmse``, ...) nested as the
    summary reports them: ``maps_rmse`` {normal, diffuse, roughness, specular}, ``render_rmse``,
    ``render_flip``, ``render_ssim``."""
    return {"maps_rmse": {k: means[f"maps_{k}"] for k in ("normal", "diffuse", "roughness", "specular")},
            "render_rmse": means["render_rmse"], "render_flip": means["render_flip"], "render_ssim": means["render_ssim"]}
