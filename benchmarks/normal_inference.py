"""Ways to run a trained normal unit at inference, on held-out procedural materials and the shared 84.

    .venv/bin/python benchmarks/normal_inference.py [--model CKPT] [--procedural 48] [--gains 1 1.2 1.4 1.7]
    .venv/bin/python benchmarks/normal_inference.py --procedural 96 --run-config runs/normal_booster/config.json \
        --gains 1 1.2 --symmetries --symmetric-gains --octaves 0,0 0.25,0 0.5,0 0.75,0 1,0 0,0.25 0.25,0.25 \
        0.5,0.25 0.75,0.25 0.5,0.5 -o benchmarks/results/normal_octaves.json
    .venv/bin/python benchmarks/normal_inference.py --procedural 96 --run-config runs/normal_booster/config.json \
        --scaled --gains 1 --symmetries --symmetric-gains --octaves 0.25,0 0.5,0 0.75,0 0,0.25 0.25,0.25 \
        -o benchmarks/results/normal_scaled.json

Two questions, each answered first on procedural materials (held-out seeds 3e9 + 900 on, the
generator of ``--run-config``, 256 px, seeded hand-held offsets) and then on the shared test set
(``evaluate``'s default protocol: its seeded offsets, light known, the network at its training
resolution). Only measured, never trained on. Normal RMSE in the stored encoding.

- **Gain**: the unit's output before its tanh multiplied by G. An MSE-trained unit that had
  converged would score best at G = 1 on its own distribution; a best G above 1 says its relief
  comes out too weak.
- **Resolution**: the unit run on the photo at its own 256 px (its slope added to the upsampled
  deviations) instead of at the network's 128 px (its slope upsampled with them), and the mean of
  the two slopes.
- **Octaves** (``--octaves A,B``): the slope at the network's 128 px plus A times the unit's
  slope on the photo area-averaged to 64 px and B times that at 32 px, each upsampled
  (``NetworkConfig.normal_unit_octaves`` (1, A, B)).

Every variant runs the unit as it says, whatever octaves the model's configuration names.
``--scaled`` adds the slope to each basis's normal made unit (``NetworkConfig.normal_slope_scaled``)
in every variant, instead of to the sum as it is.

Writes benchmarks/results/normal_inference.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
import torch.nn.functional as F
from common import RESULTS, SHARED_TEST, run_generator_settings, write_report
from normal_bands import flat_normals, stored_rmse

from mideepbasis import constants
from mideepbasis.capture.pipeline import network_resolution_limit
from mideepbasis.resampling import downsample
from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.evaluation.protocol import evaluation_offsets, flash_photos, load_evaluation_materials
from mideepbasis.model.checkpoint import load_model
from mideepbasis.model.inputs import encode_inputs, relief_inputs
from mideepbasis.model.network import DeepBasisOutput, add_slope, upsample_bilinear
from mideepbasis.model.symmetry import symmetrised_field


def variant_normals(model, photo: torch.Tensor, light: torch.Tensor, fov: float, variants: dict,
                    scaled: bool = False) -> dict:
    """The predicted unit normals (1, 3, H, W) of a photo (1, 3, H, W) at the photo's size for each
    variant (gain, where, symmetries): the unit's raw output times the gain, its slope from the
    network's resolution (``network``), the photo's (``photo``) or their mean (``mean``), or a
    tuple of weights by octave from the network's resolution down, averaged over that many
    symmetries of the square (``model.symmetry``). The rest of the network runs once."""
    config = model.config
    size = photo.shape[-1]
    limit = network_resolution_limit(model)  # as capture runs the network: at its training resolution
    small = downsample(photo, limit) if limit and size > limit else photo
    inputs = encode_inputs(small, light, fov, config.convention, config.plane_extent, config.extra_inputs)
    stage = model.basis_stage(inputs, light, fov)
    deviations = model.local_deviations(stage.local_inputs, stage.weights, stage.global_bases)
    weights = upsample_bilinear(stage.weights, size, size)
    upsampled = torch.stack([upsample_bilinear(d, size, size) for d in deviations.unbind(1)], dim=1)
    images = {"network": stage.photo.float(), "photo": photo.clamp(0, 1)}

    def unit_slope(images: torch.Tensor, lights: torch.Tensor, gain: float = 1.0) -> torch.Tensor:
        relief = relief_inputs(images, lights, fov, config.convention, config.plane_extent)
        return torch.tanh(gain * model.normal_raw(relief))

    def slope(gain: float, where, symmetries: int) -> torch.Tensor:
        if where == "mean":
            return 0.5 * (slope(gain, "network", symmetries) + slope(gain, "photo", symmetries))
        if isinstance(where, tuple):  # octaves of the network's resolution
            network = images["network"]
            return sum(weight * upsample_bilinear(symmetrised_field(lambda image, lights: unit_slope(image, lights, gain),
                                                                    F.avg_pool2d(network, 2**octave), light, symmetries),
                                                  size, size)
                       for octave, weight in enumerate(where) if weight)
        field = symmetrised_field(lambda image, lights: unit_slope(image, lights, gain), images[where], light,
                                  symmetries)
        return upsample_bilinear(field, size, size)

    normals = {}
    for name, (gain, where, symmetries) in variants.items():
        output = DeepBasisOutput.from_bases(weights, stage.global_bases,
                                            add_slope(stage.global_bases, upsampled, slope(gain, where, symmetries),
                                                      scaled), keep_bases=False)
        normals[name] = output.maps[:, constants.NORMAL]
    return normals


def score(model, maps: torch.Tensor, offsets: torch.Tensor, fov: float, variants: dict, scaled: bool = False) -> dict:
    truth = maps[:, constants.NORMAL]
    predicted = {name: [] for name in variants}
    with torch.no_grad():
        for index in range(len(maps)):
            photo, light = flash_photos(maps[index:index + 1], offsets[index:index + 1], fov, model.config.convention,
                                        model.config.plane_extent)
            for name, normals in variant_normals(model, photo, light, fov, variants, scaled).items():
                predicted[name].append(normals)
    report = {"flat": stored_rmse(flat_normals(truth), truth)}
    report.update({name: stored_rmse(torch.cat(values), truth) for name, values in predicted.items()})
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--procedural", type=int, default=48, help="held-out procedural materials")
    parser.add_argument("--run-config", type=Path, default=Path("runs/local_keep/config.json"),
                        help="draw them as this training run did (its config.json; default: the generator's defaults if absent)")
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0, 1.2, 1.4, 1.7])
    parser.add_argument("--symmetries", type=int, nargs="*", default=[2, 4, 8],
                        help="the unit's slope averaged over this many symmetries of the square (model.symmetry)")
    parser.add_argument("--symmetric-gains", type=float, nargs="*", default=[1.2, 1.4, 1.7],
                        help="gains tried on the slope averaged over all 8 symmetries")
    parser.add_argument("--octaves", nargs="*", default=[],
                        help="A,B: the slope at 128 px plus A x the slope at 64 px plus B x the slope at 32 px")
    parser.add_argument("--scaled", action="store_true",
                        help="add the slope to each basis's normal made unit (NetworkConfig.normal_slope_scaled)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "normal_inference.json")
    args = parser.parse_args()
    if not SHARED_TEST.is_dir():
        raise SystemExit(f"{SHARED_TEST} is absent")
    model = load_model(args.model)
    model.eval()
    fov = constants.DEFAULT_FOV_DEG
    variants = {f"gain {gain:g}": (gain, "network", 1) for gain in args.gains}
    variants.update({"unit at 256 px": (1.0, "photo", 1), "mean of 128 and 256 px": (1.0, "mean", 1)})
    variants.update({f"mean over {count} symmetries": (1.0, "network", count) for count in args.symmetries})
    variants.update({f"gain {gain:g}, mean over 8 symmetries": (gain, "network", 8) for gain in args.symmetric_gains})
    for text in args.octaves:
        coarse = tuple(float(v) for v in text.split(","))
        variants[f"octaves 1, {', '.join(f'{v:g}' for v in coarse)}"] = (1.0, (1.0, *coarse), 1)

    settings = run_generator_settings(args.run_config) if args.run_config.is_file() else {}
    generator = GeneratorConfig(**{**settings, "size": 256})
    procedural = torch.stack([generate(3 * 10**9 + 900 + i, config=generator).to_tensor() for i in range(args.procedural)])
    shared = load_evaluation_materials(SHARED_TEST, "deschaintre5").maps
    report = {"model": args.model or "shipped", "run_config": str(args.run_config) if settings else None,
              "procedural": score(model, procedural, evaluation_offsets(len(procedural), 11, fov), fov, variants, args.scaled),
              "shared": score(model, shared, evaluation_offsets(len(shared), 0, fov), fov, variants, args.scaled),
              "scaled": args.scaled}
    for name in ("flat", *variants):
        print(f"{name:>24}: procedural {report['procedural'][name]:.4f}, shared {report['shared'][name]:.4f}")
    write_report(args.output, "normal_inference", report)


if __name__ == "__main__":
    main()
