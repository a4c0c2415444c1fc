"""Fabric: woven cloth (plain, basket, twill, satin weaves; denim, canvas, burlap, silk-like
satin, plaids), knits (stockinette and rib), and pile or felted cloth (felt, velvet, corduroy).

A weave is a small binary pattern P[i, j]: 1 where warp thread i (running down the rows) lies over
weft thread j (running along the columns). Each thread is a rounded ridge whose height rises
where it floats over and dips where it passes under, interpolated smoothly between crossings;
the visible thread at a pixel is the higher of the two. Yarn twist, slubs, fuzz and a little
irregularity in the thread paths make it cloth rather than a grid. A knit stitch is a V of two
tilted, elliptical legs; rows overlap like the loops they are. Cloth is a rough dielectric
(roughness 0.6-1.0, F0 0.03-0.05), except satin and silk (0.3-0.5).
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, smoothstep
from ..registry import family

#: Variants and their chances.
_VARIANTS = (("plain", 0.18), ("basket", 0.06), ("twill", 0.14), ("denim", 0.1), ("satin", 0.1), ("burlap", 0.06),
             ("knit", 0.14), ("rib_knit", 0.05), ("felt", 0.06), ("velvet", 0.05), ("corduroy", 0.06))


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _dye(canvas: Canvas) -> np.ndarray:
    """A fabric colour: naturals, pastels, strong dyes and near-blacks."""
    kind = canvas.choice(["natural", "pastel", "strong", "dark", "grey"])
    if kind == "natural":
        return hsv_color(canvas.uniform(0.07, 0.13), canvas.uniform(0.1, 0.4), canvas.uniform(0.55, 0.9))
    if kind == "pastel":
        return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.15, 0.4), canvas.uniform(0.7, 0.95))
    if kind == "strong":
        return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.5, 0.95), canvas.uniform(0.35, 0.85))
    if kind == "dark":
        return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.2, 0.8), canvas.uniform(0.08, 0.3))
    return hsv_color(0.0, 0.0, canvas.uniform(0.15, 0.9))


def _thread_colors(canvas: Canvas, count: int, base: np.ndarray) -> np.ndarray:
    """(count, 3) colours of consecutive threads: one colour, a heather of shades, or stripes of a
    few colours in a repeating sequence (warp and weft stripes together make plaids)."""
    style = canvas.choice(["solid", "solid", "heather", "stripes"])
    if style == "solid":
        colors = np.broadcast_to(base, (count, 3)).copy()
    elif style == "heather":
        colors = base * (0.6 + 0.8 * canvas.rng.random((count, 1)))
    else:
        palette = np.stack([base] + [_dye(canvas) for _ in range(int(canvas.uniform(1, 4)))])
        widths = canvas.rng.integers(1, 10, size=int(canvas.uniform(2, 7)))
        sequence = np.repeat(canvas.rng.integers(len(palette), size=len(widths)), widths)
        colors = palette[np.resize(sequence, count)]
    return (colors * (0.92 + 0.16 * canvas.rng.random((count, 1)))).astype(np.float32)


def _weave_pattern(canvas: Canvas, variant: str) -> np.ndarray:
    """P[i, j] (repeat x repeat): 1 where warp thread i floats over weft thread j."""
    if variant in ("plain", "burlap"):
        i, j = np.meshgrid(np.arange(2), np.arange(2), indexing="ij")
        return ((i + j) % 2).astype(np.float32)
    if variant == "basket":
        i, j = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
        return ((i // 2 + j // 2) % 2).astype(np.float32)
    if variant in ("twill", "denim"):
        over, under = (3, 1) if variant == "denim" else canvas.choice([(2, 1), (2, 2), (3, 1), (1, 2), (1, 3)])
        n = over + under
        direction = canvas.choice([1, -1])
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        return (((i + direction * j) % n) < over).astype(np.float32)
    n, step = canvas.choice([(5, 2), (5, 3), (8, 3), (8, 5)])  # satin: one binding point per thread
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return ((i * step - j) % n != 0).astype(np.float32)


def _lift(pattern: np.ndarray, thread: np.ndarray, position: np.ndarray, along_axis: int) -> np.ndarray:
    """How high a thread lies [0 under, 1 over] along its length: the pattern at the crossings it
    passes, eased between crossing centres. ``thread`` is its index, ``position`` the coordinate
    along it [crossings]."""
    shifted = position - 0.5
    first_f = np.floor(shifted)
    t = smoothstep(0.0, 1.0, shifted - first_f)
    first = first_f.astype(np.int32)
    n_i, n_j = pattern.shape
    if along_axis == 1:  # warp: thread = i, crossings along j
        a = pattern[thread % n_i, first % n_j]
        b = pattern[thread % n_i, (first + 1) % n_j]
    else:  # weft: thread = j, crossings along i
        a = 1 - pattern[first % n_i, thread % n_j]
        b = 1 - pattern[(first + 1) % n_i, thread % n_j]
    return a + (b - a) * t


def _woven(canvas: Canvas, variant: str):
    """Warp and weft threads; returns diffuse, a roughness offset, the relief [mm] and the float
    mask (1 where a thread floats long and straight: the glossy parts of satin)."""
    pattern = _weave_pattern(canvas, variant)
    repeat = pattern.shape[0]
    pitch_range = {"burlap": (18, 45), "satin": (60, 128), "denim": (50, 110)}.get(variant, (24, 110))
    warps = canvas.uniform(*pitch_range)
    wefts = warps * canvas.uniform(0.7, 1.3)
    if canvas.tileable:  # whole repeats of the pattern across the sample
        warps = max(1, round(warps / repeat)) * repeat
        wefts = max(1, round(wefts / repeat)) * repeat
    # Threads wander a little (a fraction of their spacing), burlap a lot.
    wander = canvas.noise(beta=2.5, low=1, high=16)
    sway = (0.6 if variant == "burlap" else canvas.uniform(0.05, 0.25)) / warps
    x = (canvas.u + sway * wander) * warps
    y = (canvas.v + sway * wander.T) * wefts
    i_f, j_f = np.floor(x), np.floor(y)
    fx, fy = x - i_f, y - j_f  # float32 (subtracting integer arrays would promote to float64)
    i, j = i_f.astype(np.int32), j_f.astype(np.int32)
    fill = canvas.uniform(0.75, 0.95) if variant != "burlap" else canvas.uniform(0.55, 0.8)
    fuzz = canvas.noise(beta=0.8, low=canvas.size / 16)
    # Per-thread thickness (slubs in burlap and linen) and colour.
    # Thread properties repeat after the last thread on a tileable canvas (``i`` wraps with it).
    n_warp, n_weft = (int(warps), int(wefts)) if canvas.tileable else (int(warps) + 2, int(wefts) + 2)
    slub = 0.25 if variant == "burlap" else canvas.uniform(0.0, 0.12)
    warp_thick = (1 + slub * canvas.rng.standard_normal(n_warp)).astype(np.float32)[i % n_warp]
    weft_thick = (1 + slub * canvas.rng.standard_normal(n_weft)).astype(np.float32)[j % n_weft]

    def ridge(f, thickness):  # rounded cross-section of a thread, 0 at its sides
        half = 0.5 * fill * thickness
        return np.sqrt(np.clip(1 - ((f - 0.5) / half) ** 2, 0, 1))

    twist = canvas.frequency(canvas.uniform(1.5, 4.0))  # twist ridges per crossing, slanted across the yarn
    warp_h = ridge(fx, warp_thick) * (0.85 + 0.15 * np.sin(2 * math.pi * (y * twist + fx))) \
        + 0.6 * _lift(pattern, i, y, 1)
    weft_h = ridge(fy, weft_thick) * (0.85 + 0.15 * np.sin(2 * math.pi * (x * twist + fy))) \
        + 0.6 * _lift(pattern, j, x, 0)
    warp_top = smoothstep(-0.08, 0.08, warp_h - weft_h)
    top = np.maximum(warp_h, weft_h) + 0.08 * fuzz
    gap = np.clip(1 - top / 0.6, 0, 1)  # where neither thread covers: the shadowed gaps

    if variant == "denim":
        warp_base = hsv_color(canvas.uniform(0.58, 0.63), canvas.uniform(0.5, 0.9), canvas.uniform(0.2, 0.6))
        weft_base = hsv_color(0.1, canvas.uniform(0.05, 0.2), canvas.uniform(0.75, 0.92))
        warp_colors = _heather(canvas, n_warp, warp_base, 0.35)
        weft_colors = _heather(canvas, n_weft, weft_base, 0.1)
    else:
        base = hsv_color(canvas.uniform(0.07, 0.12), canvas.uniform(0.3, 0.55), canvas.uniform(0.4, 0.7)) \
            if variant == "burlap" else _dye(canvas)
        warp_colors = _thread_colors(canvas, n_warp, base)
        weft_colors = _thread_colors(canvas, n_weft, base * canvas.uniform(0.85, 1.15)) \
            if canvas.chance(0.6) else warp_colors[np.arange(n_weft) % n_warp]
    w3 = warp_top[..., None]
    diffuse = warp_colors[i % n_warp] * w3 + weft_colors[j % n_weft] * (1 - w3)
    diffuse = diffuse * (1 + 0.08 * fuzz[..., None]) * (1 - 0.5 * gap[..., None])
    # Thread diameter [mm] sets the relief; the yarn's own crest-to-gap relief is about a third.
    diameter = 150.0 / max(warps, wefts)
    relief = 0.3 * diameter * canvas.uniform(0.6, 1.2)
    floating = pattern.mean()  # satin floats: long straight runs reflect like a sheet
    return diffuse, 0.1 * gap, top * relief, floating


def _heather(canvas: Canvas, count: int, base: np.ndarray, spread: float) -> np.ndarray:
    """Ring-dyed yarn: the same dye, unevenly taken up from thread to thread."""
    return (base * (1 - spread / 2 + spread * canvas.rng.random((count, 1)))).astype(np.float32)


def _knit(canvas: Canvas, rib: bool):
    """Stockinette (rows of V stitches) or rib (columns of V stitches between sunken purl columns)."""
    style = canvas.choice(["solid", "heather", "stripes", "motif"])
    motif_size = int(canvas.choice([4, 6, 8]))
    columns = canvas.frequency(canvas.uniform(8, 40))
    rows = canvas.frequency(columns * canvas.uniform(1.1, 1.5))
    if canvas.tileable:  # whole motifs (and rib pairs) across the sample
        unit = motif_size if style == "motif" else 2
        columns, rows = max(1, round(columns / unit)) * unit, max(1, round(rows / unit)) * unit
    x, y = canvas.u * columns, canvas.v * rows
    i, j = np.floor(x), np.floor(y)
    fx, fy = x - i, y - j
    aspect = rows / columns  # cell width / height in the sample's units
    height = np.zeros_like(fx)
    leg_id = np.zeros_like(fx)
    # The legs of this row and of the row below, which reaches up into this one.
    for row_shift in (0.0, 1.0):
        py = (fy + row_shift - 0.55) / aspect  # in cell widths, y down
        for side in (-1.0, 1.0):
            px = fx - 0.5 - side * 0.24
            tilt = side * 0.45  # legs lean outwards at the top: a V
            c, s = math.cos(tilt), math.sin(tilt)
            along = (px * s + py * c) / (0.62 / aspect)
            across = (px * c - py * s) / 0.2
            q = along * along + across * across
            leg = np.clip(1 - q, 0, 1) ** 0.75 * (1 - 0.3 * row_shift)
            twist = 0.9 + 0.1 * np.sin(2 * math.pi * (along * 2.5 + across * 0.8))
            leg = leg * twist
            better = leg > height
            height = np.where(better, leg, height)
            leg_id = np.where(better, (j + row_shift) * 2 + (side > 0), leg_id)
    if rib:  # every other column is purled: pushed back, only bumps show
        purl = (i % 2 == 1)
        height = np.where(purl, 0.45 * height * (0.7 + 0.3 * np.abs(np.sin(math.pi * fy * 2))) - 0.2, height)
    fuzz = canvas.noise(beta=0.8, low=canvas.size / 12)
    base = _dye(canvas)
    stitch_rows = int(rows) if canvas.tileable else int(rows) + 2
    if style == "stripes":
        palette = np.stack([base, _dye(canvas), _dye(canvas)])
        widths = canvas.rng.integers(1, 6, size=int(canvas.uniform(2, 5)))
        row_colors = palette[np.resize(np.repeat(canvas.rng.integers(3, size=len(widths)), widths), stitch_rows)]
        diffuse = row_colors[(j.astype(np.int64)) % stitch_rows]
    elif style == "motif":  # a small mirrored pattern, as in Fair Isle knitting
        size = motif_size
        half = canvas.rng.random((size, size // 2)) < 0.4
        motif = np.concatenate([half, half[:, ::-1]], 1)
        second = _dye(canvas)
        cell = motif[j.astype(np.int64) % size, i.astype(np.int64) % size][..., None]
        diffuse = np.where(cell, second, base)
    else:
        diffuse = np.broadcast_to(base, fx.shape + (3,))
    if style == "heather":
        diffuse = diffuse * (1 + 0.2 * canvas.blobs(canvas.size / 6, 1.0)[..., None] - 0.1)
    shade = (0.55 + 0.45 * np.clip(height, 0, 1)) * (1 + 0.1 * fuzz)
    diffuse = diffuse * shade[..., None]
    # Stitch width [mm] sets the yarn's relief: a yarn is about a third of a stitch across and
    # lies half buried in the loops around it.
    yarn = 150.0 / columns * 0.12
    return diffuse, 0.05 * fuzz, (height + 0.1 * fuzz) * yarn, 0.0


def _pile(canvas: Canvas, variant: str):
    """Felt (matted fibres), velvet (a dense pile whose brushed direction changes its shade) and
    corduroy (pile in parallel ridges, the wales)."""
    base = _dye(canvas)
    fibres = canvas.noise(beta=0.6, low=canvas.size / 10)
    if variant == "felt":
        clouds = canvas.noise(beta=2.0, low=2, high=40)
        diffuse = base * (1 + 0.08 * clouds[..., None] + 0.1 * fibres[..., None])
        return diffuse, 0.03 * fibres, 0.08 * clouds + 0.03 * fibres, 0.0
    if variant == "velvet":  # crushed patches: pile lying another way looks lighter or darker
        crush = canvas.noise(beta=2.5, low=1, high=24)
        sheen = np.tanh(1.5 * crush)
        diffuse = base * (1 + 0.35 * sheen[..., None] + 0.05 * fibres[..., None])
        return diffuse, -0.05 * sheen, 0.05 * crush + 0.01 * fibres, 0.0
    wales = canvas.frequency(canvas.uniform(12, 50))
    angle_u = canvas.chance(0.5)
    position = (canvas.u if angle_u else canvas.v) * wales
    f = position - np.floor(position)
    ridge = np.clip(1 - ((f - 0.5) / 0.45) ** 2, 0, 1) ** 0.75  # rounded wales, narrow grooves
    diffuse = base * (0.55 + 0.45 * ridge[..., None]) * (1 + 0.1 * fibres[..., None])
    wale_mm = 150.0 / wales
    return diffuse, 0.1 * (1 - ridge), (0.18 * ridge + 0.02 * fibres) * wale_mm, 0.0


@family("fabric")
def fabric(canvas: Canvas) -> Surface:
    variant = _pick(canvas, _VARIANTS)
    if variant in ("knit", "rib_knit"):
        diffuse, rough_offset, relief_mm, floating = _knit(canvas, variant == "rib_knit")
    elif variant in ("felt", "velvet", "corduroy"):
        diffuse, rough_offset, relief_mm, floating = _pile(canvas, variant)
    else:
        diffuse, rough_offset, relief_mm, floating = _woven(canvas, variant)
    if variant == "satin":  # filament yarn (silk, polyester) floats long: a smoother sheet
        roughness = canvas.uniform(0.3, 0.5) + rough_offset
    elif variant == "velvet":
        roughness = canvas.uniform(0.75, 0.95) + rough_offset
    else:
        roughness = canvas.uniform(0.65, 0.95) + rough_offset
    # Cloth lying on a table is never quite flat: a few soft folds [mm].
    folds = canvas.noise(beta=3.0, low=1, high=5) * canvas.uniform(0.0, 1.0)
    height = (relief_mm + folds) * MILLIMETRE
    specular = dielectric_f0(canvas, 0.03, 0.05)
    return Surface(height=height.astype(np.float32), diffuse=np.clip(diffuse, 0, 1).astype(np.float32),
                   roughness=np.clip(roughness, 0, 1).astype(np.float32),
                   specular=np.broadcast_to(specular, diffuse.shape).astype(np.float32), variant=variant)
