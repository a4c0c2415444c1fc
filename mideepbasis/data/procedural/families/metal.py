"""Metal: brushed (straight or spun), hammered, galvanised, tread plate, anodised, rusted, and
painted metal with chipped paint.

Bare metal has a coloured specular albedo (F0 from ``METALS``, varied a little) and an almost
black diffuse albedo. Fine finishing marks live in the relief, because the normals are all the
GGX lobe sees of them: brushing is noise stretched along the stroke, scaled to a few degrees of
tilt across it, which spreads the flash highlight across the strokes as on real brushed metal.
Coatings are dielectrics (F0 about 0.04): anodising tints the metal's reflection by the dye it
passes through twice; rust and paint are coloured, rough (paint: any gloss) layers with their
own thickness in the relief.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import METALS, MILLIMETRE, Canvas, Surface, dielectric_f0, grid, hsv_color, smoothstep
from ..registry import family

#: Variants and their chances.
_VARIANTS = (("brushed", 0.2), ("hammered", 0.12), ("galvanised", 0.08), ("tread_plate", 0.08), ("anodised", 0.14),
             ("rusted", 0.18), ("painted", 0.2))


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _metal(canvas: Canvas, names=tuple(METALS)) -> tuple[str, np.ndarray]:
    """A metal's name and its F0, varied by a few percent (alloys, surface oxide)."""
    name = canvas.choice(list(names))
    f0 = np.asarray(METALS[name], np.float32) * canvas.uniform(0.9, 1.02)
    return name, np.clip(f0 + canvas.rng.normal(0, 0.01, 3).astype(np.float32), 0, 1)


def _slope_scale(canvas: Canvas, field: np.ndarray, degrees: float) -> np.ndarray:
    """``field`` scaled into a relief [patch half-widths] whose rms slope is ``degrees``."""
    step = 2.0 / canvas.size  # pixel spacing [patch half-widths]
    gx = np.diff(field, axis=1)
    gy = np.diff(field, axis=0)
    rms = math.sqrt(float((gx * gx).mean() + (gy * gy).mean())) / step
    return field * (math.tan(math.radians(degrees)) / max(rms, 1e-9))


def _brushing(canvas: Canvas, degrees: float) -> tuple[np.ndarray, float]:
    """Brushing grooves as relief [patch half-widths], and the stroke angle [rad]. Straight strokes,
    or on a plain canvas sometimes spun (concentric, around a centre that may be off the sample)."""
    stretch = canvas.loguniform(20, 120)
    if not canvas.tileable and canvas.chance(0.25):
        grooves = canvas.noise(beta=0.8, low=4, stretch=stretch)
        centre = canvas.rng.uniform(-0.5, 1.5, 2)
        du, dv = canvas.u - centre[0], canvas.v - centre[1]
        turns = float(round(canvas.uniform(1, 3)))
        # The stroke runs around the centre: sample the straight grooves at (angle, radius).
        along = np.arctan2(dv, du) / (2 * math.pi) * turns
        radius = np.sqrt(du * du + dv * dv)
        grooves = canvas.warp(grooves, along - canvas.u, radius - canvas.v)
        return _slope_scale(canvas, grooves, degrees), math.nan
    angle = canvas.uniform(0, math.pi)
    grooves = canvas.noise(beta=0.8, low=4, stretch=stretch, angle=angle)
    return _slope_scale(canvas, grooves, degrees), angle


def _bare(canvas: Canvas, f0: np.ndarray, roughness, height, variant: str, darkness: float = 0.02) -> Surface:
    """A bare-metal Surface: coloured F0, a dark diffuse albedo tinted like the metal."""
    shape = (canvas.size, canvas.size, 3)
    specular = np.broadcast_to(f0, shape) if np.ndim(f0) == 1 else f0
    diffuse = np.broadcast_to(f0 * canvas.uniform(0.0, darkness), shape)
    return Surface(height=np.asarray(height, np.float32), diffuse=np.asarray(diffuse, np.float32),
                   roughness=np.broadcast_to(np.asarray(roughness, np.float32), (canvas.size, canvas.size)),
                   specular=np.asarray(specular, np.float32), variant=variant)


def _brushed(canvas: Canvas) -> Surface:
    name, f0 = _metal(canvas, ("aluminium", "steel", "chromium", "nickel", "titanium", "brass", "copper",
                               "silver", "gold", "zinc"))
    height, _ = _brushing(canvas, canvas.uniform(2.0, 8.0))
    roughness = canvas.uniform(0.2, 0.5) + 0.1 * height / max(float(np.abs(height).max()), 1e-9)
    return _bare(canvas, f0, roughness, height, f"brushed_{name}")


def _hammered(canvas: Canvas) -> Surface:
    """Overlapping hammer dents: bowls around random points that meet in ridges, rounder or more
    conical (a peen's shape), over a polished surface."""
    name, f0 = _metal(canvas, ("copper", "brass", "silver", "steel", "aluminium", "bronze", "iron", "gold"))
    per_side = canvas.loguniform(5, 30)
    points = canvas.jittered_points(int(round(canvas.frequency(per_side))), canvas.uniform(0.6, 1.0))
    nearest, _, _ = canvas.cells(points)
    height = _slope_scale(canvas, nearest ** canvas.uniform(1.3, 2.2), canvas.uniform(8, 22))
    polish = canvas.noise(beta=1.0, low=8)
    height = height + _slope_scale(canvas, polish, canvas.uniform(0.2, 0.8))
    roughness = canvas.uniform(0.05, 0.3) + 0.03 * polish
    return _bare(canvas, f0, roughness, height, f"hammered_{name}")


def _galvanised(canvas: Canvas) -> Surface:
    """Hot-dip zinc spangle: large crystal grains, each with its own tilt and sheen."""
    _, f0 = _metal(canvas, ("zinc", "zinc", "aluminium"))
    points = canvas.jittered_points(int(round(canvas.frequency(canvas.loguniform(8, 30)))), 1.0)
    _, label, edge = canvas.cells(points)
    n = len(points)
    per_grain = canvas.rng.random((n, 4)).astype(np.float32)
    du, dv = canvas.u - points[label, 0], canvas.v - points[label, 1]
    if canvas.tileable:
        du, dv = (du + 0.5) % 1.0 - 0.5, (dv + 0.5) % 1.0 - 0.5
    facets = (per_grain[label, 0] - 0.5) * du + (per_grain[label, 1] - 0.5) * dv
    height = _slope_scale(canvas, facets, canvas.uniform(0.5, 2.5))
    # Dendrites: fine streaks in each grain's own direction (grain boundaries show as thin grooves).
    streaks = canvas.noise(beta=0.5, low=16, stretch=8)
    angle = per_grain[label, 2] * math.pi
    cos_a, sin_a = np.cos(angle), np.sin(angle)
    dendrites = canvas.warp(streaks, cos_a * du + sin_a * dv - du, -sin_a * du + cos_a * dv - dv)
    height = height + _slope_scale(canvas, dendrites, 1.5) - 0.02 * MILLIMETRE * (edge < 1.0 / canvas.size)
    roughness = canvas.uniform(0.15, 0.3) + 0.15 * per_grain[label, 3] + 0.04 * dendrites
    brightness = (0.88 + 0.14 * per_grain[label, 3])[..., None]
    return _bare(canvas, f0 * brightness, roughness, height, "galvanised")


def _tread_plate(canvas: Canvas) -> Surface:
    """Diamond (tread) plate: raised lozenges, alternately turned, on brushed or mill-finish metal."""
    name, f0 = _metal(canvas, ("aluminium", "aluminium", "steel", "iron", "zinc"))
    count = canvas.frequency(canvas.uniform(4, 12))
    cells = grid(canvas, count, count, 0.0)
    turn = ((np.floor(canvas.u * count) + np.floor(canvas.v * count)) % 2) * 2 - 1  # +-1
    x, y = cells.local_u - 0.5, cells.local_v - 0.5
    a = (x + turn * y) / math.sqrt(2)
    b = (-turn * x + y) / math.sqrt(2)
    length, width = canvas.uniform(0.32, 0.42), canvas.uniform(0.06, 0.1)
    lozenge = np.sqrt((a / length) ** 2 + (b / width) ** 2)  # < 1 inside
    profile = smoothstep(1.0, 0.35, lozenge) * (1 - 0.25 * (a / length) ** 2)
    bar = canvas.uniform(0.8, 1.5) * MILLIMETRE * profile
    base, _ = _brushing(canvas, canvas.uniform(0.5, 3.0))
    mottle = canvas.blobs(canvas.uniform(2, 6))
    roughness = canvas.uniform(0.25, 0.5) + 0.1 * mottle - 0.1 * profile
    return _bare(canvas, f0 * (0.9 + 0.1 * mottle[..., None]), roughness, bar + base, f"tread_plate_{name}")


def _anodised(canvas: Canvas) -> Surface:
    """Dyed anodised aluminium: the dye in the oxide tints the metal's reflection (light crosses
    it twice); the oxide's own surface adds a faint white reflection."""
    _, aluminium = _metal(canvas, ("aluminium",))
    hue = canvas.uniform(0, 1)
    value = canvas.choice([canvas.uniform(0.4, 1.0), canvas.uniform(0.05, 0.3)])  # bright dyes, or dark ones
    dye = hsv_color(hue, canvas.uniform(0.3, 0.95), value)
    f0 = 0.04 + 0.96 * aluminium * dye
    if canvas.chance(0.5):
        height, _ = _brushing(canvas, canvas.uniform(1.5, 5.0))
        finish = "brushed"
        roughness = canvas.uniform(0.25, 0.45)
    else:  # bead blasted: fine isotropic pits
        height = _slope_scale(canvas, canvas.noise(beta=0.5, low=20), canvas.uniform(2, 6))
        finish = "blasted"
        roughness = canvas.uniform(0.3, 0.55)
    surface = _bare(canvas, f0, roughness, height, f"anodised_{finish}", darkness=0.0)
    # Light scattered in the dyed oxide: a faint diffuse in the dye's colour.
    surface.diffuse = np.broadcast_to(dye * canvas.uniform(0.0, 0.04), surface.diffuse.shape).astype(np.float32)
    return surface


def _rusted(canvas: Canvas) -> Surface:
    """Iron or steel with rust: patches of rough orange-brown oxide, raised and flaky, and pits
    in the bare metal around them."""
    name, f0 = _metal(canvas, ("iron", "steel", "steel"))
    coverage = canvas.uniform(-1.2, 1.2)  # threshold on unit noise: low is heavy rust
    patches = canvas.noise(beta=2.2, low=1, high=canvas.size / 3)
    flakes = canvas.noise(beta=1.0, low=12)
    rust = smoothstep(coverage, coverage + canvas.uniform(0.1, 0.5), patches + 0.25 * flakes)
    tone = canvas.blobs(canvas.uniform(3, 12))
    dark = hsv_color(canvas.uniform(0.02, 0.05), canvas.uniform(0.5, 0.8), canvas.uniform(0.12, 0.3))
    orange = hsv_color(canvas.uniform(0.04, 0.085), canvas.uniform(0.65, 0.95), canvas.uniform(0.4, 0.75))
    mix = np.clip(tone + 0.2 * flakes, 0, 1)[..., None]
    rust_diffuse = dark * (1 - mix) + orange * mix
    bare_height, _ = _brushing(canvas, canvas.uniform(0.5, 3.0))
    pits = smoothstep(1.8, 2.4, flakes) * (1 - rust)
    thickness = canvas.uniform(0.05, 0.3) * MILLIMETRE
    height = (bare_height * (1 - rust) + thickness * rust * (0.6 + 0.4 * _flake_profile(flakes))
              - 0.05 * MILLIMETRE * pits)
    m = rust[..., None]
    metal_f0 = f0 * (0.85 + 0.15 * tone[..., None])
    rust_f0 = dielectric_f0(canvas, 0.03, 0.045)
    diffuse = rust_diffuse * m + f0 * 0.02 * (1 - m)
    specular = rust_f0 * m + metal_f0 * (1 - m)
    roughness = (canvas.uniform(0.8, 1.0) * rust + canvas.uniform(0.3, 0.6) * (1 - rust)) + 0.15 * pits
    return Surface(height=height.astype(np.float32), diffuse=diffuse.astype(np.float32),
                   roughness=roughness.astype(np.float32), specular=specular.astype(np.float32),
                   variant=f"rusted_{name}")


def _flake_profile(field: np.ndarray) -> np.ndarray:
    """|field| squashed into [0, 1): flake thickness from noise."""
    return 1.0 - np.exp(-np.abs(field))


def _painted(canvas: Canvas) -> Surface:
    """Painted metal with chipped paint: paint (a coloured dielectric, any gloss), a primer ring
    around each chip, bare (sometimes rusty) metal inside, and a step at each layer's edge."""
    _, f0 = _metal(canvas, ("steel", "iron", "aluminium", "zinc"))
    paint = hsv_color(canvas.uniform(0, 1), canvas.choice([canvas.uniform(0.0, 0.2), canvas.uniform(0.4, 0.95)]),
                      canvas.uniform(0.15, 0.9))
    primer = canvas.choice([hsv_color(0.02, 0.7, canvas.uniform(0.35, 0.5)),  # red oxide
                            hsv_color(0.1, 0.05, canvas.uniform(0.5, 0.8)),   # grey
                            paint * 0.7])
    coverage = canvas.uniform(1.0, 2.6)  # threshold on unit noise: high is few chips
    # Chips: where a smooth field (the knocks and the rusting underneath) crosses a threshold;
    # finer noise makes their edges ragged.
    chips = canvas.noise(beta=canvas.uniform(2.0, 2.8), low=1, high=canvas.size / 3)
    peel = chips + 0.12 * canvas.noise(beta=1.0, low=16)
    primer_band = canvas.uniform(0.05, 0.4)
    bare = smoothstep(coverage, coverage + 0.05, peel)
    primed = smoothstep(coverage - primer_band, coverage - primer_band + 0.05, peel) * (1 - bare)
    paint_mask = 1 - bare - primed
    orange_peel = canvas.noise(beta=2.0, low=8, high=64)
    layer = canvas.uniform(0.03, 0.12) * MILLIMETRE
    metal_height, _ = _brushing(canvas, canvas.uniform(0.5, 2.0))
    height = layer * (paint_mask * 2 + primed) + 0.004 * MILLIMETRE * orange_peel * paint_mask + metal_height * bare
    rusty = canvas.chance(0.4)
    exposed = hsv_color(0.05, 0.75, 0.35) if rusty else f0 * 0.02
    p3, r3, b3 = paint_mask[..., None], primed[..., None], bare[..., None]
    diffuse = paint * p3 + primer * r3 + exposed * b3
    coat_f0 = dielectric_f0(canvas, 0.04, 0.05)
    specular = coat_f0 * (p3 + r3) + (coat_f0 if rusty else f0) * b3
    gloss = canvas.choice([canvas.uniform(0.05, 0.2), canvas.uniform(0.25, 0.6)])
    roughness = gloss * paint_mask + canvas.uniform(0.6, 0.85) * primed + (0.9 if rusty else 0.4) * bare
    return Surface(height=height.astype(np.float32), diffuse=diffuse.astype(np.float32),
                   roughness=roughness.astype(np.float32), specular=specular.astype(np.float32),
                   variant="painted_chipped" + ("_rusty" if rusty else ""))


@family("metal")
def metal(canvas: Canvas) -> Surface:
    variant = _pick(canvas, _VARIANTS)
    return {"brushed": _brushed, "hammered": _hammered, "galvanised": _galvanised, "tread_plate": _tread_plate,
            "anodised": _anodised, "rusted": _rusted, "painted": _painted}[variant](canvas)
