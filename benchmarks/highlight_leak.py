"""How much of the flash's highlight a model puts into its diffuse map.

    .venv/bin/python benchmarks/highlight_leak.py [--model CKPT] [-o benchmarks/results/highlight_leak.json]

On the shared test set (``evaluate``'s default protocol: seeded hand-held flashes, light known,
the network at its training resolution) and on the bundled demo photo (its true light), for each
material:

- the highlight: the true material's specular lobe alone (its diffuse set to zero) rendered under
  the input's flash; its brightest 5% of pixels are the highlight region;
- the leak: the mean of (predicted - true) diffuse luminance over the highlight region, minus its
  mean over the rest, relative to the true diffuse luminance's mean. A model that bakes the
  highlight into the diffuse map shows a positive leak (0.1: the diffuse is 10% brighter under the
  highlight than elsewhere, beyond the truth); a model that errs alike everywhere shows 0. The
  same difference in albedo units is reported beside it (dark materials make the relative one
  large).

Writes the JSON report and ``highlight_leak.png`` beside it: the demo's photo, its predicted and
true diffuse, and the highlight region.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import mideepbasis  # noqa: F401
import numpy as np
import torch
from common import RESULTS, shared_predictions, write_report

from mideepbasis import constants, geometry
from mideepbasis.capturing import CaptureConfig, Capturer
from mideepbasis.material import Material
from mideepbasis.model.checkpoint import load_model
from mideepbasis.render.api import example_capture_dir
from mideepbasis.resampling import downsample_maps

#: Share of the pixels, the brightest of the specular lobe's render, that make the highlight region.
HIGHLIGHT_SHARE = 0.05


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, H, W), Rec. 709 weights."""
    return sum(weight * rgb[:, channel] for channel, weight in enumerate(constants.LUMINANCE_WEIGHTS))


def highlight_leak(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, fov: float,
                   convention: str, extent: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-material leak (B,) of predicted maps into their diffuse under the flash at ``lights``
    (B, 3), relative and in albedo units (NaN where the lobe marks no region: a material without
    specular), and the highlight regions (B, H, W) bool. Maps (B, 10, H, W)."""
    from mideepbasis.train import specular_lobe

    lobe = specular_lobe(truth, lights, fov, convention, extent)[:, 0]
    threshold = torch.quantile(lobe.flatten(1), 1.0 - HIGHLIGHT_SHARE, dim=1).view(-1, 1, 1)
    region = lobe >= threshold
    excess = luminance(predicted[:, constants.DIFFUSE]) - luminance(truth[:, constants.DIFFUSE])
    inside = (excess * region).sum(dim=(1, 2)) / region.sum(dim=(1, 2))
    outside = (excess * ~region).sum(dim=(1, 2)) / (~region).sum(dim=(1, 2))  # 0 / 0 = NaN: no region
    scale = luminance(truth[:, constants.DIFFUSE]).mean(dim=(1, 2)).clamp_min(1e-3)
    return (inside - outside) / scale, inside - outside, region


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "highlight_leak.json")
    args = parser.parse_args()

    model = load_model(args.model)
    fov, convention = constants.DEFAULT_FOV_DEG, model.config.convention
    truth, offsets, predicted = shared_predictions(model)
    leak, albedo_leak, _ = highlight_leak(predicted, truth, geometry.light_positions(offsets, fov), fov, convention,
                                          model.config.plane_extent)
    measured = torch.isfinite(leak)
    leak, albedo_leak = leak[measured], albedo_leak[measured]

    # The demo: the bundled photo captured as `mideepbasis demo` does, against its true maps and light.
    folder = example_capture_dir()
    recipe = json.loads((folder / "truth.json").read_text())
    result = Capturer(model, CaptureConfig()).capture(folder / "photo.jpg")
    size = result.material.width
    demo_maps = downsample_maps(Material.load(folder / "truth").to_tensor()[None], size)
    demo_light = geometry.light_positions(torch.tensor([recipe["offset"]]), recipe["fov_deg"])
    demo_leak, demo_albedo_leak, demo_region = highlight_leak(result.material.to_tensor()[None], demo_maps, demo_light,
                                                              recipe["fov_deg"], convention, model.config.plane_extent)
    demo_offset = recipe["offset"]

    report = {"model": args.model or "shipped", "highlight_share": HIGHLIGHT_SHARE,
              "shared": {"materials": len(leak), "mean_leak": float(leak.mean()), "median_leak": float(leak.median()),
                         "share_over_0.05": float((leak > 0.05).float().mean()),
                         "mean_albedo_leak": float(albedo_leak.mean()), "median_albedo_leak": float(albedo_leak.median())},
              "demo": {"leak": float(demo_leak[0]), "albedo_leak": float(demo_albedo_leak[0]), "found_offset": list(result.offset), "true_offset": list(demo_offset)}}
    print(f"shared 84: mean leak {report['shared']['mean_leak']:+.4f}, median {report['shared']['median_leak']:+.4f}, "
          f"{100 * report['shared']['share_over_0.05']:.0f}% of materials over +0.05; in albedo: mean "
          f"{report['shared']['mean_albedo_leak']:+.4f}, median {report['shared']['median_albedo_leak']:+.4f}")
    print(f"demo: leak {report['demo']['leak']:+.4f}, in albedo {report['demo']['albedo_leak']:+.4f}")

    from mideepbasis.imageio import linear_to_srgb, write_image

    def hwc(image):
        return image.permute(1, 2, 0).numpy().clip(0, 1)

    panels = [linear_to_srgb(hwc(result.photo)), linear_to_srgb(hwc(result.material.to_tensor()[constants.DIFFUSE])),
              linear_to_srgb(hwc(demo_maps[0, constants.DIFFUSE])),
              np.repeat(demo_region[0, ..., None].float().numpy(), 3, axis=2)]
    write_image(args.output.with_suffix(".png"), np.concatenate(panels, axis=1))
    write_report(args.output, "highlight_leak", report)


if __name__ == "__main__":
    main()
