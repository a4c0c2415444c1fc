"""Evaluation: map errors and re-rendering errors of predicted materials against ground truth.

``mideepbasis evaluate`` runs ``run_evaluation``: it writes ``summary.json``, ``per_material.csv``,
``table.md``, ``bars.png`` and ``gallery.png`` (the 4 best and 4 worst materials: true maps, then
predicted maps) and, with ``--lighting``, ``lighting.png``.

Protocol (the paper's): the input photo is re-rendered from the ground-truth maps under a flash
(centred, or a seeded hand-held offset per material), photographed as an 8-bit sRGB image, and
the method predicts the maps from it. Map RMSE is computed on the maps in their stored encoding
(the Deschaintre test maps are used as stored, so that is their in-memory value; normals as
(n + 1) / 2). The re-rendering error compares renders of the prediction and of the truth under
the same 30 random lights and viewpoints per material (seeded, identical for every method), on
clipped sRGB-encoded images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import constants, geometry
from .imageio import linear_to_srgb

#: Number of random light and view pairs per material for the re-rendering error.
RERENDER_COUNT = 30


def random_lights_and_views(count: int = RERENDER_COUNT, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` light positions and viewpoints [patch half-widths], (count, 3) each, seeded.

    Directions are cosine-distributed over the upper hemisphere at distances of 2 to 4 patch
    half-widths from a random point of the central half of the sample, as hand-held shots and
    room lights are: grazing ones are rare.
    """
    generator = torch.Generator().manual_seed(seed)

    def positions():
        u = torch.rand(count, 2, generator=generator)
        radius, angle = torch.sqrt(u[:, 0] * 0.9), 2 * math.pi * u[:, 1]  # cos(theta) >= 0.3
        direction = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), torch.sqrt(1 - radius**2)], -1)
        distance = 2.0 + 2.0 * torch.rand(count, 1, generator=generator)
        centre = torch.cat([torch.rand(count, 2, generator=generator) - 0.5, torch.zeros(count, 1)], -1)
        return centre + distance * direction

    return positions(), positions()


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
    """Per-material RMSE of each map in the stored encoding, (B,) each.

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


def rerender(maps: torch.Tensor, lights: torch.Tensor, views: torch.Tensor, convention: str,
             backend: str = "mitsuba") -> torch.Tensor:
    """Clipped, sRGB-encoded renders of (B, 10, H, W) maps under (K, 3) lights and views -> (B, K, 3, H, W).

    ``physical``: the light's intensity is pi d^2 for its mean distance d to the sample centre, so
    a white Lambertian facing it renders to about 1. ``deepbasis``: their unit lamp without falloff.
    """
    from .render import render_flash

    batch = maps.shape[0]
    intensity = math.pi * float((lights**2).sum(-1).mean()) if convention == "physical" else constants.DEEPBASIS_LAMP_INTENSITY
    with torch.no_grad():
        linear = render_flash(maps, lights.expand(batch, -1, -1), convention=convention, intensity=intensity,
                              backend=backend, views=views.expand(batch, -1, -1))
    return linear_to_srgb(linear.clamp(0.0, 1.0))


def rerender_rmse(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor,
                  convention: str, backend: str = "mitsuba") -> torch.Tensor:
    """Per-material RMSE between re-renderings of prediction and truth, (B,)."""
    difference = rerender(predicted, lights, views, convention, backend) - rerender(truth, lights, views, convention, backend)
    return (difference**2).mean(dim=(1, 2, 3, 4)).sqrt()


def trivial_baseline(materials: torch.Tensor) -> torch.Tensor:
    """The trivial prediction for a set (N, 10, H, W): a flat normal and the set's mean maps, (10, H, W)."""
    mean = materials.mean(dim=(0, 2, 3))
    baseline = mean.view(10, 1, 1).expand(10, *materials.shape[-2:]).clone()
    baseline[constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    return baseline


def flash_photos(maps: torch.Tensor, offsets: torch.Tensor, fov: float = constants.DEFAULT_FOV_DEG,
                 convention: str = constants.DEFAULT_CONVENTION, extent: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The evaluation inputs: 8-bit sRGB photos of ``maps`` (B, 10, H, W) under flashes at lateral
    ``offsets`` (B, 2) [patch half-widths], no noise. Returns (photos (B, 3, H, W) linear, lights (B, 3))."""
    from .data.synth import SynthesisConfig, simulate_photo
    from .render import render_flash

    lights = geometry.light_positions(offsets, fov)
    with torch.no_grad():
        radiance = render_flash(maps, lights.view(-1, 1, 3), fov=fov, convention=convention, extent=extent)[:, 0]
    quiet = SynthesisConfig(shot_noise=(1e-30, 1e-30), read_noise=(1e-30, 1e-30), quantize=True)
    photos = simulate_photo(radiance, torch.Generator().manual_seed(0), quiet, gains=torch.ones(maps.shape[0], 3))
    return photos, lights


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


# --- the evaluation run ------------------------------------------------------------------------------


@dataclass(frozen=True)
class EvaluationConfig:
    """An evaluation run (``mideepbasis evaluate``)."""

    data: str
    """Dataset path [folder]."""

    format: str = "deschaintre5"
    """``deschaintre5``, ``deschaintre4`` (strips) or ``folder`` (material folders or PBR maps)."""

    out: str = "evaluation"
    """Output folder."""

    model: str | None = None
    """Checkpoint of the model (None: the shipped one)."""

    light: str = "known"
    """``known``: the model is given the offset; ``search``: it finds it."""

    refine_steps: int = 0
    """Refinement steps of the model's row (the paper: 500)."""

    refine_normals: bool = False
    """Whether the refinement may turn the global bases' normals (the paper's refinement)."""

    network_resolution: int | None = None
    """Largest resolution the network runs at [pixels] (None: the model's training resolution; 0: no
    limit), as in ``capture``."""

    baselines: bool = False
    """Add the trivial, direct (``direct_model``), unrefined and refined rows."""

    direct_model: str | None = None
    """Checkpoint of the direct per-pixel network (the no-bases ablation) for ``baselines``."""

    lighting: bool = False
    """Also measure the lighting search's accuracy and the robustness to the offset."""

    seed: int = 0
    """Seed of the offsets and of the re-rendering lights and views."""

    fov: float = constants.DEFAULT_FOV_DEG
    """Field of view of the re-rendered inputs [deg]."""

    limit: int | None = None
    """Evaluate only the first this many materials (quick runs)."""

    resolution: int | None = None
    """Resample the materials to this size first [pixels] (None: as stored)."""

    environment: tuple[str, ...] = ()
    """Also compare path-traced renders under these environments (``studio``, ``sunsky``,
    ``uniform``, EXR/HDR files; ``environment_eval``); empty: not at all."""

    environment_spp: int | None = None
    """Samples per pixel of the environment renders (None: the protocol's)."""

    environment_resolution: int | None = None
    """Size of the environment renders [pixels] (None: the protocol's)."""


@dataclass
class EvaluationSet:
    """The materials of an evaluation, every one at one size.

    Attributes:
        names: one per material.
        maps: (N, 10, H, W) the maps to render (normals a dataset stored pointing into the
            surface repaired: z raised to ``material.REPAIRED_NORMAL_Z``, renormalised).
        stored: (N, 10, H, W) the maps as stored, for map metrics (equal to ``maps`` but for the
            repaired normals).
        repaired_pixels: per material, how many normals were repaired.
        skipped: unreadable materials.
    """

    names: list[str]
    maps: torch.Tensor
    stored: torch.Tensor
    repaired_pixels: list[int]
    skipped: int


def load_evaluation_materials(data: str | Path, format: str) -> EvaluationSet:
    """The readable materials of a dataset (``EvaluationSet``); only unreadable files are skipped."""
    from .data.datasets import DeschaintreDataset, MaterialFolderDataset, PBRFolderDataset

    data = Path(data)
    if format in ("deschaintre5", "deschaintre4"):
        reader = DeschaintreDataset(data)
    elif format == "folder":
        reader = MaterialFolderDataset(data)
        if not len(reader):
            reader = PBRFolderDataset(data)
    else:
        from .errors import InputError

        raise InputError(f"unknown dataset format {format!r}: expected deschaintre5, deschaintre4 or folder")
    names, maps, stored, repaired = [], [], [], []
    for source in reader.sources:
        material = reader.try_load(source)
        if material is None:
            continue
        names.append(Path(str(source)).stem)
        tensor = material.to_tensor()
        maps.append(tensor)
        if material.stored_normal is None:
            stored.append(tensor)
        else:
            stored.append(torch.cat([material.stored_normal.detach().float(), tensor[constants.REFLECTANCE]]))
        repaired.append(int(material.provenance.get("repaired_normal_pixels", 0)))
    if not maps:
        from .errors import InputError

        raise InputError(f"{data}: no readable materials ({reader.skipped} skipped)")
    size = min(m.shape[-1] for m in maps)
    maps = [m if m.shape[-1] == size else _resize_maps(m, size) for m in maps]
    stored = [m if m.shape[-1] == size else _resize_maps(m, size) for m in stored]
    return EvaluationSet(names, torch.stack(maps), torch.stack(stored), repaired, reader.skipped)


def load_evaluation_set(data: str | Path, format: str) -> tuple[list[str], torch.Tensor, int]:
    """(names, maps to render (N, 10, H, W), number skipped): ``load_evaluation_materials`` in short."""
    materials = load_evaluation_materials(data, format)
    return materials.names, materials.maps, materials.skipped


def _resize_maps(maps: torch.Tensor, size: int) -> torch.Tensor:
    small = torch.nn.functional.interpolate(maps[None], size=(size, size), mode="area")[0]
    small[constants.NORMAL] = torch.nn.functional.normalize(small[constants.NORMAL], dim=0)
    return small


def evaluation_offsets(count: int, seed: int, fov: float) -> torch.Tensor:
    """The seeded hand-held offsets of the evaluation inputs, one per material, (count, 2)."""
    from .data.synth import sample_offsets

    return sample_offsets(count, torch.Generator().manual_seed(seed), fov)


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


def _predict_all(model, truth: torch.Tensor, offsets: torch.Tensor, fov: float, light: str, refine_steps: int,
                 progress: bool, label: str, refine_normals: bool = False, network_resolution: int | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None, list[dict]]:
    """Predictions (N, 10, H, W) without and (when ``refine_steps``) with refinement, from one search
    and one prediction per material, and per-material details (light error [deg], passes, seconds)."""
    import time

    from tqdm import tqdm

    from .capture import CaptureConfig, Capturer, Photo, RefineConfig

    convention = model.config.convention
    capturer = Capturer(model, CaptureConfig(fov=fov, network_resolution=network_resolution,
                                             refine=RefineConfig(steps=refine_steps, normals=refine_normals)))
    plain, refined_maps, details = [], [], []
    for index in tqdm(range(len(truth)), desc=label, unit="material", disable=not progress):
        started = time.perf_counter()
        photos, _ = flash_photos(truth[index:index + 1], offsets[index:index + 1], fov, convention,
                                 model.config.plane_extent)
        photo = Photo(photos[0], fov, "argument")
        if light == "search":
            found = capturer.search(photo)
            offset, history = found.offset, found.history
        else:
            offset, history = offsets[index], []
        output = capturer.predict(photo, offset)
        plain.append(output.maps.cpu())
        seconds = time.perf_counter() - started
        refine_seconds = 0.0
        if refine_steps and output.weights is not None:
            started = time.perf_counter()
            refined, _ = capturer.refine(output, photo, offset)
            refined_maps.append(refined.maps.cpu())
            refine_seconds = time.perf_counter() - started
        details.append({"light_error_deg": light_error_deg(torch.as_tensor(offset).tolist(), offsets[index].tolist(), fov),
                        "search_passes": len(history), "seconds": seconds, "refine_seconds": refine_seconds})
    return torch.cat(plain), (torch.cat(refined_maps) if refined_maps else None), details


def run_evaluation(config: EvaluationConfig, progress: bool = True) -> dict:
    """Evaluate a model (and baselines) on a dataset; writes OUT and returns the summary."""
    import time

    from .capture import CaptureConfig
    from .model.checkpoint import load_model

    started = time.perf_counter()
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    materials = load_evaluation_materials(config.data, config.format)
    names, truth, stored, skipped = materials.names, materials.maps, materials.stored, materials.skipped
    repaired = materials.repaired_pixels
    if config.limit:
        names, truth, stored, repaired = names[:config.limit], truth[:config.limit], stored[:config.limit], repaired[:config.limit]
    if config.resolution and config.resolution != truth.shape[-1]:
        truth = torch.stack([_resize_maps(m, config.resolution) for m in truth])
        stored = torch.stack([_resize_maps(m, config.resolution) for m in stored])
    model = load_model(config.model)
    # Load the direct baseline now, so a wrong path fails before minutes of predictions.
    direct = load_model(config.direct_model) if config.baselines and config.direct_model else None
    convention = model.config.convention
    offsets = evaluation_offsets(len(truth), config.seed, config.fov)
    lights, views = random_lights_and_views(RERENDER_COUNT, config.seed)
    weights = LPIPS.weight_files()
    lpips = LPIPS(weights[0], weights[1]) if weights[2] is None else None
    notes = [weights[2]] if weights[2] else []

    rows: dict[str, dict] = {}
    per_material: dict[str, dict] = {}
    predictions = {}
    steps = config.refine_steps or (CaptureConfig().refine.steps if config.baselines else 0)
    plain, refined, details = _predict_all(model, truth, offsets, config.fov, config.light, steps, progress, "model",
                                           config.refine_normals, config.network_resolution)
    light_error = float(np.mean([d["light_error_deg"] for d in details]))
    seconds = float(sum(d["seconds"] for d in details))
    kept = "" if config.refine_normals else ", normals kept"
    unrefined_row, refined_row = "model (no refinement)", f"model + refinement ({steps} steps{kept})"
    if refined is None or config.baselines:
        predictions[unrefined_row] = plain
        rows[unrefined_row] = {"seconds": seconds, "light_error_deg": light_error}
    if refined is not None:
        predictions[refined_row] = refined
        rows[refined_row] = {"seconds": seconds + float(sum(d["refine_seconds"] for d in details)),
                             "light_error_deg": light_error}
    main_row = refined_row if config.refine_steps else unrefined_row
    for row, predicted in predictions.items():
        per_material[row] = score(predicted, truth, lights, views, convention, lpips, cross_check=row == main_row,
                                  stored=stored)
    if config.baselines:
        predictions["trivial"] = trivial_baseline(truth).expand_as(truth)
        per_material["trivial"] = score(predictions["trivial"], truth, lights, views, convention, lpips, stored=stored)
        rows["trivial"] = {"seconds": 0.0}
        if direct is not None:
            start = time.perf_counter()
            predictions["direct (no bases)"], _, _ = _predict_all(direct, truth, offsets, config.fov, "known", 0, progress,
                                                                  "direct", network_resolution=config.network_resolution)
            rows["direct (no bases)"] = {"seconds": time.perf_counter() - start}
            per_material["direct (no bases)"] = score(predictions["direct (no bases)"], truth, lights, views, convention,
                                                      lpips, stored=stored)
        else:
            notes.append("the direct per-pixel baseline needs --direct-model (a checkpoint trained with --no-bases)")
    for row, metrics in per_material.items():
        rows[row].update({key: float(value.mean()) for key, value in metrics.items()})

    main = rows[main_row]
    if any(repaired):
        notes.append(f"{sum(1 for r in repaired if r)} materials store {sum(repaired)} normals pointing into the "
                     "surface: repaired for rendering, compared as stored")
    summary = {"n_materials": len(truth), "skipped": skipped,
               "repaired_normal_pixels": int(sum(repaired)),
               "materials_with_repaired_normals": int(sum(1 for r in repaired if r)),
               "data": str(config.data), "format": config.format,
               "resolution": truth.shape[-1],
               "model": config.model or "shipped", "convention": convention, "light": config.light,
               "refine_steps": config.refine_steps, "refine_normals": config.refine_normals,
               "network_resolution": config.network_resolution, "row": main_row,
               **summary_scores(main), "render_lpips": main.get("render_lpips"), "render_rmse_torch_reference": main.get("render_rmse_torch"),
               "light_error_deg": main.get("light_error_deg"), "rows": rows, "notes": notes, "seed": config.seed}
    environment_scores = None
    if config.environment:
        environment_scores = _evaluate_environments(config, summary, predictions, truth, per_material, main_row,
                                                    convention, progress)
    if config.lighting:
        summary["lighting"] = lighting_accuracy(model, truth, config, out, progress)
    summary["seconds"] = time.perf_counter() - started
    write_evaluation(out, summary, names, per_material, predictions, truth, main_row, environment_scores)
    return summary


def _evaluate_environments(config: EvaluationConfig, summary: dict, predictions: dict, truth: torch.Tensor,
                           per_material: dict, main_row: str, convention: str, progress: bool):
    """Path-traced comparisons of every row under the environments, into ``summary``."""
    import dataclasses
    import time

    from .environment_eval import EnvironmentProtocol, environment_summary, evaluate_environments

    started = time.perf_counter()
    protocol = EnvironmentProtocol(environments=tuple(config.environment), seed=config.seed, floor_seed=config.seed + 1)
    overrides = {"spp": config.environment_spp, "resolution": config.environment_resolution}
    protocol = dataclasses.replace(protocol, **{k: v for k, v in overrides.items() if v})
    # predictions holds the trivial baseline (and the other baselines) under --baselines only.
    scores = evaluate_environments(dict(predictions), truth, protocol, convention, progress)
    result = environment_summary(scores, main_row, per_material[main_row]["render_rmse"].numpy(), protocol)
    summary["env"] = result["environments"]
    summary["env_protocol"] = {**result["protocol"], "seconds": time.perf_counter() - started}
    return scores


#: The paper's DeepBasis map RMSE (its 122 test scenes), for tables.
PAPER_DEEPBASIS = {"normal": 0.053, "diffuse": 0.031, "roughness": 0.162, "specular": 0.043}

#: Roughness groups of the lighting-accuracy table: upper bounds of the mean roughness.
ROUGHNESS_GROUPS = {"low": 0.33, "medium": 0.66, "high": 1.01}


def lighting_accuracy(model, truth: torch.Tensor, config: EvaluationConfig, out: Path, progress: bool,
                      offsets_per_material: int = 10, angles: int = 7) -> dict:
    """The search's angular error by roughness group, and map and re-rendering RMSE against the offset angle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from tqdm import tqdm

    from .capture import CaptureConfig, Capturer, Photo
    from .data.synth import sample_offsets

    convention = model.config.convention
    capturer = Capturer(model, CaptureConfig(fov=config.fov, network_resolution=config.network_resolution))
    errors = {group: [] for group in ROUGHNESS_GROUPS}
    for index in tqdm(range(len(truth)), desc="lighting search", unit="material", disable=not progress):
        roughness = float(truth[index, 6].mean())
        group = next(g for g, bound in ROUGHNESS_GROUPS.items() if roughness < bound)
        offsets = sample_offsets(offsets_per_material, torch.Generator().manual_seed(config.seed + 1000 + index), config.fov)
        for offset in offsets:
            photos, _ = flash_photos(truth[index:index + 1], offset.view(1, 2), config.fov, convention,
                                     model.config.plane_extent)
            found = capturer.search(Photo(photos[0], config.fov, "argument")).offset
            errors[group].append(light_error_deg(found, offset.tolist(), config.fov))
    table = {group: {"count": len(v), "mean_deg": float(np.mean(v)) if v else None,
                     "median_deg": float(np.median(v)) if v else None,
                     "p90_deg": float(np.percentile(v, 90)) if v else None} for group, v in errors.items()}
    everything = sum(errors.values(), [])
    table["all"] = {"count": len(everything), "mean_deg": float(np.mean(everything)),
                    "median_deg": float(np.median(everything)), "p90_deg": float(np.percentile(everything, 90))}

    generator = torch.Generator().manual_seed(config.seed + 7)
    directions = torch.rand(len(truth), generator=generator) * 2 * math.pi
    height = constants.camera_height(config.fov)
    lights, views = random_lights_and_views(RERENDER_COUNT, config.seed)
    robustness = []
    for angle in tqdm(np.linspace(0.0, constants.MAX_OFFSET_DEG, angles), desc="robustness", disable=not progress):
        radius = height * math.tan(math.radians(float(angle)))
        offsets = torch.stack([radius * torch.cos(directions), radius * torch.sin(directions)], -1)
        maps_rmse, render_rmse = [], []
        for index in range(len(truth)):
            photos, _ = flash_photos(truth[index:index + 1], offsets[index:index + 1], config.fov, convention,
                                               model.config.plane_extent)
            photo = Photo(photos[0], config.fov, "argument")
            found = capturer.search(photo).offset if config.light == "search" else offsets[index]
            predicted = capturer.predict(photo, found).maps.cpu()
            rmse = map_rmse(predicted, truth[index:index + 1])
            maps_rmse.append(float(sum(v[0] for v in rmse.values()) / 4))
            render_rmse.append(float(rerender_rmse(predicted, truth[index:index + 1], lights, views, convention)[0]))
        robustness.append({"angle_deg": float(angle), "maps_rmse_mean": float(np.mean(maps_rmse)),
                           "render_rmse": float(np.mean(render_rmse))})

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    groups = [g for g in ROUGHNESS_GROUPS if errors[g]]
    left.boxplot([errors[g] for g in groups], tick_labels=[f"{g}\n(n={len(errors[g])})" for g in groups])
    left.set_ylabel("angular error of the found flash [deg]")
    left.set_title("lighting search by roughness group")
    right.plot([r["angle_deg"] for r in robustness], [r["maps_rmse_mean"] for r in robustness], "o-", label="maps RMSE (mean of 4)")
    right.plot([r["angle_deg"] for r in robustness], [r["render_rmse"] for r in robustness], "s-", label="re-rendering RMSE")
    right.set_xlabel("flash offset [deg]")
    right.set_title(f"robustness to the offset (light {config.light})")
    right.legend()
    figure.tight_layout()
    from .reporting import _save_figure

    _save_figure(figure, out / "lighting.png")
    return {"search_error_by_roughness": table, "robustness": robustness, "figure": "lighting.png",
            "offsets_per_material": offsets_per_material}


def write_evaluation(out: Path, summary: dict, names: list[str], per_material: dict, predictions: dict,
                     truth: torch.Tensor, main_row: str, environment_scores=None) -> None:
    """summary.json, per_material.csv, table.md, bars.png and gallery.png in ``out`` (each written
    atomically); with environment scores also their columns in per_material.csv, their table in
    table.md, env_bars.png and env_gallery.png."""
    import csv
    import io
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .imageio import write_bytes, write_image
    from .reporting import _save_figure, map_tiles

    write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    if environment_scores is not None:
        per_material = {row: dict(values) for row, values in per_material.items()}
        for row, by_environment in environment_scores.rows.items():
            for environment, values in by_environment.items():
                for metric, numbers in values.items():
                    per_material.setdefault(row, {})[f"env_{_label(environment)}_{metric}"] = torch.from_numpy(numbers)
    metrics = sorted({key for values in per_material.values() for key in values})
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["material", "row"] + metrics)
    for row, values in per_material.items():
        for index, name in enumerate(names):
            writer.writerow([name, row] + [f"{float(values[m][index]):.6f}" if m in values else "" for m in metrics])
    write_bytes(out / "per_material.csv", buffer.getvalue().encode())

    columns = [("maps_normal", "normal"), ("maps_diffuse", "diffuse"), ("maps_roughness", "roughness"),
               ("maps_specular", "specular"), ("render_rmse", "render RMSE"), ("render_flip", "FLIP"),
               ("render_ssim", "SSIM"), ("render_lpips", "LPIPS"), ("seconds", "time [s]")]
    lines = ["| method | " + " | ".join(title for _, title in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for row, values in summary["rows"].items():
        cells = [f"{values[key]:.4f}" if isinstance(values.get(key), float) and key != "seconds"
                 else f"{values[key]:.1f}" if key == "seconds" and key in values else "-" for key, _ in columns]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines.append("| paper DeepBasis (122 scenes) | " + " | ".join(
        [f"{PAPER_DEEPBASIS[k]:.3f}" for k in ("normal", "diffuse", "roughness", "specular")] + ["-"] * 5) + " |")
    header = (f"Evaluation on {summary['n_materials']} materials of {summary['data']} ({summary['format']}), "
              f"light {summary['light']}, convention {summary['convention']}, seed {summary['seed']}. Map RMSE in the "
              "stored encoding; re-rendering under 30 random lights and views per material, clipped sRGB.\n\n")
    if "env" in summary:
        lines += ["", environment_table(summary)]
    write_bytes(out / "table.md", (header + "\n".join(lines) + "\n").encode())

    rows = list(summary["rows"])
    figure, axes = plt.subplots(1, 7, figsize=(23, 3.6))
    for axis, (key, title) in zip(axes, columns[:7]):
        values = [summary["rows"][r].get(key, float("nan")) for r in rows]
        axis.bar(range(len(rows)), values, color=[f"C{i}" for i in range(len(rows))])
        axis.set_xticks(range(len(rows)), [r.replace(" (", "\n(") for r in rows], fontsize=6, rotation=30)
        axis.set_title(title)
    figure.tight_layout()
    _save_figure(figure, out / "bars.png")

    if environment_scores is not None:
        _environment_figures(out, summary, environment_scores, main_row, names)
    order = np.argsort(per_material[main_row]["render_rmse"].numpy())
    picks = list(order[:4]) + list(order[-4:])
    strips = []
    for index in picks:
        tiles = map_tiles(truth[index]) + map_tiles(predictions[main_row][index])
        strips.append(np.concatenate(tiles, axis=1))
    write_image(out / "gallery.png", np.clip(np.concatenate(strips, axis=0), 0, 1))


def _label(environment: str) -> str:
    from .environment_eval import environment_label

    return environment_label(environment)


def environment_table(summary: dict) -> str:
    """The markdown table of the environment comparisons in ``summary['env']``."""
    protocol = summary["env_protocol"]
    lines = [f"Under environment light: path traced at {protocol['resolution']} px, {protocol['spp']} spp, views "
             f"{', '.join(f'{v:g}' for v in protocol['views_deg'])} deg from the normal, prediction and truth with "
             "the same seed; metrics over the pixels that see the sample (RMSE of clipped sRGB). The noise floor "
             "compares the truth with itself under another seed.", "",
             "| method | environment | RMSE | FLIP | SSIM |", "|---|---|---|---|---|"]
    for environment, entry in summary["env"].items():
        for row, values in entry["rows"].items():
            lines.append(f"| {row} | {environment} | {values['rmse']:.4f} | {values['flip']:.4f} | {values['ssim']:.4f} |")
        floor = entry["noise_floor"]
        lines.append(f"| noise floor | {environment} | {floor['rmse']:.4f} | {floor['flip']:.4f} | {floor['ssim']:.4f} |")
    rhos = {environment: entry.get("spearman_flash_vs_env") for environment, entry in summary["env"].items()}
    if any(value is not None for value in rhos.values()):
        lines += ["", "Spearman's rho between the materials' flash re-rendering RMSE and their RMSE under "
                  + "; ".join(f"{environment}: {value:.3f}" for environment, value in rhos.items() if value is not None)]
    return "\n".join(lines)


def _environment_figures(out: Path, summary: dict, scores, main_row: str, names: list[str]) -> None:
    """env_bars.png (RMSE, FLIP, SSIM per row and environment, the noise floor dashed) and
    env_gallery.png (truth | prediction | difference x 4 of the best and worst materials)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .imageio import write_image
    from .reporting import _save_figure

    environments = list(summary["env"])
    rows = list(next(iter(summary["env"].values()))["rows"])
    figure, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    width = 0.8 / len(rows)
    for axis, metric in zip(axes, ("rmse", "flip", "ssim")):
        for index, row in enumerate(rows):
            values = [summary["env"][e]["rows"][row][metric] for e in environments]
            axis.bar(np.arange(len(environments)) + index * width, values, width, label=row, color=f"C{index}")
        for position, environment in enumerate(environments):
            axis.hlines(summary["env"][environment]["noise_floor"][metric], position - 0.1, position + 0.9,
                        colors="k", linestyles="dashed", label="noise floor" if position == 0 else None)
        axis.set_xticks(np.arange(len(environments)) + 0.4 - width / 2, environments)
        axis.set_title(f"{metric.upper()} under environment light")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    _save_figure(figure, out / "env_bars.png")

    keys = list(scores.rows[main_row])
    mean_rmse = np.mean([scores.rows[main_row][e]["rmse"] for e in keys], axis=0)
    order = np.argsort(mean_rmse)
    picks = list(dict.fromkeys(list(order[:3]) + list(order[-3:])))  # best three, worst three, each once
    strips = []
    for index in picks:
        tiles = []
        for environment in keys:
            truth, predicted = scores.images["truth"][environment][index], scores.images[main_row][environment][index]
            tiles += [truth, predicted, np.clip(np.abs(truth - predicted) * 4, 0, 1)]
        strips.append(np.concatenate(tiles, axis=1))
    write_image(out / "env_gallery.png", np.concatenate(strips, axis=0))
