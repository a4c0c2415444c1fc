"""Does refining the global bases help? Variants of the refinement on the shared test materials.

    .venv/bin/python benchmarks/refinement.py [--every 3] [--steps 500] [--model PATH]

Every ``--every``-th of the 84 shared materials is re-rendered under its seeded hand-held offset
(the offsets of ``mideepbasis evaluate``), the model predicts once with the offset known, and each
variant refines that one prediction: no refinement, all channels (the paper: Adam at a constant
rate of 0.01), all channels with a pull toward the network's bases, and d, r, s only (normals kept,
capture's cosine schedule), at the given step count (the paper's 500) and at a half (capture's
default) and a quarter of it, and a quarter at one rate. Reported per variant: map RMSE (stored
encoding), re-rendering RMSE under the 30 random lights and views of ``evaluate``, the mean L1 between the
photo and the material rendered under the photo's flash (what the refinement minimises), and the
seconds per material. Writes benchmarks/results/refinement.json.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, SHARED_TEST, write_report
from tqdm import tqdm

from mideepbasis.capturing import Capturer, Photo, RefineConfig
from mideepbasis.evaluation import (EvaluationConfig, evaluation_offsets, flash_photos, load_evaluation_set,
                                    random_lights_and_views, score, summary_scores)
from mideepbasis.render import render_flash



def variants(steps: int) -> dict[str, RefineConfig]:
    """Name -> refinement settings (steps 0: the network's prediction as is); the rest as capture's defaults."""
    half, quarter = steps // 2, steps // 4
    constant = {"lr": 0.01, "lr_schedule": "constant"}  # Adam at one rate, as the paper's
    return {
        "none": RefineConfig(steps=0),
        f"all channels, {steps} steps (paper)": RefineConfig(steps=steps, normals=True, **constant),
        f"all channels + prior 0.1, {steps} steps": RefineConfig(steps=steps, normals=True, prior=0.1, **constant),
        f"d, r, s only, {steps} steps": RefineConfig(steps=steps),
        f"d, r, s only, {half} steps": RefineConfig(steps=half),
        f"d, r, s only, {quarter} steps": RefineConfig(steps=quarter),
        f"d, r, s only, {quarter} steps at one rate": RefineConfig(steps=quarter, **constant),
        f"d, r, s only, {half} steps, clamped": RefineConfig(steps=half, unclamped_moves=False),
        f"d, r, s only + prior 0.1, {half} steps": RefineConfig(steps=half, prior=0.1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--data", type=Path, default=SHARED_TEST)
    parser.add_argument("--every", type=int, default=3, help="use every k-th material")
    parser.add_argument("--steps", type=int, default=500, help="the paper's step count; variants also use 1/2 and 1/4")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "refinement.json")
    args = parser.parse_args()

    if not args.data.is_dir():
        raise SystemExit(f"{args.data}: shared test data not found")
    capturer = Capturer(args.model)
    model = capturer.model
    convention, extent = model.config.convention, model.config.plane_extent
    evaluation = EvaluationConfig(data="")
    seed, fov = evaluation.seed, evaluation.fov
    names, truth, _ = load_evaluation_set(args.data, "deschaintre5")
    offsets = evaluation_offsets(len(truth), seed, fov)
    chosen = list(range(0, len(truth), args.every))
    lights, views = random_lights_and_views(seed=seed)

    table = variants(args.steps)
    predictions = {name: [] for name in table}
    photo_l1 = {name: [] for name in table}
    seconds = {name: 0.0 for name in table}
    for index in tqdm(chosen, desc="materials", unit="material"):
        photos, position = flash_photos(truth[index:index + 1], offsets[index:index + 1], fov, convention, extent)
        photo, offset = Photo(photos[0], fov, "argument"), offsets[index]
        prediction = capturer.predict(photo, offset)
        for name, refine in table.items():
            started = time.perf_counter()
            maps = capturer.with_config(refine=refine).refine(prediction, photo, offset)[0].maps.cpu()
            seconds[name] += time.perf_counter() - started
            predictions[name].append(maps)
            # How well the material explains the photo it came from (what the refinement minimises).
            rendered = render_flash(maps, position.view(1, 1, 3), fov=fov, convention=convention, extent=extent)
            photo_l1[name].append(float((rendered[:, 0].clamp(0.0, 1.0) - photos).abs().mean()))

    rows = {}
    subset = truth[chosen]
    for name in table:
        metrics = score(torch.cat(predictions[name]), subset, lights, views, convention)
        rows[name] = {**summary_scores({key: float(value.mean()) for key, value in metrics.items()}),
                      "photo_l1": sum(photo_l1[name]) / len(chosen),
                      "seconds_per_material": seconds[name] / len(chosen), **asdict(table[name])}
        maps = rows[name]["maps_rmse"]
        print(f"{name:42s} n {maps['normal']:.4f} d {maps['diffuse']:.4f} r {maps['roughness']:.4f} "
              f"s {maps['specular']:.4f} | render {rows[name]['render_rmse']:.4f} flip {rows[name]['render_flip']:.4f} "
              f"| photo L1 {rows[name]['photo_l1']:.4f} | {rows[name]['seconds_per_material']:.2f} s")
    write_report(args.output, "refinement", {"model": str(args.model or "shipped"), "materials": len(chosen),
                                             "every": args.every, "light": "known", "rows": rows,
                                             "names": [names[i] for i in chosen]})


if __name__ == "__main__":
    main()
