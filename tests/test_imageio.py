"""Tests of mideepbasis.imageio: round trips, sRGB, EXIF, alpha, limits, errors, atomic writes."""

from __future__ import annotations

import struct
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
import torch
from PIL import Image, ImageOps

from mideepbasis import imageio
from mideepbasis.errors import InputError
from mideepbasis.imageio import ImageIOError, linear_to_srgb, read_image, srgb_to_linear, write_image

# Largest |read - written| of a write/read round trip, per format (values in [0, 1]):
# 8-bit is half a quantisation step, 16-bit likewise, JPEG is lossy (smooth test image),
# half floats have 11 significant bits, float32 EXR is exact.
ROUND_TRIP_TOL = {
    ("png", 8): 0.5 / 255 + 1e-6,
    ("png", 16): 1e-4,
    ("jpg", 8): 0.06,  # chroma subsampling of a colourful image
    ("exr", 16): 2.0**-11,
    ("exr", 32): 0.0,
}

# sRGB, IEC 61966-2-1, written out here as the independent reference.
def srgb_eotf_reference(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)


def srgb_oetf_reference(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


def smooth_image(h: int = 48, w: int = 64, c: int = 3, seed: int = 0) -> np.ndarray:
    """A smooth image with distinct channels (JPEG-friendly) in [0.05, 0.95]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w]).reshape(2, 1, 1)
    phases = rng.uniform(0, 2 * np.pi, size=c)
    channels = [0.5 + 0.45 * np.sin(2 * x + 3 * y + p) for p in phases]
    return np.stack(channels, axis=-1).astype(np.float32)


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def exif_bytes(orientation: int) -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    return exif.tobytes()


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))


def assert_one_line_naming(exc: pytest.ExceptionInfo, name: str) -> None:
    message = str(exc.value)
    assert "\n" not in message
    assert name in message


# --- round trips -----------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix,bit_depth", list(ROUND_TRIP_TOL))
@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip(tmp_path, suffix, bit_depth, channels):
    image = smooth_image(c=channels)
    path = write_image(tmp_path / f"img.{suffix}", image, bit_depth=bit_depth)
    assert path == tmp_path / f"img.{suffix}"
    back = read_image(path)
    assert back.dtype == np.float32
    assert back.shape == (48, 64, channels)
    assert np.abs(back - image).max() <= ROUND_TRIP_TOL[(suffix, bit_depth)]


def test_grey_input_shapes_and_torch(tmp_path):
    image = smooth_image(c=1)
    a = read_image(write_image(tmp_path / "a.png", image[..., 0]))  # (H, W)
    b = read_image(write_image(tmp_path / "b.png", torch.from_numpy(image)))  # torch (H, W, 1)
    assert a.shape == b.shape == (48, 64, 1)
    np.testing.assert_array_equal(a, b)


def test_png_bit_depth_and_channel_order_on_disk(tmp_path):
    red = np.zeros((4, 5, 3), np.float32)
    red[..., 0] = 1.0
    path = write_image(tmp_path / "red16.png", red, bit_depth=16)
    header = path.read_bytes()[:26]
    assert header[24] == 16 and header[25] == 2  # IHDR: 16-bit, RGB
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert bgr.dtype == np.uint16 and (bgr[..., 2] == 65535).all() and (bgr[..., :2] == 0).all()
    np.testing.assert_array_equal(read_image(path), red)

    grey = smooth_image(c=1)
    path = write_image(tmp_path / "grey16.png", grey, bit_depth=16)
    assert path.read_bytes()[24:26] == bytes([16, 0])  # 16-bit grey
    stored = np.asarray(Image.open(path))  # Pillow reads 16-bit grey exactly
    np.testing.assert_array_equal(stored, np.round(grey[..., 0] * 65535).astype(np.uint16))


def test_exr_channels_and_pixel_types(tmp_path):
    hdr = np.array([[[5.0, -0.5, 1e3]]], np.float32).repeat(3, 0).repeat(2, 1)
    full = write_image(tmp_path / "full.exr", hdr)
    half = write_image(tmp_path / "half.exr", hdr, bit_depth=16)
    grey = write_image(tmp_path / "grey.exr", hdr[..., :1])
    assert OpenEXR.File(str(full), separate_channels=True).channels()["R"].pixels.dtype == np.float32
    assert OpenEXR.File(str(half), separate_channels=True).channels()["R"].pixels.dtype == np.float16
    assert set(OpenEXR.File(str(grey), separate_channels=True).channels()) == {"Y"}
    np.testing.assert_array_equal(read_image(full), hdr)  # linear, unclipped
    np.testing.assert_array_equal(read_image(half), hdr)  # these values are exact in half
    np.testing.assert_array_equal(read_image(grey, decode_srgb=True), hdr[..., :1])  # EXR stays linear


def test_clipping_for_integer_formats(tmp_path):
    image = np.array([[[-0.5, 0.5, 2.0]]], np.float32)
    back = read_image(write_image(tmp_path / "c.png", image))
    np.testing.assert_allclose(back, [[[0.0, 128 / 255, 1.0]]])


# --- sRGB ------------------------------------------------------------------------------------------


def test_srgb_hand_computed_points():
    # ((0.5 + 0.055) / 1.055) ** 2.4 = 0.21404114; the threshold 0.04045 maps to 0.04045 / 12.92.
    np.testing.assert_allclose(srgb_to_linear(np.array([0.5, 0.04045, 0.0, 1.0])),
                               [0.21404114, 0.0031308, 0.0, 1.0], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(linear_to_srgb(np.array([0.21404114, 0.0031308, 0.0, 1.0])),
                               [0.5, 0.04045, 0.0, 1.0], rtol=1e-5, atol=1e-7)
    t = srgb_to_linear(torch.tensor([0.5, 0.04045], dtype=torch.float64))
    torch.testing.assert_close(t, torch.tensor([0.21404114, 0.04045 / 12.92], dtype=torch.float64), rtol=1e-7, atol=0)


def test_srgb_numpy_torch_and_reference_agree():
    x = np.linspace(-0.1, 1.1, 2001)  # both branches, and a little outside [0, 1]
    positive = np.clip(x, 0, None)
    ref_decode, ref_encode = srgb_eotf_reference(x), srgb_oetf_reference(positive)
    np.testing.assert_allclose(srgb_to_linear(x.astype(np.float32)), ref_decode, atol=1e-6)
    np.testing.assert_allclose(srgb_to_linear(torch.from_numpy(x)).numpy(), ref_decode, atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb(positive.astype(np.float32)), ref_encode, atol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(torch.from_numpy(positive)).numpy(), ref_encode, atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(torch.from_numpy(x))).numpy(), x, atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)
    assert srgb_to_linear(np.float32(0.5)).dtype == np.float32
    assert srgb_to_linear(torch.zeros(2, dtype=torch.float16)).dtype == torch.float16


def test_srgb_agrees_with_colour_science():
    # colour-science is not imported by the package (its import costs 1.2 s); it is the library reference.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_to_linear(x), colour.cctf_decoding(x, function="sRGB"), atol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(x), colour.cctf_encoding(x, function="sRGB"), atol=1e-6)


def test_srgb_torch_is_differentiable():
    # Points on both branches, away from the threshold (the curve is C1 only approximately there).
    x = torch.tensor([0.0, 0.01, 0.02, 0.2, 0.5, 0.9, 1.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(srgb_to_linear, (x,))
    assert torch.autograd.gradcheck(linear_to_srgb, (x[1:].detach().requires_grad_(),))
    y = torch.tensor([0.0, -0.1], dtype=torch.float64, requires_grad=True)
    linear_to_srgb(y).sum().backward()
    assert torch.isfinite(y.grad).all() and torch.allclose(y.grad, torch.full_like(y, 12.92))
    z = torch.tensor([0.5], requires_grad=True)
    srgb_to_linear(z).backward()
    # d/dv ((v + 0.055) / 1.055) ** 2.4 = 2.4 / 1.055 * ((v + 0.055) / 1.055) ** 1.4
    assert z.grad.item() == pytest.approx(2.4 / 1.055 * (0.555 / 1.055) ** 1.4, rel=1e-6)


def test_srgb_on_read_and_write(tmp_path):
    # 0.6 encoded is stored as round(0.6 * 255) = 153.
    linear = np.full((2, 3, 3), srgb_eotf_reference(0.6), np.float32)
    path = write_image(tmp_path / "s.png", linear, encode_srgb=True)
    assert (np.asarray(Image.open(path)) == 153).all()
    np.testing.assert_allclose(read_image(path, decode_srgb=True), srgb_eotf_reference(153 / 255), atol=1e-6)
    np.testing.assert_allclose(read_image(path), 153 / 255, atol=1e-7)


@pytest.mark.parametrize("mode", ["RGB", "L"])
def test_an_8_bit_photo_decoded_by_table_is_the_curve_on_its_codes(tmp_path, mode):
    # JPEG (and HEIC) colour is decoded through a 256-entry table: the very values of the curve.
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    image = Image.fromarray(codes if mode == "L" else np.stack([codes, codes[::-1], codes.T], axis=-1))
    path = tmp_path / "codes.jpg"
    image.save(path, quality=100)
    for reduce in (1, 2):
        decoded = read_image(path, decode_srgb=True, reduce=reduce)
        plain = read_image(path, reduce=reduce)
        assert decoded.dtype == np.float32 and decoded.shape == plain.shape
        assert np.array_equal(decoded, srgb_to_linear(plain))
    np.testing.assert_allclose(read_image(path, decode_srgb=True), srgb_eotf_reference(read_image(path)), atol=1e-6)


# --- EXIF, alpha, modes ----------------------------------------------------------------------------


def asymmetric_rgb(h: int = 4, w: int = 6) -> np.ndarray:
    return (np.arange(h * w * 3).reshape(h, w, 3) * 3 % 256).astype(np.uint8)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_png_matches_pillow(tmp_path, orientation):
    pixels = asymmetric_rgb()
    path = tmp_path / f"o{orientation}.png"
    Image.fromarray(pixels).save(path, exif=exif_bytes(orientation))
    expected = np.asarray(ImageOps.exif_transpose(Image.open(path))) / 255.0
    np.testing.assert_allclose(read_image(path), expected, atol=1e-7)


def test_exif_orientation_jpeg(tmp_path):
    # A bright block in the top-left corner; orientation 6 = display rotated 90 degrees clockwise.
    pixels = np.zeros((32, 48, 3), np.uint8)
    pixels[:8, :8] = 255
    path = tmp_path / "rot.jpg"
    Image.fromarray(pixels).save(path, exif=exif_bytes(6), quality=95)
    image = read_image(path)
    assert image.shape == (48, 32, 3)
    assert image[:8, -8:].mean() > 0.9  # the block is now top-right
    assert image[:8, :8].mean() < 0.1


def test_exif_orientation_16bit_png(tmp_path):
    data = (np.arange(4 * 6 * 3).reshape(4, 6, 3) * 900).astype(np.uint16)
    ok, buffer = cv2.imencode(".png", data[..., ::-1])
    raw = buffer.tobytes()
    idat = raw.index(b"IDAT") - 4  # an eXIf chunk before the image data
    path = tmp_path / "rot16.png"
    path.write_bytes(raw[:idat] + png_chunk(b"eXIf", exif_bytes(6)) + raw[idat:])
    np.testing.assert_array_equal(read_image(path), np.rot90(data, k=-1) / np.float32(65535))


def test_alpha_dropped_with_warning(tmp_path):
    rgba = np.dstack([asymmetric_rgb(), np.full((4, 6), 77, np.uint8)])
    path = tmp_path / "alpha.png"
    Image.fromarray(rgba, "RGBA").save(path)
    with pytest.warns(UserWarning, match="alpha.png"):
        image = read_image(path)
    np.testing.assert_allclose(image, rgba[..., :3] / 255.0, atol=1e-7)

    path = tmp_path / "grey_alpha.png"
    Image.fromarray(rgba[..., 1::2].copy(), "LA").save(path)
    with pytest.warns(UserWarning, match="grey_alpha.png"):
        assert read_image(path).shape == (4, 6, 1)

    path = tmp_path / "alpha16.png"
    cv2.imwrite(str(path), np.full((3, 2, 4), 1000, np.uint16))
    with pytest.warns(UserWarning, match="alpha16.png"):
        assert read_image(path).shape == (3, 2, 3)

    path = tmp_path / "alpha.exr"
    write_exr(path, {c: np.full((2, 2), 0.25, np.float32) for c in "RGBA"})
    with pytest.warns(UserWarning, match="alpha.exr"):
        np.testing.assert_array_equal(read_image(path), np.full((2, 2, 3), 0.25, np.float32))


def test_grey_palette_and_cmyk(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none of these has alpha
        grey = (np.arange(24).reshape(4, 6) * 10).astype(np.uint8)
        Image.fromarray(grey, "L").save(tmp_path / "grey.png")
        np.testing.assert_allclose(read_image(tmp_path / "grey.png")[..., 0], grey / 255.0, atol=1e-7)

        rgb = Image.fromarray(asymmetric_rgb())
        rgb.convert("P", palette=Image.Palette.ADAPTIVE, colors=256).save(tmp_path / "pal.png")
        expected = np.asarray(Image.open(tmp_path / "pal.png").convert("RGB")) / 255.0
        assert read_image(tmp_path / "pal.png").shape == (4, 6, 3)
        np.testing.assert_allclose(read_image(tmp_path / "pal.png"), expected, atol=1e-7)

        Image.new("CMYK", (5, 3), (0, 255, 255, 0)).save(tmp_path / "cmyk.jpg")  # red in CMYK
        image = read_image(tmp_path / "cmyk.jpg")
        assert image.shape == (3, 5, 3)
        assert image[..., 0].min() > 0.9 and image[..., 1:].max() < 0.1


def test_grey_16bit_png_with_alpha_stays_grey(tmp_path):
    # Grey + alpha, 16-bit (colour type 4), which neither Pillow nor OpenCV writes.
    grey_alpha = np.stack([np.full((3, 4), 30000), np.full((3, 4), 65535)], axis=-1).astype(">u2")
    raw = b"".join(b"\x00" + row.tobytes() for row in grey_alpha)
    ihdr = struct.pack(">IIBBBBB", 4, 3, 16, 4, 0, 0, 0)
    path = tmp_path / "ga16.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(raw))
                     + png_chunk(b"IEND", b""))
    with pytest.warns(UserWarning, match="ga16.png"):
        image = read_image(path)
    np.testing.assert_array_equal(image, np.full((3, 4, 1), 30000 / np.float32(65535)))


# --- limits and errors -----------------------------------------------------------------------------


@pytest.mark.parametrize("suffix,bit_depth", [("png", 8), ("png", 16), ("jpg", 8), ("exr", 32)])
def test_pixel_limit(tmp_path, suffix, bit_depth):
    path = write_image(tmp_path / f"big.{suffix}", smooth_image(20, 30), bit_depth=bit_depth)
    assert read_image(path, max_pixels=600).shape == (20, 30, 3)
    with pytest.raises(ImageIOError, match=r"30x20 pixels exceeds the limit of 599 pixels") as exc:
        read_image(path, max_pixels=599)
    assert_one_line_naming(exc, f"big.{suffix}")


@pytest.mark.parametrize("suffix,bit_depth", [("png", 8), ("png", 16), ("jpg", 8)])
def test_pixel_limit_checked_before_decoding(tmp_path, suffix, bit_depth):
    # A file cut right after its header: decoding it would fail, so the limit must come first.
    path = write_image(tmp_path / f"cut.{suffix}", smooth_image(64, 64), bit_depth=bit_depth)
    data = path.read_bytes()
    if suffix == "png":
        cut = data.index(b"IDAT") + 8  # IHDR and the first bytes of the image data
    else:
        start_of_scan = data.index(b"\xff\xda")  # the SOS header, then entropy-coded data
        cut = start_of_scan + 2 + struct.unpack(">H", data[start_of_scan + 2 : start_of_scan + 4])[0]
    path.write_bytes(data[:cut])
    with pytest.raises(ImageIOError, match="exceeds the limit"):
        read_image(path, max_pixels=100)
    with pytest.raises(ImageIOError, match="truncated"):
        read_image(path)


def test_huge_header_refused(tmp_path):
    # A PNG header claiming 20000x20000 pixels with almost no data behind it.
    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0)
    path = tmp_path / "bomb.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(b"\0" * 100)))
    with pytest.raises(ImageIOError, match="20000x20000 pixels exceeds the limit of 67108864 pixels"):
        read_image(path)


def test_read_errors(tmp_path):
    good = write_image(tmp_path / "good.png", smooth_image())
    cases = {"missing.png": "no such file", "folder": "is a directory", "text.png": "not an image file",
             "empty.png": "empty", "cut.png": "truncated", "cut16.png": "truncated", "cut.jpg": "truncated",
             "cut.exr": "truncated or corrupt", "nan.exr": "NaN or infinite", "z.exr": "expected channels"}
    (tmp_path / "folder").mkdir()
    (tmp_path / "text.png").write_text("hello, not a PNG\n")
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:-200])
    full16 = write_image(tmp_path / "full16.png", smooth_image(), bit_depth=16).read_bytes()
    (tmp_path / "cut16.png").write_bytes(full16[: len(full16) // 2])
    full_jpg = write_image(tmp_path / "full.jpg", smooth_image()).read_bytes()
    (tmp_path / "cut.jpg").write_bytes(full_jpg[: len(full_jpg) // 2])
    full_exr = write_image(tmp_path / "full.exr", smooth_image()).read_bytes()
    (tmp_path / "cut.exr").write_bytes(full_exr[: len(full_exr) // 2])
    nan = np.zeros((2, 2), np.float32)
    nan[0, 1] = np.nan
    write_exr(tmp_path / "nan.exr", {"R": nan, "G": nan, "B": nan})
    write_exr(tmp_path / "z.exr", {"Z": nan})
    before = sorted(p.name for p in tmp_path.iterdir())
    for name, problem in cases.items():
        with pytest.raises(ImageIOError, match=problem) as exc:
            read_image(tmp_path / name)
        assert_one_line_naming(exc, name)
        assert isinstance(exc.value, InputError) and isinstance(exc.value, ValueError)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_write_errors_write_nothing(tmp_path):
    image = smooth_image()
    nan = image.copy()
    nan[1, 2, 0] = np.nan
    cases = [
        ("nan.png", nan, {}, "NaN or infinite"),
        ("nan.exr", nan, {}, "NaN or infinite"),
        ("inf.exr", np.full((2, 2), np.inf, np.float32), {}, "NaN or infinite"),
        ("overflow.exr", np.full((2, 2), 1e6, np.float32), {"bit_depth": 16}, "half"),
        ("img.bmp", image, {}, "unsupported suffix"),
        ("img.jpg", image, {"bit_depth": 16}, "bit depth 16"),
        ("img.exr", image, {"bit_depth": 8}, "bit depth 8"),
        ("rgba.png", np.zeros((2, 2, 4), np.float32), {}, "shape"),
        ("ints.png", np.zeros((2, 2, 3), np.uint8), {}, "floating-point"),
    ]
    for name, data, kwargs, problem in cases:
        with pytest.raises(ImageIOError, match=problem) as exc:
            write_image(tmp_path / "sub" / name, data, **kwargs)
        assert_one_line_naming(exc, name)
    assert list(tmp_path.iterdir()) == []  # not even the parent folder


def test_images_are_copied_to_float32_as_numpy_would_and_kept_from_later_changes(tmp_path):
    rng = np.random.default_rng(3)
    chw = rng.uniform(-0.5, 1.5, (3, 5, 7))
    inputs = {
        "permuted float64 array": chw.copy().transpose(1, 2, 0),
        "mirrored array (negative strides)": chw.copy().transpose(1, 2, 0)[:, ::-1],
        "permuted float16 tensor": torch.from_numpy(chw.copy()).half().permute(1, 2, 0),
        "float64 tensor": torch.from_numpy(chw[0].copy()),
    }
    for name, image in inputs.items():
        expected = np.asarray(image.numpy() if isinstance(image, torch.Tensor) else image).astype(np.float32)
        copy = imageio._as_hwc(tmp_path / "x.png", image)
        assert copy.dtype == np.float32 and copy.flags.c_contiguous, name
        np.testing.assert_array_equal(copy.reshape(expected.shape), expected, err_msg=name)
        image[...] = 0  # the caller's data changes while the write may still be pending
        np.testing.assert_array_equal(copy.reshape(expected.shape), expected, err_msg=name)


def test_write_creates_parents_and_leaves_no_temporary_files(tmp_path):
    for suffix, bit_depth in ROUND_TRIP_TOL:
        write_image(tmp_path / "a" / "b" / f"img{bit_depth}.{suffix}", smooth_image(), bit_depth=bit_depth)
    imageio.write_bytes(tmp_path / "a" / "b" / "side.json", b"{}")
    names = sorted(p.name for p in (tmp_path / "a" / "b").iterdir())
    assert names == ["img16.exr", "img16.png", "img32.exr", "img8.jpg", "img8.png", "side.json"]


def _fail_after_writing(path_argument_index: int):
    """A stand-in encoder that leaves a half-written file behind and then fails."""

    def fail(*args, **kwargs):
        target = args[path_argument_index]
        Path(str(target)).write_bytes(b"half a file")
        raise OSError("disk full")

    return fail


@pytest.mark.parametrize("suffix,bit_depth", [("png", 8), ("jpg", 8), ("png", 16), ("exr", 32)])
def test_failed_write_keeps_existing_file(tmp_path, monkeypatch, suffix, bit_depth):
    target = write_image(tmp_path / f"keep.{suffix}", smooth_image(), bit_depth=bit_depth)
    original = target.read_bytes()
    if suffix == "exr":
        class FailingFile:
            def __init__(self, *args):
                pass

            write = staticmethod(_fail_after_writing(0))

        monkeypatch.setattr(imageio.OpenEXR, "File", FailingFile)
    elif bit_depth == 16:
        monkeypatch.setattr(cv2, "imencode", lambda *a: (False, None))
    else:
        monkeypatch.setattr(Image.Image, "save", lambda self, fp, *a, **k: _fail_after_writing(0)(fp))
    with pytest.raises(ImageIOError, match=f"cannot write '.*keep.{suffix}'") as exc:
        write_image(target, smooth_image(seed=1), bit_depth=bit_depth)
    assert_one_line_naming(exc, f"keep.{suffix}")
    assert target.read_bytes() == original
    assert [p.name for p in tmp_path.iterdir()] == [target.name]


@pytest.mark.parametrize("most_bytes", [imageio.BACKGROUND_BYTES, 1])
def test_background_writes_finish_at_the_end_of_the_block_and_read_back_the_same(tmp_path, most_bytes):
    # most_bytes 1: every image is larger than half the budget, so each is written by the caller.
    images = {f"img{i}.png": smooth_image(seed=i) for i in range(4)}
    with imageio.background_writes(most_bytes=most_bytes):
        for name, data in images.items():
            write_image(tmp_path / name, data)
            data[:] = 0.0  # the caller may reuse its buffer at once: the write took a copy
        imageio.write_bytes(tmp_path / "side.json", b"{}")
    for name in images:
        direct = write_image(tmp_path / "direct" / name, smooth_image(seed=int(name[3])))
        assert np.array_equal(read_image(tmp_path / name), read_image(direct))
    assert (tmp_path / "side.json").read_bytes() == b"{}"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_background_writes_check_input_at_once_and_raise_the_first_write_failure_at_the_end(tmp_path, monkeypatch):
    with pytest.raises(ImageIOError, match="NaN"):
        with imageio.background_writes():
            write_image(tmp_path / "bad.png", np.full((2, 2), np.nan, np.float32))
    monkeypatch.setattr(Image.Image, "save", lambda self, fp, *a, **k: _fail_after_writing(0)(fp))
    with pytest.raises(ImageIOError, match="cannot write '.*late.png'") as exc:
        with imageio.background_writes():
            write_image(tmp_path / "late.png", smooth_image())
            imageio.write_bytes(tmp_path / "fine.json", b"{}")
    assert_one_line_naming(exc, "late.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fine.json"]
