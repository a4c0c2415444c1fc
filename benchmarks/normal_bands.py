"""Where the normal error lives: the shared test set's relief by scale, and a model's normals beside it.

    .venv/bin/python benchmarks/normal_bands.py [--model CKPT] [--symmetrise 8] [-o benchmarks/results/normal_bands.json]
    .venv/bin/python benchmarks/normal_bands.py --procedural 48 [--coarse-relief-tilt-deg 1 15] [--coarse-relief-probability P] [--relief-tilt-deg 2.4 45]

On the shared test set (the photos of ``evaluate``'s default protocol: seeded hand-held flashes,
light known, the network at its training resolution; only measured, never trained on):

- the oracle floors: the normal RMSE (stored encoding, as ``evaluate``) of the true normal map
  area-averaged to 32, 64 and 128 px and upsampled back (what a perfect predictor at that
  resolution would score), of the true mean normal of each material, and of the flat normal;
- the normal's x and y split into three bands by scale (coarse: features of more than 1/16 of
  the image; middle: 1/64 - 1/16; fine: the rest, at 256 px), and for each band the true
  energy (RMS), the model's energy, its error (RMS) and the correlation of prediction and truth.

``--symmetrise K``: the normal unit averaged over K of the 8 mirrored and turned copies of its
input (test-time augmentation; a moved photo under the moved flash is the photo moved), each
output moved back.

The shared set is also split by how its colours follow its relief (``slope_correlation``: the
log luminance's gradient against the height's): darker is deeper (above 0.2), brighter is deeper
(below -0.2), neither; for each group, the model's normal RMSE beside the flat normal's.

``--relief-cue N [--run-config runs/RUN/config.json]``: how much the model reads relief from the
colours: its normal RMSE on N training materials (held-out seeds 3e9 on, the run's generator or
the default one) as drawn, and the same materials with their relief inverted under the same
colours (``relief_inversion_probability`` 1), beside the flat normal. A model that reads the
shading scores the two alike; one that learned "darker is deeper" loses on the inverted ones.

``--procedural N``: the same bands of the true normals of N training materials (seeds 5000 on,
128 px, shown at 256 px), with the generator's defaults or its ``coarse_relief_tilt_deg``, beside
the shared set's; no model. Writes benchmarks/results/normal_bands.json (or
normal_bands_procedural.json).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
import torch.nn.functional as F
from common import RESULTS, SHARED_TEST, run_generator_settings, slope_correlation, write_report

from mideepbasis import constants
from mideepbasis.capture import CaptureConfig, Capturer, Photo
from mideepbasis.evaluation.protocol import evaluation_offsets, flash_photos, load_evaluation_materials
from mideepbasis.model.checkpoint import load_model

#: The bands' limits: area-averaged sizes [pixels] of a 256 px map.
COARSE, MIDDLE = 16, 64


def resampled(image: torch.Tensor, size: int) -> torch.Tensor:
    """``image`` (B, C, H, W) area-averaged to size x size and bilinearly upsampled back."""
    small = F.interpolate(image, size=(size, size), mode="area")
    return F.interpolate(small, size=image.shape[-2:], mode="bilinear", align_corners=False)


def flat_normals(like: torch.Tensor) -> torch.Tensor:
    """Flat normals (+z) of the shape of the normals ``like`` (B, 3, H, W): the baseline."""
    flat = torch.zeros_like(like)
    flat[:, 2] = 1.0
    return flat


def stored_rmse(normals: torch.Tensor, truth: torch.Tensor) -> float:
    """Mean per-material RMSE of unit normals (B, 3, H, W) in the stored encoding (n + 1) / 2."""
    return float((((normals - truth) / 2) ** 2).mean(dim=(1, 2, 3)).sqrt().mean())


def bands(xy: torch.Tensor) -> dict[str, torch.Tensor]:
    coarse = resampled(xy, COARSE)
    middle = resampled(xy, MIDDLE)
    return {"coarse": coarse, "middle": middle - coarse, "fine": xy - middle}


def rms(x: torch.Tensor) -> float:
    return float((x**2).mean(dim=(1, 2, 3)).sqrt().mean())


def procedural_bands(args) -> None:
    """The relief of training materials by scale, beside the shared set's."""
    from mideepbasis.data.procedural import GeneratorConfig, generate

    tilt = tuple(args.coarse_relief_tilt_deg) if args.coarse_relief_tilt_deg else None
    family = {"relief_tilt_deg": tuple(args.relief_tilt_deg)} if args.relief_tilt_deg else {}
    config = GeneratorConfig(size=128, coarse_relief_tilt_deg=tilt,
                             coarse_relief_probability=args.coarse_relief_probability, **family)
    maps = torch.stack([generate(5000 + i, config=config).to_tensor() for i in range(args.procedural)])
    sets = {"procedural": F.interpolate(maps[:, :2], size=(256, 256), mode="bilinear", align_corners=False),
            "shared": load_evaluation_materials(SHARED_TEST, "deschaintre5").stored[:, :2]}
    report = {"coarse_relief_tilt_deg": tilt, "coarse_relief_probability": args.coarse_relief_probability,
              "relief_tilt_deg": config.relief_tilt_deg,
              "materials": args.procedural, "bands": {}}
    for name, xy in sets.items():
        report["bands"][name] = {band: rms(values) for band, values in bands(xy).items()}
        print(f"{name:>10}: " + ", ".join(f"{band} {value:.4f}" for band, value in report["bands"][name].items()))
    write_report(args.output.with_name(args.output.stem + "_procedural.json"), "normal_bands", report)


def relief_cue(args) -> None:
    """The model's normal RMSE on training materials as drawn and with their relief inverted."""
    import dataclasses

    from mideepbasis.data.procedural import GeneratorConfig, generate
    from mideepbasis.data.synth import SynthesisConfig, synthesize

    settings = run_generator_settings(args.run_config) if args.run_config else {}
    config = GeneratorConfig(**{**settings, "size": 128})
    model = load_model(args.model)
    model.eval()
    synthesis = SynthesisConfig(convention=model.config.convention)
    report = {"model": args.model or "shipped", "materials": args.relief_cue,
              "run_config": str(args.run_config) if args.run_config else None, "normal_rmse": {}}
    for name, chance in (("as drawn", 0.0), ("relief inverted", 1.0)):
        drawn = dataclasses.replace(config, relief_inversion_probability=chance)
        maps = torch.stack([generate(3 * 10**9 + i, config=drawn).to_tensor() for i in range(args.relief_cue)])
        batch = synthesize(maps, torch.Generator().manual_seed(778), synthesis)
        with torch.no_grad():
            predicted = torch.cat([model(batch.inputs[start:start + 8], batch.lights[start:start + 8],
                                         fov=synthesis.fov).maps[:, constants.NORMAL].float()
                                   for start in range(0, len(maps), 8)])
        truth = maps[:, constants.NORMAL]
        report["normal_rmse"][name] = {"model": stored_rmse(predicted, truth), "flat": stored_rmse(flat_normals(truth), truth)}
        print(f"{name:>16}: model {report['normal_rmse'][name]['model']:.4f}, flat {report['normal_rmse'][name]['flat']:.4f}")
    write_report(args.output.with_name(args.output.stem + "_relief_cue.json"), "normal_bands", report)


def by_colour_cue(predicted: torch.Tensor, truth: torch.Tensor, diffuse: torch.Tensor) -> dict:
    """Normal RMSE of the model and of the flat normal on the materials grouped by ``slope_correlation``."""
    flat = flat_normals(truth)
    cue = torch.tensor([slope_correlation(n.numpy(), d.mean(0).numpy()) for n, d in zip(truth, diffuse)])
    groups = {"darker is deeper (> 0.2)": cue > 0.2, "neither": cue.abs() <= 0.2,
              "brighter is deeper (< -0.2)": cue < -0.2}
    return {name: {"materials": int(chosen.sum()), "model": stored_rmse(predicted[chosen], truth[chosen]),
                   "flat": stored_rmse(flat[chosen], truth[chosen])}
            for name, chosen in groups.items() if chosen.any()}


class DihedralAverage(torch.nn.Module):
    """A normal unit run on ``moves`` mirrored and turned copies of its relief inputs, its outputs
    moved back and averaged (test-time augmentation; ``--symmetrise``): moves 1 is the unit itself."""

    def __init__(self, unit: torch.nn.Module, moves: int):
        super().__init__()
        self.unit, self.moves = unit, [(mirror, turns) for mirror in (False, True) for turns in range(4)][:moves]

    def forward(self, relief: torch.Tensor) -> torch.Tensor:
        from mideepbasis.model.inputs import RELIEF_DIRECTION_CHANNEL
        from mideepbasis.model.symmetry import dihedral

        total = 0.0
        for mirror, turns in self.moves:
            slope = self.unit(dihedral(relief, RELIEF_DIRECTION_CHANNEL, mirror, turns))
            total = total + dihedral(dihedral(slope, 0, False, -turns), 0, mirror, 0)
        return total / len(self.moves)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "normal_bands.json")
    parser.add_argument("--procedural", type=int, default=0, help="only the bands of this many training materials")
    parser.add_argument("--coarse-relief-tilt-deg", type=float, nargs=2, default=None,
                        help="the generator's coarse_relief_tilt_deg for --procedural")
    parser.add_argument("--relief-tilt-deg", type=float, nargs=2, default=None,
                        help="the generator's relief_tilt_deg (the families' own relief) for --procedural")
    parser.add_argument("--coarse-relief-probability", type=float, default=0.7,
                        help="the generator's coarse_relief_probability for --procedural")
    parser.add_argument("--relief-cue", type=int, default=0,
                        help="only the model on this many training materials, as drawn and with their relief inverted")
    parser.add_argument("--run-config", type=Path, default=None,
                        help="draw the --relief-cue materials as this training run did (its config.json)")
    parser.add_argument("--symmetrise", type=int, default=1, choices=range(1, 9),
                        help="average the normal unit over this many mirrored and turned copies of its input")
    args = parser.parse_args()
    if not SHARED_TEST.is_dir():
        raise SystemExit(f"{SHARED_TEST} is absent")
    if args.procedural:
        procedural_bands(args)
        return
    if args.relief_cue:
        relief_cue(args)
        return

    materials = load_evaluation_materials(SHARED_TEST, "deschaintre5")
    truth = materials.stored[:, constants.NORMAL]  # as evaluate compares: the normals as stored
    flat = flat_normals(truth)
    mean_normal = F.normalize(truth.mean(dim=(2, 3), keepdim=True).expand_as(truth), dim=1)
    floors = {f"oracle_{size}px": stored_rmse(F.normalize(resampled(truth, size), dim=1), truth) for size in (32, 64, 128)}
    floors.update({"oracle_mean_normal": stored_rmse(mean_normal, truth), "flat": stored_rmse(flat, truth)})

    model = load_model(args.model)
    if args.symmetrise > 1:
        model.normal_unit = DihedralAverage(model.normal_unit, args.symmetrise)
        if hasattr(model, "normal_booster"):  # the slopes add up: each averaged is their sum averaged
            model.normal_booster = DihedralAverage(model.normal_booster, args.symmetrise)
    fov = constants.DEFAULT_FOV_DEG
    capturer = Capturer(model, CaptureConfig(fov=fov))
    offsets = evaluation_offsets(len(truth), 0, fov)
    predicted, seconds = [], []
    with torch.no_grad():
        for index in range(len(truth)):
            photos, _ = flash_photos(materials.maps[index:index + 1], offsets[index:index + 1], fov,
                                     model.config.convention, model.config.plane_extent)
            start = time.perf_counter()
            prediction = capturer.predict(Photo(photos[0], fov, "argument"), offsets[index])
            seconds.append(time.perf_counter() - start)
            predicted.append(prediction.maps[:, constants.NORMAL])
    predicted = torch.cat(predicted)
    report = {"model": args.model or "shipped", "symmetrise": args.symmetrise,
              "prediction_seconds_median": statistics.median(seconds), "floors": floors, "model_rmse": stored_rmse(predicted, truth), "bands": {}}
    for name, true_band in bands(truth[:, :2]).items():
        predicted_band = bands(predicted[:, :2])[name]
        correlation = float((predicted_band * true_band).sum() / (predicted_band.norm() * true_band.norm()))
        report["bands"][name] = {"truth_rms": rms(true_band), "model_rms": rms(predicted_band),
                                 "error_rms": rms(predicted_band - true_band), "correlation": correlation}
    report["by_colour_cue"] = by_colour_cue(predicted, truth, materials.stored[:, constants.DIFFUSE])
    for name, value in floors.items():
        print(f"{name}: {value:.4f}")
    print(f"model: {report['model_rmse']:.4f} (prediction {1000 * report['prediction_seconds_median']:.0f} ms, median)")
    for name, row in report["bands"].items():
        print(f"{name:>6}: truth {row['truth_rms']:.4f}, model {row['model_rms']:.4f}, error {row['error_rms']:.4f}, "
              f"correlation {row['correlation']:.3f}")
    for name, row in report["by_colour_cue"].items():
        print(f"{name}: {row['materials']} materials, model {row['model']:.4f}, flat {row['flat']:.4f}")
    write_report(args.output, "normal_bands", report)


if __name__ == "__main__":
    main()
