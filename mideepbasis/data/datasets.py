"""Material readers: Deschaintre strips, folders of per-map images, material folders, the procedural stream.

Every reader yields ``Material`` objects in the conventions of docs/ARCHITECTURE.md sections 5-6
and says how its files were encoded (``encoding`` and each material's provenance). A corrupt or missing file never stops a
run: it is skipped with a warning and counted in ``skipped``.

    for material in DeschaintreDataset("../shared/data/deschaintre2018-test"): ...
    for material in PBRFolderDataset("downloads/ambientcg"): ...      # basecolor/normal/roughness/...
    stream = ProceduralStream(seed=1)                                 # endless, for DataLoader workers
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from .. import constants
from ..errors import MideepbasisError
from ..imageio import read_image
from ..material import Material

#: Image suffixes the folder readers look at.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


class MaterialReader:
    """A finite list of material sources read lazily; bad sources are skipped and counted.

    Attributes:
        sources: what each material is read from (files or folders), in order.
        encoding: how the files store the maps, e.g. ``stored-as-is`` or ``srgb-colour``.
        skipped: number of sources skipped since creation.
        skipped_sources: those sources with the reason, as (source, message).
    """

    encoding = "unknown"

    def __init__(self, sources: list):
        self.sources = list(sources)
        self.skipped = 0
        self.skipped_sources: list[tuple[str, str]] = []

    def __len__(self) -> int:
        return len(self.sources)

    def load(self, source) -> Material:  # pragma: no cover - abstract
        raise NotImplementedError

    def __iter__(self) -> Iterator[Material]:
        for source in self.sources:
            material = self.try_load(source)
            if material is not None:
                yield material

    def try_load(self, source) -> Material | None:
        """The material, or None after a warning (the source is counted as skipped)."""
        try:
            return self.load(source)
        except (MideepbasisError, OSError, ValueError) as error:
            self.skipped += 1
            self.skipped_sources.append((str(source), str(error)))
            warnings.warn(f"skipping {source}: {error}", stacklevel=2)
            return None


def _existing_folder(path) -> Path:
    folder = Path(path)
    if not folder.is_dir():
        raise FileNotFoundError(f"dataset folder {folder} does not exist")
    return folder


class DeschaintreDataset(MaterialReader):
    """The strips of Deschaintre et al. 2018 (5-panel 1440x288 or 1280x256) and 4-panel 2048x512 strips.

    Map values are used as stored (no sRGB decoding), as the reference implementations do, and
    the materials are marked with the ``deepbasis`` convention of those implementations.

    Args:
        folder: folder of ``*.png`` strips (read in sorted order).
        with_photo: also return the strip's flash panel (5-panel strips; None for 4-panel).
    """

    encoding = "stored-as-is"

    def __init__(self, folder, with_photo: bool = False):
        self.with_photo = with_photo
        super().__init__(sorted(_existing_folder(folder).glob("*.png")))

    def load(self, source):
        return Material.from_deschaintre(source, return_photo=self.with_photo)


class MaterialFolderDataset(MaterialReader):
    """Material folders of docs/ARCHITECTURE.md section 6 (``material.json`` plus four maps) under ``root``."""

    encoding = "material.json"

    def __init__(self, root):
        root = _existing_folder(root)
        folders = sorted({path.parent for path in root.rglob("material.json")})
        super().__init__(folders)

    def load(self, source):
        return Material.load(source)


# --- folders of per-map images, as public PBR libraries ship them ---------------------------------

#: Map kinds and the file-name words that announce them (ambientCG, Poly Haven, texture.com, ...).
MAP_WORDS = {
    "base_color": ("basecolor", "base_color", "basecolour", "albedo", "col", "color", "colour", "diff", "diffuse"),
    "normal": ("normal", "normalgl", "normaldx", "nor", "nrm", "norm"),
    "roughness": ("roughness", "rough", "rgh"),
    "glossiness": ("glossiness", "gloss"),
    "metallic": ("metallic", "metalness", "metal", "met"),
    "specular": ("specular", "spec"),
}
_WORD_KIND = {word: kind for kind, words in MAP_WORDS.items() for word in words}
_NOISE_WORDS = re.compile(r"^(\d+k|\d+x\d+|\d+|gl|dx|opengl|directx|png|jpg|exr|map|tex|texture)$")


def classify_map_file(path: Path) -> tuple[str, str, str] | None:
    """(material key, map kind, normal convention) of an image file name, or None.

    The key is the folder plus the name without the map word and resolution tokens, so the
    files ``Bricks075_2K_Color.jpg`` and ``Bricks075_2K_NormalDX.jpg`` share the key
    ``.../bricks075``. DirectX normals are announced by ``dx``/``directx`` in the name.
    """
    tokens = [t for t in re.split(r"[_\-. ]+", path.stem.lower()) if t]
    kinds = [(i, _WORD_KIND[t]) for i, t in enumerate(tokens) if t in _WORD_KIND]
    if not kinds:
        return None
    index, kind = kinds[-1]  # the map word usually comes last: "wood_floor_diff_2k"
    if kind == "base_color" and tokens[index] in ("diff", "diffuse"):
        kind = "diffuse"
    directx = any(t in ("dx", "directx", "normaldx") for t in tokens)
    rest = [t for i, t in enumerate(tokens) if i != index and not _NOISE_WORDS.match(t)]
    return str(path.parent / "_".join(rest)), kind, "directx" if directx else "opengl"


class PBRFolderDataset(MaterialReader):
    """Per-map images as public PBR libraries ship them, in one folder or one folder per material.

    Recognises base colour / albedo / diffuse, normal (OpenGL, or DirectX when the name says
    ``dx``), roughness or glossiness, metallic and specular maps (see ``MAP_WORDS``). Two
    workflows: metallic-roughness (base colour + metallic, converted with ``Material.from_pbr``)
    and specular (diffuse + specular, taken as they are). Colour maps are read as sRGB-encoded
    8/16-bit images (linear if EXR); normal, roughness and metallic as linear data. A missing
    normal map means a flat surface; a missing metallic map means a dielectric.

    Args:
        root: folder searched recursively.
        dielectric_f0: F0 of dielectrics in the metallic workflow [unitless].
    """

    encoding = "srgb-colour, linear data, normal (n + 1) / 2"

    def __init__(self, root, dielectric_f0: float = constants.DIELECTRIC_F0):
        self.dielectric_f0 = dielectric_f0
        groups: dict[str, dict[str, Path]] = {}
        self.normal_conventions: dict[str, str] = {}
        for path in sorted(_existing_folder(root).rglob("*")):
            if path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file():
                continue
            classified = classify_map_file(path)
            if classified is None:
                continue
            key, kind, convention = classified
            groups.setdefault(key, {}).setdefault(kind, path)
            if kind == "normal":
                self.normal_conventions[key] = convention
        super().__init__(sorted(groups))
        self.groups = groups

    def load(self, key) -> Material:
        files = self.groups[key]
        name = Path(key).name or key
        color_kind = "base_color" if "base_color" in files else "diffuse" if "diffuse" in files else None
        if color_kind is None:
            raise MideepbasisError(f"{key}: no base colour, albedo or diffuse map among {sorted(f.name for f in files.values())}")
        if "roughness" not in files and "glossiness" not in files:
            raise MideepbasisError(f"{key}: no roughness or glossiness map")

        def colour(kind):
            return torch.from_numpy(_channels(read_image(files[kind], decode_srgb=True), 3)).permute(2, 0, 1)

        def data(kind, channels):
            return torch.from_numpy(_channels(read_image(files[kind]), channels)).permute(2, 0, 1)

        color = colour(color_kind)
        roughness = data("roughness", 1) if "roughness" in files else 1.0 - data("glossiness", 1)
        normal = None
        if "normal" in files:
            normal = data("normal", 3) * 2.0 - 1.0
            if self.normal_conventions.get(key) == "directx":
                normal[1] = -normal[1]
            normal = torch.cat([normal[:2], normal[2:].clamp(min=0.0)])
            normal = normal / (normal * normal).sum(0, keepdim=True).sqrt().clamp(min=1e-6)
        shapes = {kind: tuple(t.shape[1:]) for kind, t in (("colour", color), ("roughness", roughness))}
        if normal is not None:
            shapes["normal"] = tuple(normal.shape[1:])
        if len(set(shapes.values())) > 1:
            raise MideepbasisError(f"{key}: maps differ in size {shapes}")
        provenance = {"source": name, "files": {k: str(v) for k, v in files.items()}, "encoding": self.encoding,
                      "normal_convention": self.normal_conventions.get(key, "opengl")}
        if color_kind == "base_color" and "specular" not in files:
            metallic = data("metallic", 1) if "metallic" in files else torch.zeros_like(roughness)
            provenance["workflow"] = "metallic-roughness"
            return Material.from_pbr(color, metallic, roughness, normal=normal, dielectric_f0=self.dielectric_f0,
                                     provenance=provenance, source=name)
        specular = colour("specular") if "specular" in files else torch.full_like(color, self.dielectric_f0)
        if normal is None:
            normal = torch.zeros_like(color)
            normal[2] = 1.0
        provenance["workflow"] = "specular"
        return Material(normal=normal, diffuse=color, roughness=roughness, specular=specular,
                        provenance=provenance, source=name)


def _channels(image: np.ndarray, channels: int) -> np.ndarray:
    """(H, W, C) to (H, W, channels): grey expanded to RGB, RGB averaged to grey."""
    if image.shape[2] == channels:
        return np.ascontiguousarray(image)
    if channels == 1:
        return np.ascontiguousarray(image.mean(axis=2, keepdims=True))
    return np.ascontiguousarray(np.repeat(image[..., :1], channels, axis=2))


# --- the procedural stream ----------------------------------------------------------------------


def material_seed(stream_seed: int, index: int) -> int:
    """Seed of material number ``index`` of a stream: a hash, so that streams do not overlap."""
    return int(np.random.SeedSequence([int(stream_seed), int(index)]).generate_state(1, dtype=np.uint64)[0] >> 1)


def _procedural_item(stream_seed: int, index: int, config) -> dict:
    from .procedural import generate

    material = generate(material_seed(stream_seed, index), config=config)
    return {"maps": material.to_tensor(), "index": index, "family": material.provenance["family"]}


class ProceduralMaterials(torch.utils.data.Dataset):
    """Procedural materials by number: item i is always the same material (for exact resumes).

    Items are dicts: ``maps`` (10, H, W) float32, ``index``, ``family``. The length is nominal
    (2^62): a sampler decides which numbers a run draws.

    Args:
        seed: seed of the whole set.
        config: a ``procedural.GeneratorConfig`` (size, tileable, families, ...).
    """

    def __init__(self, seed: int = 0, config=None):
        from .procedural import GeneratorConfig

        self.seed, self.config = seed, config or GeneratorConfig()

    def __len__(self) -> int:
        return 2**62

    def __getitem__(self, index: int) -> dict:
        return _procedural_item(self.seed, index, self.config)


class ProceduralStream(IterableDataset):
    """An endless, seeded stream of procedural materials, safe with DataLoader workers and DDP.

    Worker w of W in process r of R yields the material numbers congruent to ``r * W + w``
    modulo ``R * W``, from ``start`` on: together they draw every number once, each number
    always giving the same material. A material that fails to generate is skipped with a
    warning and counted; the stream goes on.

    Args:
        seed: seed of the whole stream.
        config: a ``procedural.GeneratorConfig``.
        rank, world_size: this process among the data-parallel ones.
        start: the first material number.
    """

    def __init__(self, seed: int = 0, config=None, rank: int = 0, world_size: int = 1, start: int = 0):
        super().__init__()
        self.materials = ProceduralMaterials(seed, config)
        self.rank, self.world_size, self.start = rank, world_size, start
        self.skipped = 0

    def __iter__(self):
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        stride = workers * self.world_size
        index = self.start + ((self.rank * workers + worker - self.start) % stride)
        while True:
            try:
                yield self.materials[index]
            except (MideepbasisError, ValueError) as error:  # a bad draw must not stop training
                self.skipped += 1
                warnings.warn(f"skipping procedural material {index}: {error}")
            index += stride
