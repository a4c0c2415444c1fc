"""Maps as sharp as the photo: captures at 1024 px against the truth's fine detail.

    .venv/bin/python benchmarks/detail.py [--model CKPT] [--materials 12] [--flat 4] [--size 1024]
    .venv/bin/python benchmarks/detail.py --materials 1 --flat 1 --size 256 --low 128 --lights 2 -o /tmp/detail.json --sheet /tmp/detail.png

Held-out procedural materials (seeds 5e8 on, one family after another) are generated at
``--size`` and photographed as ``evaluate`` photographs them (``flash_photos``: 8-bit sRGB, a
seeded hand-held flash at 45 deg field of view); the capture is told the flash's offset, so no
lighting search adds noise, and refines as ``capture`` does (``--refine-steps`` to change). Each
material is captured three ways:

- ``upsampled 256``: the photo area-averaged to ``--low`` px and captured, the maps upsampled
  bilinearly to ``--size`` (normals renormalised): the default capture's answer made bigger;
- ``1024, no detail``: captured at full size with ``CaptureConfig.detail`` False;
- ``1024, detail``: captured at full size with ``CaptureConfig.detail`` True.

Against the truth at full size: map RMSE (``map_rmse``, the stored encoding), re-rendering RMSE
under ``--lights`` of ``evaluate``'s seeded lights and views (clipped sRGB, ``rerender``), and the
detail: each map's energy above the 128-px band over the truth's (``high_band_energy``: energy,
so twice the amplitude reads 4), pooled over a group as the sum of the energies over the sum of the
truth's (near-constant true maps would make a mean of ratios blow up); per material in the JSON.
1.0 is right, near 0 the blur of a 128-px answer, above 1 invented detail. Beside it, the
detail's correlation with the truth's (``fine_cross``, pooled as the ratio): the share of it that
is the truth's; made-up detail of the right energy reads about 0. And a bound: the map RMSE of
the upsampled answer with its band above the 128-px band replaced by the truth's
(``with_true_detail``, key ``true_detail_rmse``), the least a detail step could reach.

Two groups, reported apart: ``relief`` (the families' materials as generated) and ``flat
textured`` (stone of veined or grained variants and wood, the same generator's materials with
their normals set flat: strong albedo texture, no relief, where a detail step must not turn
colour into relief). A flat normal has no energy to divide by: beside the ratios, each row's
fine tilt [deg] (the normals' energy above the band as an RMS angle) shows relief made up.

``--visibility`` measures instead how much of the truth's fine relief the photo shows at all
(``shading_visibility``): no capture, entry ``detail_visibility``. With ``--swap-reflectance``
each relief is photographed under the next relief material's diffuse, roughness and specular, so
that what the photo shows cannot come through an albedo that follows the relief: entry
``detail_visibility_swapped``.

``--photo-jitter SIGMA`` multiplies each photo by 1 + SIGMA N(0, 1) (``--jitter-seed``) before
capturing, far below its 8-bit steps at 1e-5: how much of a difference between the rows is the
refinement's spread on glossy materials rather than the resolution. Entry
``detail_photo_jitter_SEED``.

``--first-seed N`` takes the materials from seed N on instead of the benchmark's: a set apart
from it to calibrate the detail step's constants on (``detail.DIFFUSE_GAIN``, the relief test's
thresholds). Entry ``detail_seeds_N``; every other entry it writes ends in ``_seeds_N`` too.
``--no-relief-test`` captures without the relief test: its entries end in ``_no_relief_test``.
``--no-fine-relief`` captures with the normals' detail as the photo's contrast times their gains
instead of the relief the network's normal unit reads (``CaptureConfig.fine_relief``, on by
default): its entries end in ``_no_fine_relief``. ``--fine-relief-strength S`` other than capture's
default (``CaptureConfig.fine_relief_strength``) ends them in ``_fine_relief_S`` (the entries
``detail_fine_relief`` and ``detail_seeds_500001000_fine_relief`` hold one reading at 1, from before
capture read the photo's half turn too).
``--relief-reader FILE`` reads that relief with a relief reader (``CaptureConfig.relief_reader``):
its entries end in ``_reader`` after those.
``--denoise`` captures with the photo's fine contrast denoised (``CaptureConfig.denoise_detail``):
its entries end in ``_denoised``.
``--colour-test`` / ``--no-colour-test`` capture with or without the contrast a change of hue explains
left out of the normals' detail (``CaptureConfig.colour_test``): other than capture's default, entries
end in ``_colour_test`` or ``_no_colour_test``.
``--no-keep-lobe-peak`` captures with the roughness as refined under the normals' detail
(``CaptureConfig.keep_lobe_peak`` False): its entries end in ``_lobe_unkept``.
``--swap-reflectance`` without ``--visibility`` captures the relief materials so photographed:
entries end in ``_swapped``.

``--registration DIR`` measures instead how much of a calibrated real scene's fine detail (its
photo 00's contrast above the band) the other photos show where it is (``registration``): the
real protocol at full resolution can credit a detail step only with that. No capture, entry
``detail_registration``.

``--relief-scales`` measures instead how the relief materials' slopes at the capture's ``--low``
px compare between each material generated there and generated at ``--size`` px with its height
area-averaged to ``--low`` px (``relief_scales``): the generator scales each relief to the tilt it
draws at the size it draws at, so the larger material's relief is spread over finer octaves.
No capture, entry ``detail_relief_scales``.

Writes the figures as the entry ``detail`` of results/model_quality.json and the contact sheet (``--sheet``; ``--no-sheet`` skips it): for two
relief materials and one flat textured one, the centre half of the sample (512 px at 1024): the
photo, the true, upsampled and detailed diffuse, the true, upsampled and detailed normal.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import cv2
import mideepbasis  # noqa: F401
import numpy as np
import torch
from common import RESULTS, write_section

from mideepbasis import constants, geometry
from mideepbasis.capturing import CaptureConfig, Capturer
from mideepbasis.data.procedural import FAMILIES, GeneratorConfig, generate, generate_surface
from mideepbasis.data.procedural.core import height_to_normal
from mideepbasis.evaluation import (DETAIL_BAND, above_band, evaluation_offsets, flash_photos, high_band_energy, map_rmse,
                                    random_lights_and_views, rerender)
from mideepbasis.model.checkpoint import load_model
from mideepbasis.resampling import downsample, upsample_maps

#: First seed of the relief materials (training never draws seeds this small: ``search_prior``).
HELD_OUT_SEED = 5 * 10**8

#: First seed searched for the flat textured materials.
FLAT_SEED = HELD_OUT_SEED + 10**6

#: The flat textured materials, in turn: a family and the variants (their names' starts) taken.
FLAT_KINDS = (("stone", ("marble",)), ("wood", ()), ("stone", ("granite", "terrazzo")))

#: Materials of each group shown on the contact sheet.
SHEET_MATERIALS = {"relief": 2, "flat textured": 1}

#: The maps' names, in ``map_rmse``'s order.
MAPS = tuple(constants.MAP_SLICES)


def jittered(photos: torch.Tensor, sigma: float, seed: int) -> torch.Tensor:
    """``photos`` times 1 + sigma N(0, 1), drawn per pixel and channel from ``seed``: for
    ``--photo-jitter``, the photo changed far below its 8-bit steps (1 / 255 of full scale)."""
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(photos.shape, generator=generator, dtype=photos.dtype)
    return photos * (1.0 + sigma * noise)


def row_labels(size: int, low: int) -> tuple[str, str, str]:
    """The three ways of capturing: upsampled from ``low`` px, full size without and with detail."""
    return f"upsampled {low}", f"{size}, no detail", f"{size}, detail"


def materials(relief: int, flat: int, first_seed: int = HELD_OUT_SEED) -> list[dict]:
    """The benchmark's materials: kind, family, seed (no maps: they are made one at a time); the
    relief ones from ``first_seed`` on, the flat textured ones searched from ``first_seed`` plus
    ``FLAT_SEED - HELD_OUT_SEED``."""
    families = sorted(FAMILIES)
    chosen = [{"kind": "relief", "family": families[i % len(families)], "seed": first_seed + i}
              for i in range(relief)]
    seed = first_seed + FLAT_SEED - HELD_OUT_SEED
    for index in range(flat):
        family, variants = FLAT_KINDS[index % len(FLAT_KINDS)]
        # The variant is the family's first draw, the same at every size: read it off a small copy.
        while variants and not generate(seed, size=32, family=family).provenance["variant"].startswith(variants):
            seed += 1
        chosen.append({"kind": "flat textured", "family": family, "seed": seed})
        seed += 1
    return chosen


def true_maps(material: dict, size: int) -> tuple[torch.Tensor, str]:
    """(1, 10, size, size) the material's maps (normals flat for the flat textured), and its variant."""
    generated = generate(material["seed"], size=size, family=material["family"])
    maps = generated.to_tensor()[None]
    if material["kind"] == "flat textured":
        maps[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    return maps, generated.provenance["variant"]


def centre_crop(image: torch.Tensor) -> np.ndarray:
    """The centre half of a (C, H, W) tile as (H / 2, W / 2, 3) for the sheet."""
    height, width = image.shape[-2:]
    top, left = height // 4, width // 4
    return image[:, top:top + height // 2, left:left + width // 2].permute(1, 2, 0).numpy().copy()


def sheet_tiles(maps: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse (sRGB) and normal ((n + 1) / 2) crops of maps (1, 10, H, W)."""
    from mideepbasis.imageio import linear_to_srgb

    return (centre_crop(linear_to_srgb(maps[0, constants.DIFFUSE].clamp(0, 1))),
            centre_crop((maps[0, constants.NORMAL] + 1) / 2))


def write_sheet(path: Path, rows: list[tuple[str, list[tuple[str, np.ndarray]]]]) -> Path:
    """Rows of titled tiles ((title, (H, W, 3) in [0, 1])), a label above each row, as a PNG (atomically)."""
    from PIL import Image, ImageDraw, ImageFont

    tile = rows[0][1][0][1].shape[0]
    band, gap = 22, 4
    columns = max(len(tiles) for _, tiles in rows)
    sheet = Image.new("RGB", (columns * (tile + gap) + gap, len(rows) * (tile + 2 * band + gap) + gap), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=max(9, min(16, tile // 12)))
    for r, (label, tiles) in enumerate(rows):
        top = gap + r * (tile + 2 * band + gap)
        draw.text((gap + 2, top + 3), label, fill=(0, 0, 0), font=font)
        for c, (title, image) in enumerate(tiles):
            left = gap + c * (tile + gap)
            draw.text((left + 2, top + band + 3), title, fill=(0, 0, 0), font=font)
            pixels = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
            sheet.paste(Image.fromarray(pixels), (left, top + 2 * band))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp.png")
    sheet.save(temporary)
    temporary.replace(path)
    print(f"wrote {path}")
    return path


def finite(value: float) -> float | None:
    """A number for the JSON: None for NaN (a truth without detail)."""
    return None if math.isnan(value) else value


def network_band_moments(result, truth: torch.Tensor) -> dict:
    """How the network's diffuse and normals' slopes at its own resolution follow the truth's just
    below it: the sums of products of the two bands ``m - blur(m)`` (``detail.LOW_SIGMA``, the band
    the detail step's gains are fitted in), the truth area-averaged to the network's size, keyed
    ``diffuse`` and ``normal`` (its x and y). Pooled over a group, ``predicted_truth /
    truth_truth`` is the slope of the network's band on the truth's (1: as strong as the truth's;
    the detail step's gains inherit it: ``detail.DIFFUSE_GAIN`` makes up the diffuse's)."""
    from mideepbasis.capturing.detail import LOW_SIGMA
    from mideepbasis.resampling import gaussian_blur

    def band(image):
        return image - gaussian_blur(image, LOW_SIGMA, padding="replicate")

    moments = {}
    for name, channels in (("diffuse", constants.DIFFUSE), ("normal", slice(0, 2))):
        predicted = result.output.maps[:, channels].float().cpu()
        true = band(downsample(truth[:, channels], tuple(predicted.shape[-2:])))
        predicted = band(predicted)
        moments[name] = {"predicted_truth": float((predicted * true).sum()), "truth_truth": float((true * true).sum()),
                         "predicted_predicted": float((predicted * predicted).sum())}
    return moments


def fine_tilt_deg(normal_energy: float) -> float:
    """The normals' RMS tilt above the band [deg] from their energy there (unit normals: for small
    tilts the x and y residuals are the tilt in radians, z's is of second order)."""
    return math.degrees(math.sqrt(max(normal_energy, 0.0)))


def fine_cross(maps: torch.Tensor, truth: torch.Tensor, band: int) -> dict[str, float]:
    """Per map, the mean over pixels of the product of the maps' band above ``band`` px and the
    truth's (``above_band``), summed over the map's channels: with ``high_band_energy`` of both,
    the pooled correlation of the detail with the truth's."""
    return {name: float((above_band(maps[:, channels], band) * above_band(truth[:, channels], band))
                        .mean(dim=(2, 3)).sum()) for name, channels in constants.MAP_SLICES.items()}


def with_true_detail(maps: torch.Tensor, truth: torch.Tensor, band: int) -> torch.Tensor:
    """``maps`` (B, 10, H, W) with their band above ``band`` px replaced by the truth's
    (``above_band``), the normals renormalised and the other maps clipped to [0, 1]: what a perfect
    detail step would make of them, their answer below the band kept."""
    combined = maps - above_band(maps, band) + above_band(truth, band)
    return torch.cat([geometry.unit_vectors(combined[:, constants.NORMAL], dim=1),
                      combined[:, constants.REFLECTANCE].clamp(0.0, 1.0)], dim=1)


def summarise(records: list[dict], labels: tuple[str, ...]) -> dict:
    """A group: its size, the truth's fine tilt, and per row the mean map RMSE and re-rendering
    RMSE, the pooled detail ratio, the pooled correlation of the detail with the truth's (its share
    that is the truth's, not made up: ``fine_cross``), the normals' fine tilt (the group's mean energy as a tilt,
    ``fine_tilt_deg``: what a flat material's ratio cannot show), the median seconds a capture
    (the first material's include the warm-up)."""
    truth_energy = {name: sum(r["truth_energy"][name] for r in records) for name in MAPS}
    summary = {}
    for label in labels:
        rows = [r["rows"][label] for r in records]
        energy = {name: sum(row["energy"][name] for row in rows) for name in MAPS}
        summary[label] = {
            "maps_rmse": {name: float(np.mean([row["maps_rmse"][name] for row in rows])) for name in MAPS},
            "render_rmse": float(np.mean([row["render_rmse"] for row in rows])),
            "detail": {name: finite(energy[name] / truth_energy[name]) if truth_energy[name] > 0 else None
                       for name in MAPS},
            "detail_correlation": {
                name: finite(sum(row["cross"][name] for row in rows) / math.sqrt(energy[name] * truth_energy[name]))
                if energy[name] > 0 and truth_energy[name] > 0 else None for name in MAPS},
            "fine_tilt_deg": fine_tilt_deg(energy["normal"] / len(records)),
            "seconds_median": float(np.median([row["seconds"] for row in rows]))}
    extras = {}
    for name in ("diffuse", "normal"):
        moments = {key: sum(r["network_band"][name][key] for r in records) for key in records[0]["network_band"][name]}
        if moments["truth_truth"] > 0:  # a flat textured group's normals have no band
            extras[f"network_{name}_band"] = {
                "slope": moments["predicted_truth"] / moments["truth_truth"],
                "correlation": moments["predicted_truth"] / math.sqrt(moments["predicted_predicted"]
                                                                      * moments["truth_truth"])}
    if all("true_detail_rmse" in r for r in records):
        extras["true_detail_rmse"] = {name: float(np.mean([r["true_detail_rmse"][name] for r in records]))
                                      for name in MAPS}
    if truth_energy["normal"] > 0 and all("normal_detail" in r for r in records):
        extras["normal_detail_bound"] = relief_test_bound(records)
    return {"materials": len(records), "truth_fine_tilt_deg": fine_tilt_deg(truth_energy["normal"] / len(records)),
            "rows": summary, **extras}


def relief_test_bound(records: list[dict]) -> float:
    """The normals' pooled detail ratio a detail step would give if it added each material's true
    fine relief times the relief test's gain (``normal_detail``): ``sum g^2 E / sum E``, E the
    truth's fine energy. A detail step that follows the relief test everywhere reaches more only by
    giving some material more fine relief than its truth has; capture's fine relief lifts the
    test's gain where the unit reads steep relief (``detail.steep_share``), which this does not count."""
    total = sum(r["truth_energy"]["normal"] for r in records)
    return sum(r["normal_detail"] ** 2 * r["truth_energy"]["normal"] for r in records) / total


#: Radius of the windows of ``window_explained``'s oracle filter [pixels at the capture's size].
WINDOW_RADIUS = 6


def shading_visibility(truth: torch.Tensor, photo: torch.Tensor, light: torch.Tensor, band: int) -> dict:
    """How much of the truth's relief above ``band`` px the photo shows, to first order.

    For a matte surface lit by a point light the photo's contrast above the band,
    ``c = (I - L(I)) / L(I)`` (luminance, ``L`` the area average to ``band`` px upsampled), is to
    first order ``s = (l_xy / l_z) . dn_xy``, ``dn`` the normals above the band and ``l`` the unit
    vector to the flash: only the relief's slope along the light shows, and only in proportion
    to how far the light is off the normal.

    Args:
        truth: (1, 10, H, W); photo: (1, 3, H, W) linear; light: (3,) the flash [patch half-widths].

    Returns:
        ``correlation`` of c and s, ``slope`` of c on s (1 for a matte surface), ``along_light``
        the fine normal energy's share along the light, ``explained`` = correlation^2 x
        along_light: the share of the fine normal energy a linear estimate from c could give
        pixel by pixel, ``window_explained`` the share the best linear filter of c in windows gives
        (``window_explained``).
    """
    height, width = photo.shape[-2:]
    luminance = photo.mean(dim=1, keepdim=True)
    fine_luminance = above_band(luminance, band)
    contrast = (fine_luminance / (luminance - fine_luminance).clamp(min=1e-3)).flatten()
    points = geometry.pixel_points(height, width).reshape(3, -1)
    towards = geometry.unit_vectors(light.view(3, 1) - points, dim=0)
    tilt = towards[:2] / towards[2:3]
    fine = above_band(truth[:, 0:2], band)[0].reshape(2, -1)
    shading = (tilt * fine).sum(dim=0)
    along = ((geometry.unit_vectors(tilt, dim=0) * fine).sum(dim=0) ** 2).sum() / (fine**2).sum()
    correlation = float(torch.corrcoef(torch.stack([contrast, shading]))[0, 1])
    window = window_explained(contrast.view(height, width), tilt.view(2, height, width), fine.view(2, height, width))
    return {"correlation": correlation, "slope": float((contrast * shading).sum() / (shading**2).sum()),
            "along_light": float(along), "explained": correlation**2 * float(along), "window_explained": window}


def window_explained(contrast: torch.Tensor, tilt: torch.Tensor, fine: torch.Tensor, radius: int = WINDOW_RADIUS,
                     samples: int = 40_000, seed: int = 0, chunk: int = 8_000) -> float:
    """The share of the fine normals' energy that the best linear filter of the photo's contrast
    in (2 radius + 1)^2 windows recovers, fitted with the truth (an oracle: a ceiling, near
    enough, for any detail step that is linear in the photo).

    The first-order shading is the relief's slope along the light times the light's tilt ``t``, so
    the filter's taps are the window's contrasts times each pixel's ``t`` (where albedo swamps the
    shading, the best estimate grows with |t|) and times ``t / |t|^2`` (where shading dominates,
    the slope is the contrast over |t|). A filter of the contrast along the light integrates it into
    the height, whose gradient also gives the slope across the light. Fitted by least squares
    (ridge 1e-6 of the features' energy) on ``samples`` random pixels, scored on as many others.

    Args:
        contrast: (H, W) the photo's luminance contrast above the band; tilt: (2, H, W) the light's
            l_xy / l_z; fine: (2, H, W) the true normals above the band.

    Returns:
        1 - (residual energy) / (fine normal energy) on the scoring pixels: 0 nothing, 1 all.
    """
    height, width = contrast.shape
    generator = torch.Generator().manual_seed(seed)
    inner = (height - 2 * radius) * (width - 2 * radius)
    chosen = torch.randperm(inner, generator=generator)[:2 * samples]
    rows = chosen // (width - 2 * radius) + radius
    columns = chosen % (width - 2 * radius) + radius
    inverse = tilt / (tilt**2).sum(dim=0, keepdim=True).clamp(min=1e-2)

    def features(part: torch.Tensor) -> torch.Tensor:
        r, c = rows[part], columns[part]
        taps = torch.stack([contrast[r + dy, c + dx] for dy in range(-radius, radius + 1)
                            for dx in range(-radius, radius + 1)], dim=1)
        return torch.cat([taps * field[k, r, c, None] for field in (tilt, inverse) for k in range(2)], dim=1).double()

    half = len(chosen) // 2
    gram, moment = 0.0, 0.0
    for start in range(0, half, chunk):
        part = torch.arange(start, min(half, start + chunk))
        block = features(part)
        gram = gram + block.T @ block
        moment = moment + block.T @ fine[:, rows[part], columns[part]].T.double()
    gram += torch.eye(gram.shape[0], dtype=gram.dtype) * 1e-6 * gram.diagonal().mean()
    solution = torch.linalg.solve(gram, moment)
    residual, energy = 0.0, 0.0
    for start in range(half, len(chosen), chunk):
        part = torch.arange(start, min(len(chosen), start + chunk))
        targets = fine[:, rows[part], columns[part]].T.double()
        residual += float(((targets - features(part) @ solution) ** 2).sum())
        energy += float((targets**2).sum())
    return 1.0 - residual / energy


def with_reflectance_of(relief: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """Maps (1, 10, H, W) with the normals of ``relief`` and the diffuse, roughness and specular of
    ``other``: a relief whose albedo does not follow it."""
    return torch.cat([relief[:, constants.NORMAL], other[:, constants.REFLECTANCE]], dim=1)


def swapped_maps(material: dict, reliefs: list[dict], size: int, swap: bool) -> tuple[torch.Tensor, str]:
    """``true_maps`` of ``material``; with ``swap``, a relief one under the next relief material's
    reflectance (``with_reflectance_of``; the last under the first's), its variant saying so."""
    truth, variant = true_maps(material, size)
    if swap and material["kind"] == "relief":
        following = reliefs[(reliefs.index(material) + 1) % len(reliefs)]
        truth = with_reflectance_of(truth, true_maps(following, size)[0])
        variant = f"{variant} under {following['family']}"
    return truth, variant


def visibility_report(chosen: list[dict], offsets: torch.Tensor, args, convention: str, extent: float) -> dict:
    """``shading_visibility`` of each relief material, printed, and their means; with
    ``args.swap_reflectance`` each relief under the next relief material's reflectance
    (``with_reflectance_of``; the last under the first's)."""
    rows = []
    reliefs = [material for material in chosen if material["kind"] == "relief"]
    print(f"{'material':36s} correlation  slope  along light  explained  window")
    for index, material in enumerate(chosen):
        if material["kind"] != "relief":
            continue
        truth, variant = swapped_maps(material, reliefs, args.size, args.swap_reflectance)
        photos, lights = flash_photos(truth, offsets[index:index + 1], constants.DEFAULT_FOV_DEG, convention, extent)
        row = {**material, "variant": variant, **shading_visibility(truth, photos, lights[0], args.band)}
        rows.append(row)
        print(f"{material['family'] + ' ' + variant:36s} {row['correlation']:11.2f} {row['slope']:6.2f} "
              f"{row['along_light']:12.2f} {row['explained']:10.3f} {row['window_explained']:7.3f}", flush=True)
    keys = ("correlation", "along_light", "explained", "window_explained")
    means = {key: float(np.mean([row[key] for row in rows])) for key in keys}
    print(f"{'mean':36s} {means['correlation']:11.2f} {'':6s} {means['along_light']:12.2f} {means['explained']:10.3f} "
          f"{means['window_explained']:7.3f}")
    return {"size": args.size, "band": args.band, "seed": args.seed, "swap_reflectance": args.swap_reflectance,
            "mean": means, "per_material": rows}


def mean_tilt(height: np.ndarray) -> float:
    """The mean angle [deg] between a height field's normals (``height_to_normal``) and the vertical."""
    normal = height_to_normal(height, False)
    return float(np.degrees(np.arccos(np.clip(normal[..., 2], -1.0, 1.0))).mean())


def relief_scales(chosen: list[dict], size: int, low: int) -> dict:
    """The relief materials' mean tilt [deg] at ``low`` px: generated at ``low`` px, and generated
    at ``size`` px with the height area-averaged to ``low`` px (what the network's side of a
    capture sees of it); beside it, the ``size`` px material's own mean tilt. Printed, and their
    means."""
    rows = []
    print(f"{'material':36s} tilt at {low} px  {size} px seen at {low} px  at {size} px")
    for material in chosen:
        if material["kind"] != "relief":
            continue
        small, _, provenance = generate_surface(material["seed"], GeneratorConfig(size=low), material["family"])
        large = generate_surface(material["seed"], GeneratorConfig(size=size), material["family"])[0].height
        averaged = cv2.resize(large, (low, low), interpolation=cv2.INTER_AREA)
        row = {**material, "variant": provenance["variant"], "tilt_low": mean_tilt(small.height),
               "tilt_averaged": mean_tilt(averaged), "tilt_full": mean_tilt(large)}
        rows.append(row)
        print(f"{material['family'] + ' ' + row['variant']:36s} {row['tilt_low']:14.1f} {row['tilt_averaged']:22.1f} "
              f"{row['tilt_full']:10.1f}", flush=True)
    keys = ("tilt_low", "tilt_averaged", "tilt_full")
    means = {key: float(np.mean([row[key] for row in rows])) for key in keys}
    print(f"{'mean':36s} {means['tilt_low']:14.1f} {means['tilt_averaged']:22.1f} {means['tilt_full']:10.1f}")
    return {"size": size, "low": low, "mean": means, "per_material": rows}


def registration(folder: Path, band: int) -> list[dict]:
    """Photo 00 of the calibrated scene in ``folder`` against each other photo, at the photos' own
    size: the correlation of their luminance contrast above ``band`` px (``above_band`` over the
    band's mean) at zero shift, and at the whole-pixel shift (dy, dx) [pixels, rows down and
    columns right, within 8] by which the other photo's detail lies from photo 00's, where it
    peaks; over the centre half of the photo."""
    from mideepbasis.capturing.photo import load_photo
    from mideepbasis.evaluation.real import load_scene

    scene = load_scene(folder)

    def fine_contrast(index: int) -> torch.Tensor:
        photo = load_photo(scene.photos[index], fov=scene.fov(index), resolution="native")[0].mean(dim=0)[None, None]
        fine = above_band(photo, band)
        contrast = (fine / (photo - fine).clamp(min=1e-3))[0, 0]
        side = contrast.shape[-1]
        return contrast[side // 4:side - side // 4, side // 4:side - side // 4]

    def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).mean() / (a.std() * b.std()).clamp(min=1e-12))

    reach, reference, rows = 8, fine_contrast(0), []
    inner = reference[reach:-reach, reach:-reach]
    for index in range(1, len(scene.photos)):
        other = fine_contrast(index)
        shifted = {(dy, dx): correlation(inner, other[reach + dy:other.shape[0] - reach + dy,
                                                       reach + dx:other.shape[1] - reach + dx])
                   for dy in range(-reach, reach + 1) for dx in range(-reach, reach + 1)}
        (dy, dx), peak = max(shifted.items(), key=lambda item: item[1])
        rows.append({"photo": index, "correlation": shifted[(0, 0)], "peak_correlation": peak, "shift": [dy, dx]})
    return rows


def registration_report(folder: Path, band: int) -> dict:
    """``registration`` of each scene under ``folder``, printed."""
    from mideepbasis.evaluation.real import scene_folders

    scenes = {}
    for scene_folder in scene_folders(folder):
        rows = registration(scene_folder, band)
        scenes[scene_folder.name] = rows
        for row in rows:
            print(f"{scene_folder.name} photo {row['photo']:02d}: fine contrast's correlation with photo 00 "
                  f"{row['correlation']:+.3f}, at its peak {row['peak_correlation']:+.3f}, shift {row['shift']} px")
        print(f"{scene_folder.name}: mean correlation {np.mean([r['correlation'] for r in rows]):+.3f}, "
              f"photos off by a pixel or more {sum(r['shift'] != [0, 0] for r in rows)} of {len(rows)}")
    return {"data": str(folder), "band": band, "scenes": scenes}


def number(value: float | None) -> str:
    """A detail ratio for the printed tables ("-": no true detail)."""
    return "   -  " if value is None else f"{value:6.3f}"


def print_table(group: str, summary: dict) -> None:
    print(f"\n{group} ({summary['materials']} materials)")
    print(f"{'':22s} {'normal':>7s} {'diffuse':>7s} {'rough.':>7s} {'spec.':>7s} {'render':>7s}   "
          f"detail n / d / r / s          fine tilt [deg]  s/capture")
    print(f"{'truth':22s} {'':67s} {summary['truth_fine_tilt_deg']:6.2f}")
    for label, row in summary["rows"].items():
        rmse = row["maps_rmse"]
        print(f"{label:22s} {rmse['normal']:7.4f} {rmse['diffuse']:7.4f} {rmse['roughness']:7.4f} "
              f"{rmse['specular']:7.4f} {row['render_rmse']:7.4f}   "
              + " ".join(number(row["detail"][name]) for name in MAPS)
              + f"   {row['fine_tilt_deg']:6.2f}    {row['seconds_median']:9.2f}")
    print("the detail's correlation with the truth's (n / d), per row: " + "; ".join(
        f"{label} " + " / ".join(number(row["detail_correlation"][name]).strip() for name in ("normal", "diffuse"))
        for label, row in summary["rows"].items()))
    if "true_detail_rmse" in summary:
        bound = summary["true_detail_rmse"]
        print(f"{'upsampled, true detail':22s} " + " ".join(f"{bound[name]:7.4f}" for name in MAPS)
              + "   (the upsampled maps with the truth's band above the detail band: a bound)")
    if "normal_detail_bound" in summary:
        print(f"detail n with each material's true fine relief times the relief test's gain: "
              f"{summary['normal_detail_bound']:.3f}")
    for name in ("diffuse", "normal"):
        band = summary.get(f"network_{name}_band")
        if band is None:
            continue
        print(f"the network's {name} band at its resolution against the truth's: slope {band['slope']:.3f}, "
              f"correlation {band['correlation']:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--materials", type=int, default=12, help="relief materials, one family after another")
    parser.add_argument("--flat", type=int, default=4, help="flat textured materials (normals set flat)")
    parser.add_argument("--size", type=int, default=1024, help="the materials' and the full captures' size [pixels]")
    parser.add_argument("--low", type=int, default=constants.DEFAULT_RESOLUTION,
                        help="the upsampled row's capture resolution [pixels]")
    parser.add_argument("--band", type=int, default=DETAIL_BAND, help="the detail measure's band [pixels]")
    parser.add_argument("--lights", type=int, default=6, help="lights and views of the re-rendering error")
    parser.add_argument("--refine-steps", type=int, default=None, help="the refinement's steps (default: capture's)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the flash offsets and the lights and views")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "model_quality.json",
                        help="JSON file whose entry detail gets the figures")
    parser.add_argument("--sheet", type=Path, default=RESULTS / "detail_crops.png")
    parser.add_argument("--no-sheet", action="store_true", help="skip the contact sheet")
    parser.add_argument("--photo-jitter", type=float, default=0.0, metavar="SIGMA",
                        help="multiply each photo by 1 + SIGMA N(0, 1) per pixel and channel (seeded by "
                             "--jitter-seed): how far the result moves for a change far below the photo's 8-bit "
                             "steps; entry detail_photo_jitter_SEED")
    parser.add_argument("--jitter-seed", type=int, default=0, help="seed of --photo-jitter's noise")
    parser.add_argument("--first-seed", type=int, default=HELD_OUT_SEED,
                        help="first seed of the materials: another than the default gives a calibration set "
                             "apart from the benchmark's; entry detail_seeds_FIRST")
    parser.add_argument("--no-relief-test", action="store_true",
                        help="capture with the normals' detail not scaled by the photo's relief share "
                             "(CaptureConfig.relief_test)")
    parser.add_argument("--fine-relief", action=argparse.BooleanOptionalAction, default=CaptureConfig.fine_relief,
                        help="capture with the normals' detail read by the network's normal unit on the photo, or "
                             "(--no-fine-relief) the photo's contrast times their gains (CaptureConfig.fine_relief; "
                             "default: capture's); without it, entries end in _no_fine_relief")
    parser.add_argument("--fine-relief-strength", type=float, default=CaptureConfig.fine_relief_strength,
                        metavar="S", help="the factor of the relief the fine relief reads "
                                          "(CaptureConfig.fine_relief_strength; default: capture's); other than that, "
                                          "entries end in _fine_relief_S")
    parser.add_argument("--relief-reader", default=None, metavar="FILE",
                        help="a relief reader's weights that read the fine relief "
                             "(CaptureConfig.relief_reader); entries end in _reader")
    parser.add_argument("--denoise", action="store_true",
                        help="capture with the photo's fine contrast denoised (CaptureConfig.denoise_detail); "
                             "entries end in _denoised")
    parser.add_argument("--colour-test", action=argparse.BooleanOptionalAction, default=None,
                        help="capture with (or without) the contrast a change of hue explains left out of the "
                             "normals' detail (CaptureConfig.colour_test; default: capture's); other than capture's "
                             "default, entries end in _colour_test or _no_colour_test")
    parser.add_argument("--no-keep-lobe-peak", action="store_true",
                        help="capture with the roughness as refined under the normals' detail "
                             "(CaptureConfig.keep_lobe_peak False); entries end in _lobe_unkept")
    parser.add_argument("--visibility", action="store_true",
                        help="only measure how much of the true fine relief the photos show (shading_visibility)")
    parser.add_argument("--swap-reflectance", action="store_true",
                        help="each relief under the next relief material's diffuse, roughness and specular, so "
                             "that its albedo does not follow its relief (with --visibility, or for the captures: "
                             "entries end in _swapped)")
    parser.add_argument("--relief-scales", action="store_true",
                        help="only measure the relief materials' mean tilt at --low px, generated at --low px and at "
                             "--size px (relief_scales)")
    parser.add_argument("--registration", type=Path, default=None, metavar="DIR",
                        help="only measure how the fine detail of the calibrated scenes in DIR lines up across their "
                             "photos (registration)")
    args = parser.parse_args()
    fov = constants.DEFAULT_FOV_DEG
    try:  # capture's checks across its options, before any work
        base = CaptureConfig(fov=fov, relief_test=not args.no_relief_test, fine_relief=args.fine_relief,
                             fine_relief_strength=args.fine_relief_strength, relief_reader=args.relief_reader,
                             denoise_detail=args.denoise,
                             keep_lobe_peak=not args.no_keep_lobe_peak)
        if args.colour_test is not None:
            base = replace(base, colour_test=args.colour_test)
    except ValueError as error:
        parser.error(str(error))
    if args.registration is not None:
        write_section(args.output, "detail_registration", "detail --registration",
                      registration_report(args.registration, args.band))
        return

    if args.relief_scales:
        suffix = f"_seeds_{args.first_seed}" if args.first_seed != HELD_OUT_SEED else ""
        write_section(args.output, "detail_relief_scales" + suffix,
                      "detail --relief-scales" + (f" --first-seed {args.first_seed}" if suffix else ""),
                      relief_scales(materials(args.materials, 0, args.first_seed), args.size, args.low))
        return

    model = load_model(args.model)
    convention, extent = model.config.convention, model.config.plane_extent
    if args.refine_steps is not None:
        base = replace(base, refine=replace(base.refine, steps=args.refine_steps))
    chosen = materials(args.materials, args.flat, args.first_seed)
    offsets = evaluation_offsets(len(chosen), args.seed, fov)
    # Another set of materials than the benchmark's writes entries of its own, whatever else is asked.
    other_set = args.first_seed != HELD_OUT_SEED
    key_suffix = f"_seeds_{args.first_seed}" if other_set else ""
    command_suffix = f" --first-seed {args.first_seed}" if other_set else ""
    # Nor does a capture without the relief test overwrite the default's entry.
    key_suffix += "_no_relief_test" if args.no_relief_test else ""
    command_suffix += " --no-relief-test" if args.no_relief_test else ""
    key_suffix += "" if args.fine_relief else "_no_fine_relief"
    command_suffix += "" if args.fine_relief else " --no-fine-relief"
    if args.fine_relief and args.fine_relief_strength != CaptureConfig.fine_relief_strength:
        key_suffix += f"_fine_relief_{args.fine_relief_strength:g}"
        command_suffix += f" --fine-relief-strength {args.fine_relief_strength:g}"
    key_suffix += "_reader" if args.relief_reader else ""
    command_suffix += f" --relief-reader {args.relief_reader}" if args.relief_reader else ""
    key_suffix += "_denoised" if args.denoise else ""
    command_suffix += " --denoise" if args.denoise else ""
    if base.colour_test != CaptureConfig().colour_test:
        key_suffix += "_colour_test" if base.colour_test else "_no_colour_test"
        command_suffix += " --colour-test" if base.colour_test else " --no-colour-test"
    key_suffix += "_lobe_unkept" if args.no_keep_lobe_peak else ""
    command_suffix += " --no-keep-lobe-peak" if args.no_keep_lobe_peak else ""
    if not args.visibility:
        key_suffix += "_swapped" if args.swap_reflectance else ""
        command_suffix += " --swap-reflectance" if args.swap_reflectance else ""
    if args.visibility:
        key = "detail_visibility_swapped" if args.swap_reflectance else "detail_visibility"
        write_section(args.output, key + key_suffix,
                      f"detail --visibility{' --swap-reflectance' * args.swap_reflectance}{command_suffix}",
                      visibility_report(chosen, offsets, args, convention, extent))
        return
    labels = row_labels(args.size, args.low)
    capturers = {labels[0]: Capturer(model, replace(base, resolution=args.low, detail=False)),
                 labels[1]: Capturer(model, replace(base, resolution=args.size, detail=False)),
                 labels[2]: Capturer(model, replace(base, resolution=args.size, detail=True))}
    lights, views = random_lights_and_views(args.lights, args.seed)
    sheet_left = dict(SHEET_MATERIALS) if not args.no_sheet else {}
    sheet_rows, records = [], []
    started = time.perf_counter()
    reliefs = [material for material in chosen if material["kind"] == "relief"]
    for index, material in enumerate(chosen):
        truth, variant = swapped_maps(material, reliefs, args.size, args.swap_reflectance)
        offset = (float(offsets[index, 0]), float(offsets[index, 1]))
        photos, _ = flash_photos(truth, offsets[index:index + 1], fov, convention, extent)
        if args.photo_jitter > 0:
            photos = jittered(photos, args.photo_jitter, args.jitter_seed * 1000 + index)
        truth_renders = rerender(truth, lights, views, convention)
        truth_energy = high_band_energy(truth, args.band)
        record = {**material, "variant": variant, "offset": list(offset),
                  "truth_energy": {name: float(value[0]) for name, value in truth_energy.items()}, "rows": {}}
        tiles = None
        if sheet_left.get(material["kind"], 0) > 0:
            from mideepbasis.imageio import linear_to_srgb

            diffuse, normal = sheet_tiles(truth)
            tiles = {"photo": centre_crop(linear_to_srgb(photos[0].clamp(0, 1))), "diffuse: truth": diffuse,
                     "normal: truth": normal}
        for label, capturer in capturers.items():
            pixels = photos[0] if label != labels[0] else downsample(photos[0], args.low)
            start = time.perf_counter()
            result = capturer.with_config(light=offset).capture(pixels)
            seconds = time.perf_counter() - start
            if label == labels[1]:
                record["network_band"] = network_band_moments(result, truth)
            if label == labels[2]:
                record["normal_detail"] = result.material.provenance["capture"]["normal_detail"]
            maps = upsample_maps(result.material.to_tensor()[None], args.size)
            del result
            with torch.no_grad():
                render_rmse = float(((rerender(maps, lights, views, convention) - truth_renders) ** 2).mean().sqrt())
                energy = high_band_energy(maps, args.band)
                cross = fine_cross(maps, truth, args.band)
            rmse = map_rmse(maps, truth)
            if label == labels[0]:
                record["true_detail_rmse"] = {name: float(value[0]) for name, value in
                                              map_rmse(with_true_detail(maps, truth, args.band), truth).items()}
            record["rows"][label] = {
                "maps_rmse": {name: float(value[0]) for name, value in rmse.items()}, "render_rmse": render_rmse,
                "energy": {name: float(value[0]) for name, value in energy.items()},
                "detail": {name: finite(float(energy[name][0] / truth_energy[name][0]))
                           if float(truth_energy[name][0]) > 0 else None for name in MAPS},
                "cross": cross,
                "seconds": seconds}
            if tiles is not None and label != labels[1]:
                diffuse, normal = sheet_tiles(maps)
                tiles[f"diffuse: {label}"], tiles[f"normal: {label}"] = diffuse, normal
            del maps
        if tiles is not None:
            sheet_left[material["kind"]] -= 1
            order = ["photo", "diffuse: truth", f"diffuse: {labels[0]}", f"diffuse: {labels[2]}", "normal: truth",
                     f"normal: {labels[0]}", f"normal: {labels[2]}"]
            sheet_rows.append((f"{material['family']} {variant} ({material['kind']}), seed {material['seed']}",
                               [(title, tiles[title]) for title in order]))
        records.append(record)
        del truth, photos, truth_renders
        print(f"{index + 1}/{len(chosen)} {material['kind']:13s} {material['family']:12s} {variant:24s} "
              "render " + " / ".join(f"{record['rows'][label]['render_rmse']:.4f}" for label in labels)
              + "; detail of the diffuse " + " / ".join(number(record["rows"][label]["detail"]["diffuse"])
                                                         for label in labels)
              + f" ({time.perf_counter() - started:.0f} s)", flush=True)

    groups = {}
    for group in ("relief", "flat textured"):
        members = [r for r in records if r["kind"] == group]
        if members:
            groups[group] = summarise(members, labels)
            print_table(group, groups[group])
    report = {"model": args.model or "shipped", "size": args.size, "low": args.low, "band": args.band,
              "lights": args.lights, "seed": args.seed, "fov_deg": fov,
              "refine_steps": base.refine.steps, "photo_jitter": args.photo_jitter, "jitter_seed": args.jitter_seed,
              "first_seed": args.first_seed, "fine_relief": args.fine_relief,
              "fine_relief_strength": args.fine_relief_strength, "relief_reader": args.relief_reader,
              "denoise_detail": args.denoise, "colour_test": base.colour_test,
              "keep_lobe_peak": not args.no_keep_lobe_peak,
              "swap_reflectance": args.swap_reflectance, "groups": groups, "per_material": records}
    if args.photo_jitter > 0:
        write_section(args.output, f"detail_photo_jitter_{args.jitter_seed}{key_suffix}",
                      f"detail --photo-jitter {args.photo_jitter:g} --jitter-seed {args.jitter_seed}{command_suffix}",
                      report)
    else:
        write_section(args.output, f"detail{key_suffix}", f"detail{command_suffix}", report)
    if sheet_rows:
        write_sheet(args.sheet, sheet_rows)


if __name__ == "__main__":
    main()
