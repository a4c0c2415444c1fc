"""Stone: natural stone (granite, slate, sandstone, travertine), marble, terrazzo, and cobbles or
flagstones set in mortar.

Granite is a mosaic of crystals (Voronoi cells) of three minerals; slate is terraced by its
cleavage; sandstone and travertine are sand-speckled and bedded, travertine with elongated
voids. Marble veins are thin bands where a turbulence-warped sine crosses zero, plus a finer
network along zero crossings of a warped noise. Terrazzo chips are shrunken cells in a cement
matrix; cobbles are domed cells, flagstones flat ones, both with mortar in between. Stone that
is polished is nearly flat and glossy; honed, cleft or tumbled stone is rough and has relief.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, smoothstep
from ..registry import family

#: Variants and their chances.
_VARIANTS = (("granite", 0.16), ("slate", 0.1), ("sandstone", 0.08), ("travertine", 0.08), ("marble", 0.2),
             ("terrazzo", 0.14), ("cobbles", 0.12), ("flagstones", 0.12))

#: Surface finishes of cut stone: roughness range and relief factor.
_FINISHES = {"polished": ((0.03, 0.14), 0.05), "honed": ((0.3, 0.55), 0.4), "rough": ((0.6, 0.9), 1.0)}


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _palette(canvas: Canvas, count: int, hue: tuple[float, float], saturation: tuple[float, float],
             value: tuple[float, float], shades: int = 12) -> np.ndarray:
    """(count, 3) linear colours from an sRGB HSV box: a few drawn shades, each item one of them
    with its own brightness (drawing every item through ``hsv_color`` would be slow)."""
    draws = canvas.rng.random((shades, 3))
    palette = np.stack([hsv_color(hue[0] + (hue[1] - hue[0]) * h, saturation[0] + (saturation[1] - saturation[0]) * s,
                                  value[0] + (value[1] - value[0]) * v) for h, s, v in draws])
    pick = canvas.rng.integers(shades, size=count)
    return (palette[pick] * (0.9 + 0.2 * canvas.rng.random((count, 1)))).astype(np.float32)


def _earth_color(canvas: Canvas, dark: bool = False) -> np.ndarray:
    """A stone's base colour: greys, buffs, browns and reds, sometimes greenish or bluish."""
    warm = canvas.chance(0.7)
    hue = canvas.uniform(0.02, 0.13) if warm else canvas.uniform(0.3, 0.65)
    low, high = (0.08, 0.35) if dark else (0.25, 0.8)
    return hsv_color(hue, canvas.uniform(0.0, 0.45 if warm else 0.12), canvas.uniform(low, high))


def _points(canvas: Canvas, per_side: float, jitter: float, keep: float = 1.0) -> np.ndarray:
    """Jittered seed points, a random fraction ``keep`` of them (fewer points: mixed cell sizes)."""
    points = canvas.jittered_points(int(round(canvas.frequency(per_side))), jitter)
    if keep < 1.0:
        kept = canvas.rng.random(len(points)) < keep
        kept[0] = True
        points = points[kept]
    return points


def _wave_vector(canvas: Canvas, cycles: float) -> tuple[float, float, float]:
    """A wave vector (ku, kv) [cycles per sample] of about ``cycles`` in a random direction, whole
    numbers on a tileable canvas (so that bands wrap), and the direction the bands run along [rad]."""
    angle = canvas.uniform(0, math.pi)
    ku, kv = cycles * math.cos(angle), cycles * math.sin(angle)
    if canvas.tileable:
        ku, kv = float(round(ku)), float(round(kv))
        if ku == 0 and kv == 0:
            ku = 1.0
    return ku, kv, math.atan2(kv, ku) + math.pi / 2


def _granite(canvas: Canvas, finish: str):
    """Crystals of feldspar (the granite's colour), quartz (grey) and mica/hornblende (black)."""
    points = _points(canvas, canvas.loguniform(30, 110), 1.0, canvas.uniform(0.4, 1.0))
    _, label, edge = canvas.cells(points)
    style = canvas.choice(["grey", "pink", "red", "black", "brown", "white"])
    feldspar = {"grey": ((0.05, 0.12), (0.0, 0.1), (0.55, 0.85)), "pink": ((0.97, 1.04), (0.2, 0.45), (0.6, 0.85)),
                "red": ((0.98, 1.03), (0.45, 0.7), (0.35, 0.6)), "black": ((0.0, 1.0), (0.0, 0.1), (0.08, 0.2)),
                "brown": ((0.04, 0.08), (0.35, 0.6), (0.25, 0.5)),
                "white": ((0.08, 0.14), (0.0, 0.12), (0.75, 0.92))}[style]
    n = len(points)
    palette = np.stack([_palette(canvas, n, *feldspar),
                        _palette(canvas, n, (0.55, 0.65), (0.0, 0.12), (0.3, 0.55)),   # quartz
                        _palette(canvas, n, (0.0, 0.15), (0.0, 0.3), (0.02, 0.09))])   # mafic
    share = np.array([canvas.uniform(0.45, 0.75), canvas.uniform(0.15, 0.35), canvas.uniform(0.05, 0.3)])
    mineral = np.searchsorted(np.cumsum(share) / share.sum(), canvas.rng.random(n))
    per_cell = palette[mineral, np.arange(n)]
    diffuse = per_cell[label]
    grain = canvas.noise(beta=1.0, low=8)
    diffuse = diffuse * (1.0 + 0.08 * grain[..., None])
    # Crystals polish unevenly: mica flakes stay rougher, quartz takes the best polish.
    rough_offset = np.array([0.0, -0.03, 0.1], np.float32)[mineral][label]
    crystal = canvas.rng.random(n).astype(np.float32)[label]
    height = (0.05 * crystal + 0.03 * smoothstep(0.0, 2.0 / canvas.size, edge) + 0.02 * grain) * MILLIMETRE
    return diffuse, rough_offset + 0.04 * grain, height, f"granite_{style}"


def _slate(canvas: Canvas, finish: str):
    """Dark fine-grained stone split along its cleavage: flat terraces with jagged step edges, a
    fine lineation, and rust stains."""
    hue = canvas.choice([canvas.uniform(0.5, 0.65), canvas.uniform(0.2, 0.4), canvas.uniform(0.8, 0.95),
                         canvas.uniform(0.05, 0.12)])  # blue-grey, green, purple, or rusty brown
    base = hsv_color(hue, canvas.uniform(0.03, 0.25), canvas.uniform(0.15, 0.45))
    angle = canvas.uniform(0, math.pi)
    lineation = canvas.noise(beta=1.5, low=4, stretch=canvas.uniform(6, 20), angle=angle)
    relief = canvas.noise(beta=3.0, low=1, high=10) + 0.06 * lineation
    levels = canvas.uniform(2, 5)
    stepped = relief * levels
    level = np.floor(stepped)
    step = smoothstep(0.9, 1.0, stepped - level)
    terrace = (level + step) / levels
    edge = step * (1 - step) * 4  # the broken edge of each layer: paler, rougher
    stain = smoothstep(0.8, 1.8, canvas.warp(relief, 0.05 * lineation, 0.0) + 0.3 * lineation) * canvas.uniform(0, 1)
    rust = hsv_color(canvas.uniform(0.06, 0.1), canvas.uniform(0.5, 0.8), canvas.uniform(0.25, 0.45))
    tone = 1.0 + 0.06 * lineation + 0.2 * ((level * 0.618) % 1.0 - 0.5) + 0.4 * edge
    diffuse = base * tone[..., None]
    diffuse = diffuse * (1 - stain[..., None] * 0.7) + rust * stain[..., None] * 0.7
    height = (canvas.uniform(0.15, 0.5) * terrace + 0.01 * lineation) * MILLIMETRE
    return diffuse, 0.04 * lineation + 0.2 * edge, height, "slate"


def _bedded(canvas: Canvas, finish: str, travertine: bool):
    """Sandstone or travertine: sand speckle and bedding. The laminae are contours of a smooth field
    stretched along the bedding (cross-bedding bends them); their tone changes from layer to layer.
    Travertine adds voids stretched along the layers, open or filled."""
    if travertine:
        base = hsv_color(canvas.uniform(0.07, 0.12), canvas.uniform(0.12, 0.4), canvas.uniform(0.55, 0.85))
    else:
        base = hsv_color(canvas.uniform(0.03, 0.13), canvas.uniform(0.15, 0.6), canvas.uniform(0.3, 0.8))
    # Layers a little darker, paler or redder (iron) than the stone.
    layer_tint = np.array([1.0, canvas.uniform(0.75, 1.0), canvas.uniform(0.55, 1.0)], np.float32)
    ku, kv, angle = _wave_vector(canvas, canvas.uniform(3, 20))
    bedding = canvas.noise(beta=3.0, low=1, high=12, stretch=canvas.uniform(3, 10), angle=angle)
    sand = canvas.noise(beta=0.0, low=canvas.size / 6)
    # [laminae]: parallel layers, bent by less than a few laminae (more for cross-bedded sandstone)
    layers = ku * canvas.u + kv * canvas.v + bedding * canvas.uniform(0.3, 1.5 if travertine else 3.0)
    layer = np.floor(layers)
    tone = (np.sin(layer * 12.9898) * 43758.547) % 1.0  # a random tone per lamina
    line = np.exp(-((layers - layer - 0.5) / canvas.uniform(0.03, 0.12)) ** 2)  # thin partings
    contrast = canvas.uniform(0.15, 0.5)
    shade = 1 + contrast * (tone - 0.5) - canvas.uniform(0.0, 0.3) * line
    tint = 1 + (layer_tint - 1) * tone[..., None]
    diffuse = base * tint * (shade * (1 + 0.1 * sand))[..., None]
    height = (0.04 * sand + 0.1 * tone - 0.05 * line) * MILLIMETRE
    rough = 0.05 * sand
    if travertine:  # voids stretched along the bedding, darker inside, sometimes filled
        voids = smoothstep(1.6, 2.1, canvas.noise(beta=1.8, low=4, high=60, stretch=canvas.uniform(2, 5), angle=angle)
                           + 0.4 * line)
        filled = canvas.chance(0.4)
        diffuse = diffuse * (1 - (0.2 if filled else 0.55) * voids[..., None])
        height = height - (0.05 if filled else 0.6) * MILLIMETRE * voids
        rough = rough + (0.0 if filled else 0.3) * voids
    return diffuse, rough, height, "travertine" if travertine else "sandstone"


def _marble(canvas: Canvas, finish: str):
    """Marble: a clouded base and veins, thick bands from a turbulence-warped sine plus a fine
    network along the zero crossings of a warped noise."""
    style = canvas.choice(["white", "white", "black", "green", "brown", "pink", "grey"])
    base, vein_color = {
        "white": (hsv_color(canvas.uniform(0.05, 0.6), canvas.uniform(0.0, 0.06), canvas.uniform(0.8, 0.95)),
                  hsv_color(canvas.choice([0.6, 0.1]), canvas.uniform(0.0, 0.35), canvas.uniform(0.3, 0.7))),
        "black": (hsv_color(canvas.uniform(0, 1), canvas.uniform(0, 0.1), canvas.uniform(0.04, 0.14)),
                  hsv_color(canvas.uniform(0.05, 0.12), canvas.uniform(0.0, 0.25), canvas.uniform(0.75, 0.95))),
        "green": (hsv_color(canvas.uniform(0.35, 0.48), canvas.uniform(0.3, 0.7), canvas.uniform(0.1, 0.35)),
                  hsv_color(canvas.uniform(0.3, 0.45), canvas.uniform(0.0, 0.3), canvas.uniform(0.7, 0.95))),
        "brown": (hsv_color(canvas.uniform(0.05, 0.1), canvas.uniform(0.3, 0.6), canvas.uniform(0.25, 0.55)),
                  hsv_color(canvas.uniform(0.07, 0.12), canvas.uniform(0.1, 0.35), canvas.uniform(0.7, 0.9))),
        "pink": (hsv_color(canvas.uniform(0.97, 1.05), canvas.uniform(0.15, 0.4), canvas.uniform(0.6, 0.85)),
                 hsv_color(canvas.uniform(0.95, 1.02), canvas.uniform(0.2, 0.5), canvas.uniform(0.3, 0.55))),
        "grey": (hsv_color(canvas.uniform(0.5, 0.65), canvas.uniform(0.0, 0.12), canvas.uniform(0.4, 0.65)),
                 hsv_color(canvas.uniform(0.5, 0.65), canvas.uniform(0.0, 0.1), canvas.uniform(0.8, 0.95))),
    }[style]
    # Smooth warps: the gradient of a field with much fine detail would shred the veins.
    turbulence = canvas.noise(beta=3.0, low=1, high=12)
    detail = canvas.noise(beta=2.5, low=2, high=48)
    # Main veins: a sine across the veining direction, warped; warping by less than a period keeps
    # the veins long instead of looping.
    ku, kv, angle = _wave_vector(canvas, canvas.uniform(0.6, 2.5))
    phase = (ku * canvas.u + kv * canvas.v + canvas.uniform(0.15, 0.45) * turbulence
             + canvas.uniform(0.02, 0.08) * detail)
    # (1 - |sin|)^p: thin veins with soft flanks; p varies along the vein (thick and thin stretches).
    sharpness = canvas.loguniform(4, 50) * np.exp(0.5 * detail)
    main = (1 - np.abs(np.sin(math.pi * phase))) ** sharpness
    # Secondary network: zero crossings of noise stretched along the veining, warped.
    cracks = canvas.noise(beta=2.8, low=1, high=40, stretch=canvas.uniform(1.5, 5), angle=angle)
    cracks = canvas.warp(cracks, 0.04 * turbulence, 0.04 * turbulence.T)
    fine = np.exp(-(cracks / (canvas.loguniform(0.03, 0.1) * (1 + 0.5 * detail.clip(-1, 2)))) ** 2)
    fine = fine * canvas.uniform(0.15, 0.7) * smoothstep(-1.0, 1.0, turbulence + canvas.uniform(-1, 1.5))
    veins = np.clip(np.maximum(main * canvas.uniform(0.5, 1.0), fine), 0, 1)
    cloud = 1.0 + 0.12 * canvas.uniform(0.3, 1.0) * turbulence
    diffuse = base * cloud[..., None] * (1 - veins[..., None]) + vein_color * veins[..., None]
    height = (0.01 * (1 - veins) + 0.002 * detail) * MILLIMETRE
    return diffuse, 0.05 * veins, height, f"marble_{style}"


def _terrazzo(canvas: Canvas, finish: str):
    """Angular stone chips (shrunken Voronoi cells) and a speckle of fine aggregate in cement."""
    per_side = canvas.loguniform(6, 28)
    points = _points(canvas, per_side, 1.0, canvas.uniform(0.6, 1.0))
    _, label, edge = canvas.cells(points)
    n = len(points)
    matrix_color = hsv_color(canvas.uniform(0, 1), canvas.choice([0.0, 0.05, canvas.uniform(0.1, 0.4)]),
                             canvas.choice([canvas.uniform(0.6, 0.9), canvas.uniform(0.15, 0.5)]))
    kinds = int(canvas.uniform(2, 6))
    chip_colors = np.stack([_earth_color(canvas) if canvas.chance(0.6) else
                            hsv_color(canvas.uniform(0, 1), canvas.uniform(0.2, 0.8), canvas.uniform(0.1, 0.95))
                            for _ in range(kinds)])
    kind = canvas.rng.integers(kinds, size=n)
    tint = (0.85 + 0.3 * canvas.rng.random((n, 1))).astype(np.float32)
    # Chips fill their cell up to a random gap; some cells hold no chip at all (only cement).
    cell_size = 1.0 / per_side
    gap = (canvas.rng.uniform(0.04, 0.3, n) * cell_size).astype(np.float32)
    present = canvas.rng.random(n) < canvas.uniform(0.6, 1.0)
    ragged = canvas.noise(beta=1.5, low=4, high=canvas.size / 4)
    chip = smoothstep(0.0, 1.5 / canvas.size, edge + 0.015 * cell_size * ragged - gap[label]) * present[label]
    speck_field = canvas.warp(ragged, 0.37, 0.61)
    speck = smoothstep(1.4, 1.7, np.abs(speck_field) * 1.3) * (1 - chip)
    speck_color = chip_colors[(np.floor(speck_field * 7) % kinds).astype(np.int64)]
    chip_diffuse = chip_colors[kind][label] * tint[label]
    diffuse = matrix_color * (1 - chip[..., None]) + chip_diffuse * chip[..., None]
    diffuse = diffuse * (1 - speck[..., None]) + speck_color * speck[..., None]
    height = (0.01 * chip - 0.006 * (1 - chip) * ragged) * MILLIMETRE
    return diffuse, 0.06 * (1 - chip), height, "terrazzo"


def _set_stones(canvas: Canvas, finish: str, domed: bool):
    """Cobbles (domed) or flagstones (flat, tilted) of one or several stones, in mortar or sand."""
    per_side = canvas.loguniform(2.5, 9.0) if domed else canvas.loguniform(1.5, 4.5)
    points = _points(canvas, per_side, canvas.uniform(0.5, 1.0))
    nearest, label, edge = canvas.cells(points)
    n = len(points)
    cell_size = 1.0 / canvas.frequency(per_side)
    joint = canvas.uniform(0.04, 0.15) * cell_size if domed else canvas.uniform(0.015, 0.05) * cell_size
    mottle = canvas.noise(beta=2.5, low=2, high=32)  # smooth: it also shapes the slabs
    speckle = canvas.noise(beta=0.3, low=canvas.size / 8)
    rim = edge + 0.01 * cell_size * mottle - joint  # distance inside the stone's outline [sample widths]
    stone = smoothstep(0.0, 1.5 / canvas.size, rim)
    # Stones of one kind, or a mix of a few kinds of one region's stone.
    kinds = np.stack([_earth_color(canvas) for _ in range(1 if canvas.chance(0.5) else int(canvas.uniform(2, 4)))])
    brightness = (0.75 + 0.5 * canvas.rng.random((n, 1))).astype(np.float32)
    colors = kinds[canvas.rng.integers(len(kinds), size=n)] * brightness
    diffuse = colors[label] * (1 + 0.12 * mottle[..., None] + 0.1 * speckle[..., None])
    mortar = hsv_color(canvas.uniform(0.05, 0.14), canvas.uniform(0.0, 0.3), canvas.uniform(0.2, 0.7))
    mortar_diffuse = mortar * (1 + 0.15 * speckle[..., None])
    per_stone = canvas.rng.random((n, 3)).astype(np.float32)
    if domed:  # rounded edges and a crown a few millimetres high; worn smoother on top
        radius = canvas.uniform(0.15, 0.4) * cell_size
        x = np.clip(rim / radius, 0.0, 1.0)
        crown = 1.0 - 0.4 * (nearest / cell_size) ** 2
        # A few millimetres, at most half the rounding radius (steeper would be cliffs at 256 pixels).
        relief_mm = min(canvas.uniform(2.0, 6.0), 0.5 * radius * 150.0)
        relief = relief_mm * MILLIMETRE * (0.7 + 0.6 * per_stone[label, 0])
        height = canvas.blur(relief * np.sqrt(x * (2 - x)) * crown, cell_size * 0.04 + 0.5 / canvas.size)
        polish = -0.25 * x
    else:  # flat slabs, each slightly tilted, with a cleft surface
        tilt = (per_stone[label, 1:] - 0.5) * 0.5 * MILLIMETRE / cell_size
        du = canvas.u - points[label, 0]
        dv = canvas.v - points[label, 1]
        if canvas.tileable:
            du, dv = (du + 0.5) % 1.0 - 0.5, (dv + 0.5) % 1.0 - 0.5
        slab = canvas.uniform(0.5, 2.0) * MILLIMETRE + tilt[..., 0] * du + tilt[..., 1] * dv + 0.3 * MILLIMETRE * mottle
        height = slab * smoothstep(0.0, canvas.uniform(0.04, 0.08) * cell_size, rim)
        polish = 0.0
    height = height + 0.02 * MILLIMETRE * speckle * stone + 0.06 * MILLIMETRE * speckle * (1 - stone)
    m = stone[..., None]
    diffuse = diffuse * m + mortar_diffuse * (1 - m)
    rough = polish + 0.25 * (1 - stone)
    return diffuse, rough, height, "cobbles" if domed else "flagstones"


@family("stone")
def stone(canvas: Canvas) -> Surface:
    variant = _pick(canvas, _VARIANTS)
    if variant in ("granite", "marble", "terrazzo"):  # cut and usually polished
        finish = _pick(canvas, (("polished", 0.6), ("honed", 0.3), ("rough", 0.1)))
    elif variant in ("slate", "travertine"):
        finish = _pick(canvas, (("honed", 0.4), ("rough", 0.6)))
    else:
        finish = "rough"
    (rough_low, rough_high), relief = _FINISHES[finish]
    make = {"granite": _granite, "slate": _slate, "marble": _marble, "terrazzo": _terrazzo,
            "sandstone": lambda c, f: _bedded(c, f, False), "travertine": lambda c, f: _bedded(c, f, True),
            "cobbles": lambda c, f: _set_stones(c, f, True),
            "flagstones": lambda c, f: _set_stones(c, f, False)}[variant]
    diffuse, rough_offset, height, name = make(canvas, finish)
    if variant in ("cobbles", "flagstones"):  # the stones' relief stays; only their texture is scaled
        relief = 1.0
    roughness = canvas.uniform(rough_low, rough_high) + rough_offset
    specular = dielectric_f0(canvas, 0.04, 0.055) if finish == "polished" else dielectric_f0(canvas, 0.03, 0.05)
    return Surface(height=(height * relief).astype(np.float32), diffuse=np.clip(diffuse, 0, 1).astype(np.float32),
                   roughness=np.clip(roughness, 0, 1).astype(np.float32),
                   specular=np.broadcast_to(specular, diffuse.shape).astype(np.float32),
                   variant=f"{name}_{finish}")
