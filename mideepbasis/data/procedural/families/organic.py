"""Organic: tree bark (furrowed, plated, smooth: birch, plane, beech), a leaf seen close up, a
bed of fallen leaves, cork (agglomerated granules or natural) and moss.

Furrowed bark is noise stretched along the trunk whose zero crossings are the furrows (deep V
grooves between broad ridges), broken by cross cracks and spotted with lichen. Plated bark is
cells from a lattice stretched along the trunk, separated by deep fissures. A leaf has a midrib
and curving secondary veins drawn as lines, and a net of fine veins from cell borders, the
leaf blade puckered between them. Fallen leaves are stamped one over another, each with its own
colour, curl and veins. Cork is granules (cells) with dark gaps and pores; moss is clumps of
fine fronds. All are rough dielectrics, except waxy leaves.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, smoothstep
from ..registry import family

#: Variants and their chances.
_VARIANTS = (("furrowed_bark", 0.18), ("plated_bark", 0.12), ("smooth_bark", 0.14), ("leaf", 0.16),
             ("leaf_litter", 0.14), ("cork", 0.14), ("moss", 0.12))


def _pick(canvas: Canvas, weighted) -> str:
    names, weights = zip(*weighted)
    return names[int(np.searchsorted(np.cumsum(weights) / sum(weights), canvas.rng.random()))]


def _trunk_angle(canvas: Canvas) -> float:
    """Direction of the trunk (the bark's grain) [rad from u towards v]: mostly along the image's
    rows or columns, as a photo would be framed."""
    return canvas.choice([0.0, math.pi / 2]) + canvas.uniform(-0.15, 0.15)


def _bark_colors(canvas: Canvas) -> tuple[np.ndarray, np.ndarray]:
    """Colours of bark ridges (weathered, greyer, lighter) and furrows (darker, browner)."""
    hue = canvas.uniform(0.04, 0.11)
    ridge = hsv_color(hue, canvas.uniform(0.03, 0.4), canvas.uniform(0.2, 0.7))
    furrow = hsv_color(hue - 0.01, canvas.uniform(0.3, 0.7), canvas.uniform(0.06, 0.2))
    return ridge, furrow


def _lichen(canvas: Canvas, exposed: np.ndarray):
    """Lichen crusts on the exposed parts: a mask [0, 1] and its colour (grey-green or orange)."""
    patches = canvas.blobs(canvas.uniform(5, 20), sharpness=3.0)
    threshold = canvas.choice([canvas.uniform(0.8, 0.95), 1.0])  # 1: no lichen
    mask = smoothstep(threshold, threshold + 0.05, patches * (0.5 + 0.5 * exposed))
    if canvas.chance(0.85):
        color = hsv_color(canvas.uniform(0.15, 0.3), canvas.uniform(0.1, 0.4), canvas.uniform(0.45, 0.75))
    else:
        color = hsv_color(canvas.uniform(0.08, 0.13), canvas.uniform(0.6, 0.9), canvas.uniform(0.6, 0.9))
    return mask, color


def _bark_plates(canvas: Canvas, across: float, elongation: float):
    """Bark split into a net of long plates: Voronoi cells squeezed across the trunk (sampled at
    (elongation * u, v), a whole-number factor on a tileable canvas so that they still wrap), with
    wobbly borders. Returns the distance to the nearest furrow measured across the trunk [sample
    widths], a random value per plate, and the plates across the sample."""
    elongation = canvas.frequency(elongation)
    per_side = max(2, int(round(canvas.frequency(across / elongation))))
    _, label, edge = canvas.cells(canvas.jittered_points(per_side, canvas.uniform(0.6, 1.0)))
    per_plate = canvas.rng.random(per_side * per_side).astype(np.float32)[label]
    wobble = canvas.noise(beta=2.5, low=2, high=per_side * 4)
    du = (elongation - 1.0) * canvas.u + 0.1 / per_side * wobble
    dv = 0.1 / per_side * wobble.T
    return canvas.warp(edge, du, dv) / elongation, canvas.warp(per_plate, du, dv), per_side * elongation


def _orient(canvas: Canvas, *fields):
    """The fields as they are (trunk along v) or transposed (trunk along u); both wrap."""
    if canvas.chance(0.5):
        return fields
    return tuple(np.swapaxes(field, 0, 1) for field in fields)


def _furrowed_bark(canvas: Canvas):
    """Oak-, ash- or poplar-like bark: narrow interlaced ridges between wide, deep V furrows,
    fibrous on top, lichen on the ridges."""
    edge, per_ridge, columns = _bark_plates(canvas, canvas.uniform(4, 12), canvas.uniform(2, 6))
    fibres = canvas.noise(beta=1.0, low=8, stretch=canvas.uniform(3, 8), angle=math.pi / 2)
    width = canvas.uniform(0.25, 0.45) / columns  # furrow half-width [sample widths]
    ridge = smoothstep(0.0, width, edge + 0.1 * width * fibres) ** canvas.uniform(0.6, 1.2)
    # Furrow depth [mm]: up to about half the furrow's width, so that its walls stay below ~50 degrees.
    depth = canvas.uniform(0.25, 0.5) * width * 150.0
    height_mm = depth * ridge * (0.85 + 0.3 * per_ridge) + 0.3 * fibres
    ridge_color, furrow_color = _bark_colors(canvas)
    mix = smoothstep(0.1, 0.9, ridge)[..., None]
    diffuse = (furrow_color * (1 - mix) + ridge_color * mix * (0.85 + 0.3 * per_ridge[..., None]))
    diffuse = diffuse * (1 + 0.15 * fibres[..., None])
    lichen, lichen_color = _lichen(canvas, ridge)
    diffuse = diffuse * (1 - lichen[..., None]) + lichen_color * (1 + 0.1 * fibres[..., None]) * lichen[..., None]
    height_mm = height_mm + 0.3 * lichen * (1 + 0.5 * fibres)
    roughness = 0.85 + 0.05 * fibres + 0.05 * lichen
    diffuse, height_mm, roughness = _orient(canvas, diffuse, height_mm, roughness)
    return diffuse, roughness, height_mm, "furrowed_bark"


def _plated_bark(canvas: Canvas):
    """Pine-like bark: broad plates separated by narrow deep fissures, their surfaces flaking in
    layers that are redder underneath."""
    edge, per_plate, columns = _bark_plates(canvas, canvas.uniform(2.5, 7), canvas.uniform(1.5, 3.5))
    flakes = canvas.noise(beta=2.0, low=3, high=64)
    layers = np.floor(flakes * 2.5) / 2.5  # flaked-off layers: terraces
    gap = canvas.uniform(0.06, 0.16) / columns
    plate = smoothstep(0.0, gap, edge + 0.2 * gap * flakes)
    # Fissure depth [mm]: at most about the fissure's width, so that its walls stay below ~50 degrees.
    depth = canvas.uniform(0.4, 0.8) * gap * 150.0
    height_mm = depth * plate * (0.8 + 0.2 * per_plate) + 0.3 * layers * plate
    ridge_color, furrow_color = _bark_colors(canvas)
    fresh = hsv_color(canvas.uniform(0.02, 0.07), canvas.uniform(0.4, 0.75), canvas.uniform(0.3, 0.6))
    freshness = smoothstep(0.0, 0.5, -layers) * canvas.uniform(0.3, 1.0)  # inner layers: redder
    plate_color = ridge_color * (1 - freshness[..., None]) + fresh * freshness[..., None]
    plate_color = plate_color * (0.8 + 0.4 * per_plate[..., None])
    mix = plate[..., None]
    diffuse = furrow_color * (1 - mix) + plate_color * mix
    roughness = 0.8 + 0.05 * flakes
    diffuse, height_mm, roughness = _orient(canvas, diffuse, height_mm, roughness)
    return diffuse, roughness, height_mm, "plated_bark"


def _smooth_bark(canvas: Canvas):
    """Smooth barks: birch (white, dark lenticels across the trunk, black scars), plane tree
    (camouflage of flaked patches) or beech (grey, faintly blotched)."""
    style = canvas.choice(["birch", "plane", "beech"])
    angle = _trunk_angle(canvas)
    fine = canvas.noise(beta=1.0, low=8)
    patches = canvas.noise(beta=2.5, low=2, high=24)
    if style == "birch":
        base = hsv_color(canvas.uniform(0.05, 0.12), canvas.uniform(0.02, 0.12), canvas.uniform(0.75, 0.92))
        lenticel_field = canvas.noise(beta=0.5, low=8, high=canvas.size / 3, stretch=canvas.uniform(15, 40),
                                      angle=angle + math.pi / 2)
        lenticels = smoothstep(1.8, 2.4, lenticel_field)
        scars = smoothstep(1.4, 1.8, patches + 0.3 * fine)
        dark = hsv_color(0.08, 0.3, 0.08)
        amount = np.clip(0.8 * lenticels + scars, 0, 1)[..., None]
        diffuse = base * (1 + 0.05 * fine[..., None]) * (1 - amount) + dark * amount
        height_mm = 0.1 * lenticels + 0.5 * scars * (1 + 0.5 * fine) + 0.02 * fine
        roughness = canvas.uniform(0.45, 0.7) + 0.3 * scars
    else:
        if style == "plane":
            boxes = (((0.1, 0.2), (0.2, 0.5), (0.35, 0.7)), ((0.1, 0.15), (0.1, 0.3), (0.65, 0.85)),  # olive, cream
                     ((0.05, 0.12), (0.2, 0.4), (0.3, 0.5)), ((0.15, 0.25), (0.2, 0.4), (0.5, 0.7)))  # brown, sage
            colors = np.stack([hsv_color(*(canvas.uniform(*r) for r in box)) for box in boxes])
            step = 0.15  # each flaked-off layer [mm]
        else:
            grey = hsv_color(canvas.uniform(0.05, 0.6), canvas.uniform(0.02, 0.12), canvas.uniform(0.4, 0.65))
            colors = grey * np.array([[1.0], [0.85], [1.12], [0.95]], np.float32)
            step = 0.02
        level = np.clip(np.floor((patches + 2.0) * 1.0), 0, 3).astype(np.int64)
        diffuse = colors[level] * (1 + 0.06 * fine[..., None])
        height_mm = step * level + 0.02 * fine
        roughness = canvas.uniform(0.5, 0.75) + 0.05 * fine
    return diffuse, roughness, height_mm, f"{style}_bark"


def _vein_lines(canvas: Canvas, origin, direction, count: int, spacing: float, angle: float, length: float,
                 bend: float, segments: int = 4):
    """Secondary veins leaving a midrib on both sides and curving towards the apex, as line segments
    (starts, ends) [sample widths]."""
    starts, ends = [], []
    dx, dy = direction
    for k in range(count):
        base = np.array(origin) + (k + 0.5) * spacing * np.array([dx, dy])
        for side, shift in ((1, 0.0), (-1, canvas.uniform(0.0, 0.5))):  # opposite or alternate
            point = base + shift * spacing * np.array([dx, dy])
            theta = math.atan2(dy, dx) + side * angle
            step = length / segments
            for _ in range(segments):
                nxt = point + step * np.array([math.cos(theta), math.sin(theta)])
                starts.append(point)
                ends.append(nxt)
                point = nxt
                theta -= side * bend  # curving towards the apex
    return np.array(starts), np.array(ends)


def _leaf(canvas: Canvas):
    """A leaf blade filling the sample: midrib, curved secondary veins, a net of fine veins, the
    blade puckered between them."""
    if canvas.tileable:
        direction = canvas.choice([(1.0, 0.0), (0.0, 1.0)])
        spacing = 1.0 / canvas.frequency(canvas.uniform(4, 12))  # veins repeat along the wrapping midrib
        count = int(round(1.0 / spacing))
        start = (0.0, canvas.uniform(0.2, 0.8)) if direction[0] else (canvas.uniform(0.2, 0.8), 0.0)
        origin, end = np.array(start), np.array(start) + np.array(direction)
    else:
        angle = canvas.uniform(0, 2 * math.pi)
        direction = (math.cos(angle), math.sin(angle))
        spacing = 1.0 / canvas.uniform(4, 12)
        centre = canvas.rng.uniform(0.25, 0.75, 2)
        origin = centre - 0.9 * np.array(direction)
        end = centre + 0.9 * np.array(direction)
        count = int(1.8 / spacing)
    veins = np.zeros((canvas.size, canvas.size), np.float32)
    midrib = canvas.uniform(0.006, 0.02)
    canvas.draw_lines(veins, origin[None], end[None], 1.0, midrib)
    starts, ends = _vein_lines(canvas, origin, direction, count, spacing, canvas.uniform(0.6, 1.1),
                               canvas.uniform(0.25, 0.45), canvas.uniform(0.05, 0.25))
    canvas.draw_lines(veins, starts, ends, 1.0, canvas.uniform(0.004, 0.01))
    veins = canvas.blur(veins, 0.6 / canvas.size)
    # Fine veins: the borders of small cells (areoles); the blade bulges between them.
    per_side = canvas.loguniform(15, 45)
    _, _, edge = canvas.cells(canvas.jittered_points(int(round(canvas.frequency(per_side))), 1.0))
    fine = (1 - smoothstep(0.0, 1.5 / canvas.size, edge)) * canvas.uniform(0.2, 0.5)
    pucker = np.sqrt(np.clip(edge * per_side * 2, 0, 1))
    network = np.maximum(veins, fine)
    mottle = canvas.blobs(canvas.uniform(2, 8))
    season = canvas.choice(["green", "green", "autumn", "dry"])
    if season == "green":
        blade = hsv_color(canvas.uniform(0.18, 0.33), canvas.uniform(0.45, 0.9), canvas.uniform(0.2, 0.6))
    elif season == "autumn":
        blade = hsv_color(canvas.uniform(0.0, 0.14), canvas.uniform(0.6, 0.95), canvas.uniform(0.35, 0.8))
    else:
        blade = hsv_color(canvas.uniform(0.06, 0.1), canvas.uniform(0.35, 0.65), canvas.uniform(0.2, 0.5))
    vein_color = blade * canvas.uniform(1.2, 1.8) + hsv_color(0.16, 0.5, 0.3) * canvas.uniform(0.0, 1.0)
    diffuse = blade * (0.85 + 0.3 * mottle[..., None])
    diffuse = diffuse * (1 - network[..., None]) + vein_color * network[..., None]
    sign = canvas.choice([1.0, -1.0])  # seen from the underside the veins stand proud
    height_mm = sign * 0.25 * veins + 0.05 * sign * fine + canvas.uniform(0.005, 0.04) * pucker
    waxy = canvas.chance(0.5)
    roughness = (canvas.uniform(0.2, 0.4) if waxy else canvas.uniform(0.5, 0.8)) + 0.1 * network
    return diffuse, roughness, height_mm, f"leaf_{season}"


def _leaf_litter(canvas: Canvas):
    """Fallen leaves stamped one over another (each only in its own window of pixels), each with its
    colour, curl, midrib and side veins; soil shows between them."""
    size = canvas.size
    scale = canvas.uniform(0.08, 0.25)  # leaf half-length [sample widths]
    count = int(np.clip(canvas.uniform(1.5, 3.0) / (1.4 * scale * scale), 15, 150))  # about two layers deep
    leaf_id = np.full((size, size), -1, np.int64)
    hue_low, hue_high = canvas.choice([(0.0, 0.14), (0.04, 0.1), (0.0, 0.3)])
    leaf_colors = np.stack([hsv_color(canvas.uniform(hue_low, hue_high), canvas.uniform(0.35, 0.9),
                                      canvas.uniform(0.15, 0.7)) for _ in range(count)])
    params = canvas.rng.random((count, 8)).astype(np.float32)
    centre_u, centre_v, turn, length, ratio, point, lift, curl = params.T
    half = scale * (0.6 + 0.8 * length)
    width = half * (0.3 + 0.35 * ratio)
    theta = turn * 2 * math.pi
    cos_t, sin_t = np.cos(theta), np.sin(theta)

    def frame(k, du, dv):  # leaf coordinates: s along [-1, 1] from stalk to tip, t across
        s = (du * cos_t[k] + dv * sin_t[k]) / half[k]
        t = (-du * sin_t[k] + dv * cos_t[k]) / width[k]
        profile = np.clip(1 - s * s, 0, 1) ** (0.5 + point[k]) * (1 - 0.25 * s)  # pointed towards the tip
        return s, t, profile

    # Painter's algorithm: each leaf overwrites the ids in its own window (wrapping around on a
    # tileable canvas); the leaf coordinates are computed once afterwards for the top leaves.
    for k in range(count):
        x0, x1 = int(math.floor((centre_u[k] - half[k]) * size)), int(math.ceil((centre_u[k] + half[k]) * size)) + 1
        y0, y1 = int(math.floor((centre_v[k] - half[k]) * size)), int(math.ceil((centre_v[k] + half[k]) * size)) + 1
        if not canvas.tileable:
            x0, x1, y0, y1 = max(x0, 0), min(x1, size), max(y0, 0), min(y1, size)
            if x1 <= x0 or y1 <= y0:
                continue
        xs, ys = np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32)
        s, t, profile = frame(k, ((xs + 0.5) / size - centre_u[k])[None, :], ((ys + 0.5) / size - centre_v[k])[:, None])
        inside = (np.abs(t) < profile) & (np.abs(s) < 1)
        if 0 <= x0 and x1 <= size and 0 <= y0 and y1 <= size:
            window = (slice(y0, y1), slice(x0, x1))
        else:
            window = np.ix_(np.arange(y0, y1) % size, np.arange(x0, x1) % size)
        leaf_id[window] = np.where(inside, k, leaf_id[window])
    top = np.maximum(leaf_id, 0)
    du, dv = canvas.u - centre_u[top], canvas.v - centre_v[top]
    if canvas.tileable:
        du, dv = (du + 0.5) % 1.0 - 0.5, (dv + 0.5) % 1.0 - 0.5
    along, t, profile = frame(top, du, dv)
    across = t / np.maximum(profile, 1e-3)
    height = (0.6 * lift[top] + 0.8 * curl[top] * np.minimum(across * across, 1.0)) * MILLIMETRE
    covered = leaf_id >= 0
    soil_noise = canvas.noise(beta=1.0, low=6)
    soil = hsv_color(canvas.uniform(0.05, 0.1), canvas.uniform(0.3, 0.6), canvas.uniform(0.08, 0.2))
    midrib = np.exp(-(across / 0.06) ** 2)
    side = np.cos(2 * math.pi * (4.0 * along - 1.2 * np.abs(across)))  # chevrons of side veins
    veins = np.maximum(midrib, 0.5 * smoothstep(0.85, 1.0, side)) * covered
    color = leaf_colors[top] * (1 + 0.1 * soil_noise[..., None])
    color = color * (1 + 0.3 * veins[..., None])
    diffuse = np.where(covered[..., None], color, soil * (1 + 0.2 * soil_noise[..., None]))
    height_mm = (height / MILLIMETRE + 0.05 * veins) * covered + 0.1 * soil_noise * (~covered)
    height_mm = canvas.blur(height_mm, 0.7 / canvas.size)
    roughness = np.where(covered, canvas.uniform(0.45, 0.75), 0.95) + 0.03 * soil_noise
    return diffuse, roughness, height_mm, "leaf_litter"


def _cork(canvas: Canvas):
    """Agglomerated cork (granules with dark gaps) or natural cork (a fine cellular matrix with
    elongated dark lenticels)."""
    base = hsv_color(canvas.uniform(0.06, 0.1), canvas.uniform(0.35, 0.65), canvas.uniform(0.35, 0.75))
    pores = canvas.noise(beta=0.3, low=canvas.size / 10)
    if canvas.chance(0.65):
        per_side = canvas.loguniform(25, 70)
        points = canvas.jittered_points(int(round(canvas.frequency(per_side))), 1.0)
        nearest, label, edge = canvas.cells(points)
        per_granule = canvas.rng.random((len(points), 2)).astype(np.float32)[label]
        gap = canvas.uniform(0.05, 0.2) / per_side
        granule = smoothstep(gap, gap + 1.0 / canvas.size, edge)
        dome = 1 - 0.5 * (nearest * per_side) ** 2
        tone = (0.6 + 0.7 * per_granule[..., 0]) * (1 - 0.35 * smoothstep(1.5, 2.2, pores))
        diffuse = base * (tone * (0.25 + 0.75 * granule))[..., None]
        height_mm = (150.0 / per_side) * (0.15 * dome + 0.05 * per_granule[..., 1]) * granule - 0.1 * (1 - granule)
        return diffuse, 0.85 + 0.1 * (1 - granule), height_mm, "cork_agglomerated"
    lenticel_field = canvas.noise(beta=1.0, low=6, high=canvas.size / 4, stretch=canvas.uniform(2, 6),
                                  angle=canvas.uniform(0, math.pi))
    lenticels = smoothstep(1.9, 2.4, lenticel_field)
    mottle = canvas.blobs(canvas.uniform(3, 10))
    diffuse = base * ((0.85 + 0.3 * mottle) * (1 + 0.1 * pores) * (1 - 0.7 * lenticels))[..., None]
    height_mm = 0.03 * pores - 0.4 * lenticels
    return diffuse, 0.8 + 0.05 * pores + 0.1 * lenticels, height_mm, "cork_natural"


def _moss(canvas: Canvas):
    """Moss cushions: a dense pile of fine fronds (bright tips, dark gaps between them) gathered in
    clumps, yellower on top; some dry, brown patches."""
    clump_cycles = canvas.uniform(4, 14)
    clumps = canvas.blobs(clump_cycles, sharpness=canvas.uniform(0.8, 1.5))
    fronds = canvas.noise(beta=0.8, low=canvas.size / 16, high=canvas.size / 3)
    green = hsv_color(canvas.uniform(0.18, 0.3), canvas.uniform(0.5, 0.9), canvas.uniform(0.25, 0.55))
    tips = hsv_color(canvas.uniform(0.14, 0.22), canvas.uniform(0.5, 0.85), canvas.uniform(0.45, 0.8))
    dry = hsv_color(canvas.uniform(0.07, 0.11), canvas.uniform(0.4, 0.7), canvas.uniform(0.3, 0.5))
    tip = np.clip(0.5 + 0.35 * fronds + 0.5 * (clumps - 0.5), 0, 1)[..., None]
    dryness = smoothstep(0.55, 0.9, canvas.warp(clumps, 0.31, 0.57)) * canvas.uniform(0.0, 0.8)
    shade = (0.5 + 0.5 * clumps) * (1 + 0.3 * fronds)
    diffuse = (green * (1 - tip) + tips * tip) * shade[..., None]
    diffuse = diffuse * (1 - dryness[..., None]) + dry * shade[..., None] * dryness[..., None]
    # Cushions up to a few millimetres, less for small ones (keeps their sides below ~45 degrees).
    height_mm = min(canvas.uniform(1.5, 4.0), 30.0 / clump_cycles) * clumps + 0.12 * fronds
    return diffuse, 0.9 + 0.05 * fronds, height_mm, "moss"


@family("organic")
def organic(canvas: Canvas) -> Surface:
    variant = _pick(canvas, _VARIANTS)
    make = {"furrowed_bark": _furrowed_bark, "plated_bark": _plated_bark, "smooth_bark": _smooth_bark, "leaf": _leaf,
            "leaf_litter": _leaf_litter, "cork": _cork, "moss": _moss}[variant]
    diffuse, roughness, height_mm, name = make(canvas)
    specular = dielectric_f0(canvas, 0.04, 0.05) if variant == "leaf" else dielectric_f0(canvas, 0.03, 0.04)
    return Surface(height=(np.asarray(height_mm) * MILLIMETRE).astype(np.float32),
                   diffuse=np.clip(diffuse, 0, 1).astype(np.float32),
                   roughness=np.clip(np.broadcast_to(roughness, height_mm.shape), 0, 1).astype(np.float32),
                   specular=np.broadcast_to(specular, diffuse.shape).astype(np.float32), variant=name)
