"""Figures people look at: loss curves and validation sheets (PNG, written atomically)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .imageio import linear_to_srgb, write_image


def _save_figure(figure, path: Path) -> Path:
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")
    figure.savefig(temporary, dpi=100)
    plt.close(figure)
    temporary.replace(path)
    return path


def plot_training_log(log_path: Path, output: Path) -> Path | None:
    """Loss curves (total, supervised, variation consistency) and validation RMSE from a train.jsonl."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [json.loads(line) for line in Path(log_path).read_text().splitlines() if line.strip()]
    losses = [r for r in records if "loss" in r]
    validation = [r for r in records if "validation_rmse" in r]
    if not losses:
        return None
    figure, axes = plt.subplots(1, 2 if validation else 1, figsize=(12 if validation else 6, 4), squeeze=False)
    steps = [r["step"] for r in losses]
    for key, label in (("loss", "total"), ("l_sup", "supervised L1"), ("l_vc", "variation consistency")):
        axes[0, 0].plot(steps, [r[key] for r in losses], label=label)
    axes[0, 0].set_xlabel("step")
    axes[0, 0].set_yscale("log")
    axes[0, 0].set_title("training losses")
    axes[0, 0].legend()
    if validation:
        for name in validation[0]["validation_rmse"]:
            axes[0, 1].plot([r["step"] for r in validation], [r["validation_rmse"][name] for r in validation], label=name)
        axes[0, 1].set_xlabel("step")
        axes[0, 1].set_title("validation map RMSE (held-out procedural)")
        axes[0, 1].legend()
    figure.tight_layout()
    return _save_figure(figure, output)


def map_tiles(maps: torch.Tensor) -> list[np.ndarray]:
    """(10, H, W) maps as four (H, W, 3) sRGB-encoded tiles: normal, diffuse, roughness, specular."""
    hwc = maps.detach().cpu().permute(1, 2, 0).numpy()
    return [(hwc[..., 0:3] + 1) / 2, linear_to_srgb(np.clip(hwc[..., 3:6], 0, 1)),
            np.repeat(hwc[..., 6:7], 3, axis=2), linear_to_srgb(np.clip(hwc[..., 7:10], 0, 1))]


def validation_sheet(photos: torch.Tensor, predicted: torch.Tensor, truth: torch.Tensor, output: Path) -> Path:
    """Per row: the input photo, then predicted and true maps side by side (normal, diffuse, roughness, specular)."""
    rows = []
    for photo, pred, true in zip(photos, predicted, truth):
        tiles = [linear_to_srgb(photo.detach().cpu().permute(1, 2, 0).numpy().clip(0, 1))]
        for p, t in zip(map_tiles(pred), map_tiles(true)):
            tiles += [p, t]
        rows.append(np.concatenate(tiles, axis=1))
    return write_image(output, np.clip(np.concatenate(rows, axis=0), 0, 1))


def capture_report(result, folder: Path, rerender: torch.Tensor, error: torch.Tensor, environment: np.ndarray,
                   rerender_rmse: float) -> Path:
    """``report.png`` (photo, maps, re-rendering, error, environment rendering, estimated light,
    refinement curve, timings) and ``report.html`` around it, in ``folder``."""
    import html

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .export import light_diagram_points, report_table

    def srgb(image):
        return linear_to_srgb(image.detach().cpu().permute(1, 2, 0).numpy().clip(0, 1))

    figure, axes = plt.subplots(2, 6, figsize=(18, 6.4))
    tiles = map_tiles(result.material.to_tensor())
    panels = [("photo", srgb(result.photo)), ("normal", tiles[0]), ("diffuse", tiles[1]), ("roughness", tiles[2]),
              ("specular", tiles[3]), ("re-rendering", srgb(rerender)),
              ("|error| x 4", np.clip(error.detach().cpu().permute(1, 2, 0).numpy() * 4, 0, 1)),
              ("environment (studio)", linear_to_srgb(environment.clip(0, 1)))]
    for axis, (title, image) in zip(axes.ravel(), panels):
        axis.imshow(np.clip(image, 0, 1))
        axis.set_title(title)
        axis.axis("off")
    light_axis, curve_axis, text_axis, spare = axes.ravel()[8:]
    diagram = light_diagram_points(result.fov, result.offset)
    circle = plt.Circle((0, 0), diagram["radius_deg"], fill=False, linestyle="--", color="grey")
    light_axis.add_patch(circle)
    light_axis.plot(*diagram["estimate_deg"], "o", color="tab:orange")
    light_axis.plot(0, 0, "+", color="black")
    light_axis.set_xlim(-18, 18)
    light_axis.set_ylim(-18, 18)
    light_axis.set_aspect("equal")
    light_axis.set_title(f"flash offset {result.offset_angle_deg:.1f} deg\n({'searched' if result.searched else 'given'})")
    light_axis.set_xlabel("x [deg]")
    light_axis.set_ylabel("y [deg]")
    if result.refinement_losses:
        curve_axis.plot(result.refinement_losses)
        curve_axis.set_title("refinement (L1 to the photo)")
        curve_axis.set_xlabel("step")
    else:
        curve_axis.text(0.5, 0.5, "no refinement", ha="center", va="center")
        curve_axis.axis("off")
    timing_lines = [f"{stage}: {seconds:.2f} s" for stage, seconds in result.timings.items()]
    text_axis.text(0.0, 1.0, "\n".join(["timings"] + timing_lines + ["", f"re-render RMSE {rerender_rmse:.4f}",
                                                                   f"fov {result.fov:.1f} deg ({result.fov_source})"]),
                   va="top", family="monospace", fontsize=9)
    text_axis.axis("off")
    spare.axis("off")
    figure.tight_layout()
    png = _save_figure(figure, Path(folder) / "report.png")

    rows = {"flash offset [patch half-widths]": f"({result.offset[0]:.3f}, {result.offset[1]:.3f})",
            "flash offset [deg]": f"{result.offset_angle_deg:.2f} ({'searched' if result.searched else 'given'})",
            "field of view [deg]": f"{result.fov:.1f} ({result.fov_source})",
            "re-rendering RMSE (linear)": f"{rerender_rmse:.4f}",
            **{f"time: {stage} [s]": f"{seconds:.2f}" for stage, seconds in result.timings.items()}}
    notes = "".join(f"<li>{html.escape(note)}</li>" for note in result.notes) or "<li>none</li>"
    images = "".join(f'<figure><img src="{name}.png" width="256"><figcaption>{name}</figcaption></figure>'
                     for name in ("photo", "normal", "diffuse", "roughness", "specular", "rerender", "error", "environment"))
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>mideepbasis capture</title>
<style>body{{font-family:sans-serif;margin:2em}} figure{{display:inline-block;margin:4px}} th{{text-align:left;padding-right:1em}}</style>
</head><body>
<h1>mideepbasis capture</h1>
<img src="report.png" style="max-width:100%">
<h2>Summary</h2><table>{report_table(rows)}</table>
<h2>Notes</h2><ul>{notes}</ul>
<h2>Images</h2>{images}
<p>Files: the maps and <code>material.json</code>, <code>light.json</code>, <code>scene.xml</code> (Mitsuba),
<code>material.gltf</code> (glTF 2.0 with KHR_materials_specular).</p>
</body></html>
"""
    (Path(folder) / "report.html").write_text(page)
    return png
