"""Which map decides a model's real-photo figure: maps swapped between two models, normals tilted, light known.

    .venv/bin/python benchmarks/real_attribution.py --model A.safetensors --other B.safetensors \
        [--data ../shared/data/real-calibrated] [--inputs all] [--tilts 0,0.5,1,1.5]

On every calibrated scene of ``--data`` (``evaluate``'s real protocol: capture from one photo,
re-render the others at their positions, exposure fitted on the input, clipped sRGB), each input
photo is captured by both models (defaults of ``capture``, with and without the refinement).
Rows, the RMSE of the other photos averaged over the inputs:

- ``model`` and ``other``: each model's capture as it is;
- ``model + other's MAP``: the model's maps with one of the other's in its place, and
  ``other + model's MAP`` the converse: where a fine-tune gains, the map that carries the gain
  moves the figure;
- ``model, normals tilted T``: the model's normals with their x and y times T, renormalised (0:
  flat), which tells whether the normals help the re-rendering at all;
- ``model, light known``: the model's capture told the calibrated flash position instead of
  searching for it, which tells what the lighting search costs.

A diagnosis, not a lever to tune to one scene: the capture itself changes nothing here. Writes the
entry ``real_attribution`` of results/model_quality.json (``-o`` another file).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, SHARED_TEST, write_section
from tqdm import tqdm

from mideepbasis import constants
from mideepbasis.capturing import Capturer
from mideepbasis.evaluation.real import (CAPTURE_ROW, UNREFINED_ROW, load_scene, materials_of_scene, scene_folders,
                                         scene_photos, score_rerenders)
from mideepbasis.geometry import scaled_slopes

#: The capture rows compared (capture's default, and without its refinement).
ROWS = (CAPTURE_ROW, UNREFINED_ROW)


def tilted(maps: torch.Tensor, tilt: float) -> torch.Tensor:
    """Maps (10, H, W) whose normals' x and y are multiplied by ``tilt``, then renormalised."""
    result = maps.clone()
    result[constants.NORMAL] = scaled_slopes(maps[constants.NORMAL], tilt, dim=0)
    return result


def variants(model_maps: torch.Tensor, other_maps: torch.Tensor, tilts: list[float]) -> dict[str, torch.Tensor]:
    """The row name of every material compared (module docstring) and its maps (10, H, W)."""
    result = {"model": model_maps, "other": other_maps}
    for name, channels in constants.MAP_SLICES.items():
        swapped = model_maps.clone()
        swapped[channels] = other_maps[channels]
        result[f"model + other's {name}"] = swapped
        swapped = other_maps.clone()
        swapped[channels] = model_maps[channels]
        result[f"other + model's {name}"] = swapped
    for tilt in tilts:
        result[f"model, normals tilted {tilt:g}"] = tilted(model_maps, tilt)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--other", required=True, help="the checkpoint compared with")
    parser.add_argument("--data", type=Path, default=SHARED_TEST.parent / "real-calibrated",
                        help="calibrated scenes (evaluate's real protocol)")
    parser.add_argument("--inputs", default="all", help="input photos: 'all' or comma-separated indices")
    parser.add_argument("--tilts", default="0,0.5,1.5", help="comma-separated normal tilt factors")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "model_quality.json",
                        help="JSON file whose entry real_attribution gets the figures")
    args = parser.parse_args()
    tilts = [float(value) for value in args.tilts.split(",") if value]
    models = Capturer(args.model), Capturer(args.other)
    figures: dict[str, dict[str, list[float]]] = {row: {} for row in ROWS}
    scenes = [load_scene(folder) for folder in scene_folders(args.data)]
    for scene in tqdm(scenes, desc="scenes", unit="scene"):
        photos = scene_photos(scene, models[0].config.resolution)
        inputs = range(len(photos)) if args.inputs == "all" else [int(i) for i in args.inputs.split(",")]
        for index in tqdm(inputs, desc=scene.name, unit="input", leave=False):
            model_rows, other_rows = (materials_of_scene(capturer, scene, index, photos[index])
                                      for capturer in models)
            known = models[0].with_config(light=tuple(float(value) for value in scene.lights[index, :2]))
            known_rows = materials_of_scene(known, scene, index, photos[index])
            for row in ROWS:
                rows = {**variants(model_rows[row], other_rows[row], tilts), "model, light known": known_rows[row]}
                for name, maps in rows.items():
                    rmse = score_rerenders(maps, photos, scene, index, models[0].convention).rmse
                    figures[row].setdefault(name, []).append(rmse)
    means = {row: {name: sum(values) / len(values) for name, values in by_name.items()}
             for row, by_name in figures.items()}
    for name in means[ROWS[0]]:
        print(f"{name:30s} " + "  ".join(f"{row} {means[row][name]:.4f}" for row in ROWS))
    write_section(args.output, "real_attribution", "real_attribution",
                  {"model": args.model or "shipped", "other": args.other, "data": str(args.data),
                   "inputs": args.inputs, "scenes": [scene.name for scene in scenes],
                   "captures": len(next(iter(figures[ROWS[0]].values()))), "rmse": means})


if __name__ == "__main__":
    main()
