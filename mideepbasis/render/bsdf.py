"""The ``svbrdf`` Mitsuba BSDF plugin: plumbing around the math in ``shading.py``.

Parameters (XML or ``mi.load_dict``):

``normal``     texture, normal-mapped normal in the local tangent frame, components in
               [-1, 1] (a raw bitmap); default (0, 0, 1)
``normal_encoding`` string, ``signed`` (default: components as stored) or ``unsigned``
               (stored as (n + 1) / 2, as in PNG normal maps: decoded as 2 x - 1)
``diffuse``    texture, diffuse albedo [0, 1], linear; default 0.5
``roughness``  texture, roughness [0, 1] (alpha = r^2); default 0.5
``specular``   texture, specular albedo F0 [0, 1], linear; default 0.04
``convention`` string, ``physical`` (default) or ``deepbasis``

Texture coordinates follow Mitsuba (v = 0 is the first image row). A scene that puts the
material on a ``rectangle`` flips v in the bitmaps' ``to_uv`` so image row 0 lies at +y;
``scenes.py`` does this.

The plugin has two lobes, component 0 glossy (GGX, visible-normal sampling) and
component 1 diffuse (cosine-weighted), chosen when sampling by their albedos.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import constants
from . import shading

#: Names of the four maps, in the order of the 10 basis parameters.
MAP_NAMES = ("normal", "diffuse", "roughness", "specular")

_DEFAULT_VALUES = {"normal": (0.0, 0.0, 1.0), "diffuse": (0.5, 0.5, 0.5), "roughness": (0.5,),
                   "specular": (0.04, 0.04, 0.04)}


def constant_texture(values) -> mi.Texture:
    """A 1x1 raw bitmap holding ``values`` (1 or 3 channels), e.g. a default map."""
    data = np.asarray(values, dtype=np.float32).reshape(1, 1, -1)
    return mi.load_dict({"type": "bitmap", "data": mi.TensorXf(data), "raw": True,
                         "filter_type": "nearest"})


class SVBRDF(mi.BSDF):
    """Spatially varying Cook-Torrance (GGX) plus Lambert, driven by four texture maps."""

    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.convention = props.get("convention", constants.DEFAULT_CONVENTION)
        self.unsigned_normals = props.get("normal_encoding", "signed") == "unsigned"
        if props.get("normal_encoding", "signed") not in ("signed", "unsigned"):
            raise ValueError(f"svbrdf: normal_encoding must be 'signed' or 'unsigned', got {props.get('normal_encoding')!r}")
        if self.convention not in constants.CONVENTIONS:
            raise ValueError(f"svbrdf: unknown convention {self.convention!r}; "
                             f"expected one of {constants.CONVENTIONS}")
        self.textures = {name: (props.get_texture(name) if name in props
                                else constant_texture(_DEFAULT_VALUES[name]))
                         for name in MAP_NAMES}
        shared = mi.BSDFFlags.FrontSide | mi.BSDFFlags.SpatiallyVarying
        self.m_components = [mi.BSDFFlags.GlossyReflection | shared,
                             mi.BSDFFlags.DiffuseReflection | shared]
        self.m_flags = self.m_components[0] | self.m_components[1]

    # --- texture look-ups ----------------------------------------------------------------------

    def maps(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True):
        """Evaluate the four maps at ``si.uv``: (unit normal, diffuse, roughness, specular)."""
        normal = mi.Vector3f(self.textures["normal"].eval(si, active))
        if self.unsigned_normals:
            normal = dr.fma(normal, 2.0, -1.0)
        normal = dr.normalize(normal)
        diffuse = self.textures["diffuse"].eval(si, active)
        roughness = self.textures["roughness"].eval_1(si, active)
        specular = self.textures["specular"].eval(si, active)
        return normal, diffuse, roughness, specular

    def _lobes(self, ctx: mi.BSDFContext) -> tuple[bool, bool]:
        return (ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1),
                ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0))

    # --- the mi.BSDF interface -----------------------------------------------------------------

    def _value_and_pdf(self, ctx, si, wo, active, with_value: bool, with_pdf: bool):
        """(f * cos, pdf) of the lobes the context enables; the maps are looked up once."""
        has_diffuse, has_specular = self._lobes(ctx)
        if not (has_diffuse or has_specular):
            return mi.Color3f(0.0), mi.Float(0.0)
        normal, diffuse, roughness, specular = self.maps(si, active)
        value = (self.eval_maps(normal, diffuse, roughness, specular, si.wi, wo, has_diffuse, has_specular)
                 if with_value else mi.Color3f(0.0))
        pdf = (shading.pdf_direction(self.convention, normal, si.wi, wo, diffuse, roughness, specular,
                                     has_diffuse=has_diffuse, has_specular=has_specular)
               if with_pdf else mi.Float(0.0))
        return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

    def eval_maps(self, normal: mi.Vector3f, diffuse: mi.Color3f, roughness: mi.Float, specular: mi.Color3f,
                  wi: mi.Vector3f, wo: mi.Vector3f, include_diffuse: bool = True,
                  include_specular: bool = True) -> mi.Color3f:
        """``eval`` (f * cos) with the maps given per lane instead of looked up in the textures
        (``normal`` a unit vector, as ``maps`` returns it): for renders whose maps change every
        step inside a frozen drjit function (``render.fit``), where a texture update cannot be
        recorded."""
        return shading.eval_cosine(self.convention, normal, wi, wo, diffuse, roughness, specular,
                                   include_diffuse=include_diffuse, include_specular=include_specular)

    def eval(self, ctx, si, wo, active=True):
        return self._value_and_pdf(ctx, si, wo, active, with_value=True, with_pdf=False)[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._value_and_pdf(ctx, si, wo, active, with_value=False, with_pdf=True)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._value_and_pdf(ctx, si, wo, active, with_value=True, with_pdf=True)

    def sample(self, ctx, si, sample1, sample2, active=True):
        has_diffuse, has_specular = self._lobes(ctx)
        bs = dr.zeros(mi.BSDFSample3f)
        if not (has_diffuse or has_specular):
            return bs, mi.Color3f(0.0)
        normal, diffuse, roughness, specular = self.maps(si, active)
        wo, chose_specular = shading.sample_direction(
            self.convention, normal, si.wi, diffuse, roughness, specular, sample1, sample2,
            has_diffuse=has_diffuse, has_specular=has_specular)
        value = shading.eval_cosine(self.convention, normal, si.wi, wo, diffuse, roughness, specular,
                                    include_diffuse=has_diffuse, include_specular=has_specular)
        pdf = shading.pdf_direction(self.convention, normal, si.wi, wo, diffuse, roughness, specular,
                                    has_diffuse=has_diffuse, has_specular=has_specular)
        valid = active & (pdf > 0.0)
        bs.wo = wo
        bs.pdf = dr.select(valid, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_component = dr.select(chose_specular, mi.UInt32(0), mi.UInt32(1))
        bs.sampled_type = dr.select(chose_specular, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        # The one-sample estimator divides by the mixture density, not by the chosen lobe's.
        return bs, dr.select(valid, value / pdf, 0.0)

    def traverse(self, callback):
        for name, texture in self.textures.items():
            callback.put(name, texture, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        encoding = "unsigned" if self.unsigned_normals else "signed"
        return f"SVBRDF[convention={self.convention!r}, normal_encoding={encoding!r}]"


mi.register_bsdf("svbrdf", lambda props: SVBRDF(props))
