"""Figures and reports people look at (PNG written atomically): loss curves, validation sheets,
the capture report, and the evaluation's files (``write_evaluation``: summary, tables, bars,
galleries, the environment and lighting figures).

Nothing here computes a metric: the numbers come from ``mideepbasis.evaluation`` and the capture.
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
# Here, not in report_sheet: export.save_capture lays the sheet out beside the preview thread, and
# ImageFont loads FreeType's library, which is not to be loaded beside running threads.
from PIL import Image, ImageDraw, ImageFont

from . import constants, geometry
from .imageio import linear_to_srgb, write_image


def save_figure(figure, path: Path) -> Path:
    """Write a matplotlib figure to ``path`` (100 dpi) atomically and close it."""
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
    return save_figure(figure, output)


def map_tiles(maps: torch.Tensor) -> list[np.ndarray]:
    """(10, H, W) maps as four (H, W, 3) sRGB-encoded tiles: normal, diffuse, roughness, specular."""
    hwc = maps.detach().cpu().permute(1, 2, 0).numpy()
    return [(hwc[..., constants.NORMAL] + 1) / 2, linear_to_srgb(np.clip(hwc[..., constants.DIFFUSE], 0, 1)),
            np.repeat(hwc[..., constants.ROUGHNESS], 3, axis=2),
            linear_to_srgb(np.clip(hwc[..., constants.SPECULAR], 0, 1))]


def validation_sheet(photos: torch.Tensor, predicted: torch.Tensor, truth: torch.Tensor, output: Path) -> Path:
    """Per row: the input photo, then predicted and true maps side by side (normal, diffuse, roughness, specular)."""
    rows = []
    for photo, pred, true in zip(photos, predicted, truth):
        tiles = [linear_to_srgb(photo.detach().cpu().permute(1, 2, 0).numpy().clip(0, 1))]
        for p, t in zip(map_tiles(pred), map_tiles(true)):
            tiles += [p, t]
        rows.append(np.concatenate(tiles, axis=1))
    return write_image(output, np.clip(np.concatenate(rows, axis=0), 0, 1))


#: Size of a panel of the capture report [pixels], and of the title band above it.
REPORT_TILE, REPORT_TITLE = 256, 26


def light_diagram_points(fov: float, offset: tuple[float, float]) -> dict:
    """The reachable offsets' radius and the estimate, for the report's light diagram [deg]."""
    height = constants.camera_height(fov)
    return {"radius_deg": constants.MAX_OFFSET_DEG,
            "estimate_deg": [math.degrees(math.atan(t / height)) for t in offset],
            "max_offset": geometry.max_offset(fov)}


def report_table(rows: dict) -> str:
    """The rows of an HTML table, one ``<tr><th>key</th><td>value</td></tr>`` per item, escaped."""
    return "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows.items())


def _draw_light_diagram(draw, box: tuple[int, int, int, int], diagram: dict, font) -> None:
    """The reachable offsets (dashed circle of radius delta), the centre and the estimate, in degrees."""
    left, top, right, bottom = box
    centre_x, centre_y = (left + right) / 2, (top + bottom) / 2
    scale = (min(right - left, bottom - top) / 2 - 14) / 18.0  # the panel spans +-18 deg
    radius = diagram["radius_deg"] * scale
    for step in range(0, 360, 12):  # a dashed circle: 30 arcs
        draw.arc((centre_x - radius, centre_y - radius, centre_x + radius, centre_y + radius), step, step + 7,
                 fill=(128, 128, 128), width=2)
    draw.line((centre_x - 8, centre_y, centre_x + 8, centre_y), fill=(0, 0, 0), width=1)
    draw.line((centre_x, centre_y - 8, centre_x, centre_y + 8), fill=(0, 0, 0), width=1)
    x, y = diagram["estimate_deg"]
    point = (centre_x + x * scale, centre_y - y * scale)  # +y up
    draw.ellipse((point[0] - 6, point[1] - 6, point[0] + 6, point[1] + 6), fill=(255, 127, 14))
    draw.text((left + 4, bottom - 18), f"x, y [deg]; circle: {diagram['radius_deg']:g} deg", fill=(80, 80, 80),
              font=font)


def _panel_image(image: np.ndarray, size: int, resample):
    """An (H, W, 3) image in [0, 1] as an 8-bit Pillow image of ``size`` x ``size`` pixels."""
    return Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).resize((size, size), resample)


def _draw_curve(draw, box: tuple[int, int, int, int], values: list[float], font) -> None:
    """A line plot of ``values`` against their index, with its first and last value written."""
    left, top, right, bottom = box
    inner = (left + 34, top + 10, right - 10, bottom - 26)
    draw.rectangle(inner, outline=(160, 160, 160))
    low, high = min(values), max(values)
    span = (high - low) or 1.0
    points = [(inner[0] + (inner[2] - inner[0]) * i / max(1, len(values) - 1),
               inner[3] - (inner[3] - inner[1]) * (v - low) / span) for i, v in enumerate(values)]
    draw.line(points, fill=(31, 119, 180), width=2)
    draw.text((inner[0], bottom - 20), f"step 0 .. {len(values) - 1}: {values[0]:.4f} -> {values[-1]:.4f}",
              fill=(0, 0, 0), font=font)


@dataclass
class ReportSheet:
    """``report.png`` composed but for its environment panel (``report_sheet``): the sheet can be laid
    out while the environment preview is still path traced."""

    image: Any
    """The Pillow image of the sheet."""

    environment_box: tuple[int, int, int, int]
    """Where the environment panel goes (left, top, right, bottom) [pixels]."""

    def with_environment(self, environment: np.ndarray) -> np.ndarray:
        """The whole sheet, (H, W, 3) in [0, 1], with ``environment`` (H, W, 3) linear in its panel."""
        sheet = self.image.copy()
        left, top = self.environment_box[:2]
        sheet.paste(_panel_image(linear_to_srgb(environment.clip(0, 1)), REPORT_TILE - 8, Image.Resampling.BILINEAR),
                    (left + 4, top + 4))
        return np.asarray(sheet, dtype=np.float32) / 255.0


def report_panel(image: torch.Tensor) -> torch.Tensor:
    """(C, H, W) as a sheet's panel is made from it: area-averaged (in linear light) to twice
    ``REPORT_TILE`` where larger, before the sRGB encoding (which took 1.4 s of a 2048 px capture's
    report at full size); unchanged where not larger. Applying it twice changes nothing."""
    from .resampling import downsample

    image = image.detach().cpu()
    return downsample(image, 2 * REPORT_TILE) if image.shape[-1] > 2 * REPORT_TILE else image


def report_sheet(result, rerender: torch.Tensor, error: torch.Tensor, rerender_rmse: float) -> ReportSheet:
    """The capture's sheet (photo, maps, re-rendering, error, estimated light, refinement curve,
    timings) with an empty environment panel, titled: ``ReportSheet.with_environment`` fills it.

    The sheet is composed with Pillow, not matplotlib: importing and laying out a matplotlib
    figure took 2.8 s of a 4-s save (issue 14)."""
    from .resampling import downsample

    panel_limit = 2 * REPORT_TILE
    small = report_panel

    def srgb(image):
        return linear_to_srgb(small(image).permute(1, 2, 0).numpy().clip(0, 1))

    material = result.material
    if material.width > panel_limit:  # map by map: a 4096 px stack of all ten channels is 0.7 GB
        small_maps = torch.cat([downsample(m, panel_limit) for m in (material.normal, material.diffuse,
                                                                      material.roughness, material.specular)])
        maps = torch.cat([geometry.unit_vectors(small_maps[constants.NORMAL], dim=0), small_maps[constants.REFLECTANCE]])
    else:
        maps = material.to_tensor()
    tiles = map_tiles(maps)
    panels = [("photo", srgb(result.photo)), ("normal", tiles[0]), ("diffuse", tiles[1]), ("roughness", tiles[2]),
              ("specular", tiles[3]), ("re-rendering", srgb(rerender)),
              ("|error| x 4", np.clip(small(error).permute(1, 2, 0).numpy() * 4, 0, 1)),
              ("environment (studio)", None)]
    size, band, columns = REPORT_TILE, REPORT_TITLE, 6
    sheet = Image.new("RGB", (columns * size, 2 * (size + band)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    title_font, small_font = ImageFont.load_default(size=16), ImageFont.load_default(size=12)
    boxes = [(c * size, r * (size + band) + band, (c + 1) * size, (r + 1) * (size + band))
             for r in range(2) for c in range(columns)]
    for (title, image), box in zip(panels, boxes):
        if image is not None:
            sheet.paste(_panel_image(image, size - 8, Image.Resampling.BILINEAR), (box[0] + 4, box[1] + 4))
        draw.text((box[0] + 6, box[1] - band + 4), title, fill=(0, 0, 0), font=title_font)
    light_box, curve_box, text_box, tiling_box = boxes[8], boxes[9], boxes[10], boxes[11]
    if result.material.provenance.get("capture", {}).get("tileable"):
        from .tiling import tiled

        # The diffuse map (sRGB) repeated 3 x 3: a seam would show as a cross through the panel.
        repeated = tiled(torch.from_numpy(np.ascontiguousarray(tiles[1])).permute(2, 0, 1)).permute(1, 2, 0).numpy()
        sheet.paste(_panel_image(repeated, size - 8, Image.Resampling.BOX), (tiling_box[0] + 4, tiling_box[1] + 4))
        draw.text((tiling_box[0] + 6, tiling_box[1] - band + 4), "diffuse, tiled 3 x 3", fill=(0, 0, 0),
                  font=title_font)
    source = "searched" if result.searched else "given"
    draw.text((light_box[0] + 6, light_box[1] - band + 4), f"flash offset {result.offset_angle_deg:.1f} deg ({source})",
              fill=(0, 0, 0), font=title_font)
    _draw_light_diagram(draw, light_box, light_diagram_points(result.fov, result.offset), small_font)
    draw.text((curve_box[0] + 6, curve_box[1] - band + 4), "refinement (L1 to the photo)", fill=(0, 0, 0),
              font=title_font)
    if len(result.refinement_losses) > 1:
        _draw_curve(draw, curve_box, list(result.refinement_losses), small_font)
    else:
        draw.text((curve_box[0] + 70, (curve_box[1] + curve_box[3]) // 2), "no refinement", fill=(0, 0, 0),
                  font=small_font)
    lines = (["timings"] + [f"{stage}: {seconds:.2f} s" for stage, seconds in result.timings.items()]
             + ["", f"re-render RMSE {rerender_rmse:.4f}", f"fov {result.fov:.1f} deg ({result.fov_source})"])
    draw.multiline_text((text_box[0] + 6, text_box[1] - band + 4), "\n".join(lines), fill=(0, 0, 0), font=small_font,
                        spacing=4)
    return ReportSheet(image=sheet, environment_box=boxes[7])


def capture_report(result, folder: Path, rerender: torch.Tensor, error: torch.Tensor, environment: np.ndarray,
                   rerender_rmse: float, sheet: ReportSheet | None = None) -> Path:
    """``report.png`` (``report_sheet`` with the environment rendering) and ``report.html`` around
    it, in ``folder``; ``sheet``: the sheet already composed (``export.save_capture`` lays it out
    while the previews are path traced)."""
    write_report_sheet(folder, sheet or report_sheet(result, rerender, error, rerender_rmse), environment)
    return write_report_page(result, folder, rerender_rmse)


def write_report_sheet(folder: Path, sheet: ReportSheet, environment: np.ndarray) -> Path:
    """``report.png`` in ``folder``: the sheet with the environment rendering (linear (H, W, 3))."""
    return write_image(Path(folder) / "report.png", sheet.with_environment(environment))


def detail_summary(capture: dict) -> str | None:
    """What the maps hold above the network's resolution, in words, from a capture's provenance
    (``capture``: ``network_size``, ``detail_added``, ``relief_test_read``, ``normal_detail``,
    ``fine_relief``, ``fine_relief_strength``, ``fine_relief_symmetries``, ``colour_tested``,
    ``detail_denoised``); None for a provenance without them."""
    if "network_size" not in capture:
        return None
    if not capture.get("detail_added"):
        return f"none: the maps hold the network's {max(capture['network_size'])} px answer"
    summary = _added_detail_summary(capture)
    if capture.get("colour_tested") and float(capture.get("normal_detail", 1.0)) > 0.005:
        summary += "; the normals' detail left out the contrast a change of hue explains (--colour-test)"
    if capture.get("detail_denoised"):
        summary += "; the photo's noise was taken out of it first (--denoise-detail)"
    return summary


def _added_detail_summary(capture: dict) -> str:
    """``detail_summary`` of a capture that added the photo's detail, but for its noise."""
    from .capturing.detail import RELIEF_MIN_FACTOR

    network_size = max(capture["network_size"])
    if not capture.get("relief_test_read"):
        return (f"the photo's, by the gains fitted at {network_size} px (the relief test reads photos of "
                f"{RELIEF_MIN_FACTOR * network_size} px and more)")
    kept = float(capture.get("normal_detail", 1.0))
    if kept <= 0.005:
        return ("the photo's; the relief test read its fine contrast as albedo: no relief in the normals, the "
                "diffuse takes it as albedo")
    # The diffuse's fitted gains follow the network's diffuse, which carries some of a relief's shading.
    shading = "the diffuse's fitted gains carry some of the shading too"
    if capture.get("fine_relief"):
        # A provenance that does not record the strength read the unit's whole relief.
        strength = float(capture.get("fine_relief_strength", 1.0))
        mirrors = int(capture.get("fine_relief_symmetries") or 1)  # one reading where it is not recorded
        read_in = ("the photo" if mirrors == 1 else
                   f"the photo and its {mirrors - 1} mirror image{'s' if mirrors > 2 else ''}, where they agree")
        shading += (f"; the normals' detail is the relief the network's normal unit reads in {read_in}, times "
                    f"{strength:g} (--fine-relief-strength)")
    if kept >= 0.995:
        return ("the photo's; the relief test read its fine contrast as shading: the normals keep all of their "
                f"detail; {shading}")
    return (f"the photo's; the relief test kept {kept:.0%} of the normals' detail, and the diffuse took the other "
            f"{1.0 - kept:.0%} of the fine contrast as albedo; {shading}")


def write_report_page(result, folder: Path, rerender_rmse: float) -> Path:
    """``report.html`` in ``folder`` around its ``report.png``: the summary, the notes, the images
    and the relighting viewer (which embeds the map files: write them first). Returns report.png's path."""

    rows = {"flash offset [patch half-widths]": f"({result.offset[0]:.3f}, {result.offset[1]:.3f})",
            "flash offset [deg]": f"{result.offset_angle_deg:.2f} ({'searched' if result.searched else 'given'})",
            "field of view [deg]": f"{result.fov:.1f} ({result.fov_source})",
            "re-rendering RMSE (linear)": f"{rerender_rmse:.4f}",
            "detail above the network's resolution": detail_summary(result.material.provenance.get("capture", {})),
            **{f"time: {stage} [s]": f"{seconds:.2f}" for stage, seconds in result.timings.items()}}
    rows = {key: value for key, value in rows.items() if value is not None}
    notes = "".join(f"<li>{html.escape(note)}</li>" for note in result.notes) or "<li>none</li>"
    names = ("photo", "normal", "diffuse", "roughness", "specular", "rerender", "error", "environment",
             "preview_sphere", "preview_cloth")
    images = "".join(f'<figure><img src="{name}.png" width="256"><figcaption>{name}</figcaption></figure>'
                     for name in names if (Path(folder) / f"{name}.png").is_file())
    from .viewer import viewer_section, viewer_size

    viewer = viewer_section(Path(folder), tuple(result.light_position.tolist()), result.fov,
                            viewer_size(result.material.width))
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>mideepbasis capture</title>
<style>body{{font-family:sans-serif;margin:2em}} figure{{display:inline-block;margin:4px}} th{{text-align:left;padding-right:1em}}</style>
</head><body>
<h1>mideepbasis capture</h1>
<img src="report.png" style="max-width:100%">
{viewer}
<h2>Summary</h2><table>{report_table(rows)}</table>
<h2>Notes</h2><ul>{notes}</ul>
<h2>Images</h2>{images}
<p>Files: the maps and <code>material.json</code>, <code>light.json</code>, <code>scene.xml</code> (Mitsuba),
<code>material.gltf</code> (glTF 2.0 with KHR_materials_specular).</p>
</body></html>
"""
    (Path(folder) / "report.html").write_text(page)
    return Path(folder) / "report.png"
