"""Sparkling surfaces made of many small mirrors: sequins sewn on fabric, glitter flakes on a base,
embossed and crumpled metal foils (some holographic).

What makes them sparkle is geometry: every sequin and every flake is a planar facet with its own
tilt (height = slope . (p - centre), all in the height field, so the normals computed from it tilt
the facets), and a low roughness makes each facet flash only when its normal bisects the flash and
the camera. Facets tilt by up to about 25 degrees. Mirrors are metallic (an F0 from ``METALS`` or
a coloured metallic film, a dark diffuse albedo); the fabric and bases below are dielectrics.
Colours are built in planar (3, H, W) layout, which numpy broadcasts much faster than (H, W, 3),
and handed back as an (H, W, 3) view.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import METALS, MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, planar, smoothstep, srgb_to_linear
from ..registry import family


def _hsv_colors(hue, saturation, value) -> np.ndarray:
    """Linear RGB (n, 3) of n sRGB colours given in HSV [0, 1], like ``hsv_color`` for arrays (one
    colour per flake would take thousands of scalar conversions)."""
    h = (np.asarray(hue, np.float64) % 1.0) * 6.0
    sector = np.floor(h).astype(np.int64) % 6
    f = h - np.floor(h)
    v = np.broadcast_to(np.asarray(value, np.float64), h.shape)
    s = np.broadcast_to(np.asarray(saturation, np.float64), h.shape)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    rgb = np.stack([np.choose(sector, [v, q, p, p, t, v]), np.choose(sector, [t, v, v, q, p, p]),
                    np.choose(sector, [p, p, t, v, v, q])], -1)
    return srgb_to_linear(rgb)


def _mirror_colors(canvas: Canvas, count: int) -> tuple[np.ndarray, str]:
    """F0 (count, 3) of ``count`` small metallic mirrors and the palette's name: one metal, one
    coloured metallic film (with slight per-mirror jitter), or holographic (every hue)."""
    rng = canvas.rng
    kind = canvas.choice(["metal", "metal", "colour", "colour", "holographic"])
    if kind == "metal":
        base = np.asarray(METALS[canvas.choice(["silver", "gold", "gold", "copper", "aluminium", "brass"])], np.float32)
        return np.clip(base * rng.uniform(0.9, 1.05, (count, 1)), 0, 1).astype(np.float32), "metal"
    if kind == "colour":
        hue = canvas.uniform(0, 1) + rng.normal(0, 0.02, count)
        # Bright enough to stay metallic: a dyed lacquer over aluminium keeps most of its reflectance.
        return _hsv_colors(hue, canvas.uniform(0.3, 0.75), rng.uniform(0.85, 1.0, count)), "colour"
    return _hsv_colors(rng.random(count), canvas.uniform(0.3, 0.6), rng.uniform(0.85, 1.0, count)), "holographic"


def _tilts(canvas: Canvas, count: int, spread: float) -> np.ndarray:
    """Slopes (count, 2) of facets whose normals tilt randomly by ``spread`` [deg] (rms) in a random
    direction, clipped at 30 degrees [dh/dx, dh/dy in patch half-widths per patch half-width]."""
    angle = np.minimum(np.abs(canvas.rng.normal(0.0, math.radians(spread), count)), math.radians(30))
    direction = canvas.rng.uniform(0, 2 * math.pi, count)
    return (np.tan(angle)[:, None] * np.stack([np.cos(direction), np.sin(direction)], -1)).astype(np.float32)


def _facets(slopes: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Planar facets: height slope . (p - centre) [patch half-widths] from per-pixel slopes
    (2, H, W) and offsets (du, dv) from the facet's centre [sample widths]. Rows run down the
    image, against +y, hence the sign of the second term."""
    return 2.0 * (slopes[0] * du - slopes[1] * dv)  # 2: sample widths to patch half-widths


def _offset(du: np.ndarray, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets [sample widths] taken the shortest way round: Voronoi cells wrap on every canvas,
    so a cell at one edge may belong to a seed near the opposite edge."""
    return du - np.round(du), dv - np.round(dv)


def _fabric(canvas: Canvas, color) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Woven fabric below sequins: (relief [patch half-widths], planar diffuse, roughness)."""
    threads = canvas.frequency(canvas.uniform(60, 110))
    weave = np.sin(2 * math.pi * threads * canvas.u) * np.sin(2 * math.pi * threads * canvas.v)
    height = weave * 0.03 * MILLIMETRE
    return height, planar(color) * (1.0 + 0.15 * weave), np.full_like(height, canvas.uniform(0.6, 0.9))


class _Layers:
    """The surface as it is being made: height [patch half-widths], planar diffuse, roughness and
    planar specular."""

    def __init__(self, height, diffuse, roughness, specular, variant: str = ""):
        self.height, self.diffuse, self.roughness, self.specular = height, diffuse, roughness, specular
        self.variant = variant

    def cover(self, mask, height, diffuse, roughness, specular, height_mask=None):
        """Lay material over ``mask``: its height replaces the surface's there (over
        ``height_mask`` when given: a softer edge keeps the step at a rim from being a cliff one
        pixel wide)."""
        self.height = self.height + (mask if height_mask is None else height_mask) * (height - self.height)
        self.roughness = self.roughness + mask * (roughness - self.roughness)
        # A pixel is metal or not: F0 switches in the middle of the anti-aliased rim (a blend of a
        # metal's coloured F0 with a dielectric's would be a coloured F0 as low as a dielectric's,
        # which no material has), and the dark diffuse albedo of the metal is complete by then.
        self.diffuse = self.diffuse + np.minimum(2.0 * mask, 1.0) * (planar(diffuse) - self.diffuse)
        self.specular = self.specular + (mask >= 0.5) * (planar(specular) - self.specular)


# --- sequins -------------------------------------------------------------------------------------

def _sequins(canvas: Canvas) -> _Layers:
    """Sequins: discs in offset rows on fabric, each a tilted (often slightly cupped) mirror with a
    hole for the thread; flat with gaps between them, or overlapping like scales."""
    columns = canvas.frequency(canvas.uniform(10, 35))  # 4 to 15 mm sequins
    overlapping = canvas.chance(0.5)
    # Rows of offset discs: at 2/sqrt(3) rows per column the neighbours are equidistant (hexagonal).
    rows = canvas.frequency(columns * (canvas.uniform(1.3, 2.0) if overlapping else canvas.uniform(1.1, 1.25)))
    if canvas.tileable:
        rows += rows % 2  # offset rows must come in pairs to wrap
    radius = canvas.uniform(0.44, 0.5) / columns  # [sample widths]: discs in a row never overlap
    n_rows, n_columns = int(rows) + 3, int(columns) + 3

    fabric_color = hsv_color(canvas.uniform(0, 1), canvas.uniform(0.0, 0.8), canvas.uniform(0.05, 0.5))
    height, diffuse, roughness = _fabric(canvas, fabric_color)
    layers = _Layers(height, diffuse, roughness, planar(dielectric_f0(canvas, 0.03, 0.05)))

    count = n_rows * n_columns
    f0, palette = _mirror_colors(canvas, count)
    f0 = np.moveaxis(f0.reshape(n_rows, n_columns, 3), -1, 0)
    slopes = np.moveaxis(_tilts(canvas, count, canvas.uniform(5, 15)).reshape(n_rows, n_columns, 2), -1, 0)
    if overlapping:  # each scale rests on the row below it: its free edge lifted
        slopes[1] += canvas.uniform(0.05, 0.2)
    mirror_roughness = canvas.uniform(0.05, 0.25)
    thickness = canvas.uniform(0.1, 0.25) * MILLIMETRE
    cup = canvas.uniform(0.0, 0.2) * MILLIMETRE  # cupped sequins are deeper at the centre
    hole = canvas.uniform(0.1, 0.18)

    y = canvas.v * rows
    row = np.floor(y)
    # Painter's order: the row that lies on top is drawn last.
    order = (-1, 0, 1) if canvas.chance(0.5) else (1, 0, -1)
    for shift in order:
        r = row + shift
        x = canvas.u * columns + 0.5 * (r % 2)
        c = np.floor(x)
        du, dv = _offset((x - c - 0.5) / columns, (y - r - 0.5) / rows)
        distance = np.sqrt(du * du + dv * dv)
        disc = np.clip((radius - distance) * canvas.size + 0.5, 0.0, 1.0)
        rim = np.clip((radius - distance) * canvas.size * 0.5 + 0.5, 0.0, 1.0)
        ri = (r.astype(np.int64) % (int(rows) if canvas.tileable else n_rows))
        ci = (c.astype(np.int64) % (int(columns) if canvas.tileable else n_columns))
        tilt = slopes[:, ri, ci]
        # One level for all discs (a disc's height must not depend on the row it is seen from);
        # where they overlap, the tilts make the steps.
        # A tilted disc rests on the fabric with its lowest rim point: lift it by |slope| radius.
        lift = 2.0 * radius * np.sqrt(tilt[0] ** 2 + tilt[1] ** 2)
        facet = thickness + lift + _facets(tilt, du, dv) - cup * (1.0 - (distance / radius) ** 2)
        through = smoothstep(hole * radius * 0.8, hole * radius * 1.2, distance)  # the thread hole
        layers.cover(disc * through, facet, 0.02, mirror_roughness, f0[:, ri, ci], rim * through)
    layers.variant = f"sequins_{palette}" + ("_overlapping" if overlapping else "")
    return layers


# --- glitter -------------------------------------------------------------------------------------

def _glitter(canvas: Canvas) -> _Layers:
    """Glitter: tiny polygonal metallic flakes, each tilted at random, scattered densely or
    sparsely over a base of paper, plastic, paint or fabric."""
    rng = canvas.rng
    count = int(canvas.frequency(canvas.loguniform(30, 100)))  # flakes of 1.5 to 5 mm cells
    points = canvas.jittered_points(count, 1.0)
    _, label, edge = canvas.cells(points)
    n = len(points)
    # Offsets from each flake's centre (its Voronoi seed) [sample widths].
    du, dv = _offset(canvas.u - points[label, 0], canvas.v - points[label, 1])

    base_color = hsv_color(canvas.uniform(0, 1), canvas.uniform(0.0, 0.9), canvas.uniform(0.05, 0.9))
    base_texture = canvas.noise(beta=1.0, low=20)
    height = base_texture * canvas.uniform(0.005, 0.03) * MILLIMETRE
    layers = _Layers(height, planar(base_color) * (1.0 + 0.05 * base_texture),
                     np.full_like(height, canvas.uniform(0.3, 0.85)), planar(dielectric_f0(canvas, 0.04, 0.05)))

    f0, palette = _mirror_colors(canvas, n)
    present = rng.random(n) < canvas.uniform(0.3, 1.0)
    # Flakes are cut smaller than their cells, by a random amount each: gaps show the base.
    gap = (canvas.uniform(0.05, 0.25) * rng.uniform(0.5, 1.5, n) / count).astype(np.float32)
    inside = (edge - gap[label]) * canvas.size
    flake = np.clip(inside + 0.5, 0.0, 1.0) * present[label]
    tilts = _tilts(canvas, n, canvas.uniform(8, 20))
    slopes = np.moveaxis(tilts[label], -1, 0)
    thickness = canvas.uniform(0.01, 0.05) * MILLIMETRE
    # Every flake rests on the base by its lowest corner: tilting lifts it by |slope| times its
    # half-size (about 0.7 cell widths from the seed to the farthest corner).
    lift = (np.sqrt((tilts ** 2).sum(-1)) * 2.0 * 0.7 / count).astype(np.float32)[label]
    facet = thickness + lift + _facets(slopes, du, dv)
    layers.cover(flake, facet, 0.02, canvas.uniform(0.05, 0.2), np.moveaxis(f0[label], -1, 0),
                 np.clip(inside * 0.5 + 0.5, 0.0, 1.0) * present[label])
    layers.variant = f"glitter_{palette}"
    return layers


# --- foils ---------------------------------------------------------------------------------------

def _phases(canvas: Canvas, cycles: float, angle: float):
    """Phases [cycles] of two orthogonal plane waves of ``cycles`` per sample, the first along
    ``angle`` [rad], and a pixel's size [cycles]; whole wave vectors on a tileable canvas, so they
    wrap."""
    ku, kv = cycles * math.cos(angle), cycles * math.sin(angle)
    if canvas.tileable:
        ku, kv = float(round(ku)), float(round(kv))
        ku = ku if (ku, kv) != (0.0, 0.0) else 1.0
    return canvas.u * ku + canvas.v * kv, canvas.v * ku - canvas.u * kv, math.hypot(ku, kv) / canvas.size


def _lattice(canvas: Canvas, cycles: float, angle: float):
    """Position (x, y) in [-0.5, 0.5) inside the cells of a square lattice of ``cycles`` cells per
    sample rotated by ``angle`` [rad], and a pixel's size [cells]."""
    p1, p2, pixel = _phases(canvas, cycles, angle)
    return p1 - np.floor(p1) - 0.5, p2 - np.floor(p2) - 0.5, pixel


def _emboss(canvas: Canvas) -> tuple[np.ndarray, str]:
    """An embossing pattern, (H, W) relief profile in about [0, 1] and its name."""
    kind = canvas.choice(["diamonds", "dots", "ribs", "text", "blobs", "hammered"])
    angle = canvas.choice([0.0, math.pi / 4, canvas.uniform(0, math.pi)])
    if kind == "diamonds":  # quilted: pyramids or pillows
        x, y, _ = _lattice(canvas, canvas.loguniform(4, 30), angle)
        pyramid = 1.0 - 2.0 * np.maximum(np.abs(x), np.abs(y))
        return pyramid ** canvas.uniform(0.3, 1.0), kind
    if kind == "dots":  # domes
        x, y, _ = _lattice(canvas, canvas.loguniform(5, 40), angle)
        radius = canvas.uniform(0.2, 0.4)
        r2 = (x * x + y * y) / (radius * radius)
        return np.sqrt(np.clip(1.0 - r2, 0.0, 1.0)), kind
    if kind == "ribs":
        x, _, _ = _lattice(canvas, canvas.loguniform(8, 60), angle)
        return np.cos(math.pi * x) ** 2, kind
    if kind == "text":  # lettering pressed into the foil, with softened edges
        mask = np.zeros((canvas.size, canvas.size), np.float32)
        words = ("LUXE", "GOLD", "SPECIAL", "2025", "CHOCOLATE", "ORIGINAL", "SINCE 1887", "PREMIUM", "XO", "A", "N")
        for _ in range(int(canvas.rng.integers(1, 4 if canvas.tileable else 8))):
            text = canvas.choice(words)
            height = min(canvas.loguniform(0.05, 0.2), 0.9 / (0.85 * len(text)))
            canvas.draw_text(mask, text, (canvas.uniform(0.0, 0.5), canvas.uniform(0.15, 1.0)), height, 1.0,
                             height * canvas.uniform(0.1, 0.2), canvas.choice([0.0, 0.0, canvas.uniform(-0.5, 0.5)]))
        return canvas.blur(mask, canvas.uniform(0.6, 1.5) / canvas.size), kind
    if kind == "blobs":  # raised organic ornament (leaves, paisley-ish)
        field = canvas.blobs(canvas.loguniform(3, 12), sharpness=4.0)
        return smoothstep(0.5, 0.65, field), kind
    # Hammered: shallow round dimples, one per Voronoi cell, deepest at the cell's seed, with sharp
    # ridges between them.
    nearest, _, edge = canvas.cells(canvas.jittered_points(int(canvas.frequency(canvas.loguniform(6, 25))), 0.9))
    return 1.0 - (edge / (edge + nearest + 1e-6)) ** 2, kind


def _crinkles(canvas: Canvas) -> np.ndarray:
    """Wrinkles of handled foil: sharp creases (ridged noise), relief [patch half-widths]."""
    field = canvas.noise(beta=3.0, low=canvas.uniform(2, 6), high=60)
    return (0.5 - np.abs(field)) * canvas.uniform(0.05, 0.4) * MILLIMETRE


def _foil(canvas: Canvas, crumpled: bool) -> _Layers:
    """Metal foil: aluminium, gold, copper or a coloured lacquered foil, embossed with a pattern or
    crumpled, sometimes holographic (its F0 changes hue across the surface)."""
    kind = canvas.choice(["metal", "metal", "colour", "holographic"])
    if kind == "metal":
        f0 = planar(METALS[canvas.choice(["aluminium", "aluminium", "silver", "gold", "copper", "brass"])])
    elif kind == "colour":  # a tinted lacquer over aluminium
        f0 = planar(hsv_color(canvas.uniform(0, 1), canvas.uniform(0.3, 0.75), canvas.uniform(0.85, 1.0)))
    else:  # diffraction gratings shift the colour across the sheet: rainbow bands over silver
        p1, p2, _ = _phases(canvas, canvas.loguniform(1, 6), canvas.uniform(0, math.pi))
        hue = p1 + 0.15 * np.sin(2 * math.pi * p2)
        rainbow = 0.5 + 0.5 * np.cos(2 * math.pi * (hue + np.array([0.0, 1 / 3, 2 / 3], np.float32).reshape(3, 1, 1)))
        saturation = canvas.uniform(0.25, 0.55)
        f0 = (0.95 * (1.0 - saturation + saturation * rainbow)).astype(np.float32)
    roughness = canvas.uniform(0.04, 0.3)
    if crumpled:
        # Flattened crumpled foil: flat facets between straight creases (hip roofs of Voronoi cells
        # pushed up or down), plus fine wrinkles.
        count = int(canvas.frequency(canvas.uniform(4, 14)))
        _, label, edge = canvas.cells(canvas.jittered_points(count, 0.9))
        slope = canvas.rng.uniform(0.1, 0.5, int(label.max()) + 1) * canvas.rng.choice([-1.0, 1.0], int(label.max()) + 1)
        height = slope.astype(np.float32)[label] * edge * 2.0 + _crinkles(canvas)
        variant = f"crumpled_foil_{kind}"
    else:
        profile, pattern = _emboss(canvas)
        height = profile * canvas.uniform(0.05, 0.3) * MILLIMETRE
        if canvas.chance(0.4):
            height = height + _crinkles(canvas)
        variant = f"embossed_foil_{pattern}_{kind}"
    layers = _Layers(height, np.full((3, 1, 1), canvas.uniform(0.0, 0.03), np.float32),
                     np.full_like(height, roughness), f0)
    layers.variant = variant
    return layers


@family("sparkle")
def sparkle(canvas: Canvas) -> Surface:
    variant = canvas.choice(["sequins", "sequins", "glitter", "glitter", "embossed_foil", "crumpled_foil"])
    if variant == "sequins":
        layers = _sequins(canvas)
    elif variant == "glitter":
        layers = _glitter(canvas)
    else:
        layers = _foil(canvas, crumpled=variant == "crumpled_foil")
    # Uneven colour and gloss across the sample (only on a plain canvas).
    size = canvas.size
    return Surface(height=np.asarray(layers.height, np.float32),
                   diffuse=np.broadcast_to(layers.diffuse, (3, size, size)).transpose(1, 2, 0),
                   roughness=np.clip(np.broadcast_to(layers.roughness, (size, size)), 0.0, 1.0).astype(np.float32),
                   specular=np.broadcast_to(layers.specular, (3, size, size)).transpose(1, 2, 0),
                   variant=layers.variant)
