"""Noise against time of the path-traced environment preview (the sample on a table) by sampler.

    .venv/bin/python benchmarks/preview_noise.py [--reference-spp 2048] [--repeats 3]

For each material (two procedural ones and the bundled example material, 256 px), renders the
capture's environment preview (``render.scenes.preview_scene``, studio environment, 256 px) with
each sampler and sample count below, and reports the render time (the fastest of ``--repeats``,
the kernels compiled by an untimed render first) and the sRGB RMSE of the clipped image against a
``--reference-spp`` render with independent samples and another seed: the preview's noise.
``results/preview_noise.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402

#: (sampler, samples per pixel): the capture's preview before (64 independent) and candidates;
#: the stratified samplers' counts are the squares (of primes for ``orthogonal``) they need.
SETTINGS = (("independent", 64), ("independent", 25), ("multijitter", 25), ("multijitter", 36),
            ("orthogonal", 25), ("ldsampler", 16))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference-spp", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "preview_noise.json")
    args = parser.parse_args()

    import numpy as np

    from mideepbasis.data.procedural import GeneratorConfig, generate
    from mideepbasis.evaluation.environment import to_display
    from mideepbasis.material import Material
    from mideepbasis.render.api import example_material_dir
    from mideepbasis.render.scenes import preview_scene, render

    materials = {"procedural 7": generate(7, config=GeneratorConfig(size=256)).to_tensor(),
                 "procedural 11": generate(11, config=GeneratorConfig(size=256)).to_tensor(),
                 "example material": Material.load(example_material_dir()).to_tensor()}
    rows = []
    for name, maps in materials.items():
        reference = to_display(render(preview_scene(maps, spp=args.reference_spp), seed=7))
        for sampler, spp in SETTINGS:
            scene = preview_scene(maps, spp=spp, sampler=sampler)
            render(scene)
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                image = render(scene)
                times.append(time.perf_counter() - start)
            rmse = float(np.sqrt(((to_display(image) - reference) ** 2).mean()))
            rows.append({"material": name, "sampler": sampler, "spp": spp, "seconds": round(min(times), 3),
                         "srgb_rmse": round(rmse, 5)})
            print(f"{name:16s} {sampler:12s} {spp:3d} spp: {1000 * min(times):6.0f} ms, sRGB RMSE {rmse:.4f}", flush=True)
    write_report(args.output, "preview_noise", {"reference_spp": args.reference_spp, "rows": rows})


if __name__ == "__main__":
    main()
