"""Rendering speed at 256x256: the Mitsuba plugin path beside the torch reference.

    .venv/bin/python benchmarks/render.py [--resolution 256] [--repeats 15] [-o benchmarks/results/render.json]

Measures, warm (after untimed warm-up calls) and as the median of several runs:
- the per-pixel flash forward render;
- forward + backward through the torch <-> drjit bridge (gradients for the four maps and the light);
- 64 light candidates rendered in one batch (the lighting search's inner step);
- the path-traced environment preview at 64 spp (Mitsuba only: the torch reference has no
  path tracer).
Writes JSON with the machine, the date and every timing [ms].
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import mideepbasis  # noqa: F401  (sets the OpenMP spin before torch loads)
import torch

from common import RESULTS, write_report
from mideepbasis import constants
from mideepbasis.render import bridge, reference, scenes

TARGETS_MS = {"flash_forward_backward": 10.0, "flash_64_candidates": 30.0, "env_preview_64spp": 1000.0}


def timed(function, repeats: int, warmup: int = 3) -> dict:
    for _ in range(warmup):
        function()
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        runs.append(1e3 * (time.perf_counter() - start))
    return {"median_ms": statistics.median(runs), "min_ms": min(runs), "runs_ms": [round(r, 3) for r in runs]}


def test_material(resolution: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(1, 3, resolution, resolution, generator=generator) * 0.3
                                           + torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1), dim=1)
    rest = torch.rand(1, 7, resolution, resolution, generator=generator)
    return torch.cat([normal, rest], 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "render.json")
    args = parser.parse_args()

    size = args.resolution
    height = constants.camera_height(constants.DEFAULT_FOV_DEG)
    intensity = math.pi * height**2
    maps = test_material(size)
    light = torch.tensor([[[0.2, -0.1, height]]])
    generator = torch.Generator().manual_seed(1)
    candidates = torch.cat([torch.rand(1, 64, 2, generator=generator) * 1.4 - 0.7, torch.full((1, 64, 1), height)], -1)
    results = {}

    for name, render in {"mitsuba": bridge.render_flash, "torch_reference": reference.render_flash}.items():
        def forward():
            with torch.no_grad():
                render(maps, light, intensity)

        leaf_maps, leaf_light = maps.clone().requires_grad_(), light.clone().requires_grad_()

        def forward_backward():
            leaf_maps.grad = leaf_light.grad = None
            render(leaf_maps, leaf_light, intensity).square().mean().backward()

        def sixty_four():
            with torch.no_grad():
                render(maps, candidates, intensity)

        repeats = args.repeats if name == "mitsuba" else max(3, args.repeats // 3)
        results.setdefault("flash_forward", {})[name] = timed(forward, repeats)
        results.setdefault("flash_forward_backward", {})[name] = timed(forward_backward, repeats)
        results.setdefault("flash_64_candidates", {})[name] = timed(sixty_four, repeats, warmup=1 if name != "mitsuba" else 3)

    scene = scenes.preview_scene(maps[0], spp=64, resolution=size)
    seeds = iter(range(10_000))
    results["env_preview_64spp"] = {
        "mitsuba": timed(lambda: scenes.render(scene, seed=next(seeds)), max(5, args.repeats // 3), warmup=2),
        "torch_reference": None,
    }

    for key, value in results.items():
        line = "  ".join(f"{backend}: {timing['median_ms']:.2f} ms" if timing else f"{backend}: -"
                         for backend, timing in value.items())
        target = f"(target <= {TARGETS_MS[key]:.0f} ms)" if key in TARGETS_MS else ""
        print(f"{key:26s} {line} {target}")
    write_report(args.output, "render", {"resolution": size, "targets_ms": TARGETS_MS, "results": results})


if __name__ == "__main__":
    main()
