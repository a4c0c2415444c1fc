"""The lighting search on held-out procedural materials: its settings against its error and time.

    .venv/bin/python benchmarks/search_prior.py [--materials 40] [--offsets 3] [--priors 0 0.01 0.02 0.03 0.1]
    .venv/bin/python benchmarks/search_prior.py --materials 100 --priors 0.02 --settle-steps 0 1 --grids 11 15
    .venv/bin/python benchmarks/search_prior.py --priors 0.02 --starts centre highlight --normal-unit on off

Procedural materials from seeds the training does not draw (5e8 + i) are rendered at 256x256 under
seeded hand-held offsets (``sample_offsets``, as in training) and 8-bit sRGB, as ``evaluate``
renders its inputs. The shipped model searches for the flash with every combination of the
settings given, each of ``SearchConfig``; a setting not given is the capture's default:
``--priors`` (``SearchConfig.prior``: the pull toward the centre), ``--settle-steps``
(``settle_steps``: the passes stop once the light moves by that many grid steps or less),
``--relaxations`` (``relaxation``: how far past the best candidate a pass moves the light),
``--normal-unit`` (``normal_unit``: the search's network passes with or without the normal unit),
``--resolutions`` (``resolution``: the candidate renders' size), ``--grids`` (``grid``: candidates
per side) and ``--starts`` (``start``: the passes from the centre or from the photo's brightest
spot). Reported per setting: mean angular error [deg] per roughness group and overall (with
median and 90th percentile), network passes per search, seconds per search. The shared test set
is not used, so no setting is tuned on it. Writes benchmarks/results/search_prior.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import numpy as np
import torch
from common import RESULTS, write_report
from tqdm import tqdm

from mideepbasis.capturing import CaptureConfig, Capturer, Photo, SearchConfig
from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.synth import sample_offsets
from mideepbasis.evaluation import ROUGHNESS_GROUPS, flash_photos, light_error_deg
from mideepbasis.model.checkpoint import load_model

#: First seed of the held-out materials. Training draws 63-bit hashes of (run seed, index) as
#: material seeds (``material_seed``), so seeds this small come up with negligible probability.
HELD_OUT_SEED = 5 * 10**8

#: ``--normal-unit``'s default: the capture's (``SearchConfig.normal_unit``).
DEFAULT_NORMAL_UNIT = "on" if SearchConfig.normal_unit else "off"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--materials", type=int, default=40)
    parser.add_argument("--offsets", type=int, default=3, help="offsets per material")
    parser.add_argument("--priors", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.03, 0.1])
    parser.add_argument("--settle-steps", type=float, nargs="+", default=[SearchConfig.settle_steps])
    parser.add_argument("--relaxations", type=float, nargs="+", default=[SearchConfig.relaxation],
                        help="SearchConfig.relaxation values (how far past the best candidate a pass moves)")
    parser.add_argument("--normal-unit", nargs="+", choices=("on", "off"), default=[DEFAULT_NORMAL_UNIT],
                        help="SearchConfig.normal_unit: the search's passes with (on) or without (off) the normal unit")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[SearchConfig.resolution],
                        help="SearchConfig.resolution values (the candidate renders' size [pixels])")
    parser.add_argument("--grids", type=int, nargs="+", default=[SearchConfig.grid],
                        help="SearchConfig.grid values (candidates per side)")
    parser.add_argument("--starts", nargs="+", choices=("centre", "highlight"), default=[SearchConfig.start],
                        help="SearchConfig.start values (where the passes start)")
    parser.add_argument("--fov", type=float, default=45.0)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "search_prior.json")
    args = parser.parse_args()

    model = load_model(args.model)
    materials = [generate(HELD_OUT_SEED + i, config=GeneratorConfig(size=256)).to_tensor() for i in range(args.materials)]
    cases = []
    for index, material in enumerate(materials):
        roughness = float(material[6].mean())
        group = next(g for g, bound in ROUGHNESS_GROUPS.items() if roughness < bound)
        for offset in sample_offsets(args.offsets, torch.Generator().manual_seed(77 + index), args.fov):
            photos, _ = flash_photos(material[None], offset.view(1, 2), args.fov, model.config.convention,
                                     model.config.plane_extent)
            cases.append((group, photos[0], offset))

    rows = {}
    settings = [(prior, settle, relaxation, unit, resolution, grid, start) for prior in args.priors
                for settle in args.settle_steps for relaxation in args.relaxations for unit in args.normal_unit
                for resolution in args.resolutions for grid in args.grids for start in args.starts]
    for prior, settle, relaxation, unit, resolution, grid, start in settings:
        name = f"{prior:g}" if args.settle_steps == [SearchConfig.settle_steps] else f"prior {prior:g}, settle {settle:g}"
        name += "" if args.relaxations == [SearchConfig.relaxation] else f", relaxation {relaxation:g}"
        name += "" if args.normal_unit == [DEFAULT_NORMAL_UNIT] else f", normal unit {unit}"
        name += "" if args.resolutions == [SearchConfig.resolution] else f", {resolution} px"
        name += "" if args.grids == [SearchConfig.grid] else f", grid {grid}"
        name += "" if args.starts == [SearchConfig.start] else f", from the {start}"
        search = SearchConfig(prior=prior, settle_steps=settle, relaxation=relaxation, normal_unit=unit == "on",
                              resolution=resolution, grid=grid, start=start)
        capturer = Capturer(model, CaptureConfig(fov=args.fov, search=search))
        errors = {group: [] for group in ROUGHNESS_GROUPS}
        passes = []
        started = time.perf_counter()
        for group, photo, offset in tqdm(cases, desc=name, unit="search"):
            found = capturer.search(Photo(photo, args.fov, "argument"))
            errors[group].append(light_error_deg(found.offset, offset.tolist(), args.fov))
            passes.append(len(found.history) - 1)
        seconds = time.perf_counter() - started
        everything = sum(errors.values(), [])
        rows[name] = {**{group: {"count": len(v), "mean_deg": float(np.mean(v)) if v else None}
                         for group, v in errors.items()},
                      "all": {"count": len(everything), "mean_deg": float(np.mean(everything)),
                              "median_deg": float(np.median(everything)),
                              "p90_deg": float(np.percentile(everything, 90))},
                      "network_passes_mean": float(np.mean(passes)), "seconds": seconds,
                      "seconds_per_search": seconds / len(cases)}
        means = ", ".join(f"{g} {rows[name][g]['mean_deg']:.2f}" for g in ROUGHNESS_GROUPS if errors[g])
        print(f"{name}: {means}, all {rows[name]['all']['mean_deg']:.2f} deg (median {rows[name]['all']['median_deg']:.2f}, "
              f"90th percentile {rows[name]['all']['p90_deg']:.2f}); {np.mean(passes):.2f} network passes, "
              f"{seconds / len(cases):.2f} s a search")
    write_report(args.output, "search_prior", {"materials": args.materials, "offsets_per_material": args.offsets,
                                               "held_out_seed": HELD_OUT_SEED, "rows": rows})


if __name__ == "__main__":
    main()
