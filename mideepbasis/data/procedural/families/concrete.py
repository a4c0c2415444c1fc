"""Concrete, plaster and asphalt: cast and board-formed concrete, exposed-aggregate and polished
concrete, cement screed, plasters and renders (Venetian, orange peel, knock-down, swirl, sand
float) and asphalt.

All are rough mineral dielectrics (F0 about 0.035 to 0.045) except polished concrete, Venetian
plaster and sealed screed, which are burnished or sealed. Their relief is millimetres at most:
sand grains and pores (small pits, darker as dust settles in them), aggregate stones, trowel and
formwork marks, cracks. Colours are built in planar (3, H, W) layout, which numpy broadcasts much
faster than (H, W, 3), and handed back as an (H, W, 3) view.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, planar, smoothstep, srgb_to_linear
from ..registry import family


def _cement_color(canvas: Canvas, low: float = 0.4, high: float = 0.8) -> np.ndarray:
    """Grey cement (3,), slightly warm (sand, limestone) or barely cool, sRGB value between ``low``
    and ``high``."""
    if canvas.chance(0.7):
        return hsv_color(canvas.uniform(0.05, 0.15), canvas.uniform(0.0, 0.1), canvas.uniform(low, high))
    return hsv_color(canvas.uniform(0.5, 0.62), canvas.uniform(0.0, 0.04), canvas.uniform(low, high))


def _paint_color(canvas: Canvas) -> np.ndarray:
    """Wall paint or coloured render (3,): mostly whites and pale tints."""
    if canvas.chance(0.6):
        return hsv_color(canvas.uniform(0.05, 0.15), canvas.uniform(0.0, 0.12), canvas.uniform(0.8, 0.95))
    return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.1, 0.6), canvas.uniform(0.45, 0.9))


def _hsv_colors(hue, saturation, value) -> np.ndarray:
    """Linear RGB (n, 3) of n sRGB colours given in HSV [0, 1], like ``hsv_color`` for arrays
    (one colour per stone would take thousands of scalar conversions)."""
    h = (np.asarray(hue) % 1.0) * 6.0
    sector = np.floor(h).astype(np.int64) % 6
    f = h - np.floor(h)
    v = np.asarray(value, np.float64)
    p, q, t = v * (1 - saturation), v * (1 - saturation * f), v * (1 - saturation * (1 - f))
    rgb = np.stack([np.choose(sector, [v, q, p, p, t, v]), np.choose(sector, [t, v, v, q, p, p]),
                    np.choose(sector, [p, p, t, v, v, q])], -1)
    return srgb_to_linear(rgb)


def _stone_colors(canvas: Canvas, count: int, colorful: float = 1.0) -> np.ndarray:
    """Per-stone colours (count, 3) of a gravel mix: greys with some beige, red, black and white;
    ``colorful`` scales their saturation."""
    rng = canvas.rng
    hue = np.where(rng.random(count) < 0.3, rng.uniform(0.0, 0.12, count), rng.uniform(0.05, 0.6, count))
    saturation = rng.uniform(0.0, 0.12, count) * canvas.uniform(0.3, 1.5) * colorful
    value = np.clip(rng.normal(canvas.uniform(0.4, 0.7), canvas.uniform(0.05, 0.2), count), 0.08, 0.95)
    return _hsv_colors(hue, saturation, value)


def _grain(canvas: Canvas) -> np.ndarray:
    """Sand grains: near-white noise of unit variance, features of one to a few pixels."""
    return canvas.noise(beta=0.5, low=canvas.uniform(40, 80))


def _pores(canvas: Canvas, density: float) -> np.ndarray:
    """Air pores and bug holes: sparse round pits, (H, W) depth in [0, 1] (1 at the deepest).

    The peaks of band-limited noise are round; only the highest become pits, fewer for a lower
    ``density`` in [0, 1].
    """
    cycles = canvas.uniform(25, 70)  # pits of 1 to 3 mm on a 15 cm sample
    field = canvas.noise(beta=0.0, low=cycles * 0.5, high=cycles * 1.5)
    threshold = 3.3 - 1.3 * density
    return smoothstep(threshold, threshold + 0.9, field)


def _cracks(canvas: Canvas) -> np.ndarray:
    """Hairline cracks wandering across parts of the surface, (H, W) in [0, 1]."""
    # Long gently curving zero lines of a smooth field, made jagged by a little fine detail.
    field = canvas.noise(beta=2.5, low=1.5, high=10) + 0.08 * canvas.noise(beta=1.0, low=20, high=80)
    width = canvas.uniform(0.6, 1.2) * 0.03  # [standard deviations of the field]: about a pixel
    lines = np.exp(-(field / width) ** 2)
    return lines * smoothstep(0.45, 0.6, canvas.blobs(canvas.uniform(1, 3)))


def _aggregate(canvas: Canvas, count: float, gap: float):
    """Stones of an aggregate as Voronoi cells, ``count`` per sample width, separated by a matrix
    joint of ``gap`` (fraction of a cell) on average; stones shrink inside their cells by random
    amounts, so that sizes are graded as in a real mix.

    Returns (label, stone: (H, W) in [0, 1], rounded inside each stone).
    """
    count = canvas.frequency(count)
    _, label, edge = canvas.cells(canvas.jittered_points(int(count), canvas.uniform(0.7, 1.0)))
    cell = 1.0 / count  # [sample widths]
    # Distance to the cell border, measured inside the stone: rounded like a worn pebble, its
    # outline made irregular by noise of a few bumps per stone.
    outline = canvas.noise(beta=2.0, low=count, high=count * 3) * canvas.uniform(0.03, 0.08) * cell
    shrink = (gap * canvas.rng.uniform(0.3, 1.0, int(label.max()) + 1) ** 3 * 3.0).astype(np.float32)[label]
    inside = np.clip((edge + outline - shrink * cell) / (0.35 * cell), 0.0, 1.0)
    return label, inside * (2.0 - inside)  # a parabolic cap: steep at the rim, but not a cliff


class _Mix:
    """The surface as it is being made: height [patch half-widths], planar (3, H, W) diffuse,
    roughness."""

    def __init__(self, height, diffuse, roughness):
        self.height, self.diffuse, self.roughness = height, diffuse, roughness

    def cover(self, mask, color, roughness=None, factor=None):
        """Where ``mask`` is 1 the colour becomes ``color`` (or is multiplied by ``factor``), and the
        roughness ``roughness`` when given."""
        if color is not None:
            self.diffuse = self.diffuse + mask * (planar(color) - self.diffuse)
        if factor is not None:
            self.diffuse = self.diffuse * (1.0 + mask * (factor - 1.0))
        if roughness is not None:
            self.roughness = self.roughness + mask * (roughness - self.roughness)


# --- variants ------------------------------------------------------------------------------------

def _concrete(canvas: Canvas, variant: str) -> _Mix:
    """Cast concrete (plain or board-formed), exposed-aggregate and polished concrete."""
    color = _cement_color(canvas)
    grain = _grain(canvas)
    mottling = canvas.noise(beta=2.5, low=1, high=24)
    height = grain * canvas.uniform(0.01, 0.04) * MILLIMETRE
    diffuse = planar(color) * (1.0 + canvas.uniform(0.04, 0.15) * mottling + 0.04 * grain)
    mix = _Mix(height, diffuse, canvas.uniform(0.75, 0.95) + 0.03 * grain)

    if variant in ("exposed_aggregate", "polished_concrete"):
        count = canvas.loguniform(8, 40) if variant == "exposed_aggregate" else canvas.loguniform(12, 50)
        label, stone = _aggregate(canvas, count, canvas.uniform(0.05, 0.3))
        colors = _stone_colors(canvas, int(label.max()) + 1, canvas.uniform(0.3, 1.5))
        stone_diffuse = np.moveaxis(colors, -1, 0)[:, label] * (1.0 + 0.05 * grain)
        if variant == "exposed_aggregate":
            # Washed off before it set: the stones stand out of the cement by up to half their size.
            relief = canvas.uniform(0.1, 0.3) / count * 150 * MILLIMETRE * 0.5
            mix.height = mix.height + relief * stone * canvas.rng.uniform(0.4, 1.0, colors.shape[0]).astype(np.float32)[label]
            mix.diffuse = mix.diffuse + smoothstep(0.0, 0.3, stone) * (stone_diffuse - mix.diffuse)
            mix.roughness = mix.roughness + stone * (canvas.uniform(0.5, 0.8) - mix.roughness)
        else:
            # Ground flat and sealed: the stones are cut sections in the cement, all at one level.
            cut = smoothstep(0.0, 0.15, stone) * (canvas.rng.random(colors.shape[0]) < canvas.uniform(0.3, 0.8))[label]
            mix.diffuse = mix.diffuse + cut * (stone_diffuse - mix.diffuse)
            mix.height = mix.height * 0.2 - 0.003 * MILLIMETRE * (1 - cut)
            mix.roughness = np.full_like(mix.height, canvas.uniform(0.1, 0.4)) + 0.05 * (1 - cut)
    else:
        _formwork(canvas, mix)

    pores = _pores(canvas, canvas.uniform(0.0, 1.0) if variant != "polished_concrete" else canvas.uniform(0.0, 0.4))
    mix.height = mix.height - pores * canvas.uniform(0.2, 0.6) * MILLIMETRE
    mix.cover(pores, None, factor=canvas.uniform(0.55, 0.85))  # dust and shadowed walls
    if canvas.chance(0.3):
        cracks = _cracks(canvas)
        mix.height = mix.height - cracks * 0.2 * MILLIMETRE
        mix.cover(cracks, None, factor=0.6)
    return mix


def _formwork(canvas: Canvas, mix: _Mix):
    """Marks of the formwork on cast concrete: board joints with their fins and the boards' wood
    grain, or smooth plywood with a joint and tie holes."""
    kind = canvas.choice(["none", "boards", "plywood"])
    horizontal = canvas.chance(0.5)
    across = canvas.v if horizontal else canvas.u
    if kind == "boards":
        boards = canvas.frequency(canvas.uniform(1, 4))  # 4 to 15 cm wide boards
        phase = across * boards + canvas.uniform(0, 1)  # joints anywhere, not on the sample's edge
        local = phase - np.floor(phase)
        joint = np.exp(-((np.minimum(local, 1 - local) / boards) * canvas.size / canvas.uniform(0.8, 2.0)) ** 2)
        # Each board its own depth and the wood grain printed along it.
        n_boards = int(boards) if canvas.tileable else int(boards) + 2  # whole boards wrap round
        per_board = canvas.rng.uniform(-1, 1, n_boards).astype(np.float32)[np.floor(phase).astype(np.int64) % n_boards]
        grain = canvas.noise(beta=1.5, low=4, high=120, stretch=canvas.uniform(6, 14), angle=0.0 if horizontal else math.pi / 2)
        mix.height = mix.height + (canvas.uniform(0.05, 0.2) * grain + 0.3 * per_board + canvas.uniform(0.2, 0.6) * joint) * MILLIMETRE
        mix.cover(joint, None, factor=canvas.uniform(0.8, 1.1))
        mix.diffuse = mix.diffuse * (1.0 + 0.05 * per_board + 0.03 * grain)
    elif kind == "plywood":
        local = across - canvas.uniform(0.2, 0.8)  # one panel joint per sample
        local = local - np.round(local)
        joint = np.exp(-(local * canvas.size / 1.2) ** 2)
        mix.height = mix.height + canvas.uniform(0.1, 0.4) * joint * MILLIMETRE
        mix.cover(joint, None, factor=0.85)
        if canvas.chance(0.6):  # a tie hole: a shallow cone, plugged or open
            du, dv = canvas.u - canvas.uniform(0.25, 0.75), canvas.v - canvas.uniform(0.25, 0.75)
            if canvas.tileable:
                du, dv = du - np.round(du), dv - np.round(dv)
            radius = np.sqrt(du * du + dv * dv) / canvas.uniform(0.05, 0.1)
            hole = 1.0 - smoothstep(0.6, 1.0, radius)
            mix.height = mix.height - hole * canvas.uniform(1.0, 3.0) * MILLIMETRE
            mix.cover(1.0 - smoothstep(0.55, 0.6, radius), _cement_color(canvas, 0.3, 0.6))  # the plug


def _screed(canvas: Canvas) -> _Mix:
    """Cement screed: trowelled flat, faint arcs of the power float, cloudy, often sealed."""
    color = _cement_color(canvas, 0.35, 0.75)
    grain = _grain(canvas)
    mottling = canvas.noise(beta=2.5, low=1, high=32)
    # Trowel arcs: overlapping circles around each pass's centre.
    swirl = _swirls(canvas, canvas.uniform(2, 5), canvas.uniform(15, 50))
    height = (grain * 0.01 + swirl * canvas.uniform(0.01, 0.05)) * MILLIMETRE
    diffuse = planar(color) * (1.0 + canvas.uniform(0.05, 0.2) * mottling + canvas.uniform(0.0, 0.05) * swirl)
    sealed = canvas.chance(0.4)
    roughness = (canvas.uniform(0.2, 0.45) if sealed else canvas.uniform(0.5, 0.85)) + 0.05 * mottling * canvas.uniform(-1, 1)
    mix = _Mix(height, diffuse, roughness)
    if canvas.chance(0.5):
        cracks = _cracks(canvas)
        mix.height = mix.height - cracks * 0.1 * MILLIMETRE
        mix.cover(cracks, None, factor=0.7)
    return mix


def _swirls(canvas: Canvas, count: float, rings: float) -> np.ndarray:
    """Concentric arcs around the centres of ``count`` x ``count`` Voronoi cells, ``rings`` per
    sample width, (H, W) in [-1, 1]."""
    nearest, label, _ = canvas.cells(canvas.jittered_points(int(canvas.frequency(count)), 0.9))
    phase = canvas.rng.uniform(0, 2 * math.pi, int(label.max()) + 1).astype(np.float32)[label]
    # A hand-held tool never draws true circles: the arcs wobble and fade out towards the rim.
    wobble = canvas.noise(beta=2.0, low=2, high=16) * canvas.uniform(0.5, 2.0)
    fade = 1.0 - smoothstep(0.3, 0.9, nearest * canvas.frequency(count) * canvas.uniform(0.8, 1.4))
    return np.sin(2 * math.pi * rings * nearest + phase + wobble) * (0.3 + 0.7 * fade)


def _plaster(canvas: Canvas, variant: str) -> _Mix:
    """Plasters and renders: Venetian (burnished trowel layers), orange peel (sprayed paint),
    knock-down (flattened splatter), swirl (brushed arcs) and sand float (grainy render)."""
    color = _paint_color(canvas)
    fine = _grain(canvas)
    if variant == "venetian_plaster":
        # Thin layers laid with a steel trowel: overlapping strokes, each a terrace with a sharp
        # edge on one side, burnished to a sheen; the tone clouds between two close colours.
        field = canvas.noise(beta=3.0, low=1.5, high=30, stretch=canvas.uniform(1.5, 3), angle=canvas.uniform(0, math.pi))
        x = field * canvas.uniform(0.8, 2.0)
        step = np.floor(x) + smoothstep(0.6, 1.0, x - np.floor(x))
        height = step * canvas.uniform(0.02, 0.08) * MILLIMETRE
        second = _paint_color(canvas) if canvas.chance(0.4) else planar(color).ravel() * canvas.uniform(0.55, 0.85)
        tone = smoothstep(-1.5, 1.5, canvas.noise(beta=2.5, low=2, high=60) + 0.5 * field)
        diffuse = planar(color) + tone * (planar(second) - planar(color))
        roughness = canvas.uniform(0.1, 0.35) + canvas.uniform(0.0, 0.2) * (x - np.floor(x))
        return _Mix(height, diffuse, roughness)
    if variant == "orange_peel":
        cycles = canvas.uniform(20, 60)
        field = canvas.noise(beta=canvas.uniform(1.5, 3.0), low=cycles * 0.5, high=cycles * 3)
        height = (field * canvas.uniform(0.02, 0.08) + 0.003 * fine) * MILLIMETRE
        roughness = canvas.uniform(0.3, 0.75) + 0.03 * field
        return _Mix(height, planar(color) * (1.0 + 0.01 * field), roughness)
    if variant == "knockdown":
        # Splatter flattened with a trowel: flat-topped islands with rounded rims.
        field = canvas.noise(beta=2.0, low=canvas.uniform(3, 8), high=60)
        threshold = canvas.uniform(-0.3, 0.8)
        island = smoothstep(threshold, threshold + 0.25, field)
        height = (island * canvas.uniform(0.3, 0.9) + 0.02 * fine) * MILLIMETRE
        diffuse = planar(color) * (1.0 + 0.02 * island)
        return _Mix(height, diffuse, canvas.uniform(0.45, 0.85) - 0.05 * island)
    if variant == "swirl_stucco":
        arcs = _swirls(canvas, canvas.uniform(3, 8), canvas.uniform(25, 70))
        grooves = np.abs(arcs) ** 0.5  # brush bristles leave sharp-bottomed grooves
        height = (grooves * canvas.uniform(0.2, 0.6) + 0.02 * fine) * MILLIMETRE
        return _Mix(height, planar(color) * (1.0 + 0.02 * grooves), canvas.uniform(0.5, 0.9) + 0.03 * fine)
    # Sand float: grains of sand (1 to 3 mm) in the render, some standing proud.
    sand = canvas.noise(beta=1.0, low=canvas.uniform(25, 60))
    grains = smoothstep(0.8, 2.2, sand)
    height = (fine * 0.03 + grains * canvas.uniform(0.2, 0.6)) * MILLIMETRE
    diffuse = planar(color) * (1.0 + 0.05 * fine * canvas.uniform(0.3, 1.0))
    return _Mix(height, diffuse, canvas.uniform(0.75, 0.95) + 0.03 * fine)


def _asphalt(canvas: Canvas) -> _Mix:
    """Asphalt: stone chippings in a dark bitumen binder with sand, sometimes a worn road marking."""
    count = canvas.loguniform(20, 50)  # chippings of 3 to 8 mm
    label, stone = _aggregate(canvas, count, canvas.uniform(0.02, 0.12))
    n_stones = int(label.max()) + 1
    fine = _grain(canvas)
    exposed = canvas.rng.uniform(0.3, 1.0, n_stones).astype(np.float32)[label]  # partly buried
    relief = canvas.uniform(0.1, 0.25) / count * 150 * MILLIMETRE  # a tenth to a quarter of a stone's size
    height = relief * stone * exposed + fine * 0.05 * MILLIMETRE
    binder = hsv_color(canvas.uniform(0.05, 0.6), canvas.uniform(0.0, 0.1), canvas.uniform(0.12, 0.3))
    colors = _stone_colors(canvas, n_stones, canvas.uniform(0.1, 0.5))
    # Binder still coats many stones; traffic wears it off the highest ones first.
    coated = np.clip(canvas.rng.uniform(-0.3, 1.0, n_stones), 0, 1).astype(np.float32)[label]
    stone_mask = smoothstep(0.0, 0.3, stone) * (1.0 - coated * (1.0 - 0.6 * exposed))
    diffuse = planar(binder) * (1.0 + 0.15 * fine)
    diffuse = diffuse + stone_mask * (np.moveaxis(colors, -1, 0)[:, label] * (1.0 + 0.08 * fine) - diffuse)
    # Fresh binder is a little glossy; tyres polish the tops of the stones.
    binder_roughness = canvas.uniform(0.6, 0.95)
    roughness = binder_roughness + stone_mask * (canvas.uniform(0.8, 1.0) - binder_roughness)
    roughness = roughness - canvas.uniform(0.0, 0.2) * stone * exposed
    mix = _Mix(height, diffuse, roughness)
    if canvas.chance(0.2):  # a road marking, worn off the stones' tops first
        across = canvas.u if canvas.chance(0.5) else canvas.v
        centre, half = canvas.uniform(0.3, 0.7), canvas.uniform(0.1, 0.35)
        distance = np.abs(across - centre)
        if canvas.tileable:  # the shorter way round
            distance = np.minimum(distance, 1.0 - distance)
        band = smoothstep(half + 0.003, half, distance)
        band = band * smoothstep(0.3, 0.6, canvas.blobs(canvas.uniform(3, 10)) + 0.3 - 0.4 * stone * exposed)
        paint = hsv_color(0.14, canvas.uniform(0.6, 0.9), 0.85) if canvas.chance(0.3) else hsv_color(0.1, 0.05, 0.85)
        mix.cover(band, paint, roughness=canvas.uniform(0.55, 0.8))
        mix.height = mix.height + band * 0.3 * MILLIMETRE
    return mix


@family("concrete")
def concrete(canvas: Canvas) -> Surface:
    variant = canvas.choice(["cast_concrete", "cast_concrete", "exposed_aggregate", "polished_concrete", "screed",
                             "venetian_plaster", "orange_peel", "knockdown", "swirl_stucco", "sand_float",
                             "asphalt", "asphalt"])
    if variant in ("cast_concrete", "exposed_aggregate", "polished_concrete"):
        mix = _concrete(canvas, variant)
    elif variant == "screed":
        mix = _screed(canvas)
    elif variant == "asphalt":
        mix = _asphalt(canvas)
    else:
        mix = _plaster(canvas, variant)
    # Uneven colour and gloss across the sample (only on a plain canvas).
    polished = variant in ("polished_concrete", "venetian_plaster")
    specular = dielectric_f0(canvas, 0.04, 0.05) if polished else dielectric_f0(canvas, 0.035, 0.045)
    size = canvas.size
    return Surface(height=np.asarray(mix.height, np.float32),
                   diffuse=np.broadcast_to(mix.diffuse, (3, size, size)).transpose(1, 2, 0),
                   roughness=np.clip(np.broadcast_to(mix.roughness, (size, size)), 0.0, 1.0).astype(np.float32),
                   specular=np.broadcast_to(specular, (size, size, 3)), variant=variant)
