"""The evaluation run (``mideepbasis evaluate``): the model's (and the baselines') predictions on a
dataset under the protocol (``protocol``), scored (``metrics``), written by ``report.write_evaluation``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import constants
from ..capturing.photo import native_or_pixels
from ..capturing.refine import RefineConfig
from ..configs import non_negative, positive_int, unit_share
from ..errors import InputError
from .metrics import LPIPS, light_error_deg, map_rmse, rerender_rmse, score, summary_scores, trivial_baseline
from .protocol import (RERENDER_COUNT, ROUGHNESS_GROUPS, evaluation_offsets, flash_photos, load_evaluation_materials,
                       random_lights_and_views, resize_maps)


#: The dataset layouts ``evaluate`` reads.
FORMATS = ("deschaintre5", "deschaintre4", "folder", "calibrated")


def input_photo(text: str) -> int | str:
    """``N`` or ``all``, for ``EvaluationConfig.input_photo``."""
    if text == "all":
        return text
    if not text.isdigit():
        raise ValueError(f"must be a photo number or 'all', got {text!r}")
    return int(text)


def symmetry_count(text: str) -> int:
    """1, 2, 4 or 8, for ``EvaluationConfig.symmetries``."""
    if text not in ("1", "2", "4", "8"):
        raise ValueError(f"must be 1, 2, 4 or 8, got {text!r}")
    return int(text)


def environments(text: str) -> tuple[str, ...]:
    """``studio,sunsky,FILE.exr``, checked (``environment.parse_environments``)."""
    from .environment import parse_environments

    return parse_environments(text)


def evaluation_resolution(text: str) -> int | str:
    """``evaluate --resolution``: ``native``, or a size [pixels] (a positive integer)."""
    value = native_or_pixels(text)
    return value if value == "native" else positive_int(value)


@dataclass(frozen=True)
class EvaluationConfig:
    """An evaluation run (``mideepbasis evaluate``)."""

    data: str
    """Dataset path [folder]."""

    format: str | None = field(default=None, metadata={"choices": FORMATS})
    """``deschaintre5``, ``deschaintre4`` (strips), ``folder`` (material folders or PBR maps) or
    ``calibrated`` (real photos at calibrated positions: the real-photo protocol); None:
    ``calibrated`` where the folder holds calibrated scenes, else ``deschaintre5``."""

    input_photo: int | str = field(default=0, metadata={"parse": input_photo, "metavar": "N|all"})
    """``calibrated``: the photo of each scene the material is captured from, or ``all``: each in turn."""

    out: str = "evaluation"
    """Output folder."""

    overwrite: bool = False
    """Replace an existing, non-empty output folder (only one the tool wrote: ``outputs.OutputFolder``)."""

    model: str | None = None
    """Checkpoint of the model (None: the shipped one)."""

    light: str = field(default="known", metadata={"choices": ("known", "search")})
    """``known``: the model is given the offset; ``search``: it finds it (``calibrated``: always searched)."""

    refine: RefineConfig = RefineConfig(steps=0)
    """The refinement of the model's row (the paper: 500 steps); 0 steps: none, and where a refined
    row is shown beside (``baselines``, ``calibrated``), capture's default."""

    network_resolution: int | None = None
    """Largest resolution the network runs at [pixels] (None: the model's training resolution; 0: no
    limit), as in ``capture``."""

    detail: bool = True
    """Give the maps the photo's detail above the network's resolution, as ``capture`` does
    (``CaptureConfig.detail``)."""

    relief_test: bool | None = None
    """Scale the detail step's finer relief by the photo's relief share, and give the diffuse the
    rest as albedo, as ``capture`` does from 4 times the network's resolution on
    (``CaptureConfig.relief_test``; None: capture's default)."""

    fine_relief: bool | None = None
    """Read the normals' detail above the network's resolution with its normal unit, as ``capture
    --fine-relief`` does (``CaptureConfig.fine_relief``; None: capture's default)."""

    fine_relief_strength: float | None = field(default=None, metadata={"parse": non_negative})
    """The factor of the relief ``fine_relief`` reads, as ``capture --fine-relief-strength``
    (``CaptureConfig.fine_relief_strength``; None: capture's default)."""

    relief_reader: str | None = field(default=None, metadata={"metavar": "FILE"})
    """With ``fine_relief``, a relief reader's weights that read the normals' detail in place of
    the normal unit, as ``capture --relief-reader`` (``CaptureConfig.relief_reader``)."""

    denoise_detail: bool | None = None
    """Denoise the photo's fine contrast before the detail step adds it, as ``capture`` does
    (``CaptureConfig.denoise_detail``; None: capture's default)."""

    colour_test: bool | None = None
    """Leave out of the normals' detail the contrast a change of hue explains, as ``capture`` does
    (``CaptureConfig.colour_test``; None: capture's default)."""

    keep_lobe_peak: bool | None = None
    """Narrow the roughness under the normals' detail so that the specular peak stays as fitted,
    as ``capture`` does (``CaptureConfig.keep_lobe_peak``; None: capture's default)."""

    grey_specular: bool | None = None
    """Make the specular grey but for each pixel's metallic share, as ``capture --grey-specular``
    does (``CaptureConfig.grey_specular``; None: capture's default)."""

    specular_floor: float | None = None
    """Lowest specular of the captured maps [linear reflectance], as ``capture --specular-floor``
    (``CaptureConfig.specular_floor``; None: capture's default, 0: none)."""

    normal_strength: float | None = None
    """The factor of the captured normals' slopes, as ``capture --normal-strength``
    (``CaptureConfig.normal_strength``; None: capture's default)."""

    lobe_variation: float | None = field(default=None, metadata={"parse": unit_share})
    """The share of the network's per-pixel roughness and specular variation kept, as ``capture
    --lobe-variation`` (``CaptureConfig.lobe_variation``; None: capture's default)."""

    symmetries: int | None = field(default=None, metadata={"parse": symmetry_count, "metavar": "1|2|4|8"})
    """Turns and mirrorings of each photo the model's prediction is averaged over (1, 2, 4 or 8;
    None: capture's default, ``CaptureConfig.symmetries``)."""

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

    limit: int | None = field(default=None, metadata={"parse": positive_int})
    """Evaluate only the first this many materials (quick runs)."""

    resolution: int | str | None = field(default=None, metadata={"parse": evaluation_resolution,
                                                                 "metavar": "N|native"})
    """Resample the materials to this size first [pixels] (None or ``native``: as stored);
    ``calibrated``: the capture's working resolution, at which the photos are compared (None:
    capture's; ``native``: each scene's photos at their own size, as ``capture --resolution
    native`` takes them)."""

    upsampled_from: int | None = field(default=None, metadata={"parse": positive_int})
    """``calibrated``: also a row captured at this working resolution [pixels] whose maps are
    upsampled to ``resolution`` and compared there: a sharper capture against plain upsampling."""

    environment: tuple[str, ...] = field(default=(), metadata={"parse": environments,
                                                                "metavar": "studio,sunsky[,FILE.exr]"})
    """Also compare path-traced renders under these environments (``studio``, ``sunsky``,
    ``uniform``, EXR/HDR files; ``evaluation.environment``); empty: not at all."""

    environment_spp: int | None = field(default=None, metadata={"parse": positive_int})
    """Samples per pixel of the environment renders (None: the protocol's)."""

    environment_resolution: int | None = field(default=None, metadata={"parse": positive_int})
    """Size of the environment renders [pixels] (None: the protocol's)."""

    def __post_init__(self):
        # Capture's checks across its options, before any work (``CaptureConfig.__post_init__``).
        evaluation_capture_config(self)

    @property
    def data_format(self) -> str:
        """``format``, or the one the data's folder shows where it is None."""
        if self.format is not None:
            return self.format
        from .real import is_calibrated

        return "calibrated" if is_calibrated(self.data) else "deschaintre5"


def shown_refinement(config: EvaluationConfig) -> RefineConfig:
    """The refinement of a refined row shown beside the unrefined one: the config's, or capture's
    default where the config gives no steps."""
    from dataclasses import replace

    from ..capturing import CaptureConfig

    return config.refine if config.refine.steps else replace(config.refine, steps=CaptureConfig().refine.steps)


#: The fields an evaluation shares with ``CaptureConfig``, None in the evaluation for capture's default.
SHARED_CAPTURE_FIELDS = ("symmetries", "relief_test", "fine_relief", "fine_relief_strength", "relief_reader",
                         "denoise_detail", "colour_test", "keep_lobe_peak", "grey_specular", "specular_floor",
                         "normal_strength", "lobe_variation")


def capture_options(config: EvaluationConfig | None) -> dict:
    """The ``SHARED_CAPTURE_FIELDS`` an evaluation sets (not None): {} for None."""
    if config is None:
        return {}
    return {name: getattr(config, name) for name in SHARED_CAPTURE_FIELDS if getattr(config, name) is not None}


def evaluation_capture_config(config: EvaluationConfig | None = None, **fields):
    """The capture settings of an evaluation: ``fields``, then what ``config`` shares with capture
    (``capture_options``), then capture's own defaults."""
    from ..capturing import CaptureConfig

    return CaptureConfig(**{**fields, **capture_options(config)})


def predict_all(model, truth: torch.Tensor, offsets: torch.Tensor, fov: float, light: str, refine: RefineConfig,
                progress: bool, label: str, config: EvaluationConfig | None = None
                ) -> tuple[torch.Tensor, torch.Tensor | None, list[dict]]:
    """Predictions (N, 10, H, W) without and (when ``refine.steps``) with refinement, from one search
    and one prediction per material, and per-material details (light error [deg], passes, seconds);
    ``config``: the evaluation whose network resolution, detail and capture options
    (``capture_options``) apply (None: capture's defaults)."""
    import time

    from tqdm import tqdm

    from ..capturing import Capturer, Photo

    convention = model.config.convention
    evaluated = {} if config is None else {"network_resolution": config.network_resolution, "detail": config.detail}
    capturer = Capturer(model, evaluation_capture_config(config, fov=fov, refine=refine, **evaluated))
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
        prediction = capturer.predict(photo, offset)
        plain.append(prediction.maps.cpu())
        seconds = time.perf_counter() - started
        refine_seconds = 0.0
        if refine.steps and prediction.output.weights is not None:
            started = time.perf_counter()
            refined, _ = capturer.refine(prediction, photo, offset)
            refined_maps.append(refined.maps.cpu())
            refine_seconds = time.perf_counter() - started
        details.append({"light_error_deg": light_error_deg(torch.as_tensor(offset).tolist(), offsets[index].tolist(), fov),
                        "search_passes": len(history), "seconds": seconds, "refine_seconds": refine_seconds})
    return torch.cat(plain), (torch.cat(refined_maps) if refined_maps else None), details


def run_evaluation(config: EvaluationConfig, progress: bool = True) -> dict:
    """Evaluate a model (and baselines) on a dataset; writes OUT and returns the summary."""
    import time

    from ..outputs import OutputFolder

    started = time.perf_counter()
    if config.upsampled_from is not None and config.data_format != "calibrated":
        raise InputError(f"{config.data}: --upsampled-from applies to calibrated scenes only (the real-photo protocol)")
    # Checked and locked before the work; written beside and swapped in whole at the end.
    with OutputFolder(config.out, overwrite=config.overwrite, inputs=[config.data], kind="evaluation") as folder:
        if config.data_format == "calibrated":
            from .real import run_real_evaluation

            return run_real_evaluation(config, folder.staging, progress)
        return _run_evaluation(config, folder.staging, started, progress)


def _run_evaluation(config: EvaluationConfig, out: Path, started: float, progress: bool) -> dict:
    """``run_evaluation`` writing into ``out``."""
    import time

    from ..capturing import CaptureConfig
    from ..model.checkpoint import load_model
    from .report import write_evaluation

    materials = load_evaluation_materials(config.data, config.data_format)
    names, truth, stored, skipped = materials.names, materials.maps, materials.stored, materials.skipped
    repaired = materials.repaired_pixels
    if config.limit:
        names, truth, stored, repaired = names[:config.limit], truth[:config.limit], stored[:config.limit], repaired[:config.limit]
    if isinstance(config.resolution, int) and config.resolution != truth.shape[-1]:
        truth = torch.stack([resize_maps(m, config.resolution) for m in truth])
        stored = torch.stack([resize_maps(m, config.resolution) for m in stored])
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
    refine = shown_refinement(config) if config.baselines else config.refine
    steps = refine.steps
    plain, refined, details = predict_all(model, truth, offsets, config.fov, config.light, refine, progress, "model",
                                          config)
    light_error = float(np.mean([d["light_error_deg"] for d in details]))
    seconds = float(sum(d["seconds"] for d in details))
    kept = "" if refine.normals else ", normals kept"
    unrefined_row, refined_row = "model (no refinement)", f"model + refinement ({steps} steps{kept})"
    if refined is None or config.baselines:
        predictions[unrefined_row] = plain
        rows[unrefined_row] = {"seconds": seconds, "light_error_deg": light_error}
    if refined is not None:
        predictions[refined_row] = refined
        rows[refined_row] = {"seconds": seconds + float(sum(d["refine_seconds"] for d in details)),
                             "light_error_deg": light_error}
    main_row = refined_row if config.refine.steps else unrefined_row
    for row, predicted in predictions.items():
        per_material[row] = score(predicted, truth, lights, views, convention, lpips, cross_check=row == main_row,
                                  stored=stored)
    if config.baselines:
        predictions["trivial"] = trivial_baseline(truth).expand_as(truth)
        per_material["trivial"] = score(predictions["trivial"], truth, lights, views, convention, lpips, stored=stored)
        rows["trivial"] = {"seconds": 0.0}
        if direct is not None:
            start = time.perf_counter()
            predictions["direct (no bases)"], _, _ = predict_all(
                direct, truth, offsets, config.fov, "known", RefineConfig(steps=0), progress, "direct", config)
            rows["direct (no bases)"] = {"seconds": time.perf_counter() - start}
            per_material["direct (no bases)"] = score(predictions["direct (no bases)"], truth, lights, views, convention,
                                                      lpips, stored=stored)
        else:
            notes.append("the direct per-pixel baseline needs --direct-model (a checkpoint trained with --no-network-use-bases)")
    for row, metrics in per_material.items():
        rows[row].update({key: float(value.mean()) for key, value in metrics.items()})

    main = rows[main_row]
    if any(repaired):
        notes.append(f"{sum(1 for r in repaired if r)} materials store {sum(repaired)} normals pointing into the "
                     "surface: repaired for rendering, compared as stored")
    summary = {"n_materials": len(truth), "skipped": skipped,
               "repaired_normal_pixels": int(sum(repaired)),
               "materials_with_repaired_normals": int(sum(1 for r in repaired if r)),
               "data": str(config.data), "format": config.data_format,
               "resolution": truth.shape[-1],
               "model": config.model or "shipped", "convention": convention, "light": config.light,
               "refine_steps": config.refine.steps, "refine_normals": config.refine.normals,
               "network_resolution": config.network_resolution,
               "symmetries": config.symmetries or CaptureConfig().symmetries, "row": main_row,
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

    from .environment import EnvironmentProtocol, environment_summary, evaluate_environments

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


def lighting_accuracy(model, truth: torch.Tensor, config: EvaluationConfig, out: Path, progress: bool,
                      offsets_per_material: int = 10, angles: int = 7) -> dict:
    """The search's angular error by roughness group, and map and re-rendering RMSE against the offset angle."""
    from tqdm import tqdm

    from ..capturing import Capturer, Photo
    from ..data.synth import sample_offsets

    convention = model.config.convention
    capturer = Capturer(model, evaluation_capture_config(config, fov=config.fov,
                                                         network_resolution=config.network_resolution))
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

    from .report import lighting_figure

    lighting_figure(errors, robustness, config.light, out / "lighting.png")
    return {"search_error_by_roughness": table, "robustness": robustness, "figure": "lighting.png",
            "offsets_per_material": offsets_per_material}
