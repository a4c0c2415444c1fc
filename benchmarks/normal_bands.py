"""Where the normal error lives: the shared test set's relief by scale, and a model's normals beside it.

    .venv/bin/python benchmarks/normal_bands.py [--model CKPT] [--symmetrise 8] [-o benchmarks/results/normal_bands.json]
    .venv/bin/python benchmarks/normal_bands.py --procedural 48 [--coarse-relief-tilt-deg 1 15] [--coarse-relief-probability P]

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
from common import RESULTS, SHARED_TEST, write_report

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
    config = GeneratorConfig(size=128, coarse_relief_tilt_deg=tilt,
                             coarse_relief_probability=args.coarse_relief_probability)
    maps = torch.stack([generate(5000 + i, config=config).to_tensor() for i in range(args.procedural)])
    sets = {"procedural": F.interpolate(maps[:, :2], size=(256, 256), mode="bilinear", align_corners=False),
            "shared": load_evaluation_materials(SHARED_TEST, "deschaintre5").stored[:, :2]}
    report = {"coarse_relief_tilt_deg": tilt, "coarse_relief_probability": args.coarse_relief_probability,
              "materials": args.procedural, "bands": {}}
    for name, xy in sets.items():
        report["bands"][name] = {band: rms(values) for band, values in bands(xy).items()}
        print(f"{name:>10}: " + ", ".join(f"{band} {value:.4f}" for band, value in report["bands"][name].items()))
    write_report(args.output.with_name(args.output.stem + "_procedural.json"), "normal_bands", report)


class DihedralAverage(torch.nn.Module):
    """A normal unit run on ``moves`` mirrored and turned copies of its relief inputs, its outputs
    moved back and averaged (test-time augmentation; ``--symmetrise``): moves 1 is the unit itself."""

    def __init__(self, unit: torch.nn.Module, moves: int):
        super().__init__()
        self.unit, self.moves = unit, [(mirror, turns) for mirror in (False, True) for turns in range(4)][:moves]

    def forward(self, relief: torch.Tensor) -> torch.Tensor:
        from mideepbasis.model.inputs import RELIEF_DIRECTION_CHANNEL
        from mideepbasis.train import dihedral

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
    parser.add_argument("--coarse-relief-probability", type=float, default=0.7,
                        help="the generator's coarse_relief_probability for --procedural")
    parser.add_argument("--symmetrise", type=int, default=1, choices=range(1, 9),
                        help="average the normal unit over this many mirrored and turned copies of its input")
    args = parser.parse_args()
    if not SHARED_TEST.is_dir():
        raise SystemExit(f"{SHARED_TEST} is absent")
    if args.procedural:
        procedural_bands(args)
        return

    materials = load_evaluation_materials(SHARED_TEST, "deschaintre5")
    truth = materials.stored[:, constants.NORMAL]  # as evaluate compares: the normals as stored
    flat = torch.zeros_like(truth)
    flat[:, 2] = 1.0
    mean_normal = F.normalize(truth.mean(dim=(2, 3), keepdim=True).expand_as(truth), dim=1)
    floors = {f"oracle_{size}px": stored_rmse(F.normalize(resampled(truth, size), dim=1), truth) for size in (32, 64, 128)}
    floors.update({"oracle_mean_normal": stored_rmse(mean_normal, truth), "flat": stored_rmse(flat, truth)})

    model = load_model(args.model)
    if args.symmetrise > 1:
        model.normal_unit = DihedralAverage(model.normal_unit, args.symmetrise)
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
    for name, value in floors.items():
        print(f"{name}: {value:.4f}")
    print(f"model: {report['model_rmse']:.4f} (prediction {1000 * report['prediction_seconds_median']:.0f} ms, median)")
    for name, row in report["bands"].items():
        print(f"{name:>6}: truth {row['truth_rms']:.4f}, model {row['model_rms']:.4f}, error {row['error_rms']:.4f}, "
              f"correlation {row['correlation']:.3f}")
    write_report(args.output, "normal_bands", report)


if __name__ == "__main__":
    main()
