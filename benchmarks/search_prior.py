"""The lighting search's pull toward the centre, chosen on held-out procedural materials.

    .venv/bin/python benchmarks/search_prior.py [--materials 40] [--offsets 3] [--priors 0 0.01 0.02 0.03 0.1]

Procedural materials from seeds the training does not draw (5e8 + i) are rendered at 256x256 under
seeded hand-held offsets (``sample_offsets``, as in training) and 8-bit sRGB, as ``evaluate``
renders its inputs. The shipped model searches for the flash with each prior weight
(``CaptureConfig.search_prior``). Reported: mean angular error [deg] per roughness group and
overall. The shared test set is not used, so the weight is not tuned on it. Writes
benchmarks/results/search_prior.json.
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

from mideepbasis.capture import CaptureConfig, Capturer, Photo, SearchConfig
from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.synth import sample_offsets
from mideepbasis.evaluation import ROUGHNESS_GROUPS, flash_photos, light_error_deg
from mideepbasis.model.checkpoint import load_model

#: First seed of the held-out materials. Training draws 63-bit hashes of (run seed, index) as
#: material seeds (``material_seed``), so seeds this small come up with negligible probability.
HELD_OUT_SEED = 5 * 10**8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--materials", type=int, default=40)
    parser.add_argument("--offsets", type=int, default=3, help="offsets per material")
    parser.add_argument("--priors", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.03, 0.1])
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
    for prior in args.priors:
        capturer = Capturer(model, CaptureConfig(fov=args.fov, search=SearchConfig(prior=prior)))
        errors = {group: [] for group in ROUGHNESS_GROUPS}
        started = time.perf_counter()
        for group, photo, offset in tqdm(cases, desc=f"prior {prior:g}", unit="search"):
            found = capturer.search(Photo(photo, args.fov, "argument")).offset
            errors[group].append(light_error_deg(found, offset.tolist(), args.fov))
        everything = sum(errors.values(), [])
        rows[f"{prior:g}"] = {**{group: {"count": len(v), "mean_deg": float(np.mean(v)) if v else None}
                                 for group, v in errors.items()},
                              "all": {"count": len(everything), "mean_deg": float(np.mean(everything))},
                              "seconds": time.perf_counter() - started}
        means = ", ".join(f"{g} {rows[f'{prior:g}'][g]['mean_deg']:.2f}" for g in ROUGHNESS_GROUPS if errors[g])
        print(f"prior {prior:g}: {means}, all {rows[f'{prior:g}']['all']['mean_deg']:.2f} deg")
    write_report(args.output, "search_prior", {"materials": args.materials, "offsets_per_material": args.offsets,
                                               "held_out_seed": HELD_OUT_SEED, "rows": rows})


if __name__ == "__main__":
    main()
