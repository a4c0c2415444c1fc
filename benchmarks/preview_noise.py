"""Noise against time of the path-traced previews (the sample on a table, or on a ball and a cloth) by sampler.

    .venv/bin/python benchmarks/preview_noise.py [--reference-spp 2048] [--repeats 3] [--shapes]

For each material (two procedural ones and the bundled example material, 256 px), renders the
capture's environment preview (``render.scenes.preview_scene``, studio environment, 256 px) with
each sampler and sample count below, and reports the render time (the fastest of ``--repeats``,
the kernels compiled by an untimed render first) and the sRGB RMSE of the clipped image against a
``--reference-spp`` render with independent samples and another seed: the preview's noise. With
``--shapes``, the same for the sphere and cloth previews (``render.scenes.shape_scene``, maps
repeated twice as a capture shows them) with ``SHAPE_SETTINGS``. With ``--filters``, the capture's
own sampler and count only (all three previews), once with Mitsuba's Gaussian film filter and once
box-filtered and developed by ``render.scenes.render_preview`` (its time included), against the
same Gaussian-filtered reference. With ``--settings SAMPLER:SPP ...``, those samplers and counts
instead of the lists below, box-filtered and developed as a capture's previews are. The renders of
a material are timed round by round over its settings, so that the machine's drift falls on all
of them alike. Every mode writes ``results/preview_noise.json`` (its rows name sampler, count and
filter).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402

#: (sampler, samples per pixel) of the environment preview: independent samples (64 and 25) and
#: stratified candidates, whose counts are the squares (of primes for ``orthogonal``) they need.
SETTINGS = (("independent", 64), ("independent", 25), ("multijitter", 16), ("multijitter", 20), ("multijitter", 25),
            ("multijitter", 36), ("orthogonal", 25), ("ldsampler", 16))

#: The same for the shape previews: 32 independent samples and stratified candidates.
SHAPE_SETTINGS = (("independent", 32), ("orthogonal", 25), ("multijitter", 16), ("multijitter", 20),
                  ("multijitter", 25), ("orthogonal", 9))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference-spp", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--shapes", action="store_true", help="the sphere and cloth previews instead of the plane")
    parser.add_argument("--filters", action="store_true",
                        help="the capture's settings with the Gaussian film filter and with box + film_gaussian")
    parser.add_argument("--settings", nargs="+", default=None, metavar="SAMPLER:SPP",
                        help="these samplers and counts instead of SETTINGS (or SHAPE_SETTINGS), box-filtered "
                             "and developed as a capture's previews are (render.scenes.render_preview)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "preview_noise.json")
    args = parser.parse_args()
    output = args.output

    import numpy as np

    from mideepbasis import constants
    from mideepbasis.data.procedural import GeneratorConfig, generate
    from mideepbasis.evaluation.environment import to_display
    from mideepbasis.material import Material
    from mideepbasis.render.api import example_material_dir
    from mideepbasis.render.scenes import preview_scene, render, render_preview, shape_scene

    materials = {"procedural 7": generate(7, config=GeneratorConfig(size=256)).to_tensor(),
                 "procedural 11": generate(11, config=GeneratorConfig(size=256)).to_tensor(),
                 "example material": Material.load(example_material_dir()).to_tensor()}

    def shape_maker(shape):
        return lambda maps, spp, sampler, rfilter="gaussian": shape_scene(maps, shape, spp=spp, sampler=sampler,
                                                                          rfilter=rfilter)

    def plane(maps, spp, sampler, rfilter="gaussian"):
        return preview_scene(maps, spp=spp, sampler=sampler, rfilter=rfilter)

    # (preview, scene maker, sampler, samples per pixel, film filter) of every row, per material.
    if args.filters:
        capture_settings = {"plane": (constants.CAPTURE_PREVIEW_SAMPLER, constants.CAPTURE_PREVIEW_SPP),
                            "sphere": (constants.SHAPE_PREVIEW_SAMPLER, constants.SHAPE_PREVIEW_SPP),
                            "cloth": (constants.SHAPE_PREVIEW_SAMPLER, constants.SHAPE_PREVIEW_SPP)}
        makers = {"plane": plane, "sphere": shape_maker("sphere"), "cloth": shape_maker("cloth")}
        cases = [(shape, makers[shape], *capture_settings[shape], rfilter)
                 for shape in makers for rfilter in ("gaussian", "box")]
    else:
        settings = SHAPE_SETTINGS if args.shapes else SETTINGS
        rfilter = "gaussian"
        if args.settings:
            settings = [(text.partition(":")[0], int(text.partition(":")[2])) for text in args.settings]
            rfilter = constants.PREVIEW_FILM_FILTER
        shapes = {"sphere": shape_maker("sphere"), "cloth": shape_maker("cloth")} if args.shapes else {"plane": plane}
        cases = [(shape, make, sampler, spp, rfilter) for shape, make in shapes.items() for sampler, spp in settings]

    rows = []
    for name, maps in materials.items():
        references = {shape: to_display(render(make_scene(maps, args.reference_spp, "independent"), seed=7))
                      for shape, make_scene, *_ in cases}
        scenes = [make_scene(maps, spp, sampler, rfilter) for _, make_scene, sampler, spp, rfilter in cases]
        images = [render_preview(scene) for scene in scenes]  # the kernels compiled, untimed
        # Round by round over the cases, so that the machine's drift (a fifth within minutes) falls on all alike.
        times = [[] for _ in cases]
        for _ in range(args.repeats):
            for index, scene in enumerate(scenes):
                start = time.perf_counter()
                images[index] = render_preview(scene)
                times[index].append(time.perf_counter() - start)
        for (shape, _, sampler, spp, rfilter), image, seconds in zip(cases, images, times, strict=True):
            rmse = float(np.sqrt(((to_display(image) - references[shape]) ** 2).mean()))
            rows.append({"material": name, "shape": shape, "sampler": sampler, "spp": spp, "rfilter": rfilter,
                         "seconds": round(min(seconds), 3), "srgb_rmse": round(rmse, 5)})
            print(f"{name:16s} {shape:6s} {sampler:12s} {spp:3d} spp {rfilter:8s}: {1000 * min(seconds):6.0f} ms, "
                  f"sRGB RMSE {rmse:.4f}", flush=True)
    write_report(output, "preview_noise", {"reference_spp": args.reference_spp, "rows": rows})


if __name__ == "__main__":
    main()
