"""Pottery and glazes (vessels seen close up; tiled walls are the ``tiles_bricks`` family):
crackle glaze, glossy and reactive glazes with pooling and drips, matte speckled stoneware,
porcelain (plain, blue-and-white or gilded) and unglazed earthenware.

A glaze is glass (F0 about 0.04 to 0.05) that is smooth (roughness 0.02 to 0.15) and levels the
relief of the clay below it: it pools, thicker and darker, in the hollows of the throwing rings and
thins, paler, over their crests. Matte glazes and bare clay are rough. Relief is small except on
bare clay: throwing rings of a few tenths of a millimetre, glaze runs and beads, crackle lines.
Colours are built in planar (3, H, W) layout, which numpy broadcasts much faster than (H, W, 3),
and handed back as an (H, W, 3) view.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import METALS, MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, planar, smoothstep
from ..registry import family


def _glaze_color(canvas: Canvas, kind: str) -> np.ndarray:
    """A glaze colour (3,): ``pale`` (whites, creams, celadons, pale blues) or ``strong`` (cobalt,
    copper red, chrome green, tenmoku brown, black, turquoise, any)."""
    if kind == "pale":
        return hsv_color(canvas.choice([canvas.uniform(0.08, 0.16), canvas.uniform(0.25, 0.45), canvas.uniform(0.5, 0.62)]),
                         canvas.uniform(0.03, 0.3), canvas.uniform(0.7, 0.95))
    hue = canvas.choice([0.62, 0.0, 0.33, 0.07, 0.48, canvas.uniform(0, 1)]) + canvas.uniform(-0.03, 0.03)
    return hsv_color(hue, canvas.uniform(0.4, 0.95), canvas.uniform(0.1, 0.8))


def _throwing(canvas: Canvas) -> np.ndarray:
    """Throwing rings of a wheel-thrown pot: wobbly parallel ridges across the sample, (H, W) in
    about [-1, 1]. Horizontal, as a pot stands, or slightly tilted on a plain canvas."""
    rings = canvas.frequency(canvas.uniform(6, 30))
    tilt = 0.0 if canvas.tileable else canvas.uniform(-0.1, 0.1)
    wobble = canvas.noise(beta=3.0, low=1, high=6)
    phase = rings * (canvas.v + tilt * (canvas.u - 0.5)) + canvas.uniform(0.1, 0.4) * wobble
    # Sharpened sine: ridges left between finger grooves.
    wave = np.sin(2 * math.pi * phase)
    return np.sign(wave) * np.abs(wave) ** canvas.uniform(0.5, 1.0)


def _drips(canvas: Canvas) -> tuple[np.ndarray, np.ndarray]:
    """A run of glaze with drips hanging from its lower edge: (coverage in [0, 1], extra glaze
    thickness in [0, 1], thickest in the bead along the drips' fronts).

    The run is a band between an upper edge and a lower edge, both functions of u (rows of
    periodic noise) and measured modulo one sample down the image, so it wraps on a tileable
    canvas.
    """
    # The upper edge undulates gently: a few whole-cycle sines (cheaper than a noise field).
    cycles = np.arange(1, 5)[:, None]
    phases = canvas.rng.uniform(0, 2 * math.pi, (4, 1))
    top = canvas.uniform(0, 1) + (0.01 / cycles * np.sin(2 * math.pi * cycles * canvas.u[0][None, :] + phases)).sum(0)
    hang = canvas.noise(beta=1.0, low=canvas.uniform(8, 20), high=60)[0]  # one row: a periodic function of u
    length = canvas.uniform(0.1, 0.35) + canvas.uniform(0.05, 0.3) * np.maximum(hang, 0.0) ** 1.5
    down = (canvas.v - top[None, :]) % 1.0  # below the upper edge [sample widths]
    reach = length[None, :]
    edge = 1.5 / canvas.size
    coverage = smoothstep(0.0, 4 * edge, down) * smoothstep(reach + edge, reach - edge, down)
    bead = np.exp(-((reach - down) / canvas.uniform(0.005, 0.015)) ** 2) * (down < reach + 2 * edge)
    thickness = np.clip(0.4 * smoothstep(0.0, 0.05, down) * coverage + bead, 0.0, 1.0)
    return coverage.astype(np.float32), thickness.astype(np.float32)


def _speckles(canvas: Canvas, density: float) -> tuple[np.ndarray, np.ndarray]:
    """Iron speckles of stoneware clay bleeding into the glaze: (cores, halos) in [0, 1]."""
    field = canvas.noise(beta=0.0, low=canvas.uniform(30, 80))
    threshold = 3.2 - 1.2 * density
    return smoothstep(threshold, threshold + 0.4, field), smoothstep(threshold - 0.3, threshold, field)


class _Pot:
    """The ware as it is being made: height [patch half-widths], planar diffuse (3, H, W),
    roughness, specular F0 (3,) or planar."""

    def __init__(self, height, diffuse, roughness, specular):
        self.height, self.diffuse, self.roughness, self.specular = height, diffuse, roughness, specular


def _glazed(canvas: Canvas, thin, thick, roughness: float, leveling: float) -> _Pot:
    """A glaze over thrown clay: the glaze's surface keeps ``leveling`` of the clay's relief; its
    colour goes from ``thin`` over crests to ``thick`` where it pools."""
    # Clay relief [mm]: throwing rings and the unevenness of the wall.
    body = _throwing(canvas) * canvas.uniform(0.05, 0.3) + canvas.uniform(0.05, 0.2) * canvas.noise(beta=2.5, low=2, high=40)
    pool = smoothstep(-1.5, 1.5, -body / max(float(body.std()), 1e-6))
    height = body * leveling * MILLIMETRE
    diffuse = planar(thin) + pool * (planar(thick) - planar(thin))
    return _Pot(height, diffuse, np.full_like(height, roughness), dielectric_f0(canvas, 0.04, 0.05))


def _add_drips(canvas: Canvas, pot: _Pot, color):
    """Glaze that ran: a band with hanging drips, raised and of another (often darker) colour."""
    coverage, thickness = _drips(canvas)
    pot.height = pot.height + thickness * canvas.uniform(0.1, 0.3) * MILLIMETRE
    pot.diffuse = pot.diffuse + (0.6 * coverage + 0.4 * thickness) * (planar(color) - pot.diffuse)


def _pinholes(canvas: Canvas, pot: _Pot):
    """Sparse pinholes and burst bubbles in the glaze: tiny pits, slightly darker."""
    field = canvas.noise(beta=0.0, low=canvas.uniform(50, 100))
    pits = smoothstep(3.3, 3.9, field)
    pot.height = pot.height - pits * 0.05 * MILLIMETRE
    pot.diffuse = pot.diffuse * (1.0 - 0.3 * pits)


# --- variants ------------------------------------------------------------------------------------

def _crackle(canvas: Canvas) -> _Pot:
    """Crackle glaze: a network of fine cracks in a pale glaze, stained darker, cells of a few
    millimetres to centimetres."""
    color = _glaze_color(canvas, "pale")
    pot = _glazed(canvas, color, planar(color).ravel() * canvas.uniform(0.75, 0.95), canvas.uniform(0.03, 0.15),
                  canvas.uniform(0.1, 0.3))
    count = canvas.frequency(canvas.loguniform(6, 40))
    _, _, edge = canvas.cells(canvas.jittered_points(int(count), 1.0))
    # Cracks meander: bend the straight Voronoi borders.
    bend = canvas.uniform(0.05, 0.15) / count
    meander = canvas.noise(beta=2.5, low=1, high=1.5 * count) * bend
    # The field rolled by half the sample is as good as a second, independent one, and periodic.
    edge = canvas.warp(edge, meander, np.roll(meander, canvas.size // 2, axis=(0, 1)))
    width = canvas.uniform(0.6, 1.2) / canvas.size
    cracks = np.exp(-(edge / width) ** 2)
    stain = hsv_color(canvas.uniform(0.05, 0.1), canvas.uniform(0.2, 0.7), canvas.uniform(0.05, 0.5))
    strength = canvas.uniform(0.5, 1.0)
    pot.diffuse = pot.diffuse + cracks * strength * (planar(stain) - pot.diffuse)
    pot.height = pot.height - cracks * canvas.uniform(0.005, 0.02) * MILLIMETRE
    return pot


def _glossy(canvas: Canvas, reactive: bool) -> _Pot:
    """Glossy glazes: one colour pooling over the throwing rings, or (reactive) two or three that
    flowed into each other in streaks, with crystals; often runs and drips."""
    thick = _glaze_color(canvas, "strong")
    # Over the crests the glaze is thin and paler (it "breaks"), or shows a related second colour.
    thin = planar(thick).ravel() * canvas.uniform(1.1, 1.8)
    if canvas.chance(0.25):
        thin = planar(thin).ravel() * 0.5 + 0.5 * _glaze_color(canvas, "pale")
    pot = _glazed(canvas, np.clip(thin, 0, 1), thick, canvas.uniform(0.02, 0.12), canvas.uniform(0.1, 0.4))
    if reactive:
        # Streaks of a second glaze that flowed down through the first.
        flow = canvas.noise(beta=3.0, low=1.5, high=40, stretch=canvas.uniform(3, 8), angle=math.pi / 2)
        second = smoothstep(-0.6, 0.9, flow + canvas.uniform(-0.5, 0.5))
        pot.diffuse = pot.diffuse + second * (planar(_glaze_color(canvas, canvas.choice(["pale", "strong"]))) - pot.diffuse)
        pot.roughness = pot.roughness + second * canvas.uniform(0.0, 0.2)
        if canvas.chance(0.5):  # crystals grown in the glaze: pale flecks
            cores, halos = _speckles(canvas, canvas.uniform(0.0, 0.6))
            pot.diffuse = pot.diffuse + (0.3 * halos + 0.4 * cores) * (planar(_glaze_color(canvas, "pale")) - pot.diffuse)
    else:
        pot.diffuse = pot.diffuse * (1.0 + 0.08 * canvas.noise(beta=2.5, low=1, high=20))  # uneven application
    if canvas.chance(0.6):
        _add_drips(canvas, pot, planar(thick).ravel() * canvas.uniform(0.5, 1.0))
    if canvas.chance(0.4):
        _pinholes(canvas, pot)
    return pot


def _stoneware(canvas: Canvas) -> _Pot:
    """Matte stoneware: satin to dry glaze or bare clay in oatmeal, grey, blue-grey or brown,
    with iron speckles and gritty clay."""
    color = hsv_color(canvas.choice([canvas.uniform(0.07, 0.13), canvas.uniform(0.5, 0.62)]), canvas.uniform(0.03, 0.35),
                      canvas.uniform(0.3, 0.85))
    pot = _glazed(canvas, color, planar(color).ravel() * canvas.uniform(0.6, 0.9), canvas.uniform(0.45, 0.85),
                  canvas.uniform(0.5, 0.9))
    grit = canvas.noise(beta=0.5, low=40)
    pot.height = pot.height + grit * canvas.uniform(0.005, 0.03) * MILLIMETRE
    pot.roughness = pot.roughness + 0.03 * grit
    cores, halos = _speckles(canvas, canvas.uniform(0.2, 1.0))
    iron = hsv_color(canvas.uniform(0.04, 0.09), canvas.uniform(0.5, 0.9), canvas.uniform(0.1, 0.35))
    pot.diffuse = pot.diffuse + (0.8 * cores + 0.25 * halos) * (planar(iron) - pot.diffuse)
    pot.height = pot.height + cores * 0.02 * MILLIMETRE
    return pot


def _porcelain(canvas: Canvas) -> _Pot:
    """Porcelain: white, very smooth and glossy, plain or with cobalt painting under the glaze or
    a gilded band over it."""
    white = hsv_color(canvas.choice([canvas.uniform(0.55, 0.62), canvas.uniform(0.1, 0.15)]), canvas.uniform(0.0, 0.06),
                      canvas.uniform(0.86, 0.97))
    pot = _glazed(canvas, white, planar(white).ravel() * canvas.uniform(0.92, 1.0), canvas.uniform(0.03, 0.12), 0.05)
    decoration = canvas.choice(["plain", "cobalt", "cobalt", "gilded"])
    if decoration == "cobalt":
        _cobalt(canvas, pot)
    elif decoration == "gilded":
        _gilding(canvas, pot)
    return pot


def _cobalt(canvas: Canvas, pot: _Pot):
    """Blue-and-white: cobalt under the glaze (colour only): bands round the pot, sweeping brush
    strokes that taper, pale washes."""
    size = canvas.size
    paint = np.zeros((size, size), np.float32)
    rng = canvas.rng
    if canvas.chance(0.6):  # bands painted while the pot turned: lines along u
        for _ in range(int(rng.integers(1, 4))):
            centre, half = canvas.uniform(0, 1), canvas.uniform(0.5, 8.0) / size
            distance = np.abs(canvas.v - centre)
            distance = np.minimum(distance, 1.0 - distance) if canvas.tileable else distance
            paint = np.maximum(paint, np.clip((half - distance) * size + 0.5, 0, 1) * canvas.uniform(0.7, 1.0))
    # Sweeping strokes: chains of short segments turning a little at each step, thinning to the tip.
    for _ in range(int(rng.integers(2, 6 if canvas.tileable else 12))):
        steps = int(rng.integers(6, 14))
        # A steady turn plus a little jitter: arcs and S-curves, pressed hardest in the middle.
        heading = canvas.uniform(0, 2 * math.pi) + np.cumsum(canvas.uniform(-0.4, 0.4) + rng.normal(0, 0.15, steps))
        step = canvas.uniform(0.01, 0.03)
        offsets = np.cumsum(step * np.stack([np.cos(heading), np.sin(heading)], -1), 0)
        points = rng.random(2) + np.concatenate([[[0.0, 0.0]], offsets])
        widths = canvas.uniform(1.0, 4.0) / size * np.sin(np.linspace(0.3, math.pi - 0.3, steps))
        canvas.draw_lines(paint, points[:-1], points[1:], canvas.uniform(0.6, 1.0), widths)
    hue = canvas.uniform(0.6, 0.66)
    if canvas.chance(0.4):  # a pale wash of diluted cobalt filling a motif
        wash = smoothstep(0.66, 0.7, canvas.blobs(canvas.uniform(4, 12), sharpness=3.0)) * (1 - paint)
        pale = hsv_color(hue, canvas.uniform(0.25, 0.5), canvas.uniform(0.75, 0.9))
        pot.diffuse = pot.diffuse + wash * (planar(pale) - pot.diffuse)
    cobalt = hsv_color(hue, canvas.uniform(0.6, 0.95), canvas.uniform(0.3, 0.65))
    pot.diffuse = pot.diffuse + paint * (planar(cobalt) - pot.diffuse)


def _gilding(canvas: Canvas, pot: _Pot):
    """A gilded band (a rim or a line): metal over the glaze, with a dark diffuse albedo."""
    across = canvas.v if canvas.chance(0.7) else canvas.u
    centre, half = canvas.uniform(0.1, 0.9), canvas.uniform(0.01, 0.12)
    distance = np.abs(across - centre)
    if canvas.tileable:
        distance = np.minimum(distance, 1.0 - distance)
    band = np.clip((half - distance) * canvas.size + 0.5, 0.0, 1.0)
    metal = np.asarray(METALS[canvas.choice(["gold", "gold", "gold", "silver", "copper"])], np.float32)
    # A pixel is gold or glaze: F0 switches in the middle of the anti-aliased edge (a blend would be
    # a coloured F0 as low as a dielectric's, which no material has), and the dark diffuse albedo
    # of the metal is complete by then.
    pot.diffuse = pot.diffuse + np.minimum(2.0 * band, 1.0) * (0.02 - pot.diffuse)
    pot.specular = planar(pot.specular) + (band >= 0.5) * (planar(metal) - planar(pot.specular))
    pot.roughness = pot.roughness + band * (canvas.uniform(0.08, 0.3) - pot.roughness)
    pot.height = pot.height + band * 0.01 * MILLIMETRE


def _earthenware(canvas: Canvas) -> _Pot:
    """Unglazed earthenware: terracotta to buff clay, rough, with grog, tool marks and firing
    flashes; sometimes burnished to a soft sheen."""
    color = hsv_color(canvas.uniform(0.01, 0.09), canvas.uniform(0.35, 0.75), canvas.uniform(0.35, 0.8))
    rings = _throwing(canvas) if canvas.chance(0.6) else 0.0
    grog = canvas.noise(beta=1.0, low=20)
    scrape = canvas.noise(beta=2.0, low=3, high=80, stretch=canvas.uniform(3, 10), angle=canvas.uniform(0, math.pi))
    height = (rings * canvas.uniform(0.05, 0.3) + grog * canvas.uniform(0.02, 0.08) + scrape * canvas.uniform(0.0, 0.1)) * MILLIMETRE
    flash = canvas.blobs(canvas.uniform(1, 3), sharpness=0.7)  # flame and smoke during firing
    diffuse = planar(color) * (1.0 + 0.08 * grog) * (1.0 - canvas.uniform(0.0, 0.35) * flash)
    burnished = canvas.chance(0.25)
    roughness = (canvas.uniform(0.3, 0.5) + 0.1 * np.abs(scrape)) if burnished else (canvas.uniform(0.75, 0.95) + 0.03 * grog)
    return _Pot(height, diffuse, roughness, dielectric_f0(canvas, 0.03, 0.04))


@family("ceramic")
def ceramic(canvas: Canvas) -> Surface:
    variant = canvas.choice(["crackle_glaze", "glossy_glaze", "glossy_glaze", "reactive_glaze", "stoneware",
                             "porcelain", "earthenware"])
    if variant == "crackle_glaze":
        pot = _crackle(canvas)
    elif variant in ("glossy_glaze", "reactive_glaze"):
        pot = _glossy(canvas, variant == "reactive_glaze")
    elif variant == "stoneware":
        pot = _stoneware(canvas)
    elif variant == "porcelain":
        pot = _porcelain(canvas)
    else:
        pot = _earthenware(canvas)
    # Uneven colour and gloss across the sample (only on a plain canvas).
    size = canvas.size
    return Surface(height=np.asarray(pot.height, np.float32),
                   diffuse=np.broadcast_to(pot.diffuse, (3, size, size)).transpose(1, 2, 0),
                   roughness=np.clip(np.broadcast_to(pot.roughness, (size, size)), 0.0, 1.0).astype(np.float32),
                   specular=np.broadcast_to(planar(pot.specular), (3, size, size)).transpose(1, 2, 0), variant=variant)
