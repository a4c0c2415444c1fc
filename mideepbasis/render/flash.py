"""Per-pixel flash renders of the sample plane: ``bsdf.eval`` over the pixel grid, no ray tracing.

For every material ``b`` of a batch, every light ``k`` and every pixel (row i, col j), the
pixel sees the plane point ``p = (-1 + (2j + 1) / w, 1 - (2i + 1) / h, 0)``; camera and flash
sit together at ``c_bk``; the ``svbrdf`` plugin is evaluated with ``wi = wo = normalize(c - p)``
and the result is scaled by the light's transport factor (``shading.flash_factor``). This is
the ``physical`` formula of docs/ARCHITECTURE.md section 4 exactly.

All B x K x h x w evaluations run in one kernel. Light positions, intensity and maps are
kernel inputs rather than constants, so new positions reuse the compiled kernel.

Layout (Mitsuba side, docs/ARCHITECTURE.md section 5): the maps of a batch are stacked vertically into
one (B*h, w, C) texture per map; the result is a (B, K, h, w, 3) tensor.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import constants
from . import shading
from .bsdf import MAP_NAMES

_CHANNELS = {"normal": 3, "diffuse": 3, "roughness": 1, "specular": 3}


def plane_point(row: mi.Float, col: mi.Float, height: int, width: int, extent: float) -> mi.Point3f:
    """The point of the sample plane that pixel (row, col) of an h x w image sees [patch half-widths]."""
    return mi.Point3f(extent * (dr.fma(2.0, col, 1.0) / width - 1.0), extent * (1.0 - dr.fma(2.0, row, 1.0) / height), 0.0)


class FlashRenderer:
    """Holds one ``svbrdf`` plugin whose four textures are replaced before each render.

    Args:
        convention: shading convention of the plugin, ``physical`` or ``deepbasis``.
    """

    def __init__(self, convention: str = constants.DEFAULT_CONVENTION):
        self.convention = convention
        textures = {name: {"type": "bitmap", "raw": True, "filter_type": "nearest", "wrap_mode": "clamp",
                           "data": mi.TensorXf(np.zeros((2, 2, _CHANNELS[name]), np.float32))}
                    for name in MAP_NAMES}
        self.bsdf = mi.load_dict({"type": "svbrdf", "convention": convention, **textures})
        self.params = mi.traverse(self.bsdf)

    def set_maps(self, normal: mi.TensorXf, diffuse: mi.TensorXf, roughness: mi.TensorXf,
                 specular: mi.TensorXf) -> None:
        """Load the maps of a batch, each stacked as (B*h, w, C) with C = 3, 3, 1, 3."""
        for name, data in zip(MAP_NAMES, (normal, diffuse, roughness, specular)):
            if data.ndim != 3 or data.shape[2] != _CHANNELS[name]:
                raise ValueError(f"{name} map must have shape (B*h, w, {_CHANNELS[name]}), got {data.shape}")
            self.params[f"{name}.data"] = data
        self.params.update()

    def release_maps(self) -> None:
        """Swap the loaded maps for 2 x 2 zeros: a 4096 px material's textures hold 0.7 GB."""
        self.set_maps(*(mi.TensorXf(np.zeros((2, 2, _CHANNELS[name]), np.float32)) for name in MAP_NAMES))

    def render(self, lights: mi.Point3f, batch: int, height: int, width: int,
               intensity: float | mi.Float, views: mi.Point3f | None = None, extent: float = 1.0) -> mi.TensorXf:
        """Render every loaded material under its lights.

        Args:
            lights: B*K flash positions [patch half-widths], light k of material b at index b*K + k.
            views: B*K viewpoints (one per light) for re-renderings where camera and light are
                apart; None: co-located with the lights (the flash capture).
            extent: half-width of the framed sample [patch half-widths]: pixel (i, j) sees
                extent * (-1 + (2j + 1) / w, 1 - (2i + 1) / h, 0).
            batch: number B of stacked materials; the loaded maps have B*height rows.
            height, width: image size h, w [pixels].
            intensity: radiant intensity of the flash [W/sr] (``physical``) or lamp intensity
                (``deepbasis``).

        Returns:
            linear radiance, shape (B, K, h, w, 3).
        """
        per_material = self._check_batch(lights, batch)
        radiance, _ = self._radiance(lights, batch, height, width, intensity, views, extent)
        return mi.TensorXf(dr.ravel(radiance), shape=(batch, per_material, height, width, 3))

    def mean_l1(self, lights: mi.Point3f, photo: mi.TensorXf, intensity: float | mi.Float,
                extent: float = 1.0) -> mi.Float:
        """The mean absolute difference between ``photo`` and the loaded material (one, B = 1)
        rendered under each light and clipped to [0, 1], reduced in the render's kernel: no
        K x h x w image is handed back. The lighting search's objective.

        Args:
            lights: K co-located flash positions [patch half-widths].
            photo: (h, w, 3) linear; the loaded maps must be h x w.

        Returns:
            K values, one per light.
        """
        height, width = photo.shape[0], photo.shape[1]
        radiance, pixel = self._radiance(lights, 1, height, width, intensity, None, extent)
        error = dr.abs(dr.clip(radiance, 0.0, 1.0) - dr.gather(mi.Color3f, photo.array, pixel))
        return dr.block_sum(error.x + error.y + error.z, height * width) / (3 * height * width)

    @staticmethod
    def _check_batch(lights: mi.Point3f, batch: int) -> int:
        n_lights = dr.width(lights)
        if n_lights % batch:
            raise ValueError(f"{n_lights} lights do not split evenly over {batch} materials")
        return n_lights // batch

    def _radiance(self, lights: mi.Point3f, batch: int, height: int, width: int, intensity: float | mi.Float,
                  views: mi.Point3f | None, extent: float) -> tuple[mi.Color3f, mi.UInt32]:
        """The radiance of every (light, pixel) lane, light-major, and each lane's pixel (row-major)."""
        n_lights = dr.width(lights)
        per_material = n_lights // batch
        n_pixels = height * width
        index = dr.arange(mi.UInt32, n_lights * n_pixels)
        light_index = index // n_pixels
        pixel = index - light_index * n_pixels
        row = pixel // width
        col = pixel - row * width
        material = light_index // per_material
        row_f, col_f = mi.Float(row), mi.Float(col)
        point = plane_point(row_f, col_f, height, width, extent)
        to_light = dr.gather(mi.Point3f, lights, light_index) - point
        direction = dr.normalize(to_light)
        to_view = direction if views is None else dr.normalize(dr.gather(mi.Point3f, views, light_index) - point)

        si = dr.zeros(mi.SurfaceInteraction3f)
        si.p = point
        si.uv = mi.Point2f((col_f + 0.5) / width, (mi.Float(material * height + row) + 0.5) / (batch * height))
        si.wi = to_view
        value = self.bsdf.eval(mi.BSDFContext(), si, direction)
        return value * shading.flash_factor(self.convention, to_light, intensity), pixel

    def render_maps(self, normal: mi.Vector3f, diffuse: mi.Color3f, roughness: mi.Float, specular: mi.Color3f,
                    light: mi.Point3f, height: int, width: int, intensity: float | mi.Float,
                    extent: float = 1.0) -> mi.Color3f:
        """``render`` of one material under one co-located flash, its maps given per pixel (row-major
        arrays of h * w lanes, ``normal`` unit) instead of loaded as textures: the plugin's
        ``eval_maps``. The pixel (row-major) radiance, h * w lanes."""
        index = dr.arange(mi.UInt32, height * width)
        row = index // width
        point = plane_point(mi.Float(row), mi.Float(index - row * width), height, width, extent)
        to_light = light - point
        direction = dr.normalize(to_light)
        value = self.bsdf.eval_maps(normal, diffuse, roughness, specular, direction, direction)
        return value * shading.flash_factor(self.convention, to_light, intensity)
