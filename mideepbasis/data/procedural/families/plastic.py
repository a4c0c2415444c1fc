"""Plastics: injection-moulded surfaces, glossy to matte, smooth or textured (stipple, leather
grain, frosted), often printed: all-over patterns, text, logos, stuck-on labels, moulded lettering.

Printing ink is a change of diffuse colour and of roughness with almost no relief (a few
micrometres); labels are a sheet of paper or film a tenth of a millimetre thick; moulded lettering
is relief of the plastic itself. Colours are worked on in planar (3, H, W) layout, which numpy
broadcasts much faster than (H, W, 3), and handed back as an (H, W, 3) view.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .... import constants
from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, planar, smoothstep
from ..registry import family

#: Printed words: packaging, product and warning text.
_WORDS = ("NEW", "ORIGINAL", "RECYCLE", "MADE IN", "PP", "PET", "HDPE", "LOT", "NET WT", "SHAKE WELL",
          "FRAGILE", "KEEP DRY", "Premium", "fresh", "organic", "Max", "Eco", "Ultra", "Classic", "Series",
          "Model", "No.", "ml", "kg", "CE", "Warning", "Do not", "open here", "Batch", "EXP", "SALE",
          "Quality", "Pro", "Light", "Power", "Natural", "Extra", "Super", "Made with care", "since",
          "Design", "Sport", "Kids", "Home", "Care", "Clean", "Soft", "Strong", "Tested", "Safe",
          "BPA free", "Dishwasher safe", "Microwave", "Nutrition", "Ingredients", "Serial")


def _fill(distance: np.ndarray, pixel: float) -> np.ndarray:
    """Anti-aliased coverage of the region where a signed ``distance`` is negative, the ramp one
    ``pixel`` wide (both in the same units)."""
    return np.clip(0.5 - distance / pixel, 0.0, 1.0)


def _lattice(canvas: Canvas, cycles: float, angle: float):
    """A square lattice of ``cycles`` cells per sample rotated by ``angle`` [rad].

    Returns the position inside the cell (x, y) in [-0.5, 0.5) [cells] and the size of a pixel
    [cells]. On a tileable canvas the wave vectors are whole, so the lattice wraps.
    """
    ku, kv = cycles * math.cos(angle), cycles * math.sin(angle)
    if canvas.tileable:
        ku, kv = float(round(ku)), float(round(kv))
        ku = ku if (ku, kv) != (0.0, 0.0) else 1.0
    p1 = canvas.u * ku + canvas.v * kv
    p2 = canvas.v * ku - canvas.u * kv
    return p1 - np.floor(p1) - 0.5, p2 - np.floor(p2) - 0.5, math.hypot(ku, kv) / canvas.size


def _offset(canvas: Canvas, centre) -> tuple[np.ndarray, np.ndarray]:
    """(du, dv) from ``centre`` (u, v) to every pixel [sample widths], the shortest way round on a
    tileable canvas."""
    du, dv = canvas.u - centre[0], canvas.v - centre[1]
    if canvas.tileable:
        du, dv = du - np.round(du), dv - np.round(dv)
    return du, dv


def _phrase(canvas: Canvas) -> str:
    """A short piece of printed text: words, numbers, codes."""
    rng = canvas.rng
    kind = canvas.choice(["words", "words", "number", "code", "date"])
    if kind == "number":
        return f"{rng.integers(1, 1000)}{canvas.choice(['', ' ml', ' g', ' kg', '%', ' mm', ' W', ' V'])}"
    if kind == "code":
        letters = "".join(chr(65 + int(i)) for i in rng.integers(0, 26, int(rng.integers(1, 4))))
        return f"{letters}-{rng.integers(10, 100000)}"
    if kind == "date":
        return f"{rng.integers(1, 13):02d}/{rng.integers(2019, 2031)}"
    text = " ".join(canvas.choice(_WORDS) for _ in range(int(rng.integers(1, 4))))
    case = canvas.choice(["as is", "upper", "lower"])
    return text.upper() if case == "upper" else text.lower() if case == "lower" else text


def _text_width(text: str, height: float, thickness: float, size: int) -> float:
    """Width of ``text`` drawn by ``Canvas.draw_text`` [sample widths]."""
    scale = height * size / 22.0
    (width, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, int(round(thickness * size))))
    return width / size


def _text_lines(canvas: Canvas, mask: np.ndarray, lines: int, height: float, angle: float,
                origin=None, spacing: float = 1.6, max_width: float = 0.9) -> np.ndarray:
    """``lines`` lines of text of letter ``height`` [sample widths] as a block at ``angle`` [rad],
    first baseline at ``origin`` (u, v) (random when None), drawn into ``mask``."""
    weight = height * canvas.uniform(0.07, 0.16)  # stroke width: light to bold
    if origin is None:
        origin = (canvas.uniform(-0.05, 0.6), canvas.uniform(0.05, 0.95))
    down = np.array([-math.sin(angle), math.cos(angle)]) * height * spacing
    for line in range(lines):
        text = _phrase(canvas)
        width = _text_width(text, height, weight, canvas.size)
        letter = height * min(1.0, max_width / max(width, 1e-6))  # keep each line narrower than the sample
        start = np.asarray(origin) + line * down
        canvas.draw_text(mask, text, tuple(start), letter, 1.0, weight * letter / height, angle)
    return mask


class _Layers:
    """The plastic as it is being printed on: height [patch half-widths], planar diffuse (3, H, W)
    and roughness."""

    def __init__(self, height: np.ndarray, diffuse: np.ndarray, roughness: np.ndarray):
        self.height, self.diffuse, self.roughness = height, diffuse, roughness

    def ink(self, mask: np.ndarray, color, roughness_shift: float, thickness: float):
        """Cover ``mask`` with ink of ``color``: its roughness differs a little from the plastic's
        and it stands ``thickness`` [patch half-widths] proud."""
        self.diffuse = self.diffuse + mask * (planar(color) - self.diffuse)
        self.roughness = self.roughness + mask * roughness_shift
        self.height = self.height + mask * thickness


# --- surface finishes ----------------------------------------------------------------------------

def _finish(canvas: Canvas, finish: str) -> tuple[np.ndarray, np.ndarray]:
    """Relief [patch half-widths] and roughness of the moulded surface."""
    if finish in ("glossy", "satin"):
        # Polished mould: only the long, shallow waviness of sink marks and flow shows, in the highlight.
        height = canvas.noise(beta=3.0, low=1, high=canvas.uniform(4, 12)) * canvas.uniform(0.005, 0.03) * MILLIMETRE
        low, high = (0.02, 0.14) if finish == "glossy" else (0.18, 0.38)
        return height, np.full_like(height, canvas.uniform(low, high))
    if finish == "stipple":
        # Spark-eroded (VDI) or bead-blasted mould: dense round bumps, flat-topped when eroded deeper.
        cycles = canvas.uniform(30, 90)
        field = canvas.noise(beta=canvas.uniform(0.0, 1.5), low=cycles * 0.5, high=cycles * 1.5)
        field = smoothstep(-1.5, 1.5, field * canvas.uniform(0.6, 1.5))
        height = field * canvas.uniform(0.02, 0.08) * MILLIMETRE
        return height, canvas.uniform(0.3, 0.65) + 0.06 * (field - 0.5)
    if finish == "leather_grain":
        # Grain textures: pebbles between a network of grooves, the zero set of a band-limited noise.
        cycles = canvas.uniform(12, 45)
        field = canvas.noise(beta=2.0, low=cycles * 0.4, high=cycles * 2.5)
        pebbles = np.sqrt(np.abs(field))
        fine = canvas.noise(beta=0.5, low=60)
        height = (pebbles * canvas.uniform(0.06, 0.2) + 0.004 * fine) * MILLIMETRE
        return height, canvas.uniform(0.35, 0.7) - 0.05 * (pebbles - 0.7)
    # Frosted or soft-touch: a fine matte texture, near-white noise.
    fine = canvas.noise(beta=0.5, low=40)
    return fine * canvas.uniform(0.002, 0.008) * MILLIMETRE, np.full_like(fine, canvas.uniform(0.5, 0.85))


def _plastic_color(canvas: Canvas) -> np.ndarray:
    """Base colour (3,): any hue, from black to white, greys common."""
    saturation = canvas.uniform(0.0, 0.08) if canvas.chance(0.3) else canvas.uniform(0.3, 0.95)
    return hsv_color(canvas.uniform(0, 1), saturation, canvas.uniform(0.08, 0.95))


def _luminance(color) -> float:
    """Relative luminance of a linear colour (3,)."""
    return float(np.dot(np.asarray(color, np.float32).ravel()[:3], constants.LUMINANCE_WEIGHTS))


def _ink_color(canvas: Canvas, against=None) -> np.ndarray:
    """A printing ink (3,): black and white common, otherwise a strong colour. Text printed
    ``against`` a colour is made legible: black or white when the ink would hardly show."""
    kind = canvas.choice(["black", "white", "color", "color", "color"])
    if kind == "black":
        ink = hsv_color(0, 0, canvas.uniform(0.03, 0.15))
    elif kind == "white":
        ink = hsv_color(0, 0, canvas.uniform(0.85, 0.97))
    else:
        ink = hsv_color(canvas.uniform(0, 1), canvas.uniform(0.4, 1.0), canvas.uniform(0.3, 0.95))
    if against is not None:
        light, dark = sorted((_luminance(ink), _luminance(against)), reverse=True)
        if (light + 0.05) / (dark + 0.05) < 2.5:  # too little contrast to read
            ink = hsv_color(0, 0, 0.05) if _luminance(against) > 0.2 else hsv_color(0, 0, 0.92)
    return ink


# --- prints --------------------------------------------------------------------------------------

def _pattern(canvas: Canvas, kind: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """An all-over printed pattern as (coverage mask, ink colour) layers, painted in order."""
    angle = canvas.choice([0.0, 0.0, math.pi / 2, math.pi / 4, canvas.uniform(0, math.pi)])
    if kind == "stripes":
        x, y, pixel = _lattice(canvas, canvas.loguniform(2, 40), angle)
        layers = [(_fill(np.abs(x) - canvas.uniform(0.1, 0.35), pixel), _ink_color(canvas))]
        if canvas.chance(0.4):  # a thinner stripe of a second ink between them
            layers.append((_fill(np.abs(np.abs(x) - 0.5) - canvas.uniform(0.02, 0.08), pixel), _ink_color(canvas)))
        return layers
    if kind == "dots":
        x, y, pixel = _lattice(canvas, canvas.loguniform(3, 40), angle)
        dots = _fill(np.sqrt(x * x + y * y) - canvas.uniform(0.12, 0.4), pixel)
        if canvas.chance(0.5):  # half-drop: a second dot in the middle of every four
            x2, y2 = x - np.round(x + 0.5) + 0.5, y - np.round(y + 0.5) + 0.5
            dots = np.maximum(dots, _fill(np.sqrt(x2 * x2 + y2 * y2) - canvas.uniform(0.05, 0.25), pixel))
        return [(dots, _ink_color(canvas))]
    if kind == "checks":
        x, y, pixel = _lattice(canvas, canvas.loguniform(1.5, 20), angle)
        first, second = _fill(np.abs(x) - 0.25, pixel), _fill(np.abs(y) - 0.25, pixel)
        if canvas.chance(0.5):  # gingham: the overprint of two stripe sets is darker
            return [(0.5 * (first + second), _ink_color(canvas))]
        return [(first + second - 2 * first * second, _ink_color(canvas))]
    if kind == "chevrons":
        x, y, pixel = _lattice(canvas, canvas.loguniform(2, 24), angle)
        amplitude = canvas.uniform(0.3, 1.5)
        zigzag = x + amplitude * np.abs(y) * 2.0
        zigzag = zigzag - np.round(zigzag)
        pixel *= math.sqrt(1 + 4 * amplitude * amplitude)
        return [(_fill(np.abs(zigzag) - canvas.uniform(0.12, 0.3), pixel), _ink_color(canvas))]
    if kind == "floral":
        layers = []
        if canvas.chance(0.6):  # leaves and stems: organic blobs under the flowers
            leaves = canvas.blobs(canvas.uniform(4, 16), sharpness=6.0)
            layers.append((smoothstep(0.55, 0.6, leaves), hsv_color(canvas.uniform(0.2, 0.45), canvas.uniform(0.3, 0.8),
                                                                       canvas.uniform(0.25, 0.7))))
        x, y, pixel = _lattice(canvas, canvas.loguniform(2, 14), angle)
        radius, petals = canvas.uniform(0.25, 0.45), int(canvas.rng.integers(4, 9))
        theta = np.arctan2(y, x)
        outline = radius * (0.55 + 0.45 * np.abs(np.cos(0.5 * petals * theta)) ** canvas.uniform(0.4, 1.5))
        r = np.sqrt(x * x + y * y)
        layers.append((_fill(r - outline, pixel), _ink_color(canvas)))
        layers.append((_fill(r - radius * canvas.uniform(0.12, 0.3), pixel), _ink_color(canvas)))
        return layers
    # Camouflage or abstract blobs: one to three inks, each the high ground of its own smooth field
    # (nested level sets of one field would leave thin rings between the inks).
    cycles, edge = canvas.loguniform(2, 12), canvas.uniform(0.003, 0.02)
    layers = []
    for _ in range(int(canvas.rng.integers(1, 4))):
        field = canvas.blobs(cycles * canvas.uniform(0.7, 1.4), sharpness=canvas.uniform(1.0, 2.5))
        level = canvas.uniform(0.45, 0.65)
        layers.append((smoothstep(level - edge, level + edge, field), _ink_color(canvas)))
    return layers


def _text(canvas: Canvas) -> np.ndarray:
    """Printed text: a block of lines, or lines scattered at several sizes and angles (mask)."""
    mask = np.zeros((canvas.size, canvas.size), np.float32)
    # Every wrapped text line costs nine stamps on a tileable canvas, so fewer lines there.
    most = 3 if canvas.tileable else 7
    if canvas.chance(0.5):
        angle = 0.0 if canvas.chance(0.6) else canvas.uniform(-math.pi / 2, math.pi / 2)
        return _text_lines(canvas, mask, int(canvas.rng.integers(1, most + 1)), canvas.loguniform(0.015, 0.06), angle)
    for _ in range(int(canvas.rng.integers(1, most + 1))):
        angle = canvas.choice([0.0, 0.0, canvas.uniform(-math.pi, math.pi)])
        _text_lines(canvas, mask, 1, canvas.loguniform(0.02, 0.15), angle)
    return mask


def _logo(canvas: Canvas) -> np.ndarray:
    """A printed logo: a ring, disc or rounded box with initials (mask)."""
    size = canvas.uniform(0.08, 0.3)  # radius [sample widths]
    centre = (canvas.uniform(0.2, 0.8), canvas.uniform(0.2, 0.8))
    du, dv = _offset(canvas, centre)
    pixel = 1.0 / canvas.size
    shape = canvas.choice(["ring", "disc", "box"])
    if shape == "box":
        q = np.maximum(np.abs(du), np.abs(dv) * canvas.uniform(1.0, 2.0))
        distance = q - size
    else:
        distance = np.sqrt(du * du + dv * dv) - size
    stroke = size * canvas.uniform(0.06, 0.15)
    mask = _fill(np.abs(distance) - stroke, pixel) if shape != "disc" else _fill(distance, pixel)
    letters = "".join(chr(65 + int(i)) for i in canvas.rng.integers(0, 26, int(canvas.rng.integers(1, 4))))
    height = size * 0.7
    weight = height * canvas.uniform(0.1, 0.2)
    height = min(height, height * 1.4 * size / max(_text_width(letters, height, weight, canvas.size), 1e-6))
    width = _text_width(letters, height, weight, canvas.size)
    initials = canvas.draw_text(np.zeros_like(mask), letters, (centre[0] - width / 2, centre[1] + height / 2),
                                height, 1.0, weight)
    # Initials are cut out of a disc and printed inside a ring or box.
    return mask * (1 - initials) if shape == "disc" else np.maximum(mask, initials)


def _label(canvas: Canvas, layers: _Layers):
    """A stuck-on label: paper or film a tenth of a millimetre thick, printed with text and
    sometimes a barcode."""
    angle = canvas.uniform(-0.3, 0.3)
    centre = (canvas.uniform(0.25, 0.75), canvas.uniform(0.25, 0.75))
    half = np.array([canvas.uniform(0.15, 0.45), canvas.uniform(0.1, 0.35)])  # [sample widths]
    corner = canvas.uniform(0.0, 0.5) * half.min()
    du, dv = _offset(canvas, centre)
    x = du * math.cos(angle) + dv * math.sin(angle)
    y = -du * math.sin(angle) + dv * math.cos(angle)
    qx, qy = np.abs(x) - half[0] + corner, np.abs(y) - half[1] + corner
    distance = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2) + np.minimum(np.maximum(qx, qy), 0) - corner
    pixel = 1.0 / canvas.size
    sheet = _fill(distance, pixel)
    paper = canvas.chance(0.6)
    color = hsv_color(canvas.uniform(0.05, 0.2), canvas.uniform(0.0, 0.15), canvas.uniform(0.8, 0.95)) \
        if canvas.chance(0.7) else _ink_color(canvas)
    # The sheet bridges the texture below it; a paper label is matte, a film label glossy.
    thickness = canvas.uniform(0.05, 0.12) * MILLIMETRE
    layers.height = layers.height * (1 - 0.8 * sheet) + sheet * thickness
    layers.diffuse = layers.diffuse + sheet * (planar(color) - layers.diffuse)
    target = canvas.uniform(0.55, 0.85) if paper else canvas.uniform(0.06, 0.25)
    layers.roughness = layers.roughness + sheet * (target - layers.roughness)
    # Print inside the label's margins: lines of text from the top, a barcode below them.
    inside = _fill(distance + 0.25 * half.min(), pixel)
    barcode = canvas.chance(0.5)
    height = half[1] * canvas.uniform(0.15, 0.3)
    lines = max(1, min(int(canvas.rng.integers(1, 4)), int((0.9 if barcode else 1.6) * half[1] / (1.6 * height))))
    corner_uv = np.array(centre) + np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]) \
        @ np.array([-half[0] * 0.8, -half[1] * 0.7 + height])
    text = _text_lines(canvas, np.zeros_like(sheet), lines, height, angle, origin=tuple(corner_uv), max_width=1.6 * half[0])
    if barcode:  # bars of random widths in the lower part
        bars = canvas.rng.random(48) < 0.5
        left, width = canvas.uniform(-0.8, 0.0) * half[0], canvas.uniform(0.4, 0.75) * half[0]
        position = (x - left) / width
        in_code = (position >= 0) & (position < 1) & (y > half[1] * 0.25) & (y < half[1] * 0.8)
        code = bars[np.clip((position * 48).astype(np.int64), 0, 47)] & in_code
        text = np.maximum(text, code.astype(np.float32))
    layers.ink(text * inside, _ink_color(canvas, color), canvas.uniform(-0.1, 0.1), 0.003 * MILLIMETRE)


def _moulded_text(canvas: Canvas, layers: _Layers):
    """Lettering and marks moulded into the plastic: raised or sunk, the plastic's own colour."""
    mask = _text(canvas)
    if canvas.chance(0.5):
        mask = np.maximum(mask, _logo(canvas))
    depth = canvas.uniform(0.05, 0.2) * MILLIMETRE * canvas.choice([-1.0, 1.0])
    layers.height = layers.height + depth * mask
    # Lettering is often left polished on a textured part, or textured on a polished one.
    layers.roughness = layers.roughness + mask * canvas.uniform(-0.15, 0.15)


_PRINTS = ("none", "none", "stripes", "dots", "checks", "chevrons", "floral", "camouflage",
           "text", "text", "logo", "label", "moulded_text")


@family("plastic")
def plastic(canvas: Canvas) -> Surface:
    finish = canvas.choice(["glossy", "glossy", "satin", "stipple", "leather_grain", "frosted"])
    height, roughness = _finish(canvas, finish)
    base = _plastic_color(canvas)
    diffuse = np.broadcast_to(planar(base), (3, canvas.size, canvas.size))
    if canvas.chance(0.15):  # recycled or speckled plastic: flecks of two other colours
        flecks = canvas.noise(beta=0.0, low=canvas.uniform(40, 100))
        threshold = canvas.uniform(2.0, 3.0)
        for sign in (1.0, -1.0):
            fleck = smoothstep(threshold, threshold + 0.3, sign * flecks)
            diffuse = diffuse + fleck * (planar(_plastic_color(canvas)) - diffuse)
    layers = _Layers(height, diffuse, roughness)

    decoration = canvas.choice(_PRINTS)
    # Ink is a few micrometres thick, glossier or more matte than the plastic.
    ink_roughness, ink_thickness = canvas.uniform(-0.1, 0.15), canvas.uniform(0.001, 0.006) * MILLIMETRE
    if decoration in ("stripes", "dots", "checks", "chevrons", "floral", "camouflage"):
        for mask, color in _pattern(canvas, decoration):
            layers.ink(mask, color, ink_roughness, ink_thickness)
        if canvas.chance(0.25):
            layers.ink(_text(canvas), _ink_color(canvas, base), ink_roughness, ink_thickness)
    elif decoration == "text":
        layers.ink(_text(canvas), _ink_color(canvas, base), ink_roughness, ink_thickness)
    elif decoration == "logo":
        layers.ink(_logo(canvas), _ink_color(canvas, base), ink_roughness, ink_thickness)
        if canvas.chance(0.5):
            layers.ink(_text(canvas), _ink_color(canvas, base), ink_roughness, ink_thickness)
    elif decoration == "label":
        _label(canvas, layers)
    elif decoration == "moulded_text":
        _moulded_text(canvas, layers)

    # Uneven colour and gloss across the sample (only on a plain canvas).
    variant = finish if decoration == "none" else f"{finish}_{decoration}"
    specular = dielectric_f0(canvas, 0.04, 0.05)
    return Surface(height=layers.height.astype(np.float32), diffuse=layers.diffuse.transpose(1, 2, 0),
                   roughness=np.clip(layers.roughness, 0.0, 1.0).astype(np.float32),
                   specular=np.broadcast_to(specular, (canvas.size, canvas.size, 3)), variant=variant)
