"""The `svbrdf` plugin: sampling (Mitsuba's chi-square test), energy, and agreement with the torch reference."""

from __future__ import annotations

import itertools
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch
from mitsuba.chi2 import ChiSquareTest, SphericalDomain

from mideepbasis.render import reference

from .conftest import constant_svbrdf, tilted_normal

#: Chi-square grid: roughness, normal-map tilt [deg], incident angle [deg], convention.
CHI2_CASES = list(itertools.product([0.1, 0.2, 0.4, 0.7, 1.0], [0.0, 20.0, 40.0], [10.0, 40.0, 70.0],
                                    ["physical", "deepbasis"]))

#: Relative tolerance of the plugin's BSDF value against the torch reference, both float32.
EVAL_RTOL = {"physical": 1e-4, "deepbasis": 1e-4}


def surface_interaction(n: int, wi) -> mi.SurfaceInteraction3f:
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = wi
    si.uv = mi.Point2f(0.5, 0.5)
    return si


def incident(theta_deg: float, phi_deg: float = 0.0) -> mi.Vector3f:
    theta, phi = math.radians(theta_deg), math.radians(phi_deg)
    return mi.Vector3f(math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))


@pytest.mark.parametrize("roughness,tilt,theta,convention", CHI2_CASES)
def test_chi2_sampling_matches_pdf(roughness, tilt, theta, convention):
    bsdf = constant_svbrdf(convention, normal=tilted_normal(tilt), roughness=roughness)
    wi = incident(theta, 10.0)

    def sample(u):
        bs, weight = bsdf.sample(mi.BSDFContext(), surface_interaction(dr.width(u), wi), u[0], mi.Point2f(u[1], u[2]))
        return bs.wo, dr.select(dr.all(weight == 0), 0.0, 1.0)

    def pdf(wo):
        return bsdf.pdf(mi.BSDFContext(), surface_interaction(dr.width(wo), wi), wo)

    # Smooth lobes need finer cells and quadrature to tabulate the density faithfully.
    res, ires, count = (301, 16, 2_000_000) if roughness < 0.3 else (101, 4, 400_000)
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample, pdf_func=pdf, sample_dim=3,
                         sample_count=count, res=res, ires=ires, seed=3)
    assert test.run(significance_level=0.01, test_count=len(CHI2_CASES), quiet=True), test.messages


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
@pytest.mark.parametrize("lobe", ["specular", "diffuse"])
def test_white_material_albedo_never_exceeds_one(convention, lobe):
    """Each lobe at albedo 1 reflects at most all of the light, at every angle and tilt.

    The specular lobe is checked at s = 1 (F = 1), the diffuse lobe at d = 1 with s = 0. (The
    `physical` convention does not weight the diffuse lobe by 1 - F, so d = 1 together with
    s > 0 can exceed 1 in sum: each lobe is checked alone, through the BSDF context.)
    """
    component = 0 if lobe == "specular" else 1
    context = mi.BSDFContext()
    context.component = component
    n = 400_000
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, n)
    for roughness, tilt, theta in itertools.product([0.1, 0.3, 0.6, 1.0], [0.0, 30.0], [0.0, 45.0, 75.0, 88.0]):
        white, black = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)
        bsdf = constant_svbrdf(convention, normal=tilted_normal(tilt), roughness=roughness,
                               diffuse=white if lobe == "diffuse" else black,
                               specular=white if lobe == "specular" else black)
        _, weight = bsdf.sample(context, surface_interaction(n, incident(theta)), sampler.next_1d(), sampler.next_2d())
        albedo = dr.mean(weight, axis=None)
        standard_error = dr.sqrt(dr.mean(dr.square(weight), axis=None) / n)
        assert albedo[0] <= 1.0 + 3 * standard_error[0] + 1e-4, (roughness, tilt, theta, albedo)
        if lobe == "diffuse" and tilt == 0.0:
            assert albedo[0] == pytest.approx(1.0, abs=1e-5)  # cosine-weighted sampling is exact here


@pytest.mark.parametrize("convention", ["physical", "deepbasis"])
def test_eval_matches_torch_reference_in_every_direction(convention):
    rng = np.random.default_rng(1)
    n = 20_000

    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    wi = unit(rng.normal(size=(n, 3)) * [1, 1, 1] + [0, 0, 1.5])
    wo = unit(rng.normal(size=(n, 3)) + [0, 0, 1.5])
    normal = unit(rng.normal(size=(n, 3)) * 0.4 + [0, 0, 1])
    diffuse, specular = rng.uniform(size=(n, 3)), rng.uniform(size=(n, 3))
    roughness = rng.uniform(0.05, 1.0, size=(n, 1))
    from mideepbasis.render import shading

    def dr_vec(a, cls):
        return cls(*[mi.Float(a[:, i].astype(np.float32)) for i in range(a.shape[1])])

    value = shading.eval_cosine(convention, dr_vec(normal, mi.Vector3f), dr_vec(wi, mi.Vector3f),
                                dr_vec(wo, mi.Vector3f), dr_vec(diffuse, mi.Color3f),
                                mi.Float(roughness[:, 0].astype(np.float32)), dr_vec(specular, mi.Color3f))
    value = np.array(value).T  # drjit arrays convert to (channels, lanes)

    def t(a):  # (n, C) -> (1, C, n, 1), the reference's (..., C, H, W) layout
        return torch.from_numpy(a.astype(np.float32)).T[None, :, :, None]

    expected = reference.eval_cosine(convention, t(normal), t(wi), t(wo), t(diffuse), t(roughness), t(specular))
    expected = expected[0, :, :, 0].T.numpy()
    assert np.isfinite(value).all() and (expected > 0).mean() > 0.5
    np.testing.assert_allclose(value, expected, rtol=EVAL_RTOL[convention], atol=1e-7 * expected.max())


def test_eval_pdf_and_sample_are_consistent():
    bsdf = constant_svbrdf("physical", normal=tilted_normal(20.0), roughness=0.4)
    n = 10_000
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(1, n)
    si = surface_interaction(n, incident(35.0, 80.0))
    bs, weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(), sampler.next_2d())
    value, pdf = bsdf.eval_pdf(mi.BSDFContext(), si, bs.wo)
    np.testing.assert_allclose(np.array(pdf), np.array(bs.pdf), rtol=1e-5)
    np.testing.assert_allclose(np.array(value), np.array(bsdf.eval(mi.BSDFContext(), si, bs.wo)), rtol=1e-6)
    valid = np.array(bs.pdf) > 0
    expected_weight = np.array(value)[:, valid] / np.array(bs.pdf)[valid]
    np.testing.assert_allclose(np.array(weight)[:, valid], expected_weight, rtol=1e-5)
    assert valid.mean() > 0.9
