"""Full Mitsuba scenes around the sample: the flash capture and the environment preview.

The scenes are XML files in ``scenes/`` (installed as ``mideepbasis.scenes``), loaded with
parameters and then given the material's maps through ``mi.traverse``. Both are path traced
with the ``svbrdf`` plugin; the flash scene reproduces the per-pixel path (``flash.py``) up to
Monte Carlo noise and pixel-footprint filtering, which makes it an end-to-end check of the
plugin inside Mitsuba's own light transport.
"""

from __future__ import annotations

import functools
import math
from importlib import resources
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import torch
from tqdm import tqdm

from .. import constants
from ..errors import InputError
from ..resampling import separable_filter
from .bsdf import MAP_NAMES

#: Environments that ship with the package, by name, and the file of each.
ENVIRONMENTS = {"studio": "envmaps/studio.exr"}

#: The analytic sky, offered beside the shipped maps.
SUNSKY = "sunsky"

#: A constant white sky of unit radiance (tests: a white Lambertian under it renders to 1).
UNIFORM = "uniform"


def scenes_dir() -> Path:
    """Folder of the installed scene files (a wheel has them inside the package)."""
    return Path(str(resources.files("mideepbasis.scenes")))


def _load(name: str, **parameters) -> mi.Scene:
    return mi.load_file(str(scenes_dir() / name), **{key: str(value) for key, value in parameters.items()})


def _as_maps(material) -> torch.Tensor:
    """(10, H, W) float32 CPU tensor from a Material (``to_tensor``) or a tensor."""
    maps = material.to_tensor() if hasattr(material, "to_tensor") else torch.as_tensor(material)
    if maps.ndim != 3 or maps.shape[0] != constants.BASIS_CHANNELS:
        raise ValueError(f"maps must have shape ({constants.BASIS_CHANNELS}, H, W), got {tuple(maps.shape)}")
    return maps.detach().float().cpu()


def set_material(scene: mi.Scene, material, shape: str = "sample") -> None:
    """Replace the maps of the ``svbrdf`` material on the shape with id ``shape`` by ``material``'s."""
    params = mi.traverse(scene)
    for name, data in zip(MAP_NAMES, torch.split(_as_maps(material), [3, 3, 1, 3])):
        params[f"{shape}.bsdf.{name}.data"] = mi.TensorXf(data.permute(1, 2, 0).contiguous().numpy())
    params.update()


#: Objects of the shape previews (``shape_*.xml``); ``plane`` is the environment preview itself.
SHAPES = constants.PREVIEW_SHAPES


def environment_part(environment: str) -> dict:
    """The env_*.xml include and its parameters for an environment name or file; a one-line
    InputError for a name that is none of the known ones nor an existing file."""
    if environment == SUNSKY:
        return {"env_part": "env_sunsky.xml"}
    if environment == UNIFORM:
        return {"env_part": "env_uniform.xml"}
    path = scenes_dir() / ENVIRONMENTS[environment] if environment in ENVIRONMENTS else Path(environment)
    if not path.is_file():
        raise InputError(f"environment {environment!r} is neither {sorted(ENVIRONMENTS)}, "
                         f"{SUNSKY!r}, {UNIFORM!r} nor an existing file")
    if environment not in ENVIRONMENTS:  # a user's file: read once here, so that a bad one is one line
        try:
            mi.Bitmap(str(path))
        except RuntimeError:
            raise InputError(f"environment {environment}: not an image Mitsuba can read "
                             "(an equirectangular EXR, HDR, PNG or JPEG)") from None
    return {"env_part": "env_envmap.xml", "envmap": path.resolve()}


def shape_scene(material, shape: str = "sphere", environment: str = "studio", tiles: float = 2.0,
                spp: int = constants.DEFAULT_SPP, resolution: int = constants.PREVIEW_RESOLUTION,
                convention: str = constants.DEFAULT_CONVENTION, scale: float = 1.0,
                sampler: str = "independent", rfilter: str = "gaussian") -> mi.Scene:
    """The material on an object under an environment, path traced (``preview_shape.xml``).

    Args:
        material: a Material or a (10, H, W) tensor of stacked maps.
        shape: ``sphere`` (radius 1) or ``cloth`` (a sheet draped over a ball); ``plane`` gives
            ``preview_scene``.
        environment: as for ``preview_scene``.
        tiles: how many times the maps repeat across the object [count] (around the sphere: twice
            as many, so that texels stay square).
        spp, resolution, convention, scale, sampler: samples per pixel, image size [pixels],
            shading convention, radiance scale of the environment, Mitsuba sampler plugin.
        rfilter: the film's reconstruction filter, as for ``preview_scene``.
    """
    if shape == "plane":
        return preview_scene(material, environment, spp, resolution, convention, scale=scale, sampler=sampler,
                             rfilter=rfilter)
    if shape not in SHAPES:
        raise InputError(f"unknown preview shape {shape!r}; expected one of {list(SHAPES)}")
    if not tiles > 0:
        raise InputError(f"preview tiles must be positive, got {tiles}")
    camera = {"sphere": dict(camera_y=-4.6, camera_z=2.2, target_z=0.0, preview_fov=32),
              "cloth": dict(camera_y=-5.0, camera_z=4.2, target_z=0.3, preview_fov=50)}[shape]
    scene = _load("preview_shape.xml", spp=spp, sampler=sampler, rfilter=rfilter, resolution=resolution,
                  convention=convention, env_scale=scale,
                  shape_part=f"shape_{shape}.xml", tiles=tiles,
                  **({"tiles_around": 2 * tiles} if shape == "sphere" else {}), **camera,
                  **environment_part(environment))
    set_material(scene, material, shape="object")
    return scene


def flash_scene(material, offset: tuple[float, float] = (0.0, 0.0), fov: float = constants.DEFAULT_FOV_DEG,
                spp: int = constants.DEFAULT_SPP, resolution: int | None = None,
                convention: str = constants.DEFAULT_CONVENTION) -> mi.Scene:
    """The flash capture of docs/ARCHITECTURE.md section 3 as a Mitsuba scene.

    Args:
        material: a Material or a (10, H, W) tensor of stacked maps.
        offset: hand-held lateral offset (tx, ty) of camera and flash [patch half-widths].
        fov: field of view along the image width [deg].
        spp: samples per pixel.
        resolution: image width and height [pixels]; defaults to the material's width.
        convention: shading convention of the plugin. Mitsuba's point light always falls off
            with the squared distance, so only ``physical`` matches the per-pixel path exactly.
    """
    maps = _as_maps(material)
    height = constants.camera_height(fov)
    tx, ty = offset
    scene = _load("flash.xml", spp=spp, resolution=resolution or maps.shape[-1], fov=fov, height=height,
                  tx=tx, ty=ty, ppx=-tx / 2.0, ppy=ty / 2.0,
                  intensity=math.pi * height**2, convention=convention)
    set_material(scene, maps)
    return scene


def preview_camera_position(elevation: float = constants.PREVIEW_ELEVATION_DEG,
                            distance: float = constants.PREVIEW_DISTANCE) -> tuple[float, float, float]:
    """Where the environment preview's camera stands (x, y, z) [patch half-widths]: ``distance``
    from the sample centre, ``elevation`` [deg] above the sample plane, in front of it (-y)."""
    elevation_rad = math.radians(elevation)
    return 0.0, -distance * math.cos(elevation_rad), distance * math.sin(elevation_rad)


def preview_scene(material, environment: str = "studio", spp: int = constants.DEFAULT_SPP,
                  resolution: int = constants.PREVIEW_RESOLUTION,
                  convention: str = constants.DEFAULT_CONVENTION,
                  elevation: float = constants.PREVIEW_ELEVATION_DEG,
                  distance: float = constants.PREVIEW_DISTANCE, fov: float = constants.PREVIEW_FOV_DEG,
                  scale: float = 1.0, pixel_format: str = "rgb", sampler: str = "independent",
                  rfilter: str = "gaussian") -> mi.Scene:
    """The sample on a table, seen at an angle under an environment.

    Args:
        material: a Material or a (10, H, W) tensor of stacked maps.
        environment: ``studio`` (the shipped HDR map), ``sunsky`` (Mitsuba's analytic sun and
            sky), ``uniform`` (a constant sky of radiance ``scale``) or the path of an
            equirectangular EXR/HDR map (+y up in the map).
        spp: samples per pixel.
        resolution: image width and height [pixels].
        convention: shading convention of the plugin.
        elevation: camera elevation above the sample plane [deg].
        distance: camera distance from the sample centre [patch half-widths].
        fov: camera field of view [deg].
        scale: radiance scale of the environment [relative].
        pixel_format: ``rgb``, or ``rgba`` whose alpha marks the pixels that see the sample.
        sampler: Mitsuba sampler plugin (``independent``, ``multijitter``, ...).
        rfilter: the film's reconstruction filter: Mitsuba's default ``gaussian``, or ``box``, each
            sample kept in its own pixel, for ``film_gaussian`` to apply the Gaussian afterwards.
    """
    camera = dict(zip(("camera_x", "camera_y", "camera_z"), preview_camera_position(elevation, distance)))
    common = dict(spp=spp, resolution=resolution, preview_fov=fov, convention=convention, env_scale=scale,
                  pixel_format=pixel_format, sampler=sampler, rfilter=rfilter, **camera)
    part = environment_part(environment)
    files = {"env_sunsky.xml": "preview_sunsky.xml", "env_uniform.xml": "preview_uniform.xml",
             "env_envmap.xml": "preview_envmap.xml"}
    scene = _load(files[part.pop("env_part")], **part, **common)
    set_material(scene, material)
    return scene


def render(scene: mi.Scene, spp: int | None = None, seed: int = 0, progress: bool = False,
           pass_spp: int = 64) -> np.ndarray:
    """Path trace ``scene``; returns linear radiance, (H, W, 3) float32.

    Args:
        scene: a loaded scene.
        spp: samples per pixel; default the scene sampler's.
        seed: seed of the first pass.
        progress: show a progress bar over the passes.
        pass_spp: largest number of samples per pixel rendered in one pass; more samples are
            split into equal passes with successive seeds and averaged.
    """
    total = spp or scene.sensors()[0].sampler().sample_count()
    passes = max(1, math.ceil(total / pass_spp))
    per_pass = math.ceil(total / passes)
    accumulated = None
    for index in tqdm(range(passes), desc="path tracing", unit="pass", disable=not progress or passes == 1):
        image = mi.render(scene, spp=per_pass, seed=seed + index)
        dr.eval(image)
        image = np.array(image, dtype=np.float32)[..., :3]
        accumulated = image if accumulated is None else accumulated + image
    return accumulated / passes


#: Mitsuba's default reconstruction filter (``gaussian``): standard deviation [pixels]; it is cut
#: off at four of them, and lowered by its value there so that it ends at zero.
FILM_GAUSSIAN_STDDEV = 0.5


@functools.lru_cache(maxsize=4)
def film_gaussian_weights(stddev: float = FILM_GAUSSIAN_STDDEV) -> np.ndarray:
    """(2k + 1,) Mitsuba's Gaussian filter at the offsets d = -k..k [pixels] of a pixel's
    neighbours, normalised to sum to one (separable, as Mitsuba's is). Matched against Mitsuba's
    own film on a sharp checkerboard (tests/render/test_scenes.py), these point values come closer
    than the filter averaged over each neighbour's width, which blurs more: the film weighs every
    sample by where it fell, and a pixel's mean keeps no trace of that."""
    radius = 4.0 * stddev
    offsets = np.arange(-math.ceil(radius - 0.5), math.ceil(radius - 0.5) + 1, dtype=np.float64)
    weights = np.maximum(0.0, np.exp(-offsets**2 / (2 * stddev**2)) - math.exp(-radius**2 / (2 * stddev**2)))
    weights = weights[weights > 0]  # the filter ends at zero: at 0.5 px, no weight 2 px away
    return weights / weights.sum()


def film_gaussian(image: np.ndarray, stddev: float = FILM_GAUSSIAN_STDDEV) -> np.ndarray:
    """A ``box``-filtered render (H, W, C) developed as Mitsuba's ``gaussian`` film develops its
    samples, up to what a pixel's mean cannot tell (where in the pixel its samples fell): every
    pixel the weighted mean of its neighbours (``film_gaussian_weights``), near the edges over the
    pixels inside alone (the film does not sample beyond its edges, and divides by the weight its
    own samples bring). Splatting every sample into 16 pixels cost Mitsuba 85 - 125 ms of each
    256 px preview on two AVX2 cores; this costs about 8 ms. Returns float32."""
    weights = torch.from_numpy(film_gaussian_weights(stddev))
    image = torch.from_numpy(np.asarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    developed = separable_filter(image, weights, padding="constant")
    coverage = separable_filter(torch.ones_like(image[:, :1]), weights, padding="constant")
    return (developed / coverage)[0].permute(1, 2, 0).contiguous().numpy()


def render_preview(scene: mi.Scene, **options) -> np.ndarray:
    """``render`` (its ``options``) of a preview scene, developed by ``film_gaussian`` where its
    film was given the ``box`` filter (``constants.PREVIEW_FILM_FILTER``): either way it looks as
    Mitsuba's Gaussian film would. Returns linear radiance, (H, W, 3) float32."""
    image = render(scene, **options)
    return film_gaussian(image) if scene.sensors()[0].film().rfilter().is_box_filter() else image
