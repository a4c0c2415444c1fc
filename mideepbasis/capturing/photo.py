"""The photo: reading, EXIF field of view, crop, centre square and working resolution.

JPEG, PNG (8/16-bit), HEIC or EXR; EXIF orientation applied; sRGB decoded to linear; the centre
square cropped; resampled to the working resolution (256 by default, or the photo's own up to
4096 with ``resolution="native"``). The field of view comes from the EXIF 35 mm-equivalent focal
length when present, else the one given, else 45 degrees.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .. import constants
from ..errors import InputError
from ..imageio import image_size, read_focal_length_35mm, read_image

#: Smallest photo side accepted [pixels].
MIN_PHOTO_SIZE = 64

#: Largest working resolution, and the one of ``resolution="native"`` for larger photos [pixels]: a
#: 4096 px capture peaks at 2.5 GiB of memory (benchmarks/README.md), within an 8 GB laptop's means.
MAX_NATIVE_RESOLUTION = 4096

#: Diagonal of a 35 mm film frame [mm]: EXIF 35 mm-equivalent focal lengths match its field of view.
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)


def field_of_view_from_focal(focal_35mm: float, width: int, height: int, square: int | None = None) -> float:
    """Field of view across the centre square of a width x height photo [deg], from its
    35 mm-equivalent focal length [mm] (which matches the field of view of the frame's diagonal);
    or across a square of ``square`` pixels of it (a crop)."""
    half_diagonal = math.atan(FILM_DIAGONAL_MM / 2.0 / focal_35mm)
    side = (square or min(width, height)) / math.hypot(width, height)
    return math.degrees(2.0 * math.atan(math.tan(half_diagonal) * side))


def load_photo(path: str | Path, fov: float | None = None, resolution: int | str = constants.DEFAULT_RESOLUTION,
               decoding: str = "srgb", crop: tuple[int, int, int, int] | None = None
               ) -> tuple[torch.Tensor, float, str, list[str]]:
    """Read a flash photo for capture.

    ``decoding`` turns 8/16-bit values into linear ones: ``srgb`` (the IEC curve) or ``gamma2.2``
    (the authors' networks were given x^2.2). EXR photos are linear already. ``crop`` (x, y,
    width, height) [pixels of the photo as shown] keeps that part of it (then its centre square).
    A photo much larger than the working resolution is decoded at a reduced size (``read_image``'s
    ``reduce``), at least twice the working resolution, so that 48 MP photos fit in little memory.

    Returns:
        (photo (3, R, R) linear, field of view [deg] of the square used, its source, notes).

    Raises:
        InputError: unreadable, not an image, smaller than 64 pixels, a crop outside the photo.
    """
    path = Path(path)
    full_width, full_height = image_size(path)
    box = (0, 0, full_width, full_height) if crop is None else _checked_crop(path, crop, full_width, full_height)
    side = min(box[2], box[3])
    if side < MIN_PHOTO_SIZE:
        what = "the crop" if crop else "the photo"
        raise InputError(f"'{path}': {what} is {box[2]}x{box[3]} pixels, smaller than the {MIN_PHOTO_SIZE} pixels "
                         "a capture needs")
    needed = 2 * working_resolution(side, resolution)
    reduce = max(1, side // needed)
    image = read_image(path, decode_srgb=decoding == "srgb", reduce=reduce)
    if decoding == "gamma2.2" and path.suffix.lower() != ".exr":
        image = image**2.2
    notes = []
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    x, y, w, h = (v // reduce for v in box)
    image = image[y:y + h, x:x + w]
    height, width = image.shape[:2]
    focal, note = (None, None) if path.suffix.lower() == ".exr" else read_focal_length_35mm(path)
    if note:
        notes.append(note)
    if fov is not None:  # what the user says wins over what the file says
        used_fov, source = float(fov), "argument"
    elif focal:
        # The lens saw the whole frame; the square used (its centre square, or a crop's) is part of it.
        used_fov, source = field_of_view_from_focal(focal, full_width, full_height, side), "exif"
        notes.append(f"field of view {used_fov:.1f} deg from the EXIF 35 mm-equivalent focal length {focal:g} mm")
    else:
        used_fov, source = constants.DEFAULT_FOV_DEG, "default"
        notes.append(f"no EXIF focal length: field of view {used_fov:g} deg assumed (set it with --fov)")
    if resolution == "native" and side > MAX_NATIVE_RESOLUTION:
        notes.append(f"native resolution: the photo's {side} px square is worked at the most, "
                     f"{MAX_NATIVE_RESOLUTION} px")
    if crop is not None:
        notes.append(f"cropped to {box[2]}x{box[3]} pixels at ({box[0]}, {box[1]}) of the {full_width}x{full_height} photo")
    if width != height:
        side = min(width, height)
        top, left = (height - side) // 2, (width - side) // 2
        image = image[top:top + side, left:left + side]
        notes.append(f"the {'crop' if crop is not None else 'photo'} is {width}x{height}: "
                     f"its centre {side}x{side} square was used")
    photo = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float()
    target = working_resolution(photo.shape[-1], resolution)
    if target != photo.shape[-1]:
        photo = F.interpolate(photo[None], size=(target, target), mode="area" if target < photo.shape[-1] else "bilinear",
                              align_corners=None if target < photo.shape[-1] else False)[0]
    photo = photo.clamp(0.0, 1.0)
    mean = float(photo.mean())
    if mean < 0.01:
        warnings.warn(f"'{path.name}' is nearly black (mean {mean:.4f}): the capture will be poor")
    if float((photo >= 0.999).float().mean()) > 0.25:
        warnings.warn(f"'{path.name}' is clipped over a quarter of its pixels: the capture will be poor")
    return photo, used_fov, source, notes


def _checked_crop(path: Path, crop, width: int, height: int) -> tuple[int, int, int, int]:
    """The crop (x, y, w, h) as integers, or a one-line InputError when it leaves the photo."""
    x, y, w, h = (int(v) for v in crop)
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise InputError(f"'{path}': the crop {x},{y},{w},{h} (x, y, width, height) does not lie inside the "
                         f"{width}x{height} photo")
    return x, y, w, h


def native_or_pixels(text: str) -> int | str:
    """``native``, or the whole number of pixels the text holds; else a one-line error naming both."""
    if text == "native":
        return text
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"expected native or a size in pixels, got {text!r}") from None


def parse_resolution(text: str) -> int | str:
    """A working resolution from its text: ``native``, or pixels (at least ``MIN_PHOTO_SIZE``)."""
    value = native_or_pixels(text)
    if value == "native":
        return value
    if not MIN_PHOTO_SIZE <= value <= MAX_NATIVE_RESOLUTION:
        raise ValueError(f"the resolution must be native or {MIN_PHOTO_SIZE} to {MAX_NATIVE_RESOLUTION} pixels, "
                         f"got {value}")
    return value


def working_resolution(side: int, resolution: int | str) -> int:
    """The side [pixels] a photo of ``side`` pixels is resampled to for ``resolution`` (pixels or ``native``)."""
    if resolution == "native":
        return min(side, MAX_NATIVE_RESOLUTION)
    return int(resolution)
