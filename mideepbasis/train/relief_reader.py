"""Training of the relief reader (``model.relief_reader``): procedural materials generated at
``ReliefTrainingConfig.size`` px, photographed as a phone takes them, and the reader fitted by
least squares to the true normals' slope above the capture network's band, on random crops.

Materials come from a stream of seeds of their own (``datasets.material_seed``) into a pool that
is refreshed one material at a time; a run is resumable (``--resume``) and stops cleanly after
``max_minutes``. Every ``validate_every`` steps it reads a held-out set (``VALIDATION_SEED``, the
detail benchmark's calibration seeds, photographed without noise as the benchmark photographs
them) and writes the curve as ``curve.png`` and ``log.jsonl``; the best weights so far are
``best.safetensors``.
"""

from __future__ import annotations

import json
import math
import random
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from .. import constants, geometry
from ..errors import InputError
from ..model.relief_reader import (VECTOR_CHANNELS, ReliefReader, ReliefReaderConfig, from_normal_unit, load_reader,
                                   read_relief, reader_inputs, save_reader)
from ..data.scenes import flashes_around
from ..evaluation.metrics import above_band
from ..model.symmetry import Symmetry

#: First seed of the validation materials: the detail benchmark's calibration set (``benchmarks/
#: detail.py --first-seed``), not its held-out figures' seeds.
VALIDATION_SEED = 500001000

#: Pixels at a crop's edges left out of the loss: the band there is the whole image's, but the
#: reader sees only the crop.
CROP_MARGIN = 16



@dataclass(frozen=True)
class ReliefTrainingConfig:
    """How a relief reader is trained."""

    out: str = "runs/relief_reader"
    """Folder of the run: checkpoint, best weights, log and curve."""
    steps: int = 40000
    """Steps in all (the learning rate follows a cosine over them)."""
    batch: int = 2
    """Crops per step."""
    crop: int = 256
    """Side of a crop [pixels]; a multiple of the reader's."""
    size: int = 1024
    """Side the materials are generated and photographed at [pixels]."""
    band: int = 128
    """Side of the capture network's band, taken out of inputs and target [pixels]."""
    pool: int = 24
    """Materials held at once."""
    refresh_every: int = 3
    """Steps between replacing the pool's oldest material by the stream's next."""
    learning_rate: float = 3e-4
    """Adam's rate at the start."""
    stream_seed: int = 7
    """Seed of the materials' stream."""
    validate_every: int = 500
    """Steps between validations; 0: none."""
    validation_count: int = 12
    """Validation materials (relief, from ``VALIDATION_SEED``)."""
    render_weight: float = 0.0
    """Weight of the re-rendering loss: the crop rendered with the true maps, its normals' band
    above the network's replaced by the reader's, against the true crop, in clipped sRGB, under
    ``render_lights`` flashes around the photo's (as a calibrated scene's other photos are taken;
    the flash renderer, ``render.render_flash``). Where a glossy lobe makes a misread relief cost
    more than none (glints, foil), it teaches the reader to read less. 0: the slope's error alone."""
    render_lights: int = 3
    """Flashes of the re-rendering loss per crop."""
    max_minutes: float = 0.0
    """Stop with a checkpoint after this long [min]; 0: run to ``steps``."""
    threads: int = 2
    """Torch's CPU threads."""
    width: int = 16
    """The reader's first level's channels (``ReliefReaderConfig.width``)."""
    init_from_unit: bool = False
    """Start from the shipped network's normal unit (``relief_reader.from_normal_unit``: its
    architecture, its inputs beside the reader's own, its tanh) rather than from random weights;
    ``width`` is then the unit's."""


@dataclass
class PoolMaterial:
    """One material of the training pool, its tensors float16 at ``ReliefTrainingConfig.size``."""

    inputs: torch.Tensor
    """(READER_CHANNELS, S, S) the reader's inputs of its photo."""
    target: torch.Tensor
    """(2, S, S) the true normals' x and y above the band."""
    maps: torch.Tensor | None
    """(10, S, S) the true maps, for the re-rendering loss; None without it (``render_weight`` 0:
    20 MB a material at 1024 px)."""
    fov: float
    """The photo's field of view [deg]."""


def photographed(seed: int, config: ReliefTrainingConfig) -> PoolMaterial:
    """One training material of ``seed``, photographed once as a phone takes it."""
    from ..data.procedural import generate
    from ..data.synth import (PHONE_PHOTOS, SynthesisConfig, flash_cone_falloff, sample_camera, sample_fov,
                              sample_offsets, simulate_photo)
    from ..render import render_flash

    synthesis = replace(SynthesisConfig(**PHONE_PHOTOS), convention=constants.DEFAULT_CONVENTION)
    generator = torch.Generator().manual_seed(seed % (2**63))
    maps = generate(seed, size=config.size).to_tensor()[None]
    fov = sample_fov(generator, synthesis)
    offset = sample_offsets(1, generator, fov, synthesis.max_offset_deg, synthesis.offset_sigma_divisor)
    light = geometry.light_positions(offset, fov)
    camera = sample_camera(1, generator, synthesis)
    with torch.no_grad():
        radiance = render_flash(maps, light.view(1, 1, 3), fov=fov, convention=synthesis.convention,
                                intensity=math.pi * float(light[0, 2]) ** 2)[:, 0]
    if synthesis.flash_cone[1] > 0:
        low, high = synthesis.flash_cone
        exponent = low + (high - low) * torch.rand(1, generator=generator)
        radiance = radiance * flash_cone_falloff(light, exponent, *radiance.shape[-2:])
    photo = simulate_photo(radiance, generator, synthesis, camera=camera)
    inputs = reader_inputs(photo, light, (config.band, config.band), fov, synthesis.convention,
                           unit_inputs=config.init_from_unit)
    target = above_band(maps[:, 0:2], config.band)
    return PoolMaterial(inputs[0].half(), target[0].half(), maps[0].half() if config.render_weight else None,
                        float(fov))


def flips_symmetry(flips: tuple[bool, bool, bool]) -> Symmetry:
    """The symmetry (``model.symmetry.Symmetry``) that mirrors the columns, then the rows, then
    transposes, as ``flips`` says. A mirror of the columns then a transposition is a transposition
    then a mirror of the rows (and rows then a transposition, one then columns)."""
    columns, rows, transpose = flips
    return Symmetry(transpose, rows if transpose else columns, columns if transpose else rows)


def mirror(image: torch.Tensor, vectors: tuple[tuple[int, int], ...], flips: tuple[bool, bool, bool]) -> torch.Tensor:
    """``image`` (B, C, H, W) mirrored: its columns, its rows, then transposed, as ``flips`` says,
    the x and y channels of each vector in ``vectors`` (adjacent channels; those within C) turned
    along (``flips_symmetry``); a new tensor."""
    symmetry = flips_symmetry(flips)
    image = symmetry.image(image).clone()
    for x, y in vectors:
        if y < image.shape[1]:
            image[:, x:y + 1] = symmetry.vectors(image[:, x:y + 1])
    return image


def mirror_points(points: torch.Tensor, flips: tuple[bool, bool, bool]) -> torch.Tensor:
    """Positions (..., 3) about the image's centre, mirrored as ``mirror`` mirrors an image."""
    return flips_symmetry(flips).vectors(points, dim=-1)


def mirrored(inputs: torch.Tensor, target: torch.Tensor, flips: tuple[bool, bool, bool]):
    """The crop's inputs and target (B, C, H, W) mirrored alike (``mirror``)."""
    return mirror(inputs, VECTOR_CHANNELS, flips), mirror(target, ((0, 1),), flips)


def framed_flashes(flashes: torch.Tensor, top: int, left: int, crop: int, size: int) -> torch.Tensor:
    """Flash positions (..., 3) over a ``size`` px image [its patch half-widths] as seen from the
    centre of its ``crop`` px crop at (``top``, ``left``): the crop rendered as a sample of its own,
    of half-width ``crop / size``, under them is that part of the image's render."""
    centre = torch.tensor([(2 * left + crop) / size - 1.0, 1.0 - (2 * top + crop) / size, 0.0])
    return flashes - centre


def rerender_error(maps: torch.Tensor, slope: torch.Tensor, target: torch.Tensor, lights: torch.Tensor,
                   extent: float, intensity: torch.Tensor) -> torch.Tensor:
    """The mean squared clipped-sRGB difference between the true crops ``maps`` (B, 10, h, w) and
    the same with their normals' x and y above the band ``target`` (B, 2, h, w) replaced by ``slope``,
    rendered under ``lights`` (B, K, 3) (the crop framed as a sample of half-width ``extent``, the
    lights relative to its centre) at ``intensity`` (B,) [W/sr]."""
    from ..imageio import linear_to_srgb
    from ..render import render_flash

    read = maps.clone()
    normal = torch.cat([maps[:, 0:2] - target + slope, maps[:, 2:3].clamp(min=1e-3)], dim=1)
    read[:, constants.NORMAL] = normal / normal.norm(dim=1, keepdim=True)
    errors = []
    for item in range(maps.shape[0]):  # one intensity per render
        pair = torch.cat([read[item:item + 1], maps[item:item + 1]])
        rendered = render_flash(pair, lights[item:item + 1].expand(2, -1, -1), intensity=float(intensity[item]),
                                extent=extent, convention=constants.DEFAULT_CONVENTION)
        shown = linear_to_srgb(rendered.clamp(1e-8, 1.0))
        errors.append((shown[0] - shown[1].detach()).square().mean())
    return torch.stack(errors).mean()


def validation_set(config: ReliefTrainingConfig) -> list[tuple[torch.Tensor, torch.Tensor, float, torch.Tensor]]:
    """The held-out materials as the detail benchmark photographs them: (photo, light, fov, target)."""
    from ..data.procedural import FAMILIES, generate
    from ..evaluation import evaluation_offsets, flash_photos

    fov = constants.DEFAULT_FOV_DEG
    offsets = evaluation_offsets(config.validation_count, 1, fov)
    families = sorted(FAMILIES)
    items = []
    for index in range(config.validation_count):
        maps = generate(VALIDATION_SEED + index, size=config.size, family=families[index % len(families)]).to_tensor()[None]
        photos, lights = flash_photos(maps, offsets[index:index + 1], fov)
        items.append((photos, lights, fov, above_band(maps[:, 0:2], config.band)))
    return items


def slope_figures(read, items) -> dict:
    """How a reading ``read(photo, light, fov)`` -> slope (1, 2, H, W) above the band compares with
    the truth's on ``items`` (``validation_set``), pooled over the materials: the mean squared
    error, the energy over the truth's and the correlation; the materials' mean correlation and the
    truth's mean energy."""
    read_energy = true_energy = cross = error = 0.0
    correlations = []
    for photo, light, fov, target in items:
        slope = read(photo, light, fov)
        a, b, c = float(slope.square().mean()), float(target.square().mean()), float((slope * target).mean())
        read_energy, true_energy, cross = read_energy + a, true_energy + b, cross + c
        error += float((slope - target).square().mean())
        correlations.append(c / math.sqrt(a * b + 1e-30))
    return {"mse": error / len(items), "energy": read_energy / true_energy,
            "correlation": cross / math.sqrt(read_energy * true_energy + 1e-30),
            "mean_correlation": sum(correlations) / len(correlations), "truth_energy": true_energy / len(items)}


def validate(reader: ReliefReader, items, band: int) -> dict:
    """``slope_figures`` of the reader (``read_relief``) on ``items``."""
    reader.eval()
    figures = slope_figures(lambda photo, light, fov: read_relief(reader, photo, light, fov, (band, band)), items)
    reader.train()
    return figures


def plot_curve(log: Path, output: Path) -> Path | None:
    """The training loss and the validation's correlation and energy, from ``log.jsonl``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..reporting import save_figure

    records = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    losses = [r for r in records if "loss" in r]
    checks = [r for r in records if "validation" in r]
    if not losses:
        return None
    figure, axes = plt.subplots(1, 2, figsize=(12, 4), squeeze=False)
    axes[0, 0].plot([r["step"] for r in losses], [r["loss"] for r in losses])
    axes[0, 0].set(xlabel="step", ylabel="mean squared slope error", yscale="log", title="training loss")
    for key in ("correlation", "energy"):
        axes[0, 1].plot([r["step"] for r in checks], [r["validation"][key] for r in checks], marker="o", label=key)
    axes[0, 1].set(xlabel="step", title="validation: fine slope against the truth's")
    axes[0, 1].legend()
    figure.tight_layout()
    return save_figure(figure, output)


def train_reader(config: ReliefTrainingConfig, resume: bool = False, progress: bool = True) -> Path:
    """Train (or go on training) a relief reader; returns the checkpoint's path."""
    from tqdm import tqdm

    from ..data.datasets import material_seed

    torch.set_num_threads(config.threads)
    out = Path(config.out)
    checkpoint = out / "checkpoint.safetensors"
    log = out / "log.jsonl"
    if resume:
        reader, document, tensors = load_reader(checkpoint)
        stored = document.get("training", {})
        config = replace(config, **{key: value for key, value in stored.items()
                                    if key in ("crop", "size", "band", "pool", "stream_seed", "width",
                                               "init_from_unit")})
        step, next_material = document["step"], document["next_material"]
        best = document.get("best_mse", math.inf)
    else:
        if checkpoint.exists():
            raise InputError(f"{out} already holds a run: pass --resume to continue it or choose another --out")
        if config.init_from_unit:
            from ..model.checkpoint import load_model

            reader = from_normal_unit(load_model(None))
        else:
            reader = ReliefReader(ReliefReaderConfig(width=config.width))
        tensors, step, next_material, best = {}, 0, 0, math.inf
    if (config.crop % reader.config.multiple or not 2 * CROP_MARGIN < config.crop <= config.size
            or config.crop * config.band % config.size):
        raise InputError(f"crop {config.crop} must be a multiple of {reader.config.multiple} above "
                         f"{2 * CROP_MARGIN}, at most size {config.size}, and hold a whole number of the band's "
                         f"pixels ({config.size // config.band} px each)")
    # The band of a crop: read_relief takes the whole photo's out of the reader's slope.
    crop_band = config.crop * config.band // config.size
    optimizer = torch.optim.Adam(reader.parameters(), lr=config.learning_rate)
    if tensors:
        state = optimizer.state_dict()
        for index, parameter in enumerate(reader.parameters()):
            if f"adam.{index}.exp_avg" in tensors:
                state["state"][index] = {"step": tensors[f"adam.{index}.step"].reshape(()),
                                         "exp_avg": tensors[f"adam.{index}.exp_avg"],
                                         "exp_avg_sq": tensors[f"adam.{index}.exp_avg_sq"]}
        optimizer.load_state_dict(state)
    reader.train()
    # The pool: the stream's materials up to the next one, rebuilt on resuming.
    first = max(0, next_material - config.pool)
    pool = [photographed(material_seed(config.stream_seed, index), config)
            for index in tqdm(range(first, next_material if resume else config.pool), desc="pool", disable=not progress)]
    if not resume:
        next_material = config.pool
    items = validation_set(config) if config.validate_every else []
    crops = random.Random(config.stream_seed * 1_000_003 + step)
    flash_draws = torch.Generator().manual_seed(config.stream_seed * 1_000_003 + step)
    started = time.monotonic()
    running = None

    def save(path: Path, extra: bool) -> None:
        adam = {}
        if extra:
            for index, parameter in enumerate(reader.parameters()):
                state = optimizer.state.get(parameter)
                if state:
                    adam.update({f"adam.{index}.step": torch.as_tensor(state["step"]).reshape(1).float(),
                                 f"adam.{index}.exp_avg": state["exp_avg"], f"adam.{index}.exp_avg_sq": state["exp_avg_sq"]})
        save_reader(path, reader, {"training": asdict(config), "step": step, "next_material": next_material,
                                   "best_mse": best}, adam)

    bar = tqdm(total=config.steps, initial=step, desc="relief reader", disable=not progress)
    while step < config.steps:
        rate = config.learning_rate * 0.5 * (1.0 + math.cos(math.pi * step / config.steps))
        for group in optimizer.param_groups:
            group["lr"] = rate
        inputs, targets, maps, lights, intensities = [], [], [], [], []
        for _ in range(config.batch):
            material = pool[crops.randrange(len(pool))]
            top, left = (crops.randrange(0, config.size - config.crop + 1, 8) for _ in range(2))
            window = (slice(None), slice(top, top + config.crop), slice(left, left + config.crop))
            flips = tuple(crops.random() < 0.5 for _ in range(3))
            crop_inputs, crop_target = mirrored(material.inputs[window][None].float(),
                                                material.target[window][None].float(), flips)
            inputs.append(crop_inputs)
            targets.append(crop_target)
            if config.render_weight:
                maps.append(mirror(material.maps[window][None].float(), ((0, 1),), flips))
                flashes = framed_flashes(flashes_around(config.render_lights, material.fov, flash_draws),
                                         top, left, config.crop, config.size)
                lights.append(mirror_points(flashes, flips)[None])
                intensities.append(math.pi * constants.camera_height(material.fov) ** 2)
        inputs, targets = torch.cat(inputs), torch.cat(targets)
        margin = (slice(None), slice(None), slice(CROP_MARGIN, -CROP_MARGIN), slice(CROP_MARGIN, -CROP_MARGIN))
        slope = above_band(reader(inputs), crop_band)
        loss = (slope - targets)[margin].square().mean()
        if config.render_weight:
            loss = loss + config.render_weight * rerender_error(
                torch.cat(maps)[margin], slope[margin], targets[margin], torch.cat(lights),
                (config.crop - 2 * CROP_MARGIN) / config.size, torch.tensor(intensities))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        value = float(loss.detach())
        running = value if running is None else 0.98 * running + 0.02 * value
        bar.update(1)
        bar.set_postfix(loss=f"{running:.5f}")
        if step % config.refresh_every == 0:
            pool.pop(0)
            pool.append(photographed(material_seed(config.stream_seed, next_material), config))
            next_material += 1
        records = []
        if step % 50 == 0:
            records.append({"step": step, "loss": running, "rate": rate})
        if config.validate_every and step % config.validate_every == 0:
            result = validate(reader, items, config.band)
            records.append({"step": step, "validation": result})
            if result["mse"] < best:
                best = result["mse"]
                save(out / "best.safetensors", extra=False)
            bar.write(f"step {step}: validation correlation {result['correlation']:+.3f}, "
                      f"energy {result['energy']:.3f}, mse {result['mse']:.5f}")
        if records:
            out.mkdir(parents=True, exist_ok=True)
            with log.open("a") as handle:
                handle.writelines(json.dumps(record) + "\n" for record in records)
        out_of_time = config.max_minutes and time.monotonic() - started > 60 * config.max_minutes
        if step % 250 == 0 or step == config.steps or out_of_time:
            save(checkpoint, extra=True)
            if log.exists():
                plot_curve(log, out / "curve.png")
        if out_of_time:
            break
    bar.close()
    return checkpoint
