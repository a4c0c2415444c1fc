"""Where the time of a capture's environment preview goes: the same render with parts removed.

    .venv/bin/python benchmarks/preview_cost.py [--repeats 3]

Renders the capture's environment preview (the studio environment, 256 px, the capture's sampler
and samples per pixel) of the bundled example material, then variants that each take one part
away: the maps shrunk to 2 px (the texture look-ups), the ``svbrdf`` plugin replaced by Mitsuba's
``diffuse`` (the BSDF's own arithmetic), the environment map replaced by a constant sky (its
sampling and look-ups), and a ``depth`` integrator (camera rays, intersection, the film's
Gaussian splatting and the sampler: the floor). The variants are built with ``mi.load_dict`` with
the camera of ``render.scenes.preview_scene``. Each time is the fastest of ``--repeats`` after an
untimed render that compiles the kernels. Then the loading of a command's three preview scenes
(``preview_scene`` and ``shape_scene`` of the sphere and the cloth) with the studio environment
map and with the constant ``uniform`` sky: what building the map costs each scene (the median of
``--repeats`` after a first load, which is also reported). ``results/preview_cost.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "preview_cost.json")
    args = parser.parse_args()

    import mitsuba as mi

    from mideepbasis import constants
    from mideepbasis.material import Material
    from mideepbasis.render.api import example_material_dir
    from mideepbasis.render.scenes import (ENVIRONMENTS, UNIFORM, preview_camera_position, preview_scene, render,
                                           scenes_dir, shape_scene)
    from mideepbasis.resampling import downsample_maps

    maps = Material.load(example_material_dir()).to_tensor()
    tiny_maps = downsample_maps(maps[None], 2)[0]
    sampler, spp = constants.CAPTURE_PREVIEW_SAMPLER, constants.CAPTURE_PREVIEW_SPP
    origin = list(preview_camera_position())

    def variant(bsdf: str = "svbrdf", environment: bool = True, integrator: str = "direct") -> mi.Scene:
        return mi.load_dict({
            "type": "scene",
            "integrator": ({"type": "direct", "emitter_samples": 1, "bsdf_samples": 1} if integrator == "direct"
                           else {"type": integrator}),
            "sensor": {"type": "perspective", "fov": constants.PREVIEW_FOV_DEG, "fov_axis": "x",
                       "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0], up=[0, 0, 1]),
                       "sampler": {"type": sampler, "sample_count": spp},
                       "film": {"type": "hdrfilm", "width": constants.PREVIEW_RESOLUTION,
                                "height": constants.PREVIEW_RESOLUTION, "pixel_format": "rgb"}},
            "environment": ({"type": "envmap", "filename": str(scenes_dir() / ENVIRONMENTS["studio"]),
                             "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)} if environment
                            else {"type": "constant"}),
            "sample": {"type": "rectangle", "bsdf": {"type": bsdf}}})

    cases = {
        "the capture's preview": lambda: preview_scene(maps, spp=spp, sampler=sampler),
        "maps shrunk to 2 px": lambda: preview_scene(tiny_maps, spp=spp, sampler=sampler),
        "svbrdf with its default maps (load_dict)": lambda: variant(),
        "diffuse instead of svbrdf": lambda: variant(bsdf="diffuse"),
        "diffuse under a constant sky": lambda: variant(bsdf="diffuse", environment=False),
        "depth integrator (the floor)": lambda: variant(bsdf="diffuse", integrator="depth"),
    }
    results = {}
    for name, build in cases.items():
        scene = build()
        render(scene)  # compiles the kernels
        times = []
        for seed in range(args.repeats):
            start = time.perf_counter()
            render(scene, seed=seed + 1)
            times.append(time.perf_counter() - start)
        results[name] = {"fastest_s": round(min(times), 4), "runs_s": [round(t, 4) for t in times]}
        print(f"{name:42s} {min(times) * 1e3:7.1f} ms")

    loads = {}
    for environment in ("studio", UNIFORM):
        builders = {"environment": lambda: preview_scene(maps, environment=environment, spp=spp, sampler=sampler),
                    **{shape: (lambda shape=shape: shape_scene(maps, shape, environment,
                                                               spp=constants.SHAPE_PREVIEW_SPP,
                                                               sampler=constants.SHAPE_PREVIEW_SAMPLER))
                       for shape in ("sphere", "cloth")}}
        for name, build in builders.items():
            times = []
            for _ in range(args.repeats + 1):
                start = time.perf_counter()
                build()
                times.append(time.perf_counter() - start)
            key = f"{name}, {environment}"
            loads[key] = {"first_s": round(times[0], 4), "median_s": round(statistics.median(times[1:]), 4)}
            print(f"load {name:12s} {environment:8s} first {times[0] * 1e3:6.1f} ms, "
                  f"then {loads[key]['median_s'] * 1e3:6.1f} ms")
    write_report(args.output, "preview_cost", {"sampler": sampler, "spp": spp,
                                               "resolution": constants.PREVIEW_RESOLUTION, "results": results,
                                               "scene_loads": loads})


if __name__ == "__main__":
    main()
