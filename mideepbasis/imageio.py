"""Image I/O: PNG (8/16-bit), JPEG and OpenEXR, the sRGB transfer function, EXIF, size limits.

Everything inside the project is linear (docs/ARCHITECTURE.md section 5); the sRGB curve is applied here, at the
file boundary, and only when the caller says the data is colour. Arrays on disk and in this module
are (H, W, C) float32; C is 1 (grey) or 3 (RGB).

Every failure is an :class:`ImageIOError` whose message is one line naming the file and the
problem. Every write is atomic: a temporary file in the target folder, moved into place with
``os.replace``, so a reader never sees half a file and a failed write leaves an old file intact.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import contextvars
import functools
import os
import secrets
import struct
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import OpenEXR
import torch
from PIL import Image, JpegImagePlugin, PngImagePlugin

from . import constants
from .errors import InputError


__all__ = ["ImageIOError", "read_image", "write_image", "write_bytes", "srgb_to_linear", "linear_to_srgb",
           "read_focal_length_35mm"]

#: ISO base media (HEIF) brands of still images, after ``ftyp`` at bytes 4 - 8 (iPhones write ``heic``).
_HEIF_BRANDS = {b"heic", b"heix", b"heim", b"heis", b"hevc", b"hevx", b"mif1", b"msf1"}
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_JPEG_MAGIC = b"\xff\xd8\xff"
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_EXIF_ORIENTATION = 0x0112
_GREY_MODES = {"1", "L", "LA", "La", "I", "I;16", "I;16B", "I;16L", "F"}


class ImageIOError(InputError):
    """An image file cannot be read or written; the message is one line naming the file."""


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# --- sRGB ------------------------------------------------------------------------------------------


def srgb_to_linear(x: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Decode sRGB-encoded values to linear (the sRGB EOTF).

    Both paths use the IEC 61966-2-1 piecewise curve: ``x / 12.92`` for ``x <= 0.04045``, else
    ``((x + 0.055) / 1.055) ** 2.4``, written out here for NumPy and for torch (gradients flow, the
    tensor stays on its device). colour-science, whose ``cctf_decoding`` the tests hold both to,
    is not imported: its package import pulls in matplotlib and costs 1.2 s of every start-up.

    Args:
        x: encoded values [0, 1], any shape.

    Returns:
        Linear values [0, 1], same shape; float32 for NumPy input, ``x``'s dtype for tensors.
    """
    if isinstance(x, torch.Tensor):
        # Clamp the base of the power so the unused branch of `where` has a finite gradient.
        power = ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4
        return torch.where(x <= 0.04045, x / 12.92, power)
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Encode linear values with the sRGB OETF (inverse EOTF).

    Both paths use the IEC 61966-2-1 piecewise curve: ``12.92 x`` for ``x <= 0.0031308``, else
    ``1.055 x ** (1 / 2.4) - 0.055``, for NumPy and for torch (gradients flow), checked against
    colour-science's ``cctf_encoding`` in the tests.

    Args:
        x: linear values [0, 1], any shape.

    Returns:
        Encoded values [0, 1], same shape; float32 for NumPy input, ``x``'s dtype for tensors.
    """
    if isinstance(x, torch.Tensor):
        power = 1.055 * x.clamp(min=0.0031308) ** (1.0 / 2.4) - 0.055
        return torch.where(x <= 0.0031308, x * 12.92, power)
    # float32 throughout: 7.6 times faster than float64 (1.3 s of a 1024 px capture's outputs), and
    # 7 in a million values land one 8-bit level away.
    x = np.asarray(x, dtype=np.float32)
    linear = x * np.float32(12.92)
    power = np.float32(1.055) * np.maximum(x, np.float32(0.0031308)) ** np.float32(1.0 / 2.4) - np.float32(0.055)
    return np.where(x <= np.float32(0.0031308), linear, power).astype(np.float32, copy=False)


# --- reading ---------------------------------------------------------------------------------------


def read_image(
    path: str | os.PathLike, *, decode_srgb: bool = False, max_pixels: int = constants.MAX_IMAGE_PIXELS,
    reduce: int = 1,
) -> np.ndarray:
    """Read a PNG (8/16-bit), JPEG, HEIC/HEIF or OpenEXR image.

    The format is recognised from the file's content, not its name. Integer data are scaled to
    [0, 1]; EXIF orientation is applied; alpha is dropped with a warning; palette, CMYK and similar
    modes become RGB; grey images keep one channel. The pixel count is checked from the header,
    before any pixel is decoded.

    Args:
        path: the image file.
        decode_srgb: decode PNG/JPEG values with the sRGB EOTF (for colour data: photos, diffuse,
            specular). EXR is linear by definition and returned as stored.
        max_pixels: largest accepted width * height [pixels].
        reduce: return the image ``reduce`` times smaller on each side (box filter, sizes rounded
            down), decoded in 8 bits first (JPEGs at a reduced scale already), so that a 48 MP
            photo never exists as a full-size float array. 8-bit PNG, JPEG and HEIC only. The
            codes are averaged, not linear light: linear means gave the shipped model worse maps
            (benchmarks/README.md, refinement_real).

    Returns:
        (H, W, C) float32 image, C = 1 or 3.

    Raises:
        ImageIOError: missing file, directory, not an image, truncated or corrupt data, too many
            pixels, or (EXR) NaN / infinite values.
    """
    path = Path(path)
    magic = _read_magic(path)
    if magic.startswith(_EXR_MAGIC):
        return _reduced(_read_exr(path, max_pixels), reduce)
    if magic.startswith(_PNG_MAGIC):
        image = _read_png(path, max_pixels, reduce)
    elif magic.startswith(_JPEG_MAGIC):
        return _read_pil(path, JpegImagePlugin.JpegImageFile, max_pixels, reduce, decode_srgb)
    elif magic[4:8] == b"ftyp" and magic[8:12] in _HEIF_BRANDS:
        return _read_pil(path, _open_heif, max_pixels, reduce, decode_srgb)
    elif not magic:
        raise ImageIOError(f"cannot read '{path}': file is empty")
    else:
        raise ImageIOError(f"cannot read '{path}': not an image file (expected PNG, JPEG, HEIC or OpenEXR)")
    return srgb_to_linear(image) if decode_srgb else image


def _open_heif(path: Path) -> Image.Image:
    """A HEIC/HEIF image through pillow-heif, which applies the stored rotation while decoding
    (and resets the EXIF orientation to 1, so it is not applied twice)."""
    import pillow_heif

    pillow_heif.register_heif_opener()
    return Image.open(path, formats=["HEIF"])


def _reduced(image: np.ndarray, reduce: int) -> np.ndarray:
    """Block means of ``reduce`` x ``reduce`` pixels of an (H, W, C) array (sizes rounded down)."""
    if reduce <= 1:
        return image
    height, width = (image.shape[0] // reduce) * reduce, (image.shape[1] // reduce) * reduce
    blocks = image[:height, :width].reshape(height // reduce, reduce, width // reduce, reduce, -1)
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image as shown (EXIF orientation applied), from its header only."""
    path = Path(path)
    magic = _read_magic(path)
    heif = magic[4:8] == b"ftyp" and magic[8:12] in _HEIF_BRANDS
    if not (heif or magic.startswith(_PNG_MAGIC) or magic.startswith(_JPEG_MAGIC)):
        # EXR photos are rare and small; anything else gets read_image's own one-line error.
        return tuple(read_image(path).shape[1::-1])
    opener = _open_heif if heif else (JpegImagePlugin.JpegImageFile if magic.startswith(_JPEG_MAGIC)
                                      else PngImagePlugin.PngImageFile)  # header only, no bomb check of Pillow's
    try:
        with opener(path) as img:
            width, height = img.size
            _check_pixels(path, width, height, constants.MAX_IMAGE_PIXELS)
            orientation = _exif_orientation(img.getexif)
    except ImageIOError:
        raise
    except (OSError, SyntaxError, EOFError, struct.error, ValueError, Image.DecompressionBombError) as exc:
        raise _decode_error(path, exc) from exc
    return (height, width) if orientation in (5, 6, 7, 8) else (width, height)


def _read_magic(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(12)
    except FileNotFoundError:
        raise ImageIOError(f"cannot read '{path}': no such file") from None
    except IsADirectoryError:
        raise ImageIOError(f"cannot read '{path}': is a directory, not an image file") from None
    except OSError as exc:
        raise ImageIOError(f"cannot read '{path}': {_one_line(exc)}") from exc


def _check_pixels(path: Path, width: int, height: int, max_pixels: int) -> None:
    if width * height > max_pixels:
        raise ImageIOError(
            f"cannot read '{path}': {width}x{height} pixels exceeds the limit of {max_pixels} pixels"
        )


def _decode_error(path: Path, exc: BaseException) -> ImageIOError:
    message = _one_line(exc)
    if "truncat" in message.lower() or isinstance(exc, (EOFError, struct.error)):
        return ImageIOError(f"cannot read '{path}': file is truncated")
    return ImageIOError(f"cannot read '{path}': corrupt image data ({message})")


def _read_png(path: Path, max_pixels: int, reduce: int = 1) -> np.ndarray:
    with open(path, "rb") as f:
        header = f.read(26)
    # IHDR is always the first chunk: length (8:12), b"IHDR" (12:16), width, height, depth, type.
    if len(header) < 26 or header[12:16] != b"IHDR":
        raise ImageIOError(f"cannot read '{path}': file is truncated or not a valid PNG")
    width, height, depth, colour_type = struct.unpack(">IIBB", header[16:26])
    if depth != 16:
        return _read_pil(path, PngImagePlugin.PngImageFile, max_pixels, reduce)

    # Pillow reads 16-bit RGB(A) PNGs as 8-bit, so OpenCV decodes them. Pillow still checks the
    # chunk structure and CRCs first (OpenCV returns None or a partial image on broken data) and
    # supplies the EXIF orientation (from an eXIf chunk before the image data, as the PNG
    # specification places it), which OpenCV ignores under IMREAD_UNCHANGED.
    _check_pixels(path, width, height, max_pixels)
    try:
        with PngImagePlugin.PngImageFile(path) as img:
            orientation = _exif_orientation(lambda: _exif_from_bytes(img.info.get("exif")))
            img.verify()
    except (OSError, SyntaxError, EOFError, struct.error, ValueError) as exc:
        raise _decode_error(path, exc) from exc
    import cv2  # here: importing OpenCV takes 0.14 s of every command's start, and only 16-bit PNGs need it

    data = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != np.uint16:
        raise ImageIOError(f"cannot read '{path}': corrupt 16-bit PNG data")
    data = data[..., None] if data.ndim == 2 else data
    has_alpha = colour_type in (4, 6) or data.shape[2] == 4
    # OpenCV returns BGR(A) and expands grey + alpha to BGRA; PNG colour types 0 and 4 are grey.
    data = data[..., :1] if colour_type in (0, 4) else data[..., 2::-1]
    if has_alpha:
        _warn_alpha(path)
    image = data.astype(np.float32) / 65535.0
    return _reduced(_orient(image, orientation), reduce)


@functools.lru_cache(maxsize=1)
def _srgb_table() -> np.ndarray:
    """``srgb_to_linear`` of the 256 8-bit codes (as ``k / 255`` in float32, as they are read)."""
    return srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0))


def _read_pil(path: Path, opener: Callable[[Path], Image.Image], max_pixels: int, reduce: int = 1,
              decode_srgb: bool = False) -> np.ndarray:
    # The format plugins open lazily (header only) and, unlike Image.open, do not apply Pillow's
    # own decompression-bomb limit, so `max_pixels` is the one limit that applies.
    try:
        with opener(path) as img:
            _check_pixels(path, *img.size, max_pixels)
            target = (max(1, img.width // reduce), max(1, img.height // reduce))
            if reduce > 1 and img.format == "JPEG":
                img.draft(img.mode, target)  # the decoder itself skips to 1/2, 1/4 or 1/8 scale
            img.load()
            if img.size != target:
                img = img.resize(target, Image.Resampling.BOX, reducing_gap=2.0)
            orientation = _exif_orientation(img.getexif)
            has_alpha = "A" in img.mode or "transparency" in img.info
            if img.mode in ("P", "PA"):
                img = img.convert("RGBA")
            img = img.convert("L" if img.mode in _GREY_MODES else "RGB")
            data = np.asarray(img)
    except ImageIOError:
        raise
    except (OSError, SyntaxError, EOFError, struct.error, ValueError) as exc:
        raise _decode_error(path, exc) from exc
    if has_alpha:
        _warn_alpha(path)
    data = data[..., None] if data.ndim == 2 else data
    # 8-bit codes decoded by table: the same values as the curve on k / 255, without its float64
    # powers over every pixel (0.08 s of a 512 px photo's first read).
    return _orient(_srgb_table()[data] if decode_srgb else data.astype(np.float32) / 255.0, orientation)


def _exif_from_bytes(raw: bytes | None) -> Image.Exif:
    exif = Image.Exif()
    if raw:
        exif.load(raw)
    return exif


def _exif_orientation(get_exif: Callable[[], Image.Exif]) -> int:
    # A malformed EXIF block must not stop the pixels from being read: fall back to "as stored".
    try:
        orientation = int(get_exif().get(_EXIF_ORIENTATION, 1))
    except Exception:  # noqa: BLE001 - any EXIF parsing failure means "no orientation"
        return 1
    return orientation if 1 <= orientation <= 8 else 1


#: EXIF tags: the Exif sub-IFD pointer and the 35 mm-equivalent focal length in it.
_EXIF_IFD = 0x8769
_EXIF_FOCAL_35MM = 0xA405


def read_focal_length_35mm(path: str | os.PathLike) -> tuple[float | None, str | None]:
    """The EXIF 35 mm-equivalent focal length [mm] of a JPEG/PNG, and a note when EXIF is unreadable.

    Returns:
        (focal length or None when absent, None or a one-line note such as
        "the EXIF block could not be parsed and was ignored").
    """
    path = Path(path)
    broken = f"the EXIF block of '{path.name}' could not be parsed and was ignored"
    try:
        # Pillow reports some damage only as a warning ("Corrupt EXIF data"): catch those too.
        with warnings.catch_warnings(record=True) as caught, Image.open(path) as img:
            warnings.simplefilter("always")
            exif = img.getexif()
            focal = exif.get_ifd(_EXIF_IFD).get(_EXIF_FOCAL_35MM) or exif.get(_EXIF_FOCAL_35MM)
    except Exception:  # noqa: BLE001 - a broken EXIF block must never stop a capture
        return None, broken
    if any("exif" in str(w.message).lower() for w in caught):
        return None, broken
    try:
        focal = float(focal) if focal else None
    except (TypeError, ValueError):
        return None, f"the EXIF focal length of '{path.name}' is not a number and was ignored"
    return (focal if focal and focal > 0 else None), None


def _orient(image: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation (1..8) to an (H, W, C) array, as ``ImageOps.exif_transpose`` does."""
    transpose = lambda a: a.transpose(1, 0, 2)  # noqa: E731
    ops = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],  # mirror left-right
        3: lambda a: a[::-1, ::-1],  # rotate 180
        4: lambda a: a[::-1],  # mirror top-bottom
        5: transpose,  # mirror along the main diagonal
        6: lambda a: np.rot90(a, k=-1),  # rotate 90 clockwise
        7: lambda a: transpose(a[::-1, ::-1]),  # mirror along the anti-diagonal
        8: lambda a: np.rot90(a, k=1),  # rotate 90 counter-clockwise
    }
    return np.ascontiguousarray(ops[orientation](image))


def _warn_alpha(path: Path) -> None:
    warnings.warn(f"'{path}': alpha channel dropped", stacklevel=4)  # points at the caller of read_image


def _read_exr(path: Path, max_pixels: int) -> np.ndarray:
    try:
        header = OpenEXR.File(str(path), header_only=True).header()
        lo, hi = header["dataWindow"]
        _check_pixels(path, int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1), max_pixels)
        channels = {
            name: channel.pixels
            for name, channel in OpenEXR.File(str(path), separate_channels=True).channels().items()
        }
    except ImageIOError:
        raise
    except Exception as exc:  # noqa: BLE001 - OpenEXR raises bare Exception / RuntimeError
        # OpenEXR's messages cannot tell a cut-off file from a damaged one.
        raise ImageIOError(f"cannot read '{path}': truncated or corrupt OpenEXR file ({_one_line(exc)})") from exc
    if {"R", "G", "B"} <= channels.keys():
        image = np.stack([channels[c] for c in "RGB"], axis=-1)
    elif "Y" in channels:
        image = channels["Y"][..., None]
    else:
        found = ", ".join(sorted(channels)) or "none"
        raise ImageIOError(f"cannot read '{path}': expected channels R, G, B or Y, found {found}")
    if "A" in channels:
        _warn_alpha(path)
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise ImageIOError(f"'{path}' contains NaN or infinite values")
    return image


# --- writing ---------------------------------------------------------------------------------------

_SUFFIXES = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".exr": "exr"}
_BIT_DEPTHS = {"png": (8, 16), "jpeg": (8,), "exr": (16, 32)}

#: zlib level of 8-bit PNGs: 1 encodes a 1024 x 1024 photo 4 times faster than Pillow's 6, for
#: files 5 % larger (benchmarks/README.md, capture section).
PNG_COMPRESS_LEVEL = 1

#: The writer of ``background_writes`` in force, if any: (thread pool, the writes it was given with
#: the bytes each holds, the most bytes that unfinished writes may hold at once).
_BACKGROUND: contextvars.ContextVar[tuple[ThreadPoolExecutor, list[tuple[Future, int]], int] | None] = \
    contextvars.ContextVar("background_writes", default=None)

#: Most bytes of images that unfinished background writes hold at once [bytes]: six 2048 px maps
#: (48 MB each) wait at once; an image of more than half of it (a 4096 px map, 192 MB) is written
#: by the caller once the others are done, so that a 4096 px capture's peak memory stays within
#: 3 GB (benchmarks/README.md).
BACKGROUND_BYTES = 6 * 2048 * 2048 * 3 * 4

#: Rows encoded at once by ``_quantised``: the float temporaries of the clip, the sRGB curve and the
#: rounding are a few MB at any width, not copies of the whole image.
ENCODE_ROWS = 256


@contextlib.contextmanager
def background_writes(threads: int = 2, most_bytes: int = BACKGROUND_BYTES) -> Iterator[None]:
    """Within this block ``write_image`` and ``write_bytes`` check their input at once and hand
    the encoding and writing to ``threads`` worker threads (zlib, NumPy and OpenEXR release the
    GIL, so they overlap with the caller's work); the block's end waits for them all and raises
    the first failure. Files may be finished in any order: use it where a whole folder is
    published at the end (``export.save_capture`` renames its staging folder). A write waits
    while the unfinished ones hold ``most_bytes`` of images (one is always let through)."""
    if _BACKGROUND.get() is not None:  # nested: the outer block waits
        yield
        return
    pool = ThreadPoolExecutor(threads, thread_name_prefix="image-writer")
    writes: list[tuple[Future, int]] = []
    token = _BACKGROUND.set((pool, writes, most_bytes))
    try:
        yield
    finally:
        _BACKGROUND.reset(token)
        pool.shutdown(wait=True)
    for write, _ in writes:
        write.result()  # the first failure, an ImageIOError naming its file


def _submit(function: Callable[[], Path], path: Path, size: int = 0) -> Path:
    """Run ``function`` now, or on the writer threads of ``background_writes``; ``size`` [bytes]
    is what the write holds until it is done."""
    background = _BACKGROUND.get()
    if background is None:
        return function()
    pool, writes, most = background
    pending = [(write, held) for write, held in writes if not write.done()]
    if size > most // 2:  # a 4096 px map: written here, once the others are done, holding no second copy
        concurrent.futures.wait([write for write, _ in pending])
        return function()
    while pending and sum(held for _, held in pending) + size > most:
        concurrent.futures.wait([write for write, _ in pending], return_when=concurrent.futures.FIRST_COMPLETED)
        pending = [(write, held) for write, held in pending if not write.done()]
    writes.append((pool.submit(function), size))
    return path


def write_image(
    path: str | os.PathLike,
    image: np.ndarray | torch.Tensor,
    *,
    encode_srgb: bool = False,
    bit_depth: int | None = None,
) -> Path:
    """Write an image atomically; the format comes from the suffix (.png, .jpg/.jpeg, .exr).

    PNG and JPEG values are clipped to [0, 1] (and sRGB-encoded first if ``encode_srgb``); EXR is
    written linear and unclipped. A single-channel image becomes a grey PNG/JPEG or an EXR with one
    ``Y`` channel. Parent folders are created.

    Args:
        path: target file.
        image: (H, W), (H, W, 1) or (H, W, 3) floating-point NumPy array or torch tensor.
        encode_srgb: apply the sRGB OETF before quantising (colour data only; ignored for EXR).
        bit_depth: PNG 8 or 16; JPEG 8; EXR 32 (float) or 16 (half). None: 8 for PNG/JPEG, 32 for
            EXR.

    Returns:
        The path written.

    Raises:
        ImageIOError: unknown suffix, bad bit depth, bad shape or dtype, NaN / infinite values, or
            the write failed. Nothing is left behind and an existing file is untouched.
    """
    path = Path(path)
    kind = _SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise ImageIOError(
            f"cannot write '{path}': unsupported suffix '{path.suffix}' (expected .png, .jpg, .jpeg or .exr)"
        )
    bit_depth = bit_depth if bit_depth is not None else (32 if kind == "exr" else 8)
    if bit_depth not in _BIT_DEPTHS[kind]:
        allowed = " or ".join(map(str, _BIT_DEPTHS[kind]))
        raise ImageIOError(f"cannot write '{path}': bit depth {bit_depth} is not supported for {kind} ({allowed})")
    data = _as_hwc(path, image)
    return _submit(lambda: _encode_and_write(path, kind, data, encode_srgb, bit_depth), path, data.nbytes)


def _encode_and_write(path: Path, kind: str, data: np.ndarray, encode_srgb: bool, bit_depth: int) -> Path:
    """The encoding and the atomic write of ``write_image``, its input checked."""
    if kind == "exr":
        with np.errstate(over="ignore"):  # values beyond the half range (65504) become inf ...
            data = data.astype(np.float16 if bit_depth == 16 else np.float32, copy=False)
        if not np.isfinite(data).all():  # ... and are refused here
            raise ImageIOError(f"cannot write '{path}': values exceed the range of half floats")
        names = "RGB" if data.shape[2] == 3 else "Y"
        channels = {name: np.ascontiguousarray(data[..., i]) for i, name in enumerate(names)}
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        return _atomic(path, lambda tmp: OpenEXR.File(header, channels).write(str(tmp)))

    if bit_depth == 16:
        # Pillow cannot write 16-bit RGB PNGs; OpenCV can (it expects BGR).
        data = _quantised(data, encode_srgb, np.uint16)
        data = data[..., 0] if data.shape[2] == 1 else data[..., ::-1]

        import cv2  # here, not on a writer thread: a library loaded beside running threads can deadlock

        def encode16(tmp: Path) -> None:
            ok, buffer = cv2.imencode(".png", np.ascontiguousarray(data))
            if not ok:
                raise OSError("OpenCV could not encode the PNG")
            tmp.write_bytes(buffer.tobytes())

        return _atomic(path, encode16)
    data = _quantised(data, encode_srgb, np.uint8)
    img = Image.fromarray(data[..., 0] if data.shape[2] == 1 else data)
    options = {"quality": 95} if kind == "jpeg" else {"compress_level": PNG_COMPRESS_LEVEL}
    return _atomic(path, lambda tmp: img.save(tmp, format=kind.upper(), **options))


def _quantised(data: np.ndarray, encode_srgb: bool, dtype) -> np.ndarray:
    """(H, W, C) floats clipped to [0, 1], sRGB-encoded if asked, as 8- or 16-bit integers,
    ``ENCODE_ROWS`` rows at a time."""
    top = float(np.iinfo(dtype).max)
    out = np.empty(data.shape, dtype=dtype)
    for start in range(0, data.shape[0], ENCODE_ROWS):
        rows = np.clip(data[start:start + ENCODE_ROWS], 0.0, 1.0)
        if encode_srgb:
            rows = np.clip(linear_to_srgb(rows), 0.0, 1.0)
        out[start:start + ENCODE_ROWS] = np.round(rows * top)
    return out


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write bytes (e.g. a JSON side-car) atomically, creating parent folders.

    Raises:
        ImageIOError: the write failed; an existing file is untouched.
    """
    path = Path(path)
    return _submit(lambda: _atomic(path, lambda tmp: tmp.write_bytes(data)), path, len(data))


def _as_hwc(path: Path, image: np.ndarray | torch.Tensor) -> np.ndarray:
    """``image`` as an (H, W, C) float32 array of its own (the write may run after the caller
    changes its data), checked."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu()
        floating, dtype = image.is_floating_point(), str(image.dtype).removeprefix("torch.")
    else:
        image = np.asarray(image)
        floating, dtype = np.issubdtype(image.dtype, np.floating), image.dtype
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in (1, 3) or 0 in image.shape:
        raise ImageIOError(
            f"cannot write '{path}': expected an image of shape (H, W), (H, W, 1) or (H, W, 3), "
            f"got {tuple(image.shape)}"
        )
    if not floating:
        raise ImageIOError(f"cannot write '{path}': expected floating-point values, got {dtype}")
    finite = bool(torch.isfinite(image).all()) if isinstance(image, torch.Tensor) else bool(np.isfinite(image).all())
    if not finite:  # before the cast: a finite value beyond float32's range stays writable (PNG clips it)
        raise ImageIOError(f"cannot write '{path}': image contains NaN or infinite values")
    with np.errstate(over="ignore"):
        return _float32_copy(image)


def _float32_copy(image: np.ndarray | torch.Tensor) -> np.ndarray:
    """A C-ordered float32 copy. Maps arrive as permuted (C, H, W) views: torch copies those on
    every core, NumPy's astype on one and strided (0.08 s a 2048 px map)."""
    if isinstance(image, np.ndarray):
        if not image.flags.writeable:  # torch warns of those (it only reads here)
            return np.array(image, dtype=np.float32, order="C")
        try:
            image = torch.from_numpy(image)
        except (TypeError, ValueError):  # negative strides, or a float type torch lacks
            return np.array(image, dtype=np.float32, order="C")
    return torch.empty(image.shape, dtype=torch.float32).copy_(image).numpy()


def _atomic(path: Path, write: Callable[[Path], object]) -> Path:
    """Run ``write(tmp)`` on a temporary file beside ``path`` and move it into place."""
    # The temporary name keeps the real suffix so that encoders pick the right format.
    tmp = path.with_name(f".{path.stem}.tmp-{secrets.token_hex(6)}{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        with open(tmp, "rb+") as f:  # on disk before the rename, so a crash cannot leave an empty file
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception as exc:  # noqa: BLE001 - every failure becomes one line naming the file
        tmp.unlink(missing_ok=True)
        raise ImageIOError(f"cannot write '{path}': {_one_line(exc)}") from exc
    return path
