"""Quality of a trained model on the 84 shared test materials, beside the trivial baseline.

    .venv/bin/python benchmarks/model_quality.py [--model PATH] [-o benchmarks/results/model_quality.json]

Inputs are rendered from the ground-truth maps (used as stored) under the centred flash with the
model's shading convention and quantised to 8-bit sRGB; the model predicts the maps at 256x256
(the network at its training resolution, as ``capture`` runs it, unless ``--network-resolution``).
Reported: map RMSE of normal, diffuse, roughness and specular in the stored encoding, and the RMSE
of re-renderings under 30 seeded random lights and views per material (clipped, sRGB-encoded),
for the model, for its global blend alone (the blending weights times the global bases, without
the local deviations: what the local unit's error map renders and the refinement moves) and for
the trivial baseline (flat normal and the set's mean maps). The paper's DeepBasis row (on its 122
scenes) is listed for reference.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, SHARED_TEST, write_report

from mideepbasis.capturing import network_resolution_limit, predict
from mideepbasis.data.datasets import DeschaintreDataset
from mideepbasis.evaluation import flash_photos, map_rmse, random_lights_and_views, rerender_rmse, trivial_baseline
from mideepbasis.model.checkpoint import load_model, shipped_model_path
from mideepbasis.model.network import DeepBasisOutput

PAPER = {"normal": 0.053, "diffuse": 0.031, "roughness": 0.162, "specular": 0.043}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--data", type=Path, default=SHARED_TEST)
    parser.add_argument("--batch", type=int, default=6)
    parser.add_argument("--network-resolution", type=int, default=None,
                        help="largest resolution the network runs at (default: the model's training resolution, "
                             "as in capture; 0: 256, the materials' own)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "model_quality.json")
    args = parser.parse_args()

    if not args.data.is_dir():
        raise SystemExit(f"shared test data not found at {args.data}")
    model = load_model(args.model)
    convention = model.config.convention
    reader = DeschaintreDataset(args.data)
    materials = torch.stack([m.to_tensor() for m in reader])
    names = [Path(s).stem for s in reader.sources]
    lights, views = random_lights_and_views(seed=0)
    start = time.perf_counter()
    predictions, blends = [], []
    for first in range(0, len(materials), args.batch):
        truth = materials[first:first + args.batch]
        photos, flash = flash_photos(truth, torch.zeros(len(truth), 2), convention=convention)
        output = predict(model, photos, flash, network_resolution=args.network_resolution)
        predictions.append(output.maps.cpu())
        if output.weights is not None and output.deviations is not None:
            blends.append(DeepBasisOutput.from_bases(output.weights, output.global_bases, keep_bases=False).maps.cpu())
    predicted = torch.cat(predictions)
    seconds = time.perf_counter() - start
    baseline = trivial_baseline(materials).expand_as(materials)

    rows = {}
    estimates = [("model", predicted), ("trivial", baseline)]
    if blends:  # what the local unit starts from and the refinement moves
        estimates.insert(1, ("global blend", torch.cat(blends)))
    for name, estimate in estimates:
        maps = map_rmse(estimate, materials)
        render = torch.cat([rerender_rmse(estimate[i:i + 6], materials[i:i + 6], lights, views, convention)
                            for i in range(0, len(materials), 6)])
        rows[name] = {**{k: round(float(v.mean()), 4) for k, v in maps.items()}, "render_rmse": round(float(render.mean()), 4)}
    report = {"model": str(args.model or shipped_model_path()), "convention": convention, "materials": len(materials),
              "network_resolution": network_resolution_limit(model, args.network_resolution) or 256, "light": "centred flash", "rerender": "30 random lights and views, seed 0, clipped sRGB",
              "prediction_seconds": round(seconds, 1), "rows": rows, "paper_deepbasis_122_scenes": PAPER,
              "per_material_names": names}
    write_report(args.output, "model_quality", report)
    print(f"{'':12s} {'normal':>8s} {'diffuse':>8s} {'rough':>8s} {'specular':>8s} {'render':>8s}")
    for name, row in rows.items():
        print(f"{name:12s} " + " ".join(f"{row[k]:8.4f}" for k in ("normal", "diffuse", "roughness", "specular", "render_rmse")))
    print(f"{'paper':12s} " + " ".join(f"{PAPER[k]:8.4f}" for k in ("normal", "diffuse", "roughness", "specular")))


if __name__ == "__main__":
    main()
