"""Building blocks of the procedural generator: the canvas, noise, cells, drawing, colour, surfaces.

Every material is built on a ``Canvas``: the sample seen as the unit square [0, 1)^2 in texture
coordinates (u to the right, v down the image rows) at some pixel size, with one seeded
``np.random.Generator`` and a ``tileable`` flag. Every primitive here is periodic on the unit
square when the canvas is tileable, so a family that builds only from these primitives tiles
without a seam. Frequencies are in cycles (or cells) per sample width.

A family returns a ``Surface``: height [patch half-widths], linear diffuse and specular albedo and
roughness, all (H, W[, 3]) float32 numpy arrays in image layout. Normals come from the height at
the end (``height_to_normal``). The numbers follow docs/ARCHITECTURE.md section 3: the sample spans 2 patch half-widths
(about 15 cm in a typical phone capture, so 1 mm of relief is about 0.013).

Speed matters (at least 20 materials per second at 256^2 on one core), so noise is spectral
(one inverse FFT per field) and cells and distances use OpenCV's distance transform.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import cv2
import numpy as np

#: Smallest side of a procedural material [pixels].
MIN_SIZE = 8

#: OpenCV 5 draws text into 8-bit images only (4.x, the pinned version, takes float32 too); a
#: machine with another OpenCV, such as a GPU server's image, still generates the same families.
_OPENCV_TEXT_NEEDS_BYTES = int(cv2.__version__.split(".")[0]) >= 5

#: Relief that one millimetre of height corresponds to on a typical 15 cm sample [patch half-widths].
MILLIMETRE = 2.0 / 150.0

#: Specular albedo (F0, linear RGB) of common metals, from measured refractive indices.
METALS = {
    "silver": (0.97, 0.96, 0.91), "aluminium": (0.91, 0.92, 0.92), "gold": (1.00, 0.78, 0.34),
    "copper": (0.96, 0.64, 0.54), "brass": (0.91, 0.78, 0.42), "bronze": (0.80, 0.58, 0.38),
    "iron": (0.56, 0.57, 0.58), "steel": (0.63, 0.62, 0.60), "chromium": (0.55, 0.56, 0.55),
    "nickel": (0.66, 0.61, 0.53), "titanium": (0.54, 0.50, 0.45), "zinc": (0.66, 0.68, 0.70),
}


def srgb_to_linear(values) -> np.ndarray:
    """sRGB-encoded colour [0, 1] to linear (the IEC 61966-2-1 curve), as float32."""
    x = np.asarray(values, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def hsv_color(hue: float, saturation: float, value: float) -> np.ndarray:
    """Linear RGB of an sRGB colour given in HSV [0, 1]: what a person would pick on screen."""
    return srgb_to_linear(colorsys.hsv_to_rgb(hue % 1.0, saturation, value))


def planar(color) -> np.ndarray:
    """A colour (3,) or a grey value as (3, 1, 1), to broadcast over planar (3, H, W) images;
    a (3, H, W) image passes through."""
    color = np.asarray(color, np.float32)
    return color if color.ndim == 3 else np.broadcast_to(color, (3,)).reshape(3, 1, 1)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def normalized(field: np.ndarray) -> np.ndarray:
    """Affinely rescale a field to [0, 1] (constant fields become 0.5)."""
    low, high = float(field.min()), float(field.max())
    if high - low < 1e-12:
        return np.full_like(field, 0.5)
    return (field - low) / (high - low)


@dataclass
class Surface:
    """What a family produces, before normals: image layout, float32.

    Attributes:
        height: (H, W) relief [patch half-widths].
        diffuse: (H, W, 3) linear diffuse albedo [0, 1].
        roughness: (H, W) GGX roughness [0, 1], alpha = r^2.
        specular: (H, W, 3) linear specular albedo F0 [0, 1].
        variant: what the family made, e.g. ``bricks`` (kept in the material's provenance).
    """

    height: np.ndarray
    diffuse: np.ndarray
    roughness: np.ndarray
    specular: np.ndarray
    variant: str = ""

    def blend(self, other: "Surface", mask: np.ndarray) -> "Surface":
        """``other`` where ``mask`` is 1, ``self`` where it is 0, linearly in between."""
        m = mask.astype(np.float32)
        m3 = m[..., None]
        return Surface(height=self.height * (1 - m) + other.height * m,
                       diffuse=self.diffuse * (1 - m3) + other.diffuse * m3,
                       roughness=self.roughness * (1 - m) + other.roughness * m,
                       specular=self.specular * (1 - m3) + other.specular * m3, variant=self.variant)

    def clipped(self) -> "Surface":
        """Values clipped to [0, 1] and made plausible where blending mixed metal and dielectric:
        an F0 below 0.1 (a dielectric's) is grey, and where F0 is a metal's the diffuse is dark."""
        diffuse = np.clip(self.diffuse, 0, 1)
        specular = np.clip(self.specular, 0, 1)
        f0 = specular.mean(axis=-1, keepdims=True)
        specular = np.where(f0 < 0.1, f0, specular)
        metal = smoothstep(0.3, 0.5, f0)
        diffuse = diffuse * (1 - metal) + np.minimum(diffuse, 0.04) * metal
        return Surface(self.height.astype(np.float32), diffuse.astype(np.float32),
                       np.clip(self.roughness, 0, 1).astype(np.float32), specular.astype(np.float32), self.variant)


class Canvas:
    """The sample as a periodic (when ``tileable``) unit square sampled on ``size`` x ``size`` pixels.

    Attributes:
        size: width and height [pixels].
        rng: the one random generator every primitive draws from, in call order.
        tileable: whether every primitive wraps around the square's edges.
        u, v: (H, W) pixel-centre coordinates in [0, 1): u along columns, v along rows (down).
    """

    #: Highest spectral frequency whose coefficients do not depend on the resolution [cycles].
    FIXED_BAND = 64

    def __init__(self, size: int, rng: np.random.Generator, tileable: bool = False):
        if size < MIN_SIZE:
            raise ValueError(f"procedural materials need at least {MIN_SIZE} pixels, got {size}")
        self.size, self.rng, self.tileable = size, rng, tileable
        axis = (np.arange(size, dtype=np.float32) + 0.5) / size
        self.u = np.broadcast_to(axis[None, :], (size, size))
        self.v = np.broadcast_to(axis[:, None], (size, size))
        frequencies = np.fft.fftfreq(size, 1.0 / size).astype(np.float32)
        self._kx = np.fft.rfftfreq(size, 1.0 / size).astype(np.float32)[None, :]
        self._ky = frequencies[:, None]

    # --- randomness helpers ---------------------------------------------------------------------

    def uniform(self, low: float = 0.0, high: float = 1.0) -> float:
        return float(self.rng.uniform(low, high))

    def loguniform(self, low: float, high: float) -> float:
        return float(math.exp(self.rng.uniform(math.log(low), math.log(high))))

    def chance(self, probability: float) -> bool:
        return bool(self.rng.random() < probability)

    def choice(self, options):
        return options[int(self.rng.integers(len(options)))]

    def ramp(self) -> np.ndarray | float:
        """A linear ramp across the sample in a random direction, about [-1, 1]; 0 when tileable."""
        if self.tileable:
            return 0.0
        angle = self.uniform(0, 2 * math.pi)
        return 2.0 * ((self.u - 0.5) * math.cos(angle) + (self.v - 0.5) * math.sin(angle))

    def frequency(self, cycles: float) -> float:
        """A frequency [cycles per sample] that tiles: whole numbers on a tileable canvas."""
        return float(max(1, round(cycles))) if self.tileable else float(cycles)

    # --- noise ----------------------------------------------------------------------------------

    def noise(self, beta: float = 2.0, low: float = 1.0, high: float | None = None,
              stretch: float = 1.0, angle: float = 0.0) -> np.ndarray:
        """Gaussian noise with a power-law spectrum, zero mean and unit variance, periodic.

        The power spectrum is P(k) ~ |k|^-beta between ``low`` and ``high`` cycles per sample, zero
        elsewhere (beta = 2 to 3: natural, fBm-like relief; beta = 0: white noise in the band).
        ``stretch`` > 1 elongates features along ``angle`` [rad] (grain, brushing, fibres).
        Coefficients up to ``FIXED_BAND`` cycles come first from the generator, so a larger
        canvas draws the same coarse structure and only adds finer detail.
        """
        size = self.size
        band = min(size // 2, self.FIXED_BAND)
        coefficients = np.empty((size, size // 2 + 1), dtype=np.complex64)
        rows = np.r_[0:band, size - band:size]
        coefficients[rows, : band + 1] = _complex_normal(self.rng, (2 * band, band + 1))
        # Finer detail comes from a generator of its own, so the main one advances by the same
        # amount at every resolution and later draws stay the same.
        detail = np.random.default_rng(int(self.rng.integers(2**63)))
        if size // 2 > band:
            coefficients[band:size - band, :] = _complex_normal(detail, (size - 2 * band, size // 2 + 1))
            coefficients[rows, band + 1:] = _complex_normal(detail, (2 * band, size // 2 - band))
        cos_a, sin_a = math.cos(angle), math.sin(angle)
        along = self._kx * cos_a + self._ky * sin_a
        across = -self._kx * sin_a + self._ky * cos_a
        high = high if high is not None else size / 2
        radius2 = np.maximum((along * stretch) ** 2 + across**2, 1e-12)
        amplitude = np.where((radius2 >= low * low) & (radius2 <= high * high), radius2 ** np.float32(-beta / 4.0), 0)
        field = np.fft.irfft2(coefficients * amplitude, s=(size, size))
        std = float(field.std())
        return ((field - field.mean()) / std if std > 0 else field).astype(np.float32)

    def blobs(self, cycles: float, sharpness: float = 1.0) -> np.ndarray:
        """Smooth band-limited noise around ``cycles`` per sample, mapped to [0, 1]."""
        field = self.noise(beta=1.0, low=max(1.0, cycles * 0.5), high=cycles * 2.0)
        return 1.0 / (1.0 + np.exp(-sharpness * 1.7 * field))

    def warp(self, field: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """``field`` sampled at (u + du, v + dv) [sample widths], wrapping around, bilinear."""
        size = self.size
        map_x = (self.u + du) * size - 0.5
        map_y = (self.v + dv) * size - 0.5
        return cv2.remap(field.astype(np.float32), map_x.astype(np.float32), map_y.astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def blur(self, field: np.ndarray, sigma: float) -> np.ndarray:
        """Gaussian blur of ``sigma`` sample widths, wrapping around on a tileable canvas.

        (OpenCV's blur cannot wrap, so a tileable field is padded with its own opposite edges.)
        """
        sigma_px = max(sigma * self.size, 1e-3)
        if not self.tileable:
            return cv2.GaussianBlur(field, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
        pad = min(self.size, int(math.ceil(3 * sigma_px)) + 1)
        padded = cv2.copyMakeBorder(field, pad, pad, pad, pad, cv2.BORDER_WRAP)
        return cv2.GaussianBlur(padded, (0, 0), sigma_px)[pad:-pad, pad:-pad]

    # --- cells ----------------------------------------------------------------------------------

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voronoi cells of ``points`` ((n, 2) in [0, 1)^2, as (u, v)), periodic.

        Returns:
            nearest: (H, W) distance to the nearest point [sample widths];
            label: (H, W) int index of the nearest point;
            edge: (H, W) distance to the nearest cell border [sample widths].
        """
        size = self.size
        # Every pixel's nearest point, wrapped copies included, must lie on the padded canvas.
        margin = min(size, int(math.ceil(size * 1.5 / math.sqrt(max(len(points), 1)))) + 2)
        full = size + 2 * margin
        seeds = np.ones((full, full), np.uint8)
        shifts = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
        label_of_seed = np.zeros(len(points) * 9 + 1, np.int32)
        # Seeds are drawn in order; OpenCV labels connected zero pixels in scan order, so the label
        # of each seed pixel is read back from the label image afterwards.
        pixel = np.floor(points * size).astype(np.int64)
        for dx, dy in shifts:
            xs, ys = pixel[:, 0] + dx * size + margin, pixel[:, 1] + dy * size + margin
            keep = (xs >= 0) & (xs < full) & (ys >= 0) & (ys < full)
            seeds[ys[keep], xs[keep]] = 0
        _, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                           labelType=cv2.DIST_LABEL_PIXEL)
        for dx, dy in shifts:
            xs, ys = pixel[:, 0] + dx * size + margin, pixel[:, 1] + dy * size + margin
            keep = (xs >= 0) & (xs < full) & (ys >= 0) & (ys < full)
            label_of_seed[labels[ys[keep], xs[keep]]] = np.nonzero(keep)[0]
        index = label_of_seed[labels]
        border = np.ones((full, full), np.uint8)
        border[:, 1:][index[:, 1:] != index[:, :-1]] = 0
        border[1:, :][index[1:, :] != index[:-1, :]] = 0
        edge = cv2.distanceTransform(border, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        crop = (slice(margin, margin + size), slice(margin, margin + size))
        index = index[crop]
        # The transform's distances are approximate (OpenCV drops the precise mask when labelling)
        # and its seeds sit on pixel centres; the labels are right, so measure exactly from them.
        du = self.u - points[index, 0]
        dv = self.v - points[index, 1]
        nearest = np.sqrt((du - np.round(du)) ** 2 + (dv - np.round(dv)) ** 2)
        return nearest.astype(np.float32), index, (edge[crop] / size).astype(np.float32)

    def jittered_points(self, cells_per_side: int, jitter: float = 1.0) -> np.ndarray:
        """One random point per cell of a cells x cells grid, (n, 2) in [0, 1)^2."""
        n = max(1, int(cells_per_side))
        grid = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="xy"), -1).reshape(-1, 2)
        offset = 0.5 + jitter * (self.rng.random((n * n, 2)) - 0.5)
        return ((grid + offset) / n % 1.0).astype(np.float32)

    # --- drawing --------------------------------------------------------------------------------

    def _copies(self):
        """Pixel shifts at which a drawing is repeated so that it wraps (just one when not tileable)."""
        if not self.tileable:
            return [(0, 0)]
        return [(dx * self.size, dy * self.size) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]

    def draw_lines(self, image: np.ndarray, starts: np.ndarray, ends: np.ndarray, values, widths) -> np.ndarray:
        """Anti-aliased line segments from ``starts`` to ``ends`` ((n, 2) in sample widths, u, v),
        combined with ``image`` by maximum.

        On a tileable canvas each segment is drawn once on a 3 x 3 canvas that is folded back
        onto the square, so a line crossing an edge continues exactly on the other side.
        """
        size = self.size
        shift_bits = 4
        tiles, margin = (3, size) if self.tileable else (1, 0)
        layer = np.zeros((tiles * size, tiles * size), np.float32)
        values = np.broadcast_to(np.asarray(values, np.float32), (len(starts),))
        widths = np.broadcast_to(np.asarray(widths, np.float32), (len(starts),))
        # Pixel j's centre is u = (j + 0.5) / size: pixel coordinate u * size - 0.5.
        points = lambda p: tuple(int(x) for x in np.round((p * size - 0.5 + margin) * (1 << shift_bits)))  # noqa: E731
        for a, b, value, width in zip(starts, ends, values, widths):
            cv2.line(layer, points(a), points(b), float(value), max(1, int(round(width * size))), cv2.LINE_AA,
                     shift_bits)
        if self.tileable:
            layer = layer.reshape(3, size, 3, size).max(axis=(0, 2))
        np.maximum(image, layer, out=image)
        return image

    def draw_text(self, image: np.ndarray, text: str, origin, height: float, value: float, thickness: float,
                  angle: float = 0.0) -> np.ndarray:
        """Vector-font text (OpenCV Hershey) with its baseline start at ``origin`` (u, v), letters
        ``height`` sample widths tall, rotated by ``angle`` [rad] about the origin."""
        size = self.size
        font = cv2.FONT_HERSHEY_SIMPLEX
        scale = height * size / 22.0  # Hershey simplex capitals are about 22 px tall at scale 1
        weight = max(1, int(round(thickness * size)))
        (w, h), baseline = cv2.getTextSize(text, font, scale, weight)
        if _OPENCV_TEXT_NEEDS_BYTES:
            patch = np.zeros((h + baseline + 2 * weight, w + 2 * weight), np.uint8)
            cv2.putText(patch, text, (weight, h + weight), font, scale, 255, weight, cv2.LINE_AA)
            patch = patch.astype(np.float32) / 255.0
        else:
            patch = np.zeros((h + baseline + 2 * weight, w + 2 * weight), np.float32)
            cv2.putText(patch, text, (weight, h + weight), font, scale, 1.0, weight, cv2.LINE_AA)
        rotation = cv2.getRotationMatrix2D((weight, h + weight), math.degrees(-angle), 1.0)
        for sx, sy in self._copies():
            matrix = rotation.copy()
            matrix[:, 2] += [origin[0] * size - 0.5 - weight + sx, origin[1] * size - 0.5 - h - weight + sy]
            stamped = cv2.warpAffine(patch, matrix, (size, size), flags=cv2.INTER_LINEAR)
            np.maximum(image, stamped * value, out=image)
        return image


def _complex_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """Complex standard normal values (real and imaginary parts N(0, 1)), complex64."""
    return rng.standard_normal((*shape, 2), dtype=np.float32).view(np.complex64)[..., 0]


def height_to_normal(height: np.ndarray, tileable: bool) -> np.ndarray:
    """Unit normals (H, W, 3) of a height field [patch half-widths] on the [-1, 1]^2 sample.

    Rows run towards -y (row 0 is the top edge), so d/dy = -d/drow. Central differences, wrapped
    around on a tileable canvas.
    """
    size = height.shape[0]
    half_step = np.float32(size / 4.0)  # 1 / (2 * pixel spacing), the spacing being 2 / size
    border = cv2.BORDER_WRAP if tileable else cv2.BORDER_REPLICATE
    padded = cv2.copyMakeBorder(height.astype(np.float32), 1, 1, 1, 1, border)
    d_dcol = (padded[1:-1, 2:] - padded[1:-1, :-2]) * half_step
    d_drow = (padded[2:, 1:-1] - padded[:-2, 1:-1]) * half_step
    inverse_length = 1.0 / np.sqrt(d_dcol * d_dcol + d_drow * d_drow + 1.0)
    return np.stack([-d_dcol * inverse_length, d_drow * inverse_length, inverse_length], axis=-1)


@dataclass
class Grid:
    """A running-bond grid of rectangular cells (tiles, bricks, planks), per pixel.

    Attributes:
        index: (H, W) int cell index in [0, count), unique per cell.
        count: number of cell indices (draw per-cell random values as ``rng.random(count)[index]``).
        edge: (H, W) distance to the nearest cell border [sample widths].
        local_u, local_v: (H, W) position inside the cell [0, 1).
    """

    index: np.ndarray
    count: int
    edge: np.ndarray
    local_u: np.ndarray
    local_v: np.ndarray


def grid(canvas: Canvas, columns: float, rows: float, row_offset: float = 0.0) -> Grid:
    """Cells of a grid with ``columns`` x ``rows`` cells per sample, every other row shifted by
    ``row_offset`` cells (0.5: running bond). On a tileable canvas use whole numbers (and an even
    number of rows when offset)."""
    row_f = canvas.v * rows
    row = np.floor(row_f)
    col_f = canvas.u * columns + row_offset * (row % 2)
    col = np.floor(col_f)
    local_u, local_v = col_f - col, row_f - row
    edge = np.minimum(np.minimum(local_u, 1 - local_u) / columns, np.minimum(local_v, 1 - local_v) / rows)
    n_columns = int(math.ceil(columns)) + 1
    if canvas.tileable:  # the half cell that wraps around is the same cell on both sides
        col = col % max(1, round(columns))
    index = row.astype(np.int64) * n_columns + col.astype(np.int64)
    return Grid(index=index, count=int(math.ceil(rows)) * n_columns, edge=edge.astype(np.float32),
                local_u=local_u.astype(np.float32), local_v=local_v.astype(np.float32))


def dielectric_f0(canvas: Canvas, low: float = 0.02, high: float = 0.08) -> np.ndarray:
    """A grey specular albedo F0 of a dielectric, as (3,) float32 [0.02, 0.08 by default]."""
    return np.full(3, canvas.uniform(low, high), np.float32)


def constant(canvas: Canvas, value, channels: int = 3) -> np.ndarray:
    """An (H, W, channels) or (H, W) image filled with ``value``."""
    shape = (canvas.size, canvas.size, channels) if channels > 1 else (canvas.size, canvas.size)
    return np.broadcast_to(np.asarray(value, np.float32), shape).astype(np.float32)
