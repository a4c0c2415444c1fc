"""Wood: solid boards with growth rings and knots, floor planks, basket-weave parquet and figured
veneers (quarter-sawn, curly, burl), each raw, weathered, oiled or lacquered.

Growth rings are the contours of a ring phase: a ramp across the grain (the rings of a board cut
along a log) plus smooth noise stretched along the grain, whose hills the rings wrap around (the
cathedral figure of flat-sawn boards). Each ring runs from pale, porous earlywood to dark, dense
latewood and ends sharply. The textures are made once in "grain space", with the grain along u,
and sampled through ``Canvas.warp`` at each pixel's grain coordinates: a rotation for one board, a
per-board shift for planks, a per-block turn for parquet, so every board shows another part of
the tree and everything wraps on a tileable canvas (grain coordinates are whole-number
combinations of u and v there).
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, grid, hsv_color, smoothstep
from ..registry import family

#: Layouts and their chances.
_LAYOUTS = (("solid", 0.3), ("planks", 0.3), ("parquet", 0.12), ("quartersawn", 0.1), ("curly", 0.1),
            ("burl", 0.08))

#: Finishes: roughness range, F0 range and how much of the pores' depth stays open.
_FINISHES = {"raw": ((0.55, 0.85), (0.035, 0.045), 1.0), "weathered": ((0.75, 0.95), (0.03, 0.04), 1.0),
             "oiled": ((0.3, 0.55), (0.04, 0.05), 0.7), "lacquered": ((0.04, 0.2), (0.045, 0.05), 0.2)}


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _species_color(canvas: Canvas, finish: str) -> tuple[np.ndarray, np.ndarray]:
    """Linear earlywood and latewood colours: natural woods from pale maple to wenge, with some
    greyed (weathered) or stained boards."""
    if finish == "weathered":
        hue, saturation, value = canvas.uniform(0.06, 0.12), canvas.uniform(0.04, 0.2), canvas.uniform(0.4, 0.7)
    elif canvas.chance(0.08):  # a coloured stain
        hue, saturation, value = canvas.uniform(0, 1), canvas.uniform(0.25, 0.6), canvas.uniform(0.25, 0.6)
    else:
        hue = canvas.uniform(0.025, 0.115)
        saturation = canvas.uniform(0.3, 0.75)
        value = canvas.loguniform(0.16, 0.92)
    early = hsv_color(hue, saturation, value)
    # Latewood: denser cell walls, darker and a little more saturated.
    late = hsv_color(hue - canvas.uniform(0, 0.015), min(1.0, saturation * canvas.uniform(1.0, 1.35)),
                     value * canvas.uniform(0.45, 0.85))
    return early, late


def _direction(canvas: Canvas) -> tuple[float, float]:
    """The grain direction as (a, b) = (cos, sin) of its angle from u towards v; on a tileable
    canvas a whole-number direction so that grain coordinates stay periodic."""
    if canvas.tileable:
        return canvas.choice([(1, 0), (0, 1), (1, 1), (1, -1)])
    angle = canvas.uniform(0, math.pi)
    return math.cos(angle), math.sin(angle)


def _ring_profile(phase: np.ndarray, early: float, transition: float, aa: float) -> np.ndarray:
    """Latewood amount [0, 1] of a ring phase [rings]: earlywood for the first ``early`` of each
    ring, a ``transition`` to latewood, then a sharp (anti-aliased over ``aa``) earlywood start."""
    t = phase - np.floor(phase)
    return smoothstep(early, early + transition, t) * (1.0 - smoothstep(1.0 - aa, 1.0, t))


def _ring_tone(phase: np.ndarray) -> np.ndarray:
    """A per-ring random brightness in [-0.5, 0.5]: some years grow darker wood than others."""
    k = np.floor(phase)
    return (np.sin(k * 12.9898) * 43758.547) % 1.0 - 0.5


class _GrainSpace:
    """The tree's textures with the grain along u: smooth figure noise that bends the rings,
    fine fibre streaks, and elongated pores."""

    def __init__(self, canvas: Canvas):
        self.canvas = canvas
        stretch = canvas.uniform(5, 20)
        self.figure = canvas.noise(beta=3.0, low=1, high=16, stretch=stretch)
        self.fibre = canvas.noise(beta=1.2, low=6, stretch=canvas.uniform(10, 30))
        self.pores = canvas.noise(beta=0.0, low=canvas.size / 10, stretch=canvas.uniform(3, 9))

    def sample(self, along: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The three textures at grain coordinates (along, across) [sample widths], per pixel."""
        du, dv = along - self.canvas.u, across - self.canvas.v
        return tuple(self.canvas.warp(field, du, dv) for field in (self.figure, self.fibre, self.pores))


def _knots(canvas: Canvas, along_dir: tuple[float, float], count: int):
    """Knot centres as a bump field the rings wrap around and a core mask [0, 1]."""
    bump = np.zeros((canvas.size, canvas.size), np.float32)
    core = np.zeros_like(bump)
    a, b = along_dir
    norm = math.hypot(a, b)
    for _ in range(count):
        cu, cv = canvas.rng.random(2)
        radius = canvas.uniform(0.015, 0.05)  # [sample widths]
        du, dv = canvas.u - cu, canvas.v - cv
        if canvas.tileable:
            du, dv = (du + 0.5) % 1.0 - 0.5, (dv + 0.5) % 1.0 - 0.5
        along = (a * du + b * dv) / norm
        across = (-b * du + a * dv) / norm
        # Knots are cut at an angle through a branch: elongated along the grain.
        d2 = (along / canvas.uniform(1.2, 2.5)) ** 2 + across**2
        bump += np.exp(-d2 / (2 * (2.5 * radius) ** 2))
        core = np.maximum(core, 1.0 - smoothstep(0.7, 1.0, np.sqrt(d2) / radius))
    return bump, core


def _layout(canvas: Canvas, layout: str):
    """Grain coordinates (along, across) [sample widths] of every pixel, the across coordinate that
    drives the ring ramp, per-board random values, the distance to board joints (None when the
    wood is one piece) and the grain direction (a, b)."""
    u, v = canvas.u, canvas.v
    if layout in ("planks", "parquet"):
        rng = canvas.rng
        if layout == "planks":
            rows = canvas.frequency(canvas.loguniform(1.0, 6.0))  # boards across the sample
            columns = canvas.frequency(canvas.loguniform(0.25, 1.5) * (1 if canvas.tileable else rows / 2))
            columns = max(columns, 1.0) if canvas.tileable else columns
            stagger = canvas.choice([0.5, 0.33, 0.25]) if canvas.tileable else canvas.uniform(0.2, 0.8)
            cells = grid(canvas, columns, rows, stagger)
            direction = (1, 0)
            if canvas.chance(0.5):  # boards along v: the same grid, transposed (still periodic)
                cells = type(cells)(cells.index.T, cells.count, cells.edge.T, cells.local_u.T, cells.local_v.T)
                u, v, direction = v, u, (0, 1)
            per_board = rng.random((cells.count, 6)).astype(np.float32)[cells.index]
            along = u + per_board[..., 0] * 7.0  # each board a different stretch of the log
            across = cells.local_v / rows + per_board[..., 1] * 5.0
            ramp = cells.local_v / rows
            edge = cells.edge
        else:
            blocks = canvas.frequency(canvas.uniform(1.5, 5.0))
            slats = int(canvas.choice([2, 3, 3, 4, 5]))
            cells = grid(canvas, blocks, blocks, 0.0)
            col = np.floor(u * blocks)
            row = np.floor(v * blocks)
            turned = ((col + row) % 2).astype(bool)  # the basket weave: alternate blocks turn 90 degrees
            lu, lv = cells.local_u, cells.local_v
            along_local = np.where(turned, lv, lu)
            across_local = np.where(turned, lu, lv) * slats
            slat = np.floor(across_local)
            slat_f = across_local - slat
            slat_id = cells.index * slats + slat.astype(np.int64)
            per_board = rng.random((cells.count * slats, 6)).astype(np.float32)[slat_id]
            along = along_local / blocks + per_board[..., 0] * 7.0
            across = slat_f / (blocks * slats) + per_board[..., 1] * 5.0
            ramp = slat_f / (blocks * slats)
            slat_edge = np.minimum(slat_f, 1 - slat_f) / (blocks * slats)
            edge = np.minimum(cells.edge, slat_edge)
            direction = (1, 0)
        return along, across, ramp, per_board, edge, direction
    a, b = _direction(canvas)
    along = a * u + b * v
    across = -b * u + a * v
    if layout != "burl" and canvas.chance(0.3 if layout in ("quartersawn", "curly") else 0.1):
        # Book-matched veneer: neighbouring leaves are mirror images across their joint.
        leaves = canvas.choice([2, 4]) if canvas.tileable else canvas.choice([1, 2, 3])  # even: wraps
        x = across * leaves
        across = np.abs(x - 2 * np.floor(x / 2 + 0.5)) / leaves
    return along, across, across, None, None, (a, b)


@family("wood")
def wood(canvas: Canvas) -> Surface:
    layout = _pick(canvas, _LAYOUTS)
    veneer = layout in ("quartersawn", "curly", "burl")
    finish = _pick(canvas, (("raw", 0.3), ("weathered", 0.1 if layout in ("solid", "planks") else 0.0),
                            ("oiled", 0.25), ("lacquered", 0.45 if veneer else 0.3)))
    (rough_low, rough_high), (f0_low, f0_high), open_pores = _FINISHES[finish]
    early_color, late_color = _species_color(canvas, finish)
    space = _GrainSpace(canvas)
    along, across, ramp, per_board, edge, direction = _layout(canvas, layout)
    figure, fibre, pores = space.sample(along, across)

    # Ring phase [rings]: a ramp across the grain bent by the figure noise (cathedrals where the
    # bend exceeds a ring). Quarter-sawn wood is cut radially: straight, tight, parallel rings.
    rings = canvas.frequency(canvas.loguniform(5, 60) if layout != "quartersawn" else canvas.loguniform(25, 90))
    bend = rings * canvas.loguniform(0.01, 0.2) * (0.15 if layout == "quartersawn" else 1.0)
    if per_board is not None:  # each board its own ring density and figure
        board_rings = rings * (0.6 + 0.8 * per_board[..., 2])
        phase = board_rings * ramp + bend * (0.3 + 1.4 * per_board[..., 3]) * figure + per_board[..., 4] * 10
    elif layout == "burl":  # burl: tangled growth around many buds, rings follow swirling noise
        swirl = canvas.noise(beta=3.0, low=1.5, high=canvas.uniform(8, 16))
        phase = canvas.uniform(4, 10) * swirl + 0.5 * figure
    else:
        phase = rings * ramp + bend * figure
    if layout == "solid" and canvas.chance(0.35):
        bump, knot_core = _knots(canvas, direction, int(canvas.uniform(1, 3)))
        phase = phase + canvas.uniform(2, 6) * bump
    else:
        knot_core = None
    aa = float(np.clip(2.0 * rings / canvas.size, 0.02, 0.4))
    late = _ring_profile(phase, canvas.uniform(0.3, 0.75), canvas.uniform(0.1, 0.4), aa)
    tone = _ring_tone(phase)

    # Pores: ring-porous woods (oak, ash) crowd them into the earlywood; all have a few.
    ring_porous = canvas.uniform(0, 1)
    pore_density = canvas.uniform(1.4, 2.6)  # threshold on unit noise: higher is sparser
    pore = smoothstep(pore_density, pore_density + 0.8, pores) * (1.0 - ring_porous * late)

    contrast = canvas.uniform(0.4, 1.0)
    color = early_color + (late_color - early_color) * (contrast * late)[..., None]
    shade = 1.0 + canvas.uniform(0.04, 0.12) * fibre + canvas.uniform(0.0, 0.25) * tone
    shade = shade - canvas.uniform(0.2, 0.6) * pore
    if per_board is not None:  # boards from different trees: brightness and hue differ
        shade = shade * (0.75 + 0.5 * per_board[..., 5])
    diffuse = color * shade[..., None]

    base_rough = canvas.uniform(rough_low, rough_high)
    roughness = base_rough - 0.08 * late * (finish in ("raw", "weathered")) + 0.15 * pore * open_pores
    roughness = roughness + 0.03 * fibre

    # Relief [patch half-widths]: pores are pits; sanded wood is nearly flat, weathered wood has
    # its soft earlywood eroded so the latewood stands proud.
    grain_relief = {"raw": 0.02, "weathered": 0.25, "oiled": 0.015, "lacquered": 0.005}[finish]
    fibre_relief = {"raw": 0.012, "weathered": 0.03, "oiled": 0.008, "lacquered": 0.002}[finish]
    height = (canvas.uniform(0.5, 1.5) * grain_relief * late + fibre_relief * fibre) * MILLIMETRE
    height = height - canvas.uniform(0.03, 0.08) * MILLIMETRE * open_pores * pore

    if layout == "quartersawn":  # ray flecks: glossy, pale ribbons crossing the grain
        flecks = canvas.noise(beta=2.5, low=3, high=40, stretch=canvas.uniform(1.5, 3),
                              angle=math.atan2(direction[1], direction[0]) + canvas.uniform(1.2, 1.9))
        fleck = smoothstep(0.6, 1.2, flecks + 0.3 * fibre) * canvas.uniform(0.5, 1.0)
        diffuse = diffuse * (1 + 0.35 * fleck[..., None])
        roughness = roughness - 0.1 * fleck
    elif layout == "curly":  # fiddleback: ripples across the grain that catch the light
        curls = canvas.frequency(canvas.uniform(15, 60))
        ripple = np.sin(2 * math.pi * (curls * along + 0.6 * figure))
        height = height + canvas.uniform(0.004, 0.015) * MILLIMETRE * ripple * (60 / curls)
        diffuse = diffuse * (1 + canvas.uniform(0.05, 0.15) * ripple[..., None])
    elif layout == "burl":  # bud eyes: tiny dark knots in clusters
        eye = smoothstep(2.2, 2.8, pores) * smoothstep(0.0, 1.0, figure)
        diffuse = diffuse * (1 - 0.7 * eye[..., None])

    if knot_core is not None:
        diffuse = diffuse * (1 - 0.5 * knot_core[..., None])
        roughness = roughness - 0.1 * knot_core * (finish == "raw")
        height = height + 0.03 * MILLIMETRE * knot_core * (finish in ("raw", "weathered"))

    if edge is not None:  # joints between boards: a small bevel and a dark gap
        gap = canvas.uniform(0.0003, 0.004) if layout == "planks" else canvas.uniform(0.0002, 0.0015)
        bevel = canvas.uniform(0.0005, 0.006)
        joint = smoothstep(gap, gap + bevel, edge)
        height = height + canvas.uniform(0.2, 0.8) * MILLIMETRE * np.sqrt(joint)
        open_gap = (1.0 - smoothstep(0.5 * gap, gap + 1.0 / canvas.size, edge))
        diffuse = diffuse * (1 - 0.8 * open_gap[..., None])
        roughness = roughness + (0.9 - roughness) * open_gap
        if per_board is not None:  # slight cupping and tilt of each board
            height = height + 0.1 * MILLIMETRE * (per_board[..., 2] - 0.5) * joint

    if finish == "lacquered":  # the clear coat follows the boards in slow waves
        height = height + 0.01 * MILLIMETRE * figure
    specular = dielectric_f0(canvas, f0_low, f0_high)
    return Surface(height=height.astype(np.float32), diffuse=diffuse.astype(np.float32),
                   roughness=roughness.astype(np.float32),
                   specular=np.broadcast_to(specular, diffuse.shape).astype(np.float32),
                   variant=f"{layout}_{finish}")
