"""How the network composes the normal unit's slope with the bases, against how the pool trains it.

    .venv/bin/python benchmarks/normal_composition.py [--model CKPT] [--materials 48] \
        [--run-config runs/normal_octaves/config.json] [-o benchmarks/results/normal_composition.json]

Training materials of held-out seeds (the generator of ``--run-config``, or its defaults where
that file is absent) photographed as the normal pool photographs them (``synthesize`` with the
training synthesis, seeded), and for each: the normal RMSE (unit vectors, as ``train``'s
validation) and mean tilt [deg] of

- the whole network's normals;
- its bases without the normal unit (``with_normal_unit`` False);
- the unit's slope over a flat unit normal (``train.normals_over_flat``: what the pool trains);

beside the flat normal and the truth, and the blending-weighted mean length (and z) of each
basis's normal sum, global plus deviation, to which the network adds the slope before making it
unit (``NetworkConfig.normal_slope_scaled`` False): a length above 1 weakens the unit's relief by
as much. Only measured, never trained on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, run_generator_settings, write_report

from mideepbasis import constants
from mideepbasis.data.procedural import GeneratorConfig
from mideepbasis.data.synth import SynthesisConfig, synthesize
from mideepbasis.model.checkpoint import load_model
from mideepbasis.train import TrainingMaterials, mean_tilt_deg, normals_over_flat

#: Seed of the held-out materials' sources (training runs use their own seeds).
HELD_OUT_SEED = 999


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--materials", type=int, default=48)
    parser.add_argument("--run-config", type=Path, default=Path("runs/normal_octaves/config.json"),
                        help="draw them as this training run did (its config.json; default: the generator's defaults if absent)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "normal_composition.json")
    args = parser.parse_args()

    model = load_model(args.model)
    model.eval()
    settings = run_generator_settings(args.run_config) if args.run_config.is_file() else {}
    materials = TrainingMaterials(("procedural",), 128, HELD_OUT_SEED, GeneratorConfig(**{**settings, "size": 128}))
    maps = torch.stack([materials[i] for i in range(args.materials)])
    synthesis = SynthesisConfig()
    batch = synthesize(maps, torch.Generator().manual_seed(5), synthesis, model.config.extra_inputs)
    fov, truth = synthesis.fov, batch.maps[:, constants.NORMAL]

    def row(normals: torch.Tensor) -> dict:
        return {"rmse": float(((normals - truth) ** 2).mean().sqrt()),
                "mean_tilt_deg": mean_tilt_deg(torch.cat([normals, batch.maps[:, 3:]], dim=1))}

    with torch.no_grad():
        whole = model(batch.inputs, batch.lights, fov=fov).maps[:, constants.NORMAL]
        bases = model(batch.inputs, batch.lights, fov=fov, with_normal_unit=False).maps[:, constants.NORMAL]
        stage = model.basis_stage(batch.inputs, batch.lights, fov)
        deviations = model.local_deviations(stage.local_inputs, stage.weights, stage.global_bases)
        over_flat = normals_over_flat(model.normal_slope(stage, deviations, batch.lights, fov))
        sums = (stage.global_bases[..., None, None] + deviations)[:, :, constants.NORMAL]
    flat = torch.zeros_like(truth)
    flat[:, 2] = 1.0
    report = {"model": args.model or "shipped", "materials": args.materials,
              "run_config": str(args.run_config) if settings else None,
              "normal_slope_scaled": model.config.normal_slope_scaled,
              "flat": row(flat), "truth_mean_tilt_deg": mean_tilt_deg(batch.maps),
              "whole_network": row(whole), "bases_without_the_unit": row(bases), "slope_over_flat": row(over_flat),
              "weighted_sum_length": float((stage.weights * sums.norm(dim=2)).sum(dim=1).mean()),
              "weighted_sum_z": float((stage.weights * sums[:, :, 2]).sum(dim=1).mean())}
    for name in ("flat", "whole_network", "bases_without_the_unit", "slope_over_flat"):
        print(f"{name:>24}: normal RMSE {report[name]['rmse']:.4f}, mean tilt {report[name]['mean_tilt_deg']:.2f} deg")
    print(f"truth's mean tilt {report['truth_mean_tilt_deg']:.2f} deg; the bases' normal sums: weighted length "
          f"{report['weighted_sum_length']:.3f}, z {report['weighted_sum_z']:.3f}")
    write_report(args.output, "normal_composition", report)


if __name__ == "__main__":
    main()
