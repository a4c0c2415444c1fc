"""Which map the re-rendering error comes from: each predicted map swapped for the true one, and alone.

    .venv/bin/python benchmarks/rerender_attribution.py [--model CKPT] [-o benchmarks/results/rerender_attribution.json]

On the shared test set, with ``evaluate``'s default protocol (seeded hand-held flashes, light
known, the network at its training resolution, 30 seeded lights and views per material), the
re-rendering RMSE (clipped sRGB) of:

- the prediction (``evaluate``'s figure);
- the prediction with one map replaced by the truth (what a perfect map of that kind would gain);
- the truth with one map replaced by the prediction (what that map's error costs alone);
- the prediction with a flat normal.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, shared_predictions, write_report

from mideepbasis import constants
from mideepbasis.evaluation.metrics import flat_normals, rerender_rmse
from mideepbasis.evaluation.protocol import RERENDER_COUNT, random_lights_and_views
from mideepbasis.model.checkpoint import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "rerender_attribution.json")
    args = parser.parse_args()

    model = load_model(args.model)
    truth, _, predicted = shared_predictions(model)
    convention = model.config.convention
    lights, views = random_lights_and_views(RERENDER_COUNT, 0)

    def error(maps: torch.Tensor) -> float:
        return float(rerender_rmse(maps, truth, lights, views, convention).mean())

    report = {"model": args.model or "shipped", "prediction": error(predicted), "true_map": {}, "predicted_map_alone": {}}
    for name, channels in constants.MAP_SLICES.items():
        swapped = predicted.clone()
        swapped[:, channels] = truth[:, channels]
        report["true_map"][name] = error(swapped)
        alone = truth.clone()
        alone[:, channels] = predicted[:, channels]
        report["predicted_map_alone"][name] = error(alone)
    report["flat_normal"] = error(flat_normals(predicted))
    print(f"prediction {report['prediction']:.4f}; with a flat normal {report['flat_normal']:.4f}")
    for name in constants.MAP_SLICES:
        print(f"{name:>9}: true map {report['true_map'][name]:.4f}, "
              f"the predicted map alone {report['predicted_map_alone'][name]:.4f}")
    write_report(args.output, "rerender_attribution", report)


if __name__ == "__main__":
    main()
