"""How much of the flash's highlight a model puts into its diffuse map.

    .venv/bin/python benchmarks/highlight_leak.py [--model CKPT] [-o benchmarks/results/highlight_leak.json] [capture options]

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

On real photos there is no truth: the imprint is measured where the flash's highlight falls (the
brightest 5% of the lighting mark, a glossy reference rendered under the light the capture found):
the diffuse luminance there minus elsewhere, over its mean. A blob makes it positive, a hole
negative; real surfaces vary, so its magnitude over many photos is the figure (``mean_abs``). The
imprint is measured on the held-out phone scenes (``data scenes``; photo 00, with the truth-based leak
beside) and on the 13 photos of ``real-flash-photos``, with the specular map's tint (its mean sRGB
channels' spread: a dielectric's is grey). On the real photos it is measured again with each
basis's local diffuse deviations at their mean over its pixels (``imprint_local_at_mean``): what is
left is the weights' and the global bases' share. The phone scenes' leak is also given by the
brightness of their true diffuse (thirds, darkest first) and apart for photos with clipped pixels
(``leak_by``), with the leak's correlation over the scenes with the captured specular lobe's miss under the
highlight (``lobe_log_ratio``: the log of the captured maps' lobe rendered alone over the true maps' there; a
lobe too weak leaves a blob in the diffuse, one too strong a hole). For both, what the local unit starts from (``error_map_figures``, one network pass):
its error map away from and under the highlight, and its mean diffuse deviation.

Writes the JSON report and ``highlight_leak.png`` beside it: the contact sheet of the real photos,
a row each: photo, diffuse, normal, roughness, specular, the re-render under the found flash.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import mideepbasis  # noqa: F401
import numpy as np
import torch
from common import RESULTS, SHARED_TEST, shared_predictions, write_report

from mideepbasis import constants, geometry
from mideepbasis.capturing import CaptureConfig, Capturer
from mideepbasis.capturing.refine import CLIPPED
from mideepbasis.configs import add_config_arguments, config_from_arguments, given_fields
from mideepbasis.material import Material
from mideepbasis.model.checkpoint import load_model
from mideepbasis.render.api import example_capture_dir
from mideepbasis.resampling import downsample_maps
from mideepbasis.train.losses import rgb_luminance as luminance

#: Share of the pixels, the brightest of the specular lobe's render, that make the highlight region.
HIGHLIGHT_SHARE = 0.05


def highlight_leak(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, fov: float,
                   convention: str, extent: float = 1.0, true_lobe: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-material leak (B,) of predicted maps into their diffuse under the flash at ``lights``
    (B, 3), relative and in albedo units (NaN where the lobe marks no region: a material without
    specular), and the highlight regions (B, H, W) bool. Maps (B, 10, H, W); ``true_lobe``
    (B, 1, H, W): the truth's ``specular_lobe`` under ``lights`` where the caller has rendered it."""
    from mideepbasis.train import specular_lobe

    if true_lobe is None:
        true_lobe = specular_lobe(truth, lights, fov, convention, extent)
    lobe = true_lobe[:, 0]
    threshold = torch.quantile(lobe.flatten(1), 1.0 - HIGHLIGHT_SHARE, dim=1).view(-1, 1, 1)
    region = lobe >= threshold
    excess = luminance(predicted[:, constants.DIFFUSE]) - luminance(truth[:, constants.DIFFUSE])
    inside = (excess * region).sum(dim=(1, 2)) / region.sum(dim=(1, 2))
    outside = (excess * ~region).sum(dim=(1, 2)) / (~region).sum(dim=(1, 2))  # 0 / 0 = NaN: no region
    scale = luminance(truth[:, constants.DIFFUSE]).mean(dim=(1, 2)).clamp_min(1e-3)
    return (inside - outside) / scale, inside - outside, region


def imprint(diffuse: torch.Tensor, light: torch.Tensor, fov: float, convention: str, extent: float = 1.0) -> float:
    """The flash's imprint in a diffuse map (3, H, W) captured under ``light`` (3,): mean luminance
    where the lighting mark's highlight falls (its brightest ``HIGHLIGHT_SHARE``) minus elsewhere,
    over the mean (no truth needed)."""
    from mideepbasis.model.inputs import lighting_mark

    height, width = diffuse.shape[-2:]
    mark = luminance(lighting_mark(light.view(1, 3), height, width, fov, convention, extent))[0]
    region = mark >= torch.quantile(mark.flatten(), 1.0 - HIGHLIGHT_SHARE)
    value = luminance(diffuse[None])[0]
    return float((value[region].mean() - value[~region].mean()) / value.mean().clamp_min(1e-3))


def error_map_figures(capturer, photo: torch.Tensor, light: torch.Tensor, fov: float) -> dict:
    """What the local unit starts from, in one network pass (no symmetries) on the photo (3, H, W)
    under the flash at ``light`` (3,): the mean luminance of its error map (the global blend's
    render, clipped at 1, minus the photo) away from the highlight and under it (the lighting mark's
    brightest ``HIGHLIGHT_SHARE``), and the mean of the diffuse deviations, weighted as blended
    (signed space: -1 is the bound of the local unit's tanh)."""
    from mideepbasis.capturing.pipeline import predict_small
    from mideepbasis.model.inputs import lighting_mark

    output = predict_small(capturer.model, photo[None], light.view(1, 3), fov, capturer.config.network_resolution).output
    height, width = output.error.shape[-2:]
    mark = luminance(lighting_mark(light.view(1, 3), height, width, fov, capturer.convention,
                                   capturer.model.config.plane_extent))[0]
    region = mark >= torch.quantile(mark.flatten(), 1.0 - HIGHLIGHT_SHARE)
    error = luminance(output.error)[0]
    deviation = (output.weights[0, :, None] * output.deviations[0, :, constants.DIFFUSE]).sum(dim=0)
    return {"error_map_outside": float(error[~region].mean()), "error_map_highlight": float(error[region].mean()),
            "diffuse_deviation": float(deviation.mean())}


def specular_tint(specular: torch.Tensor) -> float:
    """Spread (largest minus smallest) of a specular map's (3, H, W) mean sRGB channels."""
    from mideepbasis.imageio import linear_to_srgb

    means = linear_to_srgb(specular.clamp(0, 1)).mean(dim=(1, 2))
    return float(means.max() - means.min())


def real_photos(capturer, folder: Path) -> tuple[dict, list[np.ndarray]]:
    """Each photo of ``folder`` captured: its imprint and specular tint, and its contact-sheet row."""
    from mideepbasis.imageio import linear_to_srgb
    from mideepbasis.render import render_flash

    figures, rows = {}, []
    for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")):
        result = capturer.capture(path)
        maps = result.material.to_tensor()
        light = result.light_position
        # Where the imprint lives: the same capture with each basis's local diffuse deviations at
        # their mean over the basis's pixels (the weights and the refined global bases kept).
        at_mean = result.output.with_shrunk_deviations(constants.DIFFUSE, 0.0).maps_at(*maps.shape[-2:])[0]
        figures[path.stem] = {"imprint": imprint(maps[constants.DIFFUSE], light, result.fov, capturer.convention),
                              "imprint_local_at_mean": imprint(at_mean[constants.DIFFUSE], light, result.fov,
                                                               capturer.convention),
                              "specular_tint": specular_tint(maps[constants.SPECULAR]),
                              "clipped_share": float((result.photo.amax(dim=0) >= CLIPPED).float().mean()),
                              **error_map_figures(capturer, result.photo, light, result.fov)}
        with torch.no_grad():
            rerender = render_flash(maps[None], light.view(1, 1, 3), fov=result.fov, convention=capturer.convention)[0, 0]
        tiles = [linear_to_srgb(result.photo.clamp(0, 1)), linear_to_srgb(maps[constants.DIFFUSE]),
                 maps[constants.NORMAL] * 0.5 + 0.5, maps[constants.ROUGHNESS].expand(3, -1, -1),
                 linear_to_srgb(maps[constants.SPECULAR]), linear_to_srgb(rerender.clamp(0, 1))]
        small = [torch.nn.functional.interpolate(t[None].float(), size=(128, 128), mode="area")[0] for t in tiles]
        rows.append(torch.cat(small, dim=2).permute(1, 2, 0).numpy())
    return figures, rows


def phone_scenes(capturer, folder: Path, convention: str, light_known: bool = False) -> dict:
    """Photo 00 of each calibrated scene captured: its imprint and the truth-based leak;
    ``light_known``: the capture is told the flash's true offset instead of searching for it."""
    from mideepbasis.evaluation.real import load_scene, scene_folders, true_maps

    from mideepbasis.train import specular_lobe

    figures = {}
    for scene_folder in scene_folders(folder):
        scene = load_scene(scene_folder)
        light = (float(scene.lights[0, 0]), float(scene.lights[0, 1])) if light_known else None
        result = capturer.with_config(fov=scene.fov(0), light=light).capture(scene.photos[0])
        maps = result.material.to_tensor()
        truth = true_maps(scene, maps.shape[-1])
        lobes = specular_lobe(torch.stack([maps, truth]), scene.lights[:1].float().expand(2, 3), scene.fov(0),
                              convention)
        leak, albedo_leak, region = highlight_leak(maps[None], truth[None], scene.lights[:1], scene.fov(0), convention,
                                                   true_lobe=lobes[1:])
        lobes = lobes[:, 0]
        figures[scene.name] = {"imprint": imprint(maps[constants.DIFFUSE], result.light_position, result.fov,
                                                  convention),
                               "true_imprint": imprint(truth[constants.DIFFUSE], result.light_position, result.fov,
                                                       convention),
                               "leak": float(leak[0]), "leak_in_albedo": float(albedo_leak[0]),
                               "lobe_log_ratio": float(torch.log(lobes[0][region[0]].mean().clamp(min=1e-6)
                                                                 / lobes[1][region[0]].mean().clamp(min=1e-6))),
                               "specular_tint": specular_tint(maps[constants.SPECULAR]),
                               "true_diffuse_mean": float(luminance(truth[None, constants.DIFFUSE]).mean()),
                               "clipped_share": float((result.photo.amax(dim=0) >= CLIPPED).float().mean()),
                               **error_map_figures(capturer, result.photo, result.light_position, result.fov)}
    return figures


def signed(value: float | None) -> str:
    """A leak for the printed summary ("-": no scene)."""
    return "-" if value is None else f"{value:+.3f}"


def leak_by_darkness(figures: dict) -> dict:
    """The scenes' mean leak (relative and in albedo units) in thirds by their true diffuse's mean
    luminance (darkest first), apart for the scenes whose photo has clipped pixels and those without, and
    the leak's correlation with the captured lobe's miss (``lobe_log_ratio``)."""
    scenes = sorted(figures.values(), key=lambda figure: figure["true_diffuse_mean"])

    def thirds(key: str) -> list[float]:
        return [float(third.mean()) for third in np.array_split(np.array([figure[key] for figure in scenes]), 3)]

    clipped = [figure["leak"] for figure in scenes if figure["clipped_share"] > 0]
    unclipped = [figure["leak"] for figure in scenes if figure["clipped_share"] == 0]
    return {"by_diffuse_third": thirds("leak"), "in_albedo_by_diffuse_third": thirds("leak_in_albedo"),
            "clipped": float(np.mean(clipped)) if clipped else None, "clipped_scenes": len(clipped),
            "unclipped": float(np.mean(unclipped)) if unclipped else None,
            "correlation_with_lobe_log_ratio": float(np.corrcoef([figure["leak"] for figure in scenes],
                                                                 [figure["lobe_log_ratio"] for figure in scenes])[0, 1])}


def summary(figures: dict) -> dict:
    """Means over photos of the imprint's magnitude and sign, and of the specular tint."""
    values = {key: np.array([f[key] for f in figures.values() if np.isfinite(f[key])]) for key in next(iter(figures.values()))}
    result = {"photos": len(figures), "mean_abs_imprint": float(np.abs(values["imprint"]).mean()),
              "mean_imprint": float(values["imprint"].mean()), "mean_specular_tint": float(values["specular_tint"].mean()),
              "tinted_over_0.05": int((values["specular_tint"] > 0.05).sum())}
    if "imprint_local_at_mean" in values:
        result["mean_abs_imprint_local_at_mean"] = float(np.abs(values["imprint_local_at_mean"]).mean())
    if "error_map_outside" in values:
        result.update({f"mean_{key}": float(values[key].mean())
                       for key in ("error_map_outside", "error_map_highlight", "diffuse_deviation")})
    if "clipped_share" in values:
        result["largest_clipped_share"] = float(values["clipped_share"].max())
    if "leak" in values:
        result.update({"mean_leak": float(values["leak"].mean()),
                       "mean_abs_true_imprint": float(np.abs(values["true_imprint"]).mean()),
                       "mean_lobe_log_ratio": float(values["lobe_log_ratio"].mean())})
    return result


def error_map_line(part: dict) -> str:
    """The printed line of ``error_map_figures``' means."""
    return (f"  the local unit's error map {part['mean_error_map_outside']:+.3f} away from the highlight, "
            f"{part['mean_error_map_highlight']:+.3f} under it; its diffuse deviations {part['mean_diffuse_deviation']:+.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "highlight_leak.json")
    parser.add_argument("--real", type=Path, default=SHARED_TEST.parent / "real-flash-photos",
                        help="a folder of real flash photos (no truth)")
    parser.add_argument("--scenes", type=Path, default=Path("runs/phone_scenes"),
                        help="calibrated phone scenes with their truth (mideepbasis data scenes)")
    parser.add_argument("--scenes-light-known", action="store_true",
                        help="tell the phone scenes' captures the true flash offset (no search)")
    parser.add_argument("--skip-shared", action="store_true", help="leave out the shared set and the demo")
    # The captures' options, as `mideepbasis capture` takes them (--refine-steps 0: the network's maps alone).
    add_config_arguments(parser, CaptureConfig, describe=False)
    args = parser.parse_args()

    model = load_model(args.model)
    fov, convention = constants.DEFAULT_FOV_DEG, model.config.convention
    capturer = Capturer(model, config_from_arguments(CaptureConfig, args))
    report = {"model": args.model or "shipped", "highlight_share": HIGHLIGHT_SHARE,
              "scenes_light_known": args.scenes_light_known,
              "capture_changes": given_fields(args, CaptureConfig)}
    real, rows = real_photos(capturer, args.real)
    report["real_photos"] = {**summary(real), "per_photo": real}
    print(f"real photos ({len(real)}): mean |imprint| {report['real_photos']['mean_abs_imprint']:.4f} (signed "
          f"{report['real_photos']['mean_imprint']:+.4f}), specular tint {report['real_photos']['mean_specular_tint']:.4f}, "
          f"{report['real_photos']['tinted_over_0.05']} tinted over 0.05; with the local diffuse deviations at each "
          f"basis's mean {report['real_photos']['mean_abs_imprint_local_at_mean']:.4f}")
    print(error_map_line(report["real_photos"]))
    from mideepbasis.imageio import write_image

    write_image(args.output.with_suffix(".png"), np.concatenate(rows, axis=0).clip(0, 1))
    if args.scenes.is_dir():
        scenes = phone_scenes(capturer, args.scenes, convention, args.scenes_light_known)
        report["phone_scenes"] = {**summary(scenes), "leak_by": leak_by_darkness(scenes), "per_scene": scenes}
        print(f"phone scenes ({len(scenes)}): mean |imprint| {report['phone_scenes']['mean_abs_imprint']:.4f} (truth's "
              f"{report['phone_scenes']['mean_abs_true_imprint']:.4f}), leak {report['phone_scenes']['mean_leak']:+.4f}, "
              f"specular tint {report['phone_scenes']['mean_specular_tint']:.4f}, the captured lobe's log ratio to "
              f"the true one under the highlight {report['phone_scenes']['mean_lobe_log_ratio']:+.2f}")
        print(error_map_line(report["phone_scenes"]))
        by = report["phone_scenes"]["leak_by"]
        print("  leak by the true diffuse's brightness, darkest third first: "
              + " / ".join(f"{leak:+.3f}" for leak in by["by_diffuse_third"]) + " (in albedo "
              + " / ".join(f"{leak:+.4f}" for leak in by["in_albedo_by_diffuse_third"]) + ")"
              + f"; {by['clipped_scenes']} scenes with clipped pixels {signed(by['clipped'])}, the others "
              f"{signed(by['unclipped'])}; correlation with the captured lobe's log ratio to the true one under the "
              f"highlight {by['correlation_with_lobe_log_ratio']:+.2f}")
    if args.skip_shared:
        write_report(args.output, "highlight_leak", report)
        return
    truth, offsets, predicted = shared_predictions(model)
    leak, albedo_leak, _ = highlight_leak(predicted, truth, geometry.light_positions(offsets, fov), fov, convention,
                                          model.config.plane_extent)
    measured = torch.isfinite(leak)
    leak, albedo_leak = leak[measured], albedo_leak[measured]

    # The demo: the bundled photo captured as `mideepbasis demo` does, against its true maps and light.
    folder = example_capture_dir()
    recipe = json.loads((folder / "truth.json").read_text())
    result = capturer.capture(folder / "photo.jpg")
    size = result.material.width
    demo_maps = downsample_maps(Material.load(folder / "truth").to_tensor()[None], size)
    demo_light = geometry.light_positions(torch.tensor([recipe["offset"]]), recipe["fov_deg"])
    demo_leak, demo_albedo_leak, _ = highlight_leak(result.material.to_tensor()[None], demo_maps, demo_light,
                                                              recipe["fov_deg"], convention, model.config.plane_extent)
    demo_offset = recipe["offset"]

    report.update({
              "shared": {"materials": len(leak), "mean_leak": float(leak.mean()), "median_leak": float(leak.median()),
                         "share_over_0.05": float((leak > 0.05).float().mean()),
                         "mean_albedo_leak": float(albedo_leak.mean()), "median_albedo_leak": float(albedo_leak.median())},
              "demo": {"leak": float(demo_leak[0]), "albedo_leak": float(demo_albedo_leak[0]),
                       "found_offset": list(result.offset), "true_offset": list(demo_offset)}})
    print(f"shared 84: mean leak {report['shared']['mean_leak']:+.4f}, median {report['shared']['median_leak']:+.4f}, "
          f"{100 * report['shared']['share_over_0.05']:.0f}% of materials over +0.05; in albedo: mean "
          f"{report['shared']['mean_albedo_leak']:+.4f}, median {report['shared']['median_albedo_leak']:+.4f}")
    print(f"demo: leak {report['demo']['leak']:+.4f}, in albedo {report['demo']['albedo_leak']:+.4f}")

    write_report(args.output, "highlight_leak", report)


if __name__ == "__main__":
    main()
