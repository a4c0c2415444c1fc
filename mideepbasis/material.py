"""The Material container: four SVBRDF maps, their on-disk folder, dataset strips and PBR conversion.

In memory (docs/ARCHITECTURE.md section 5) a material is four float32 CPU tensors, all linear:
``normal`` (3, H, W) unit vectors, +z out of the surface, OpenGL (+y up); ``diffuse`` (3, H, W)
albedo [0, 1]; ``roughness`` (1, H, W) [0, 1], alpha = r^2; ``specular`` (3, H, W) F0 [0, 1].

On disk a material is a folder of ``normal``, ``diffuse``, ``roughness`` and ``specular`` images
(PNG 8/16-bit: diffuse and specular sRGB-encoded, normal (n + 1) / 2, roughness linear; or EXR:
all linear, normal signed) and a ``material.json`` naming the encodings, the shading convention and
the provenance.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import constants
from .errors import InputError
from .geometry import unit_vectors, vector_length
from .imageio import ImageIOError, linear_to_srgb, read_image, srgb_to_linear, write_bytes, write_image

__all__ = ["Material", "MaterialError", "MAP_NAMES"]

#: The maps of a material, in the order of :meth:`Material.to_tensor`, and their channel counts.
MAP_NAMES = ("normal", "diffuse", "roughness", "specular")
_CHANNELS = {"normal": 3, "diffuse": 3, "roughness": 1, "specular": 3}

_FORMAT_NAME = "mideepbasis-material"
_FORMAT_VERSION = 1
#: save() format -> (file suffix, bit depth).
#: z given to normals that point into the surface when a published strip is repaired for rendering.
REPAIRED_NORMAL_Z = 1e-3

_SAVE_FORMATS = {"png": ("png", 8), "png16": ("png", 16), "exr": ("exr", 32)}
#: Encodings a material folder may declare per map; the first is the default per format
#: (docs/ARCHITECTURE.md section 6).
_DEFAULT_ENCODING = {
    "png": {"normal": "unsigned-opengl", "diffuse": "srgb", "roughness": "linear", "specular": "srgb"},
    "exr": {"normal": "signed", "diffuse": "linear", "roughness": "linear", "specular": "linear"},
}
_NORMAL_ENCODINGS = ("signed", "signed-directx", "unsigned-opengl", "unsigned-directx")
_VALUE_ENCODINGS = ("srgb", "linear")

#: Deschaintre et al. 2018 strips: (width, height) -> (panels, panel size, crop offset) [pixels].
_DESCHAINTRE_LAYOUTS = {(1440, 288): (5, 288, 16), (1280, 256): (5, 256, 0), (2048, 512): (4, 512, 0)}

#: Decoded 8-bit normals of grazing directions can land just below the surface (z = -1/255);
#: z in [-_Z_QUANTUM, 0) is read as 0 [unitless].
_Z_QUANTUM = 2.0 / 255.0


class MaterialError(InputError):
    """A material (in memory, a folder or a dataset file) is unusable: ``"<source>: <problem>"``."""


@dataclass(eq=False, repr=False)
class Material:
    """An SVBRDF: normal, diffuse, roughness and specular maps (docs/ARCHITECTURE.md sections 4-6).

    NumPy arrays are accepted and every map becomes a float32 CPU tensor (autograd history is
    kept). Validation: (C, H, W) shapes with the right channel counts and equal H, W >= 2; finite
    values; diffuse, roughness and specular in [0, 1] within ``RANGE_TOLERANCE`` (then clamped);
    normals of unit length within ``UNIT_NORMAL_TOLERANCE`` (then renormalised) with
    z >= -``UNIT_NORMAL_TOLERANCE``.

    Attributes:
        normal: (3, H, W) unit normals, +z out of the surface, OpenGL convention (+y up).
        diffuse: (3, H, W) linear diffuse albedo [0, 1].
        roughness: (1, H, W) roughness [0, 1]; alpha = r^2.
        specular: (3, H, W) linear specular albedo F0 [0, 1].
        convention: shading convention the maps are meant for (``constants.CONVENTIONS``).
        provenance: JSON-serialisable record of where the maps came from and how they were encoded.
        source: name used in error messages (a file or folder, or "material").
        stored_normal: (3, H, W) the normals as a dataset stored them where they had to be
            repaired for rendering (``from_deschaintre``), else None; for metrics only.

    Raises:
        MaterialError: one line ``"<source>: <problem>"``.
    """

    normal: torch.Tensor
    diffuse: torch.Tensor
    roughness: torch.Tensor
    specular: torch.Tensor
    convention: str = constants.DEFAULT_CONVENTION
    provenance: dict = field(default_factory=dict)
    source: str = "material"
    stored_normal: torch.Tensor | None = None

    def __post_init__(self) -> None:
        src = self.source
        if self.convention not in constants.CONVENTIONS:
            expected = _or(constants.CONVENTIONS)
            raise MaterialError(f"{src}: unknown convention '{self.convention}' (expected {expected})")
        if not isinstance(self.provenance, dict):
            raise MaterialError(f"{src}: provenance must be a dict, got {type(self.provenance).__name__}")
        try:
            json.dumps(self.provenance)
        except (TypeError, ValueError) as exc:
            raise MaterialError(f"{src}: provenance is not JSON-serialisable ({exc})") from None

        maps = {name: _as_map(src, name, getattr(self, name), _CHANNELS[name]) for name in MAP_NAMES}
        sizes = {name: tuple(t.shape[1:]) for name, t in maps.items()}
        if len(set(sizes.values())) > 1:
            listed = ", ".join(f"{name} {w}x{h}" for name, (h, w) in sizes.items())
            raise MaterialError(f"{src}: maps differ in size ({listed})")
        h, w = sizes["normal"]
        if h < 2 or w < 2:
            raise MaterialError(f"{src}: maps must be at least 2x2 pixels, got {w}x{h}")
        for name, t in maps.items():
            if not torch.isfinite(t).all():
                raise MaterialError(f"{src}: {name} contains NaN or infinite values")

        for name in ("diffuse", "roughness", "specular"):
            maps[name] = _clamp_unit(src, name, maps[name])
        n = maps["normal"]
        length = vector_length(n.detach(), dim=0)
        tol = constants.UNIT_NORMAL_TOLERANCE
        if ((length - 1).abs() > tol).any():
            raise MaterialError(
                f"{src}: normals are not unit vectors (|n| in [{length.min():.4g}, {length.max():.4g}]): "
                "is the normal map a tangent-space one (a flat map is (128, 128, 255), not grey)?"
            )
        if (n.detach()[2] < -tol).any():
            raise MaterialError(f"{src}: normals point into the surface (min z = {n.detach()[2].min():.4g})")
        maps["normal"] = n / vector_length(n, dim=0, keepdim=True)
        for name, t in maps.items():
            setattr(self, name, t)

    def __repr__(self) -> str:
        return f"Material({self.width}x{self.height}, convention={self.convention!r}, source={self.source!r})"

    @property
    def height(self) -> int:
        """Height H [pixels]."""
        return self.normal.shape[1]

    @property
    def width(self) -> int:
        """Width W [pixels]."""
        return self.normal.shape[2]

    # --- tensors -----------------------------------------------------------------------------------

    def to_tensor(self) -> torch.Tensor:
        """The maps stacked as (10, H, W): normal 3, diffuse 3, roughness 1, specular 3."""
        return torch.cat([self.normal, self.diffuse, self.roughness, self.specular], dim=0)

    @classmethod
    def from_tensor(cls, t: torch.Tensor | np.ndarray, **kwargs: Any) -> Material:
        """Build a material from a (10, H, W) tensor laid out as :meth:`to_tensor` does.

        Unlike the constructor this repairs its input, as a network output needs: normals are
        folded to z >= 0 and normalised, the other maps clamped to [0, 1].

        Args:
            t: (10, H, W) maps.
            **kwargs: ``convention``, ``provenance``, ``source``.
        """
        source = kwargs.get("source", "material")
        t = _as_map(source, "tensor", t, constants.BASIS_CHANNELS)
        normal = t[constants.NORMAL]
        normal = torch.cat([normal[0:2], normal[2:3].clamp(min=0)], dim=0)
        normal = unit_vectors(normal, dim=0)
        reflectance = t[constants.REFLECTANCE].clamp(0, 1)  # not all ten channels: 0.2 GB less at 4096 px
        start = constants.REFLECTANCE.start
        return cls(normal, *(reflectance[part.start - start:part.stop - start]
                             for part in (constants.DIFFUSE, constants.ROUGHNESS, constants.SPECULAR)), **kwargs)

    @classmethod
    def constant(
        cls,
        height: int,
        width: int,
        normal: tuple[float, float, float] = (0.0, 0.0, 1.0),
        diffuse: float | tuple[float, float, float] = 0.5,
        roughness: float = 0.5,
        specular: float | tuple[float, float, float] = constants.DIELECTRIC_F0,
        **kwargs: Any,
    ) -> Material:
        """A spatially uniform material of height x width pixels.

        Args:
            height, width: size [pixels].
            normal: normal direction (normalised here).
            diffuse, specular: linear albedo, a scalar (grey) or an RGB triple [0, 1].
            roughness: roughness [0, 1].
            **kwargs: ``convention``, ``provenance``, ``source``.
        """

        def fill(value: Any, channels: int) -> torch.Tensor:
            v = torch.as_tensor(value, dtype=torch.float32).reshape(-1)
            if v.numel() not in (1, channels):
                source = kwargs.get("source", "material")
                raise MaterialError(f"{source}: expected 1 or {channels} values, got {v.numel()}")
            return v.expand(channels).reshape(channels, 1, 1).expand(channels, height, width).clone()

        n = torch.as_tensor(normal, dtype=torch.float32)
        return cls(fill(n / n.norm(), 3), fill(diffuse, 3), fill(roughness, 1), fill(specular, 3), **kwargs)

    # --- material folder ---------------------------------------------------------------------------

    def save(self, folder: str | os.PathLike, *, format: str = "png", normal_convention: str = "opengl") -> Path:
        """Write the material folder (docs/ARCHITECTURE.md section 6): four maps, then ``material.json``.

        Every file is written atomically and ``material.json`` last, so a folder with a
        ``material.json`` is complete.

        Args:
            folder: target folder (created).
            format: ``png`` (8-bit, the normal 16-bit), ``png16`` or ``exr`` (float32).
            normal_convention: ``opengl`` (+y up, the in-memory convention) or ``directx`` (green
                flipped, for tools that expect it).

        Returns:
            The folder.
        """
        if format not in _SAVE_FORMATS:
            raise MaterialError(f"{self.source}: unknown material format '{format}' (expected {_or(_SAVE_FORMATS)})")
        if normal_convention not in ("opengl", "directx"):
            raise MaterialError(
                f"{self.source}: unknown normal convention '{normal_convention}' (expected opengl or directx)"
            )
        suffix, bit_depth = _SAVE_FORMATS[format]
        # The normal is never quantised to 8 bits: gentle slopes would band (16-bit PNG instead).
        bit_depths = {name: max(bit_depth, 16) if name == "normal" and suffix == "png" else bit_depth
                      for name in MAP_NAMES}
        encoding = dict(_DEFAULT_ENCODING[suffix])
        if normal_convention == "directx":
            encoding["normal"] = "unsigned-directx" if suffix == "png" else "signed-directx"
        meta = {
            "format": _FORMAT_NAME,
            "version": _FORMAT_VERSION,
            "file_format": suffix,
            "bit_depth": bit_depths,
            "size": {"width": self.width, "height": self.height},
            "encoding": encoding,
            "convention": self.convention,
            "provenance": self.provenance,
        }
        text = json.dumps(meta, indent=2) + "\n"
        folder = Path(folder)
        try:
            for name in MAP_NAMES:
                data = _encode(getattr(self, name).detach(), encoding[name])
                write_image(folder / f"{name}.{suffix}", data.permute(1, 2, 0), bit_depth=bit_depths[name])
            write_bytes(folder / "material.json", text.encode())
        except ImageIOError as exc:
            raise MaterialError(str(exc)) from exc
        return folder

    @classmethod
    def load(cls, folder: str | os.PathLike) -> Material:
        """Read a material folder written by :meth:`save` or by hand.

        ``material.json`` decides the file format and encodings. Without it the folder must hold
        one complete set of ``.png`` or ``.exr`` maps, read with the defaults of docs/ARCHITECTURE.md
        section 6 (noted in the provenance). Decoded normals are renormalised (undoing quantisation).

        Raises:
            MaterialError: missing folder or map, bad ``material.json``, unreadable map, maps of
                different sizes, NaN or out-of-range values.
        """
        folder = Path(folder)
        src = str(folder)
        if not folder.is_dir():
            raise MaterialError(f"{src}: {'not a folder' if folder.exists() else 'no such folder'}")
        meta_path = folder / "material.json"
        if meta_path.is_file():
            suffix, encoding, meta = _read_meta(meta_path)
            convention = meta.get("convention", constants.DEFAULT_CONVENTION)
            provenance = meta.get("provenance", {})
        else:
            suffix = _guess_suffix(folder)
            encoding, meta, convention = dict(_DEFAULT_ENCODING[suffix]), {}, constants.DEFAULT_CONVENTION
            provenance = {
                "source": folder.name,
                "file_format": suffix,
                "encoding": encoding,
                "note": "no material.json; docs/ARCHITECTURE.md section 6 defaults assumed",
            }
        paths = {name: folder / f"{name}.{suffix}" for name in MAP_NAMES}
        for name, path in paths.items():
            if not path.is_file():
                raise MaterialError(f"{src}: missing {name} map ({path.name})")
        try:
            images = {name: read_image(path) for name, path in paths.items()}
        except ImageIOError as exc:
            raise MaterialError(str(exc)) from exc

        sizes = {name: image.shape[:2] for name, image in images.items()}
        if len(set(sizes.values())) > 1:
            listed = ", ".join(f"{paths[name].name} {w}x{h}" for name, (h, w) in sizes.items())
            raise MaterialError(f"{src}: maps differ in size ({listed})")
        expected = meta.get("size")
        h, w = sizes["normal"]
        if isinstance(expected, dict) and (expected.get("width"), expected.get("height")) != (w, h):
            raise MaterialError(
                f"{src}: maps are {w}x{h} but material.json says {expected.get('width')}x{expected.get('height')}"
            )

        maps = {}
        for name, image in images.items():
            t = torch.from_numpy(image).permute(2, 0, 1)
            if name == "normal" and t.shape[0] != 3:
                raise MaterialError(f"{src}: {paths[name].name} has {t.shape[0]} channel(s), expected 3")
            if name == "roughness" and t.shape[0] == 3:
                t = t.mean(dim=0, keepdim=True)  # a grey map saved as RGB
            elif name != "roughness" and t.shape[0] == 1:
                t = t.expand(3, -1, -1)  # a grey albedo saved as one channel
            maps[name] = _decode(t, encoding[name])
        return cls(**maps, convention=convention, provenance=provenance, source=src)

    # --- datasets ----------------------------------------------------------------------------------

    @classmethod
    def from_deschaintre(
        cls, path: str | os.PathLike, *, return_photo: bool = False, convention: str = "deepbasis",
        repair_normals: bool = True,
    ) -> Material | tuple[Material, torch.Tensor | None]:
        """Read a strip of the Deschaintre et al. 2018 dataset.

        Layouts (width x height [pixels]): 1440x288, five 288-px panels (flash render, normal,
        diffuse, roughness, specular), each cropped to its central 256x256 (offset 16); 1280x256,
        the same five panels without crop; 2048x512, four 512-px panels (normal, diffuse,
        roughness, specular). Stored values are used as-is, as the reference implementations do:
        diffuse and specular are stored / 255 (no sRGB decoding), roughness the channel mean,
        normal 2 x - 1 renormalised.

        Args:
            path: the PNG strip.
            return_photo: also return the flash panel.
            convention: the shading convention the maps were made for; the default is that of the
                reference implementations whose renderer produced the dataset.
            repair_normals: published strips hold some normals that point into the surface
                (z < 0), which no renderer can shade. With True their z is raised to
                ``REPAIRED_NORMAL_Z`` and they are renormalised; the count is in
                ``provenance["repaired_normal_pixels"]`` and the normals as stored (unit length,
                z < 0 kept) in ``material.stored_normal``, for metrics in the stored encoding.
                With False such a strip is refused.

        Returns:
            The material, or (material, photo) with photo (3, H, W) in [0, 1] as stored (sRGB
            encoded), None for four-panel strips.
        """
        path = Path(path)
        src = str(path)
        try:
            image = read_image(path)
        except ImageIOError as exc:
            raise MaterialError(str(exc)) from exc
        h, w, c = image.shape
        layout = _DESCHAINTRE_LAYOUTS.get((w, h))
        if layout is None:
            expected = _or([f"{lw}x{lh}" for lw, lh in _DESCHAINTRE_LAYOUTS])
            raise MaterialError(f"{src}: {w}x{h} is not a Deschaintre et al. 2018 strip size (expected {expected})")
        if c != 3:
            raise MaterialError(f"{src}: expected an RGB strip, got {c} channel(s)")
        count, size, crop = layout
        strip = torch.from_numpy(image).permute(2, 0, 1)
        panels = [strip[:, crop : size - crop, i * size + crop : (i + 1) * size - crop] for i in range(count)]
        photo = panels.pop(0) if count == 5 else None
        normal, diffuse, roughness, specular = panels
        normal = _decode(normal, "unsigned-opengl")
        inward = normal[2] < -constants.UNIT_NORMAL_TOLERANCE
        stored_normal = None
        if repair_normals and bool(inward.any()):
            stored_normal = unit_vectors(normal, dim=0)
            normal = normal.clone()
            normal[2] = torch.where(inward, torch.full_like(normal[2], REPAIRED_NORMAL_Z), normal[2])
            normal = normal / vector_length(normal, dim=0, keepdim=True)
        provenance = {"source": path.name, "format": f"deschaintre{count}", "encoding": "stored-as-is"}
        if stored_normal is not None:
            provenance["repaired_normal_pixels"] = int(inward.sum())
        material = cls(
            normal=normal,
            diffuse=diffuse.clone(),
            roughness=roughness.mean(dim=0, keepdim=True),
            specular=specular.clone(),
            convention=convention,
            provenance=provenance,
            source=src,
        )
        material.stored_normal = stored_normal
        if return_photo:
            return material, None if photo is None else photo.clone()
        return material

    # --- metallic-roughness ------------------------------------------------------------------------

    @classmethod
    def from_pbr(
        cls,
        base_color: torch.Tensor | np.ndarray,
        metallic: torch.Tensor | np.ndarray,
        roughness: torch.Tensor | np.ndarray,
        normal: torch.Tensor | np.ndarray | None = None,
        dielectric_f0: float = constants.DIELECTRIC_F0,
        **kwargs: Any,
    ) -> Material:
        """Build a material from metallic-roughness maps (glTF style).

        ``diffuse = base (1 - m)``, ``specular = f0 (1 - m) + base m``. Our shading model has no
        (1 - F) factor on the diffuse, so neither does this conversion.

        Args:
            base_color: (3, H, W) linear base colour [0, 1].
            metallic: (1, H, W) metalness [0, 1].
            roughness: (1, H, W) roughness [0, 1].
            normal: (3, H, W) unit normals; None for a flat surface.
            dielectric_f0: F0 of the non-metal part [unitless].
            **kwargs: ``convention``, ``provenance``, ``source``.
        """
        src = kwargs.get("source", "material")
        base = _clamp_unit(src, "base_color", _as_map(src, "base_color", base_color, 3))
        m = _clamp_unit(src, "metallic", _as_map(src, "metallic", metallic, 1))
        if normal is None:
            normal = torch.zeros_like(base)
            normal[2] = 1.0
        return cls(normal, base * (1 - m), roughness, dielectric_f0 * (1 - m) + base * m, **kwargs)

    def to_pbr(self, dielectric_f0: float = constants.DIELECTRIC_F0) -> dict[str, torch.Tensor]:
        """Convert to metallic-roughness maps, inverting :meth:`from_pbr` per pixel.

        With luminances D of the diffuse and S of the specular, ``D = B (1 - m)`` and
        ``S = f0 (1 - m) + B m``; eliminating B gives ``f0 m^2 + (D + S - 2 f0) m + (f0 - S) = 0``,
        whose root in [0, 1] (the only positive one when S > f0) is taken in the cancellation-free
        form ``m = 2 (S - f0) / (b + sqrt(b^2 + 4 f0 (S - f0)))``, b = D + S - 2 f0. Where
        S <= f0 the pixel is a dielectric (m = 0): the glTF convention, which also maps metals
        darker than f0 to dielectrics. The base colour blends the diffuse estimate d / (1 - m) and
        the specular estimate (s - f0 (1 - m)) / m with weights (1 - m) and m, each clamped to
        [0, 1]; for maps made by :meth:`from_pbr` both estimates are exact.

        Returns:
            ``base_color`` (3, H, W) linear [0, 1], ``metallic`` (1, H, W) [0, 1],
            ``roughness`` (1, H, W) [0, 1].
        """
        base_color = torch.empty_like(self.diffuse)
        metallic = torch.empty_like(self.roughness)
        # float64 (the estimates divide by m and 1 - m) a band of rows at a time: a 2048 x 2048
        # material in one piece would take 0.8 GB of float64 temporaries.
        for top in range(0, self.height, _PBR_BAND_ROWS):
            rows = slice(top, top + _PBR_BAND_ROWS)
            base_color[:, rows], metallic[:, rows] = _metallic_roughness(self.diffuse[:, rows], self.specular[:, rows],
                                                                         dielectric_f0)
        return {"base_color": base_color, "metallic": metallic, "roughness": self.roughness.clone()}


#: Rows of the material ``Material.to_pbr`` converts at a time.
_PBR_BAND_ROWS = 256


def _luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 1, H, W) luminance of (..., 3, H, W) linear colours (``constants.LUMINANCE_WEIGHTS``), in
    their dtype."""
    weights = torch.tensor(constants.LUMINANCE_WEIGHTS, dtype=rgb.dtype, device=rgb.device).reshape(3, 1, 1)
    return (weights * rgb).sum(-3, keepdim=True)


def _metallic_of_luminances(lum_d: torch.Tensor, lum_s: torch.Tensor, dielectric_f0: float) -> torch.Tensor:
    """``metallic_share`` from the luminances (1, H, W) of the diffuse and the specular."""
    excess = (lum_s - dielectric_f0).clamp(min=0)
    b = lum_d + lum_s - 2 * dielectric_f0
    denominator = b + torch.sqrt(b * b + 4 * dielectric_f0 * excess)
    metallic = torch.where(excess > 1e-9, 2 * excess / denominator.clamp(min=1e-12), torch.zeros_like(b))
    return metallic.clamp(0, 1)


def metallic_share(diffuse: torch.Tensor, specular: torch.Tensor, dielectric_f0: float) -> torch.Tensor:
    """The metallic (..., 1, H, W) in [0, 1] of ``Material.to_pbr`` for diffuse and specular
    (..., 3, H, W), computed in their dtype: 0 where the specular's luminance is at most ``dielectric_f0``."""
    return _metallic_of_luminances(_luminance(diffuse), _luminance(specular), dielectric_f0)


def grey_dielectric_specular(diffuse: torch.Tensor, specular: torch.Tensor, dielectric_f0: float) -> torch.Tensor:
    """The specular (3, H, W) with each pixel's colour kept in proportion to its metallic share
    (``metallic_share`` at ``dielectric_f0``) and grey of the same luminance otherwise: a
    dielectric's F0 has no colour, only a metal's does."""
    luminance = _luminance(specular)
    metallic = _metallic_of_luminances(_luminance(diffuse), luminance, dielectric_f0)
    return (luminance + metallic * (specular - luminance)).clamp(0, 1)


def _metallic_roughness(diffuse: torch.Tensor, specular: torch.Tensor, dielectric_f0: float
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """(base colour (3, h, w), metallic (1, h, w)) of diffuse and specular (3, h, w): the
    arithmetic of ``Material.to_pbr``, in float64."""
    d, s = diffuse.double(), specular.double()
    f0 = float(dielectric_f0)
    metallic = metallic_share(d, s, f0)
    eps = 1e-9
    from_diffuse = (d / (1 - metallic).clamp(min=eps)).clamp(0, 1)
    from_specular = ((s - f0 * (1 - metallic)) / metallic.clamp(min=eps)).clamp(0, 1)
    base = (1 - metallic) * from_diffuse + metallic * from_specular
    return base.clamp(0, 1).float(), metallic.float()


# --- helpers ---------------------------------------------------------------------------------------


def _or(items: Any) -> str:
    items = list(items)
    return ", ".join(items[:-1]) + f" or {items[-1]}" if len(items) > 1 else items[0]


def _as_map(source: str, name: str, value: Any, channels: int) -> torch.Tensor:
    """``value`` as a float32 CPU tensor of shape (channels, H, W)."""
    if isinstance(value, np.ndarray):
        value = torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32))
    elif not isinstance(value, torch.Tensor):
        raise MaterialError(f"{source}: {name} must be a tensor or array, got {type(value).__name__}")
    t = value.to(device="cpu", dtype=torch.float32)
    if t.ndim != 3 or t.shape[0] != channels:
        raise MaterialError(f"{source}: {name} must have shape ({channels}, H, W), got {tuple(t.shape)}")
    return t


def _clamp_unit(source: str, name: str, t: torch.Tensor) -> torch.Tensor:
    """Check ``t`` lies in [0, 1] within the range tolerance, then clamp it there."""
    lo, hi = float(t.detach().min()), float(t.detach().max())
    tol = constants.RANGE_TOLERANCE
    if lo < -tol or hi > 1 + tol:
        raise MaterialError(f"{source}: {name} values lie in [{lo:.4g}, {hi:.4g}], outside [0, 1]")
    # No copy where nothing is clamped (as after ``from_tensor``): 0.5 GB at 4096 px.
    return t if 0.0 <= lo and hi <= 1.0 else t.clamp(0, 1)


def _encode(t: torch.Tensor, encoding: str) -> torch.Tensor:
    """In-memory map (C, H, W) -> the values stored on disk under ``encoding``."""
    if encoding.endswith("directx"):
        t = t * torch.tensor([1.0, -1.0, 1.0]).reshape(3, 1, 1)
    if encoding.startswith("unsigned"):
        return (t + 1) / 2
    if encoding != "srgb":
        return t
    # In bands of rows: the curve's temporaries are four copies of what it is given.
    encoded = torch.empty_like(t)
    for top in range(0, t.shape[-2], _ENCODE_BAND_ROWS):
        encoded[..., top:top + _ENCODE_BAND_ROWS, :] = linear_to_srgb(t[..., top:top + _ENCODE_BAND_ROWS, :])
    return encoded


#: Rows of a map ``_encode`` puts through the sRGB curve at a time.
_ENCODE_BAND_ROWS = 512


#: Shortest median length of a stored normal map's vectors that ``_decode`` renormalises.
_SHORTEST_STORED_NORMAL = 0.5


def _decode(t: torch.Tensor, encoding: str) -> torch.Tensor:
    """Stored values (C, H, W) under ``encoding`` -> the in-memory map.

    Unsigned (integer-quantised) normals are renormalised; signed (float) normals are taken as
    stored, so that a map which is not of unit vectors is reported rather than silently repaired.
    """
    if encoding == "srgb":
        return srgb_to_linear(t)
    if encoding == "linear":
        return t
    n = t.clone()
    if encoding.startswith("unsigned"):
        n = 2 * n - 1
        n[2] = torch.where((n[2] < 0) & (n[2] >= -_Z_QUANTUM), torch.zeros_like(n[2]), n[2])
        length = vector_length(n, dim=0, keepdim=True)
        # Quantisation moves a unit vector's length by under 1 %. A map whose typical vector is
        # much shorter (a flat grey (128, 128, 128) map is nearly zero) holds no normals: it stays
        # as it is, so that validation reports it instead of reading arbitrary unit vectors; stray
        # short pixels of a real normal map are renormalised (zero-length ones kept for validation).
        if float(length.median()) > _SHORTEST_STORED_NORMAL:
            n = torch.where(length > 1e-6, n / length.clamp(min=1e-6), n)
    if encoding.endswith("directx"):
        n[1] = -n[1]
    return n


def _read_meta(path: Path) -> tuple[str, dict[str, str], dict]:
    """Parse and check material.json; returns (file suffix, encoding per map, the whole record)."""
    src = str(path)
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise MaterialError(f"{src}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MaterialError(f"{src}: cannot read ({exc})") from None
    except RecursionError:
        raise MaterialError(f"{src}: not a material description (its JSON nests too deeply)") from None
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT_NAME:
        raise MaterialError(f"{src}: not a '{_FORMAT_NAME}' description")
    version = meta.get("version")
    if not isinstance(version, int) or not 1 <= version <= _FORMAT_VERSION:
        raise MaterialError(f"{src}: unsupported version {version!r} (this reader knows {_FORMAT_VERSION})")
    suffix = meta.get("file_format")
    if suffix not in _DEFAULT_ENCODING:
        raise MaterialError(f"{src}: unknown file_format {suffix!r} (expected png or exr)")
    declared = meta.get("encoding", {})
    if not isinstance(declared, dict):
        raise MaterialError(f"{src}: 'encoding' must be an object")
    encoding = {**_DEFAULT_ENCODING[suffix], **declared}
    for name in MAP_NAMES:
        allowed = _NORMAL_ENCODINGS if name == "normal" else _VALUE_ENCODINGS
        if encoding[name] not in allowed:
            raise MaterialError(f"{src}: unknown {name} encoding {encoding[name]!r} (expected {_or(allowed)})")
    if meta.get("convention", constants.DEFAULT_CONVENTION) not in constants.CONVENTIONS:
        raise MaterialError(f"{src}: unknown convention {meta['convention']!r}")
    if not isinstance(meta.get("provenance", {}), dict):
        raise MaterialError(f"{src}: 'provenance' must be an object")
    return suffix, encoding, meta


def _guess_suffix(folder: Path) -> str:
    """Without material.json: the file format of the one complete set of maps in ``folder``."""
    complete = [s for s in ("png", "exr") if all((folder / f"{n}.{s}").is_file() for n in MAP_NAMES)]
    if len(complete) == 2:
        raise MaterialError(f"{folder}: both .png and .exr maps exist and no material.json says which to use")
    if complete:
        return complete[0]
    # Name the first missing map of the format the folder seems to be in.
    suffix = "exr" if any((folder / f"{n}.exr").is_file() for n in MAP_NAMES) else "png"
    missing = next(n for n in MAP_NAMES if not (folder / f"{n}.{suffix}").is_file())
    raise MaterialError(f"{folder}: missing {missing} map ({missing}.{suffix}) and no material.json")
