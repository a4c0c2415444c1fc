"""Paper and board: office and notebook paper, coloured and watercolour paper, kraft, corrugated
cardboard, newsprint and coated magazine paper; printed text, handwriting, rulings, folds and
crumples.

Paper is matte (roughness 0.6 to 0.95) except coated stock and toner or pen ink, which are
glossier. Its relief is slight: the cloudy formation and fibres (hundredths of a millimetre), the
flutes of corrugated board under the liner, and folds and crumples, which tilt the sheet itself.
Body text is too small to read at the sample's resolution (a line is a few pixels), so it is drawn
procedurally as lines of words ("greeked"); headlines, stamps and handwriting are drawn with the
canvas's text and line primitives. Colours are built in planar (3, H, W) layout, which numpy
broadcasts much faster than (H, W, 3), and handed back as an (H, W, 3) view.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import MILLIMETRE, Canvas, Surface, dielectric_f0, hsv_color, planar, smoothstep
from ..registry import family

#: Words for headlines and stamps.
_HEADLINES = ("NEWS", "Weekly", "The Times", "REPORT", "Chapter", "Summary", "Notes", "INVOICE", "Dear",
              "Minutes", "Agenda", "Recipe", "Travel", "Science", "Sport", "Markets", "Opinion", "Letters",
              "Fashion", "Interview", "Spring", "Contents", "Page", "Part", "Exclusive", "Review")
_STAMPS = ("FRAGILE", "THIS SIDE UP", "HANDLE WITH CARE", "KEEP DRY", "MADE IN", "RECYCLABLE", "BOX",
           "NET", "No.", "LOT", "PRIORITY", "OPEN HERE", "TOP", "DO NOT STACK")


def _wave(canvas: Canvas, cycles: float, angle: float) -> tuple[np.ndarray, float]:
    """Phase [cycles] of a plane wave of ``cycles`` per sample along ``angle`` [rad] and its
    wave number [cycles per sample]; the wave vector is whole on a tileable canvas, so it wraps."""
    ku, kv = cycles * math.cos(angle), cycles * math.sin(angle)
    if canvas.tileable:
        ku, kv = float(round(ku)), float(round(kv))
        ku = ku if (ku, kv) != (0.0, 0.0) else 1.0
    return canvas.u * ku + canvas.v * kv, math.hypot(ku, kv)


def _paper_color(canvas: Canvas, kind: str) -> np.ndarray:
    """Stock colour (3,): bright white (optical brighteners look slightly blue), cream, grey
    recycled, newsprint, kraft brown or a dyed colour."""
    if kind == "white":
        return hsv_color(canvas.uniform(0.55, 0.65), canvas.uniform(0.0, 0.04), canvas.uniform(0.88, 0.97))
    if kind == "cream":
        return hsv_color(canvas.uniform(0.1, 0.15), canvas.uniform(0.06, 0.2), canvas.uniform(0.85, 0.95))
    if kind == "recycled":
        return hsv_color(canvas.uniform(0.08, 0.15), canvas.uniform(0.03, 0.1), canvas.uniform(0.7, 0.85))
    if kind == "newsprint":
        return hsv_color(canvas.uniform(0.1, 0.15), canvas.uniform(0.05, 0.14), canvas.uniform(0.72, 0.86))
    if kind == "kraft":
        return hsv_color(canvas.uniform(0.065, 0.1), canvas.uniform(0.35, 0.62), canvas.uniform(0.45, 0.75))
    return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.3, 0.85), canvas.uniform(0.3, 0.9))


def _ink_color(canvas: Canvas) -> np.ndarray:
    """Printing or writing ink (3,): mostly black, else blue, red or a colour."""
    kind = canvas.choice(["black", "black", "black", "blue", "red", "color"])
    if kind == "black":
        return hsv_color(0.6, canvas.uniform(0.0, 0.2), canvas.uniform(0.04, 0.18))
    if kind == "blue":
        return hsv_color(canvas.uniform(0.6, 0.68), canvas.uniform(0.6, 0.95), canvas.uniform(0.3, 0.65))
    if kind == "red":
        return hsv_color(canvas.uniform(0.97, 1.02), canvas.uniform(0.6, 0.95), canvas.uniform(0.5, 0.85))
    return hsv_color(canvas.uniform(0, 1), canvas.uniform(0.5, 1.0), canvas.uniform(0.3, 0.8))


def _sheet(canvas: Canvas, fibre_relief: float, cloudiness: float) -> tuple[np.ndarray, np.ndarray]:
    """The sheet's own texture: (relief [patch half-widths], albedo factor around 1).

    Formation (flocs of fibres, a cloudy look in transmitted light) and single fibres, mostly
    along the machine direction. ``fibre_relief`` [mm] sets the fibres' relief, ``cloudiness`` the
    formation's albedo contrast.
    """
    formation = canvas.noise(beta=2.0, low=2, high=canvas.uniform(25, 60))
    fibres = canvas.noise(beta=1.0, low=30, stretch=canvas.uniform(1.5, 5.0), angle=canvas.uniform(0, math.pi))
    height = (0.3 * formation + fibres) * fibre_relief * MILLIMETRE
    albedo = 1.0 + cloudiness * formation + 0.25 * cloudiness * fibres
    return height, albedo


# --- shape of the sheet ---------------------------------------------------------------------------

def _folds(canvas: Canvas) -> tuple[np.ndarray, np.ndarray]:
    """A sheet folded and opened again: (relief [patch half-widths], crease lines in [0, 1]).

    Each fold is a sharp crease with the sheet rising or falling away from it at a few degrees. On
    a tileable canvas the folds repeat as a zigzag along a whole wave vector (an accordion).
    """
    height = np.zeros((canvas.size, canvas.size), np.float32)
    crease = np.zeros_like(height)
    sharpness = canvas.uniform(0.5, 2.0) / canvas.size  # crease rounding [sample widths]
    for _ in range(int(canvas.rng.integers(1, 3))):
        slope = canvas.uniform(0.03, 0.15) * canvas.choice([-1.0, 1.0])
        angle = canvas.uniform(0, math.pi)
        if canvas.tileable:
            phase, wavenumber = _wave(canvas, canvas.uniform(1, 2.5), angle)
            distance = np.abs(phase - np.round(phase)) / wavenumber  # to the nearest crease [sample widths]
            ridge = np.sqrt(distance * distance + sharpness * sharpness)
            line = np.minimum(distance, 0.5 / wavenumber - distance)  # both zigzag corners are creases
        else:
            distance = (canvas.u - canvas.uniform(0.1, 0.9)) * math.cos(angle) + (canvas.v - canvas.uniform(0.1, 0.9)) * math.sin(angle)
            ridge = np.sqrt(distance * distance + sharpness * sharpness)
            line = np.abs(distance)
        height += slope * 2.0 * ridge  # 2: sample widths to patch half-widths
        crease = np.maximum(crease, np.exp(-(line * canvas.size / canvas.uniform(0.7, 1.5)) ** 2))
    return height, crease


def _crumples(canvas: Canvas) -> tuple[np.ndarray, np.ndarray]:
    """A crumpled sheet flattened again: flat facets between straight creases, (relief [patch
    half-widths], crease lines in [0, 1]).

    Each Voronoi cell is a hip roof (height proportional to the distance to the cell's border),
    pushed up or down by a random amount: the surface stays continuous, with valleys along the
    cell borders and ridges along each cell's medial axis, all straight.
    """
    count = canvas.frequency(canvas.uniform(3, 9))
    _, label, edge = canvas.cells(canvas.jittered_points(int(count), canvas.uniform(0.6, 1.0)))
    slopes = canvas.rng.uniform(0.05, 0.35, label.max() + 1) * canvas.rng.choice([-1.0, 1.0], label.max() + 1)
    height = (slopes.astype(np.float32)[label] * edge * 2.0)  # 2: sample widths to patch half-widths
    crease = np.exp(-(edge * canvas.size / canvas.uniform(0.7, 1.5)) ** 2)
    return height, crease


# --- printing and writing -------------------------------------------------------------------------

def _body_text(canvas: Canvas, pitch: float, columns: int = 1, angle: float = 0.0,
               block=(0.0, 0.0, 1.0, 1.0)) -> np.ndarray:
    """Greeked body text: lines of words of ink coverage, as an (H, W) mask.

    ``pitch`` is the line spacing [sample widths]; letters are a fraction of it wide. Words,
    paragraph ends and blank lines come from per-line and per-letter random numbers. ``columns``
    splits the block into columns; ``block`` (u0, v0, u1, v1) limits the text on a plain canvas
    (the whole sample on a tileable one, where lines, letters and columns are whole numbers).
    """
    u, v = canvas.u, canvas.v
    if angle and not canvas.tileable:  # a page photographed slightly askew
        c, s = math.cos(angle), math.sin(angle)
        u, v = 0.5 + (u - 0.5) * c + (v - 0.5) * s, 0.5 - (u - 0.5) * s + (v - 0.5) * c
    lines = canvas.frequency(1.0 / pitch)
    letters = canvas.frequency(lines / canvas.uniform(0.3, 0.5))
    columns = int(canvas.frequency(columns)) if canvas.tileable else columns
    # Lines, letters and columns start anywhere, not on the sample's edge; on a tileable canvas
    # their counts are whole and their indices wrap round.
    line_f, letter_f = v * lines + canvas.uniform(0, 1), u * letters + canvas.uniform(0, 1)
    line, letter = np.floor(line_f).astype(np.int64), np.floor(letter_f).astype(np.int64)
    n_lines, n_letters = (int(lines), int(letters)) if canvas.tileable else (int(lines) + 3, int(letters) + 3)
    line, letter = line % n_lines, letter % n_letters
    within = line_f - np.floor(line_f)  # position down the line [line pitches]

    rng = canvas.rng
    glyph = rng.random((n_lines, n_letters)).astype(np.float32)[line, letter]
    space = canvas.uniform(0.14, 0.22)
    # Paragraphs: a line ends early or is blank now and then.
    line_end = np.where(rng.random(n_lines) < 0.15, rng.uniform(0.05, 0.9, n_lines), 1.0).astype(np.float32)
    line_end[rng.random(n_lines) < 0.04] = 0.0
    x_height = canvas.uniform(0.28, 0.42)
    pixel = lines / canvas.size  # one pixel [line pitches]
    tall = glyph > 0.8  # ascenders and capitals reach higher
    top = 0.5 - x_height / 2 - np.where(tall, 0.2, 0.0)
    band = smoothstep(top - pixel, top, within) * smoothstep(0.5 + x_height / 2 + pixel, 0.5 + x_height / 2, within)
    # Ink per letter cell: strokes are thinner than a pixel, so a letter covers only part of its
    # cell, more for bold type; letters differ, spaces are empty, stems show when letters are large.
    coverage = canvas.uniform(0.45, 0.8)
    inside_letter = letter_f - np.floor(letter_f)
    density = np.where(glyph < space, 0.0, coverage * (0.6 + 0.4 * glyph)) * \
        (0.75 + 0.25 * np.cos(2 * math.pi * (2 * inside_letter + 3 * glyph)))

    column_f = u * columns + canvas.uniform(0, 1)
    in_column = column_f - np.floor(column_f)
    gutter = canvas.uniform(0.04, 0.1) if columns > 1 else 0.0
    along = in_column / (1.0 - gutter)  # position along the line [column widths]
    inside = (along < line_end[line]).astype(np.float32)
    if not canvas.tileable:
        u0, v0, u1, v1 = block
        inside *= (u >= u0) & (u < u1) & (v >= v0) & (v < v1)
    return (band * density * inside).astype(np.float32)


def _headlines(canvas: Canvas, mask: np.ndarray, words=_HEADLINES, count: int = 1, angle: float = 0.0) -> np.ndarray:
    """A few lines of large text (headlines, stamps) at random places, drawn into ``mask``."""
    for _ in range(count):
        text = " ".join(canvas.choice(words) for _ in range(int(canvas.rng.integers(1, 3))))
        letter = canvas.loguniform(0.04, 0.12)  # letter height [sample widths]
        start = (canvas.uniform(-0.05, 0.5), canvas.uniform(0.1, 0.95))
        # Keep the line shorter than the sample so that its wrapped copies meet.
        letter = min(letter, 0.9 / (0.85 * max(len(text), 1)))
        canvas.draw_text(mask, text, start, letter, 1.0, letter * canvas.uniform(0.08, 0.18), angle)
    return mask


def _handwriting(canvas: Canvas, lines: int, pitch: float, top: float, left: float) -> np.ndarray:
    """Cursive-like writing: per line a looping stroke (a prolate trochoid) with words, letters
    of random heights and a wandering baseline, as an (H, W) mask.

    The strokes stay inside the sample, so they are drawn without wrapped copies even on a tileable
    canvas: seamless, and nine times cheaper than the wrapped drawing.
    """
    flat = Canvas(canvas.size, canvas.rng, tileable=False)
    mask = np.zeros((canvas.size, canvas.size), np.float32)
    rng = canvas.rng
    x_height = pitch * canvas.uniform(0.25, 0.45)
    advance = x_height * canvas.uniform(0.7, 1.1)  # per letter [sample widths]
    slant = canvas.uniform(-0.1, 0.4)
    loop = canvas.uniform(0.2, 0.45)  # above 1 / (2 pi) the stroke loops back on itself
    starts, ends = [], []
    for line in range(lines):
        baseline = top + line * pitch
        if baseline > 0.95:
            break
        count = int((0.95 - left) / advance * canvas.uniform(0.4, 1.0))
        steps = 5 * count  # five points per letter: enough for a loop, and few segments to draw
        s = np.arange(steps + 1) / 5.0
        heights = np.where(rng.random(count + 1) < 0.2, 2.2, 1.0) * rng.uniform(0.8, 1.2, count + 1)
        rise = x_height * heights[np.minimum(s.astype(int), count)] * (0.5 - 0.5 * np.cos(2 * math.pi * s))
        wander = np.cumsum(rng.normal(0, 0.03 * x_height, steps + 1))
        x = left + advance * s + loop * advance * np.sin(2 * math.pi * s) + slant * rise
        y = baseline + wander - rise
        points = np.stack([x, y], -1)
        spaces = rng.random(count + 1) < 0.18  # the pen lifts between words
        keep = ~spaces[s[:-1].astype(int)] & (x[1:] < 0.97)
        starts.append(points[:-1][keep])
        ends.append(points[1:][keep])
    if starts:
        starts, ends = np.concatenate(starts), np.concatenate(ends)
        inside = (starts.min(1) > 0.01) & (starts.max(1) < 0.99) & (ends.min(1) > 0.01) & (ends.max(1) < 0.99)
        flat.draw_lines(mask, starts[inside], ends[inside], canvas.uniform(0.6, 1.0), canvas.uniform(0.8, 2.0) / canvas.size)
    return mask


def _rulings(canvas: Canvas) -> tuple[np.ndarray, np.ndarray, float]:
    """Notebook rulings: (blue lines or squares, red margin line) as coverage masks, and the
    number of lines per sample."""
    pitch = canvas.uniform(0.035, 0.06)  # 5 to 9 mm on a 15 cm sample [sample widths]
    width = canvas.uniform(0.3, 0.8)  # [pixels]: printed lines are thinner than a pixel
    lines = canvas.frequency(1.0 / pitch)

    def line_mask(phase, per_sample, width):
        """Coverage of lines ``width`` pixels wide where ``phase`` (``per_sample`` cycles per
        sample) is whole."""
        distance = np.abs(phase - np.round(phase)) * canvas.size / per_sample  # [pixels]
        return np.clip(width + 0.5 - distance, 0.0, 1.0) * min(1.0, width)

    rows = line_mask(canvas.v * lines, lines, width)
    if canvas.chance(0.35):  # squared paper
        rows = np.maximum(rows, line_mask(canvas.u * lines, lines, width))
    margin = np.zeros_like(rows)
    if canvas.chance(0.5):  # one margin line per sample: wraps on a tileable canvas
        margin = line_mask(canvas.u - canvas.uniform(0.1, 0.3), 1.0, canvas.uniform(0.8, 1.5))
    return rows, margin, lines


def _photo(canvas: Canvas) -> np.ndarray:
    """Printed picture content, planar (3, H, W): a backdrop graded between two colours (sky and
    ground, a studio sweep), a few soft shapes over it, fine detail."""
    palette = [hsv_color(canvas.uniform(0, 1), canvas.uniform(0.1, 0.9), canvas.uniform(0.1, 0.95)) for _ in range(3)]
    angle = canvas.uniform(0, 2 * math.pi) if not canvas.tileable else 0.0
    if canvas.tileable:  # a periodic gradation
        ramp = 0.5 + 0.5 * np.sin(2 * math.pi * canvas.v)
    else:
        ramp = np.clip(0.5 + (canvas.u - 0.5) * math.cos(angle) + (canvas.v - 0.5) * math.sin(angle), 0, 1)
    image = planar(palette[0]) + ramp * (planar(palette[1]) - planar(palette[0]))
    shapes = smoothstep(0.55, 0.7, canvas.blobs(canvas.loguniform(1.5, 5), sharpness=canvas.uniform(1, 3)))
    detail = canvas.noise(beta=2.2, low=4, high=90)
    image = image + shapes * (planar(palette[2]) * (1.0 + 0.2 * detail) - image)
    return image * (1.0 + 0.08 * detail)


# --- the family ---------------------------------------------------------------------------------

@family("paper")
def paper(canvas: Canvas) -> Surface:
    variant = canvas.choice(["office", "office", "notebook", "coloured", "watercolour", "kraft",
                             "cardboard", "cardboard", "newsprint", "magazine", "magazine"])
    size = canvas.size
    ink = np.zeros((size, size), np.float32)  # coverage of the main ink
    ink_color = _ink_color(canvas)
    ink_roughness = None  # ink roughness when it differs from the paper's
    extra = []  # further inks: (coverage, colour)
    tint = 1.0  # transparent paint over the paper: a planar factor on its colour

    if variant in ("office", "newsprint"):
        stock = "newsprint" if variant == "newsprint" else canvas.choice(["white", "white", "cream", "recycled"])
        color = _paper_color(canvas, stock)
        height, albedo = _sheet(canvas, canvas.uniform(0.005, 0.02), canvas.uniform(0.01, 0.05))
        roughness = canvas.uniform(0.7, 0.95)
        if variant == "newsprint" or canvas.chance(0.7):
            pitch = canvas.uniform(0.015, 0.04)
            columns = int(canvas.rng.integers(2, 5)) if variant == "newsprint" else canvas.choice([1, 1, 2])
            margin = (canvas.uniform(-0.2, 0.3), canvas.uniform(-0.2, 0.3), canvas.uniform(0.7, 1.2), canvas.uniform(0.7, 1.2))
            ink = _body_text(canvas, pitch, columns, canvas.uniform(-0.05, 0.05), margin)
            if canvas.chance(0.4):
                _headlines(canvas, ink, count=int(canvas.rng.integers(1, 3)))
            ink_color = hsv_color(0.6, canvas.uniform(0.0, 0.15), canvas.uniform(0.04, 0.15))
            # Laser toner is fused plastic, glossier than the paper; offset ink soaks in.
            ink_roughness = canvas.uniform(0.35, 0.55) if variant == "office" else None
    elif variant == "notebook":
        color = _paper_color(canvas, canvas.choice(["white", "cream", "recycled"]))
        height, albedo = _sheet(canvas, canvas.uniform(0.005, 0.02), canvas.uniform(0.01, 0.04))
        roughness = canvas.uniform(0.65, 0.9)
        rows, margin, lines = _rulings(canvas)
        extra += [(rows, hsv_color(canvas.uniform(0.53, 0.62), canvas.uniform(0.3, 0.7), canvas.uniform(0.6, 0.9))),
                  (margin, hsv_color(canvas.uniform(0.95, 1.0), canvas.uniform(0.5, 0.8), canvas.uniform(0.7, 0.95)))]
        # Writing sits on the rulings, just above a line.
        first = (int(canvas.rng.integers(1, max(2, int(lines * 0.4)))) - 0.08) / lines
        ink = _handwriting(canvas, int(canvas.rng.integers(2, 10)), 1.0 / lines, first, canvas.uniform(0.03, 0.3))
        if canvas.chance(0.3):  # pencil: graphite is grey and shinier than the paper
            ink_color = hsv_color(0.6, 0.03, canvas.uniform(0.25, 0.45))
            ink_roughness = canvas.uniform(0.3, 0.5)
        else:  # ballpoint or fountain pen
            ink_color = _ink_color(canvas)
            ink_roughness = canvas.uniform(0.4, 0.7) if canvas.chance(0.5) else None
    elif variant in ("coloured", "watercolour"):
        color = _paper_color(canvas, "dyed" if variant == "coloured" else canvas.choice(["white", "cream"]))
        relief = canvas.uniform(0.01, 0.04) if variant == "coloured" else canvas.uniform(0.04, 0.12)
        height, albedo = _sheet(canvas, relief, canvas.uniform(0.02, 0.08))
        roughness = canvas.uniform(0.75, 0.95)
        if variant == "watercolour":  # cold-pressed: a felt texture of rounded bumps
            height = height + canvas.noise(beta=2.5, low=canvas.uniform(8, 20), high=90) * relief * MILLIMETRE
            if canvas.chance(0.5):  # a transparent wash of paint laid with a broad brush
                # Brush-stroke shaped (stretched) areas, mottled where pigment settled in the paper's
                # texture, darker along the edge where the wash dried.
                wash = canvas.noise(beta=3.0, low=1, high=12, stretch=canvas.uniform(1.5, 4), angle=canvas.uniform(0, math.pi))
                wash = wash + 0.15 * (albedo - 1.0) / 0.05
                level = canvas.uniform(-0.8, 0.5)
                inside = smoothstep(level, level + 0.08, wash)
                rim = np.exp(-((wash - level - 0.08) / 0.06) ** 2) * inside
                amount = inside * canvas.uniform(0.25, 0.7) * (0.7 + 0.3 * smoothstep(-1, 1, wash - level)) + 0.25 * rim
                pigment = hsv_color(canvas.uniform(0, 1), canvas.uniform(0.3, 0.8), canvas.uniform(0.4, 0.9))
                tint = 1.0 + np.clip(amount, 0, 1) * (planar(pigment) - 1.0)
    elif variant == "kraft":
        color = _paper_color(canvas, "kraft")
        height, albedo = _sheet(canvas, canvas.uniform(0.01, 0.03), canvas.uniform(0.04, 0.1))
        roughness = canvas.uniform(0.7, 0.92)
    elif variant == "cardboard":
        color = _paper_color(canvas, "kraft" if canvas.chance(0.8) else "white")
        height, albedo = _sheet(canvas, canvas.uniform(0.01, 0.03), canvas.uniform(0.03, 0.1))
        roughness = canvas.uniform(0.75, 0.95)
        # The flutes under the liner: 3 to 8 mm apart, their crests and glue lines show through.
        phase, _ = _wave(canvas, canvas.uniform(20, 45), canvas.choice([0.0, math.pi / 2]) + canvas.uniform(-0.02, 0.02))
        flutes = 0.5 + 0.5 * np.cos(2 * math.pi * phase)
        height = height + flutes * canvas.uniform(0.05, 0.2) * MILLIMETRE
        albedo = albedo * (1.0 - canvas.uniform(0.0, 0.06) * flutes ** 8)
        if canvas.chance(0.6):  # flexo-printed box markings, faded in patches
            stamps = _headlines(canvas, ink, _STAMPS, count=int(canvas.rng.integers(1, 3)),
                                angle=canvas.choice([0.0, 0.0, math.pi / 2]))
            ink = stamps * np.clip(0.6 + 0.6 * canvas.noise(beta=1.0, low=8, high=60), 0, 1)
            ink_color = _ink_color(canvas)
    else:  # magazine: coated paper, pictures and columns of text, glossy or silk
        color = _paper_color(canvas, "white")
        height, albedo = _sheet(canvas, canvas.uniform(0.002, 0.006), canvas.uniform(0.0, 0.01))
        roughness = canvas.uniform(0.12, 0.35) if canvas.chance(0.6) else canvas.uniform(0.35, 0.55)
        picture = _photo(canvas)
        if canvas.tileable or canvas.chance(0.4):  # the whole sample is a picture
            frame = np.ones((size, size), np.float32)
        else:
            u0, v0 = canvas.uniform(-0.3, 0.4), canvas.uniform(-0.3, 0.4)
            frame = ((canvas.u >= u0) & (canvas.u < u0 + canvas.uniform(0.4, 1.0)) &
                     (canvas.v >= v0) & (canvas.v < v0 + canvas.uniform(0.4, 1.0))).astype(np.float32)
            ink = _body_text(canvas, canvas.uniform(0.015, 0.03), int(canvas.rng.integers(1, 4))) * (1 - frame)
            ink_color = _ink_color(canvas)
        color = planar(color) + frame * (picture - planar(color))
        if canvas.chance(0.4):  # a title over the page
            extra.append((_headlines(canvas, np.zeros((size, size), np.float32)), _ink_color(canvas)))

    diffuse = planar(color) * albedo * tint
    for coverage, printed in extra:
        diffuse = diffuse + coverage * (planar(printed) * albedo - diffuse)
    diffuse = diffuse + ink * (planar(ink_color) - diffuse)
    roughness = roughness + canvas.uniform(-0.5, 0.5) * (albedo - 1.0)  # denser flocs are smoother or rougher
    if ink_roughness is not None:
        roughness = roughness + ink * (ink_roughness - roughness)
    height = height + ink * canvas.uniform(0.002, 0.01) * MILLIMETRE  # toner and ink lie on top

    # Folds and crumples tilt the sheet; creases break the fibres, which look paler.
    shape = canvas.choice(["flat", "flat", "flat", "folded", "crumpled"] if variant not in ("cardboard", "magazine")
                          else ["flat", "flat", "flat", "flat", "folded"])
    if shape != "flat":
        relief, crease = _folds(canvas) if shape == "folded" else _crumples(canvas)
        height = height + relief
        whitening = crease * (canvas.uniform(0.05, 0.3) if shape == "folded" else canvas.uniform(0.0, 0.08))
        diffuse = diffuse + whitening * (0.85 - diffuse)
        roughness = roughness + whitening * 0.1
        variant = f"{variant}_{shape}"

    # Uneven colour and gloss across the sample (only on a plain canvas).
    # Coating (clay and latex) reflects a little more than bare cellulose fibres and air.
    specular = dielectric_f0(canvas, 0.04, 0.05) if variant.startswith("magazine") else dielectric_f0(canvas, 0.03, 0.045)
    return Surface(height=np.asarray(height, np.float32), diffuse=np.broadcast_to(diffuse, (3, size, size)).transpose(1, 2, 0),
                   roughness=np.clip(np.broadcast_to(roughness, (size, size)), 0.0, 1.0).astype(np.float32),
                   specular=np.broadcast_to(specular, (size, size, 3)), variant=variant)
