"""Leather: pebbled grain leather, smooth (nappa) leather, suede, reptile skins (crocodile-like
tiles and overlapping snake or fish scales) and patent leather.

Grain leather is a mosaic of small rounded pebbles (Voronoi cells whose borders are the grooves)
crossed by creases; the finish gathers darker in the grooves. Suede is a nap of fine fibres,
very rough. Crocodile scales are quasi-rectangular cells with domed tops; snake and fish scales
lie in offset rows, each overlapping the next, rising towards its free edge. Patent leather is
a glossy lacquer over a smooth hide. Dielectric throughout (F0 0.035-0.05).
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, smoothstep
from ..registry import family

#: Variants and their chances.
_VARIANTS = (("pebbled", 0.28), ("smooth", 0.16), ("suede", 0.16), ("crocodile", 0.14), ("scales", 0.14),
             ("patent", 0.12))


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _hide_color(canvas: Canvas) -> np.ndarray:
    """Tanned browns, tans and blacks most of the time; otherwise a dyed colour."""
    kind = canvas.choice(["brown", "brown", "tan", "black", "dyed", "pale"])
    if kind == "brown":
        return hsv_color(canvas.uniform(0.02, 0.09), canvas.uniform(0.45, 0.85), canvas.uniform(0.15, 0.5))
    if kind == "tan":
        return hsv_color(canvas.uniform(0.06, 0.11), canvas.uniform(0.35, 0.7), canvas.uniform(0.5, 0.85))
    if kind == "black":
        return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.0, 0.3), canvas.uniform(0.04, 0.12))
    if kind == "pale":
        return hsv_color(canvas.uniform(0.05, 0.12), canvas.uniform(0.02, 0.25), canvas.uniform(0.75, 0.95))
    return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.4, 0.9), canvas.uniform(0.2, 0.75))


def _creases(canvas: Canvas) -> np.ndarray:
    """Creases [0, 1]: short, roughly parallel wrinkles (zero crossings of noise stretched across
    the bending direction) gathered in patches where the hide was flexed."""
    angle = canvas.uniform(0, math.pi)
    field = canvas.noise(beta=2.5, low=2, high=48, stretch=canvas.uniform(2, 5), angle=angle)
    where = smoothstep(0.45, 0.75, canvas.blobs(canvas.uniform(1.5, 4)))
    return np.exp(-(field / canvas.uniform(0.05, 0.12)) ** 2) * where


def _pebbled(canvas: Canvas, smooth: bool):
    """Grain leather: rounded pebbles between soft grooves (smooth leather: only faint ones),
    creases and pores. Returns relief [mm], cavity [0, 1], a roughness offset and a tone."""
    per_side = canvas.loguniform(30, 90) if not smooth else canvas.loguniform(60, 140)
    points = canvas.jittered_points(int(round(canvas.frequency(per_side))), canvas.uniform(0.7, 1.0))
    _, label, edge = canvas.cells(points)
    # Wobbly borders: real pebbles are not polygons.
    wobble = canvas.noise(beta=2.0, low=per_side / 2, high=per_side * 3)
    edge = canvas.warp(edge, 0.25 / per_side * wobble, 0.25 / per_side * wobble.T)
    pebble = np.sqrt(smoothstep(0.0, canvas.uniform(0.25, 0.5) / per_side, edge))  # rounded shoulders
    crease = _creases(canvas) * canvas.uniform(0.3, 1.0)
    pores = canvas.noise(beta=0.0, low=canvas.size / 8)
    pore = smoothstep(2.0, 2.6, pores)
    per_pebble = canvas.rng.random(len(points)).astype(np.float32)[label]
    depth = 0.02 if smooth else canvas.uniform(0.05, 0.15)  # [mm]
    height_mm = depth * (pebble + 0.15 * per_pebble) - 0.06 * crease - 0.02 * pore
    cavity = (1 - pebble) * (0.3 if smooth else 0.8) + 0.6 * crease
    return height_mm, np.clip(cavity, 0, 1), 0.1 * pore + 0.05 * per_pebble, per_pebble


def _suede(canvas: Canvas):
    """Suede and nubuck: a fine fibrous nap; brushing it one way or another shifts the shade."""
    fibres = canvas.noise(beta=0.5, low=canvas.size / 12)
    nap = canvas.noise(beta=2.5, low=1, high=16, stretch=canvas.uniform(1, 3), angle=canvas.uniform(0, math.pi))
    height_mm = 0.015 * fibres + 0.03 * nap
    return height_mm, np.clip(0.4 + 0.25 * nap + 0.1 * fibres, 0, 1), 0.02 * fibres, 0.5 + 0.1 * fibres


def _crocodile(canvas: Canvas):
    """Crocodile or alligator: rows of quasi-rectangular scales (cells of a jittered, stretched
    grid), domed, some with a bony central ridge, separated by deep creased grooves."""
    columns = int(canvas.frequency(canvas.uniform(4, 14)))
    rows = int(canvas.frequency(columns * canvas.uniform(0.6, 1.6)))
    jitter = canvas.uniform(0.1, 0.45)
    gu, gv = np.meshgrid((np.arange(columns) + 0.5) / columns, (np.arange(rows) + 0.5) / rows, indexing="xy")
    offset = canvas.rng.uniform(-0.5, 0.5, (rows, 1)) / columns  # each row slides a little
    points = np.stack([(gu + offset).ravel(), gv.ravel()], -1)
    points += (canvas.rng.random(points.shape) - 0.5) * jitter / np.array([columns, rows])
    points = (points % 1.0).astype(np.float32)
    nearest, label, edge = canvas.cells(points)
    cell = 1.0 / max(columns, rows)
    dome = smoothstep(0.0, canvas.uniform(0.15, 0.35) * cell, edge)
    crown = 1.0 - (nearest / cell) ** 2 * 0.5
    per_scale = canvas.rng.random((len(points), 2)).astype(np.float32)
    ridge = (per_scale[label, 1] < canvas.uniform(0.0, 0.5)) * np.exp(-(nearest / (0.18 * cell)) ** 2)
    scale_mm = 150.0 * cell
    height_mm = scale_mm * (0.06 * dome * crown + 0.05 * ridge) + 0.01 * per_scale[label, 0]
    wrinkles = canvas.noise(beta=1.2, low=8)
    height_mm = height_mm + 0.02 * wrinkles * dome
    return height_mm, 1 - dome, 0.04 * wrinkles, per_scale[label, 0]


def _scales(canvas: Canvas):
    """Snake or fish scales in offset rows. Each row lies over the row below it (scales point to
    the tail, down the image), so a scale shows only its lower part, rising towards its free
    edge; rounder (fish) or diamond-like and sometimes keeled (snake)."""
    columns = canvas.frequency(canvas.uniform(8, 30))
    rows = canvas.frequency(columns * canvas.uniform(0.8, 1.6))
    if canvas.tileable:
        rows += rows % 2  # offset rows must pair up to wrap
    x, y = canvas.u * columns, canvas.v * rows
    j = np.floor(y)
    half_x, half_y = canvas.uniform(0.55, 0.75), canvas.uniform(0.75, 1.0)  # scale half-size [cells]
    power = canvas.uniform(1.1, 2.2)  # 2: rounded (fish), towards 1: diamond (snake)
    keel = canvas.uniform(0.0, 0.4) if power < 1.6 else 0.0
    n_columns, n_rows = int(columns) + 2, int(rows) + 2
    rise = np.zeros(x.shape, np.float32)
    scale_id = np.zeros(x.shape, np.int64)
    centre_u = np.zeros(x.shape, np.float32)
    centre_v = np.zeros(x.shape, np.float32)
    covered = np.zeros(x.shape, bool)
    # Later candidates overwrite earlier ones: go from the row below up to the row above, so the
    # uppermost covering scale wins.
    for dj in (1, 0, -1):
        row = j + dj
        shift = 0.5 * (row % 2)
        k = np.floor(x - shift)
        dx = x - (k + 0.5 + shift)
        dy = y - (row + 0.5)
        q = (np.abs(dx) / half_x) ** power + (np.abs(dy) / half_y) ** power
        inside = q < 1.0
        profile = (0.5 + 0.5 * dy / half_y) * (1 - smoothstep(0.7, 1.0, q) * 0.7) \
            + keel * np.exp(-(dx / 0.08) ** 2) * (1 - q)
        rise = np.where(inside, profile, rise)
        if canvas.tileable:
            row_index, column_index = row % rows, k % columns
        else:
            row_index, column_index = row + 1, k + 1
        scale_id = np.where(inside, row_index * n_columns + column_index, scale_id).astype(np.int64)
        centre_u = np.where(inside, (k + 0.5 + shift) / columns, centre_u)
        centre_v = np.where(inside, (row + 0.5) / rows, centre_v)
        covered |= inside
    per_scale = canvas.rng.random(n_rows * n_columns + n_columns).astype(np.float32)[scale_id % (n_rows * n_columns)]
    # A body pattern (blotches, bands), read at each scale's centre so whole scales take its colour.
    pattern = canvas.blobs(canvas.uniform(2, 8), sharpness=canvas.uniform(1, 4))
    pattern = canvas.warp(pattern, centre_u - canvas.u, centre_v - canvas.v)
    scale_mm = 150.0 / columns
    height_mm = scale_mm * 0.05 * rise * covered
    cavity = 1 - smoothstep(0.0, 0.35, rise) * covered
    return height_mm, cavity, 0.05 * per_scale, 0.15 * per_scale + 0.9 * pattern - 0.05


@family("leather")
def leather(canvas: Canvas) -> Surface:
    variant = _pick(canvas, _VARIANTS)
    color = _hide_color(canvas)
    if variant in ("pebbled", "smooth", "patent"):
        height_mm, cavity, rough_offset, tone = _pebbled(canvas, smooth=variant != "pebbled")
    elif variant == "suede":
        height_mm, cavity, rough_offset, tone = _suede(canvas)
    elif variant == "crocodile":
        height_mm, cavity, rough_offset, tone = _crocodile(canvas)
    else:
        height_mm, cavity, rough_offset, tone = _scales(canvas)

    # Finishes gather in the low places: darker grooves (antiqued leather much darker).
    darkening = {"suede": canvas.uniform(0.1, 0.3), "patent": 0.0}.get(variant, canvas.uniform(0.2, 0.7))
    shade = (1 - darkening * cavity) * (1 + canvas.uniform(0.05, 0.25) * (tone - 0.5))
    mottle = canvas.blobs(canvas.uniform(2, 10))
    diffuse = color * (shade * (0.9 + 0.2 * mottle))[..., None]
    if variant == "scales" and canvas.chance(0.6):  # two-tone skins: the pattern in a second colour
        second = _hide_color(canvas)
        mix = smoothstep(0.3, 0.7, tone)[..., None]
        diffuse = diffuse * (1 - mix) + second * shade[..., None] * mix

    if variant == "patent":  # a thick glossy lacquer: grain filled, slow waves remain
        height_mm = 0.2 * height_mm + 0.05 * canvas.noise(beta=3.0, low=1, high=8)
        roughness = canvas.uniform(0.02, 0.08) + 0.0 * rough_offset
        f0 = dielectric_f0(canvas, 0.045, 0.05)
    elif variant == "suede":
        roughness = canvas.uniform(0.85, 1.0) + rough_offset
        f0 = dielectric_f0(canvas, 0.035, 0.04)
    else:  # aniline (matte) to heavily finished (satin-glossy) leather
        roughness = canvas.uniform(0.3, 0.7) + rough_offset + 0.15 * cavity
        f0 = dielectric_f0(canvas, 0.035, 0.05)
    return Surface(height=(height_mm * MILLIMETRE).astype(np.float32),
                   diffuse=np.clip(diffuse, 0, 1).astype(np.float32),
                   roughness=np.clip(roughness, 0, 1).astype(np.float32),
                   specular=np.broadcast_to(f0, diffuse.shape).astype(np.float32), variant=variant)
