"""The SVBRDF model as pure drjit functions: D, G, F, the BSDF value, sampling and densities.

Everything here works in the local shading frame of the surface, where the geometric
normal is +z. The normal map gives a per-point normal ``n`` in that frame; the
microfacet model is evaluated around ``n``. Two conventions exist (docs/ARCHITECTURE.md section 4):

``physical``
    ``f = d / pi + D G F / (4 (n.l)(n.v))`` with GGX ``D``, the separable Smith ``G`` and
    the Schlick ``F``; zero where either direction is below the normal-mapped or the
    geometric hemisphere.

``deepbasis``
    the convention of the DeepBasis reference implementation: Schlick-GGX ``G`` with
    ``k = alpha / 2``, the spherical-Gaussian Schlick ``F``, diffuse ``d (1 - s) / pi`` and
    every cosine clamped to a tiny positive value instead of zero.

``eval_cosine`` returns ``f * cos`` (what ``mi.BSDF.eval`` returns): the light transport
factor of the light is applied by the caller (``flash_factor``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import constants

# --- microfacet terms --------------------------------------------------------------------------


def ggx_ndf(cos_theta_m: mi.Float, sin2_theta_m: mi.Float, alpha: mi.Float) -> mi.Float:
    """GGX normal distribution D(m) = alpha^2 / (pi ((n.m)^2 (alpha^2 - 1) + 1)^2).

    The denominator is evaluated as alpha^2 cos^2 + sin^2, which equals (n.m)^2 (alpha^2 - 1) + 1
    but keeps float32 precision at the peak of smooth materials, where 1 - cos^2 would cancel.

    Args:
        cos_theta_m: cosine between the normal and the microfacet normal m.
        sin2_theta_m: squared sine of the same angle, |n x m|^2.
        alpha: GGX width, alpha = roughness^2.
    """
    alpha2 = dr.square(alpha)
    denominator = dr.fma(alpha2, dr.square(cos_theta_m), sin2_theta_m)
    return alpha2 / (dr.pi * dr.square(denominator))


def smith_g1(cos_theta: mi.Float, alpha: mi.Float) -> mi.Float:
    """Smith masking for GGX, G1(x) = 2x / (x + sqrt(alpha^2 + (1 - alpha^2) x^2))."""
    alpha2 = dr.square(alpha)
    root = dr.safe_sqrt(dr.fma(1.0 - alpha2, dr.square(cos_theta), alpha2))
    return 2.0 * cos_theta / (cos_theta + root)


def schlick_fresnel(f0: mi.Color3f, cos_theta_vh: mi.Float) -> mi.Color3f:
    """Schlick Fresnel F = F0 + (1 - F0)(1 - v.h)^5."""
    weight = dr.power(dr.clip(1.0 - cos_theta_vh, 0.0, 1.0), 5)
    return dr.fma(1.0 - f0, weight, f0)


def deepbasis_visibility(cos_v: mi.Float, cos_l: mi.Float, alpha: mi.Float) -> mi.Float:
    """Schlick-GGX masking of the DeepBasis code, already divided by (n.l)(n.v); k = alpha / 2."""
    k = dr.maximum(0.5 * alpha, constants.DEEPBASIS_COSINE_EPS)
    return 1.0 / (dr.fma(cos_l, 1.0 - k, k) * dr.fma(cos_v, 1.0 - k, k))


def deepbasis_fresnel(f0: mi.Color3f, cos_theta_vh: mi.Float) -> mi.Color3f:
    """Spherical-Gaussian Schlick Fresnel F = F0 + (1 - F0) 2^((-5.55473 v.h - 6.98316) v.h)."""
    exponent = cos_theta_vh * dr.fma(-5.55473, cos_theta_vh, -6.98316)
    return dr.fma(1.0 - f0, dr.exp2(exponent), f0)


# --- the BSDF value ----------------------------------------------------------------------------


def roughness_to_alpha(roughness: mi.Float, convention: str) -> mi.Float:
    """alpha = r^2, with r clamped from below so the GGX peak stays finite."""
    floor = (constants.DEEPBASIS_MIN_ROUGHNESS if convention == "deepbasis"
             else constants.PHYSICAL_MIN_ROUGHNESS)
    return dr.square(dr.maximum(roughness, floor))


def eval_cosine(convention: str, normal: mi.Vector3f, wi: mi.Vector3f, wo: mi.Vector3f,
                diffuse: mi.Color3f, roughness: mi.Float, specular: mi.Color3f,
                include_diffuse: bool = True, include_specular: bool = True) -> mi.Color3f:
    """The BSDF value times the cosine at the outgoing direction, f(wi, wo) max(n.wo, 0).

    Args:
        convention: ``physical`` or ``deepbasis``.
        normal: unit normal-mapped normal n in the local frame.
        wi, wo: unit directions towards the viewer and the light, local frame.
        diffuse: diffuse albedo d [0, 1].
        roughness: roughness r [0, 1], alpha = r^2.
        specular: specular albedo s (F0) [0, 1].
        include_diffuse, include_specular: which lobes to evaluate.

    Returns:
        f * max(n.wo, 0) per lane; zero where wi or wo lies below the geometric surface.
    """
    above_surface = (mi.Frame3f.cos_theta(wi) > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)
    half = dr.normalize(wi + wo)
    cos_v = dr.dot(normal, wi)
    cos_l = dr.dot(normal, wo)
    cos_h = dr.dot(normal, half)
    sin2_h = dr.squared_norm(dr.cross(normal, half))
    cos_vh = dr.dot(wi, half)
    alpha = roughness_to_alpha(roughness, convention)
    value = dr.zeros(mi.Color3f, dr.width(cos_l))

    if convention == "physical":
        active = above_surface & (cos_v > 0.0) & (cos_l > 0.0)
        if include_diffuse:
            value += diffuse * dr.inv_pi
        if include_specular:
            g = smith_g1(cos_l, alpha) * smith_g1(cos_v, alpha)
            value += ggx_ndf(cos_h, sin2_h, alpha) * g * schlick_fresnel(specular, cos_vh) / (4.0 * cos_l * cos_v)
        return dr.select(active, value * cos_l, 0.0)

    if convention == "deepbasis":
        eps = constants.DEEPBASIS_COSINE_EPS
        cos_v, cos_l = dr.maximum(cos_v, eps), dr.maximum(cos_l, eps)
        cos_h, cos_vh = dr.maximum(cos_h, eps), dr.maximum(cos_vh, eps)
        if include_diffuse:
            value += diffuse * (1.0 - specular) * dr.inv_pi
        if include_specular:
            value += (0.25 * ggx_ndf(cos_h, sin2_h, alpha) * deepbasis_visibility(cos_v, cos_l, alpha)
                      * deepbasis_fresnel(specular, cos_vh))
        return dr.select(above_surface, value * cos_l, 0.0)

    raise ValueError(f"unknown shading convention {convention!r}; expected one of {constants.CONVENTIONS}")


def flash_factor(convention: str, to_light: mi.Vector3f, intensity: mi.Float) -> mi.Float:
    """Factor turning ``eval_cosine`` into pixel radiance under a point light.

    Args:
        convention: ``physical`` (inverse-square falloff of a point light of radiant
            intensity ``intensity`` [W/sr]) or ``deepbasis`` (no falloff, pi * lamp intensity).
        to_light: vector from the shaded point to the light [patch half-widths].
        intensity: radiant intensity of the light [W/sr], or the lamp intensity for
            ``deepbasis``.
    """
    if convention == "deepbasis":
        return dr.pi * intensity
    return intensity / dr.squared_norm(to_light)


# --- sampling ----------------------------------------------------------------------------------


def sample_ggx_visible(wi: mi.Vector3f, alpha: mi.Float, sample: mi.Point2f) -> mi.Vector3f:
    """Sample a GGX microfacet normal from the distribution of normals visible from wi.

    Spherical-cap construction of Dupuy and Benyoub (2023); ``wi`` is in the frame of the
    mean surface normal (+z) and must lie above it.
    """
    wi_std = dr.normalize(mi.Vector3f(wi.x * alpha, wi.y * alpha, wi.z))
    phi = 2.0 * dr.pi * sample.x
    z = dr.fma(1.0 - sample.y, 1.0 + wi_std.z, -wi_std.z)
    sin_theta = dr.safe_sqrt(1.0 - dr.square(z))
    sin_phi, cos_phi = dr.sincos(phi)
    h = mi.Vector3f(sin_theta * cos_phi, sin_theta * sin_phi, z) + wi_std
    return dr.normalize(mi.Vector3f(h.x * alpha, h.y * alpha, dr.maximum(h.z, 0.0)))


def pdf_ggx_visible_reflection(wi: mi.Vector3f, wo: mi.Vector3f, alpha: mi.Float) -> mi.Float:
    """Density over wo of reflecting wi about a visible-normal GGX sample [1/sr].

    ``wi`` and ``wo`` are in the frame of the mean surface normal (+z).
    """
    m = dr.normalize(wi + wo)
    cos_i = mi.Frame3f.cos_theta(wi)
    # D_wi(m) = G1(wi) max(0, wi.m) D(m) / cos_i, and d(wo)/d(m) = 1 / (4 wo.m) with wi.m = wo.m.
    pdf = (smith_g1(cos_i, alpha) * ggx_ndf(mi.Frame3f.cos_theta(m), mi.Frame3f.sin_theta_2(m), alpha)
           / (4.0 * cos_i))
    return dr.select((cos_i > 0.0) & (dr.dot(wi, m) > 0.0), pdf, 0.0)


def specular_probability(convention: str, wi_n: mi.Vector3f, diffuse: mi.Color3f,
                         specular: mi.Color3f) -> mi.Float:
    """Probability of sampling the specular lobe, from the two lobes' albedos at wi.

    The specular albedo is taken as the Fresnel reflectance at normal-space incidence
    ``wi_n`` (it grows towards grazing angles); the diffuse one as the diffuse albedo.
    """
    cos_i = dr.clip(mi.Frame3f.cos_theta(wi_n), 0.0, 1.0)
    specular_weight = dr.mean(schlick_fresnel(specular, cos_i))
    diffuse_color = diffuse * (1.0 - specular) if convention == "deepbasis" else diffuse
    diffuse_weight = dr.mean(diffuse_color)
    total = specular_weight + diffuse_weight
    return dr.select(total > 0.0, specular_weight / total, 1.0)


def sample_direction(convention: str, normal: mi.Vector3f, wi: mi.Vector3f, diffuse: mi.Color3f,
                     roughness: mi.Float, specular: mi.Color3f, sample1: mi.Float,
                     sample2: mi.Point2f, has_diffuse: bool = True,
                     has_specular: bool = True) -> tuple[mi.Vector3f, mi.Bool]:
    """Draw an outgoing direction: GGX visible normals or a cosine-weighted diffuse lobe.

    The lobe is chosen with ``sample1`` against ``specular_probability``; both lobes live in
    the frame of the normal-mapped normal.

    Returns:
        (wo in the local frame, True where the specular lobe was chosen).
    """
    frame = mi.Frame3f(normal)
    wi_n = frame.to_local(wi)
    if has_specular and has_diffuse:
        chose_specular = sample1 < specular_probability(convention, wi_n, diffuse, specular)
    else:
        chose_specular = mi.Bool(has_specular)
    alpha = roughness_to_alpha(roughness, convention)
    m = sample_ggx_visible(wi_n, alpha, sample2)
    wo_specular = mi.reflect(wi_n, m)
    wo_diffuse = mi.warp.square_to_cosine_hemisphere(sample2)
    return frame.to_world(dr.select(chose_specular, wo_specular, wo_diffuse)), chose_specular


def pdf_direction(convention: str, normal: mi.Vector3f, wi: mi.Vector3f, wo: mi.Vector3f,
                  diffuse: mi.Color3f, roughness: mi.Float, specular: mi.Color3f,
                  has_diffuse: bool = True, has_specular: bool = True) -> mi.Float:
    """Density of ``sample_direction`` over wo [1/sr], zero where the BSDF value is zero."""
    frame = mi.Frame3f(normal)
    wi_n, wo_n = frame.to_local(wi), frame.to_local(wo)
    if has_specular and has_diffuse:
        p_specular = specular_probability(convention, wi_n, diffuse, specular)
    else:
        p_specular = mi.Float(1.0 if has_specular else 0.0)
    alpha = roughness_to_alpha(roughness, convention)
    pdf = (p_specular * pdf_ggx_visible_reflection(wi_n, wo_n, alpha)
           + (1.0 - p_specular) * mi.warp.square_to_cosine_hemisphere_pdf(wo_n))
    valid = ((mi.Frame3f.cos_theta(wi) > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)
             & (mi.Frame3f.cos_theta(wi_n) > 0.0) & (mi.Frame3f.cos_theta(wo_n) > 0.0))
    return dr.select(valid, pdf, 0.0)
