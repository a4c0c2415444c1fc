"""Evaluation under environment light: path-traced comparisons of predicted and true materials.

A material can match a flash photo and still look wrong in a room. For every material this path
traces the predicted and the true maps with Mitsuba and the ``svbrdf`` plugin in the preview scene
(the sample on a table, seen at an angle) under each environment and from each view, the two with
the same seed and sample count (correlated sampling), and compares them, binned 2 x 2, on the
pixels that see the sample (the film's alpha): RMSE of clipped sRGB, FLIP and SSIM.

The noise floor is the same comparison between two renders of the *true* material with different
seeds: what Monte Carlo noise alone gives. The sample count is chosen so that it stays under a
tenth of the trivial baseline's error (benchmarks/README.md, "evaluate --environment").

Shapes: maps (10, H, W) [normal 3, diffuse 3, roughness 1, specular 3]; renders (H, W, 3) linear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .. import constants
from .metrics import ssim_map

#: Metrics of an environment comparison, each over the pixels that see the sample.
METRICS = ("rmse", "flip", "ssim")


@dataclass(frozen=True)
class EnvironmentProtocol:
    """How materials are compared under environment light."""

    environments: tuple[str, ...] = ("studio", "sunsky")
    """``studio`` (the shipped HDR map), ``sunsky`` (Mitsuba's analytic sky), ``uniform`` (a constant
    white sky) or paths of equirectangular EXR/HDR maps."""

    views_deg: tuple[float, ...] = (40.0, 65.0)
    """Angles of the camera from the sample's normal [deg]: the preview's, and a grazing one."""

    resolution: int = 64
    """Width and height of the renders [pixels]; small, so that many samples per pixel are cheap."""

    spp: int = 256
    """Samples per pixel of every render (noise floor: benchmarks/README.md)."""

    sampler: str = "multijitter"
    """Mitsuba sampler of the renders: stratified samples leave 40% less noise than independent
    ones at the same cost here."""

    metric_bin: int = 2
    """The metrics compare the renders averaged over blocks of this many pixels squared (a pixel of
    the comparison sees the sample when all of its block does): half the noise of single pixels.
    With the defaults the noise floor is about a tenth of the trivial baseline's RMSE."""

    seed: int = 0
    """Seed of the compared renders (the same for prediction and truth)."""

    floor_seed: int = 1
    """Seed of the second render of the truth, for the noise floor."""

    floor_every: int = 4
    """Measure the noise floor on every this-many-th material only (the first included): it is a
    property of the renderer and the sample count, and a quarter of the set measures it well."""

    distance: float = constants.PREVIEW_DISTANCE
    """Distance of the camera from the sample centre [patch half-widths]."""

    fov: float = constants.PREVIEW_FOV_DEG
    """Field of view of the camera [deg]."""


def parse_environments(text: str) -> tuple[str, ...]:
    """``studio,sunsky,FILE.exr`` -> names, checked: a clear error for an unknown name or missing file."""
    from ..errors import InputError
    from ..render.scenes import environment_part

    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if not names:
        raise InputError("--environment needs at least one of studio, sunsky, uniform or an EXR/HDR file")
    for name in names:
        try:
            environment_part(name)  # the scenes' own check
        except InputError as error:
            raise InputError(f"--environment: {error}") from None
    return names


def environment_label(name: str) -> str:
    """A short label of an environment (a file's stem)."""
    from pathlib import Path

    return Path(name).stem if ("/" in name or "." in name) else name


class EnvironmentRenderer:
    """One loaded scene per environment and view; each render swaps in a material's maps.

    Args:
        protocol: environments, views, resolution and samples.
        convention: shading convention of the plugin.
    """

    def __init__(self, protocol: EnvironmentProtocol, convention: str = constants.DEFAULT_CONVENTION):
        from ..render.scenes import preview_scene

        self.protocol = protocol
        placeholder = torch.zeros(10, 4, 4)
        placeholder[2] = 1.0
        self.scenes = {(environment, view): preview_scene(
            placeholder, environment=environment, spp=protocol.spp, resolution=protocol.resolution,
            convention=convention, elevation=90.0 - view, distance=protocol.distance, fov=protocol.fov,
            pixel_format="rgba", sampler=protocol.sampler) for environment in protocol.environments for view in protocol.views_deg}

    def render(self, maps: torch.Tensor, environment: str, view: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(linear radiance (H, W, 3), mask (H, W) of the pixels that see the sample)."""
        import drjit as dr
        import mitsuba as mi

        from ..render.scenes import set_material

        scene = self.scenes[(environment, view)]
        set_material(scene, maps)
        image = mi.render(scene, spp=self.protocol.spp, seed=seed)
        dr.eval(image)
        image = np.array(image, dtype=np.float32)
        return image[..., :3], image[..., 3] > 0.5


def to_display(radiance: np.ndarray) -> np.ndarray:
    """Clipped, sRGB-encoded (H, W, 3) in [0, 1]."""
    from ..imageio import linear_to_srgb

    return np.asarray(linear_to_srgb(np.clip(radiance, 0.0, 1.0)), dtype=np.float32)


def binned(image: np.ndarray, mask: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``image`` (H, W, 3) over size x size blocks, and the blocks all inside ``mask`` (H, W)."""
    if size == 1:
        return image, mask
    height, width = (mask.shape[0] // size) * size, (mask.shape[1] // size) * size
    blocks = image[:height, :width].reshape(height // size, size, width // size, size, -1).mean(axis=(1, 3))
    return blocks.astype(np.float32), mask[:height, :width].reshape(height // size, size, width // size, size).all(axis=(1, 3))


def compare(reference: np.ndarray, test: np.ndarray, mask: np.ndarray, protocol: EnvironmentProtocol) -> dict[str, float]:
    """The protocol's comparison of two sRGB renders (H, W, 3): ``masked_metrics`` of their binned images."""
    a, block_mask = binned(reference, mask, protocol.metric_bin)
    b, _ = binned(test, mask, protocol.metric_bin)
    return masked_metrics(a, b, block_mask)


def masked_metrics(reference: np.ndarray, test: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """RMSE, mean FLIP and mean SSIM of two sRGB images (H, W, 3) in [0, 1] over ``mask`` (H, W).

    SSIM's 11 x 11 window needs a margin: its map covers the image less 5 pixels at each edge, and
    the mask is cropped alike.
    """
    import flip_evaluator

    if not mask.any():
        raise ValueError("no pixel of the render sees the sample")
    rmse = float(np.sqrt(((reference - test) ** 2)[mask].mean()))
    error_map, _, _ = flip_evaluator.evaluate(np.ascontiguousarray(reference), np.ascontiguousarray(test), "LDR",
                                              applyMagma=False)
    flip = float(np.asarray(error_map).reshape(mask.shape)[mask].mean())
    structure = ssim_map(torch.from_numpy(reference).permute(2, 0, 1)[None],
                         torch.from_numpy(test).permute(2, 0, 1)[None])[0].mean(0).numpy()
    margin = (mask.shape[0] - structure.shape[0]) // 2
    inner = mask[margin:margin + structure.shape[0], margin:margin + structure.shape[1]]
    ssim = float(structure[inner].mean()) if inner.any() else float(structure.mean())
    return {"rmse": rmse, "flip": flip, "ssim": ssim}


@dataclass
class EnvironmentScores:
    """Per-material environment metrics: ``rows[row][environment][metric]`` and ``floor[environment][metric]``,
    each (N,) averaged over the views (the floor NaN where not measured); ``images[row][environment]`` keeps the first view's sRGB renders
    (N, H, W, 3) for galleries (``truth`` among the rows)."""

    rows: dict
    floor: dict
    images: dict


def evaluate_environments(predictions: dict[str, torch.Tensor], truth: torch.Tensor, protocol: EnvironmentProtocol,
                          convention: str = constants.DEFAULT_CONVENTION, progress: bool = True) -> EnvironmentScores:
    """Compare every row's predictions (N, 10, H, W) with the truth under every environment and view.

    The truth is rendered once per environment and view (and once more with ``floor_seed`` for
    the noise floor); every row is rendered with the truth's seed.
    """
    from tqdm import tqdm

    renderer = EnvironmentRenderer(protocol, convention)
    count = truth.shape[0]
    views = len(protocol.views_deg)
    rows = {row: {env: {m: np.zeros(count) for m in METRICS} for env in protocol.environments} for row in predictions}
    floor = {env: {m: np.full(count, np.nan) for m in METRICS} for env in protocol.environments}
    images = {row: {env: [] for env in protocol.environments} for row in ["truth", *predictions]}
    for index in tqdm(range(count), desc="environment renders", unit="material", disable=not progress):
        for environment in protocol.environments:
            for view_index, view in enumerate(protocol.views_deg):
                reference, mask = renderer.render(truth[index], environment, view, protocol.seed)
                reference = to_display(reference)
                if index % protocol.floor_every == 0:
                    second, _ = renderer.render(truth[index], environment, view, protocol.floor_seed)
                    for metric, value in compare(reference, to_display(second), mask, protocol).items():
                        floor[environment][metric][index] = np.nan_to_num(floor[environment][metric][index]) + value / views
                if view_index == 0:
                    images["truth"][environment].append(reference)
                for row, maps in predictions.items():
                    test, _ = renderer.render(maps[index], environment, view, protocol.seed)
                    test = to_display(test)
                    for metric, value in compare(reference, test, mask, protocol).items():
                        rows[row][environment][metric][index] += value / views
                    if view_index == 0:
                        images[row][environment].append(test)
    images = {row: {env: np.stack(renders) for env, renders in by_env.items()} for row, by_env in images.items()}
    return EnvironmentScores(rows=rows, floor=floor, images=images)


def spearman(a, b) -> float:
    """Spearman's rank correlation of two sequences (average ranks for ties)."""
    def ranks(values):
        values = np.asarray(values, dtype=np.float64)
        order = np.argsort(values, kind="mergesort")
        result = np.empty(len(values))
        result[order] = np.arange(len(values), dtype=np.float64)
        for value in np.unique(values):  # ties share their mean rank
            tied = values == value
            result[tied] = result[tied].mean()
        return result

    ra, rb = ranks(a), ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denominator = math.sqrt(float((ra**2).sum() * (rb**2).sum()))
    return float((ra * rb).sum() / denominator) if denominator > 0 else float("nan")


def environment_summary(scores: EnvironmentScores, main_row: str, flash_rmse: np.ndarray | None,
                        protocol: EnvironmentProtocol) -> dict:
    """``env`` -> label -> {rmse, flip, ssim (main row), noise_floor {...}, rows {row: {...}},
    spearman_flash_vs_env}, plus the protocol."""
    result = {}
    for environment in protocol.environments:
        entry = {metric: float(scores.rows[main_row][environment][metric].mean()) for metric in METRICS}
        entry["noise_floor"] = {metric: float(np.nanmean(scores.floor[environment][metric])) for metric in METRICS}
        entry["rows"] = {row: {metric: float(values[environment][metric].mean()) for metric in METRICS}
                         for row, values in scores.rows.items()}
        if flash_rmse is not None and len(flash_rmse) > 2:
            entry["spearman_flash_vs_env"] = spearman(flash_rmse, scores.rows[main_row][environment]["rmse"])
        result[environment_label(environment)] = entry
    return {"environments": result, "protocol": {"environments": list(protocol.environments),
                                                 "views_deg": list(protocol.views_deg),
                                                 "resolution": protocol.resolution, "spp": protocol.spp,
                                                 "sampler": protocol.sampler, "metric_bin": protocol.metric_bin,
                                                 "seed": protocol.seed, "floor_seed": protocol.floor_seed,
                                                 "floor_every": protocol.floor_every}}
