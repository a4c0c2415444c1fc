"""The data of a training run: its materials by number (``TrainingMaterials``, ``augment``), the
batches of material numbers each step takes (``StepBatchSampler``), and the photographed pools of
a unit trained alone (``NormalUnitPool``, ``LocalUnitPool``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from .. import constants, geometry
from ..data.procedural import GeneratorConfig
from ..data.synth import TrainingBatch, synthesize
from ..errors import InputError
from ..model.inputs import RELIEF_CHANNELS, RELIEF_DIRECTION_CHANNEL, decode_photo, octave_relief_inputs
from ..model.symmetry import dihedral
from .config import TrainConfig
from .losses import highlight_weights


class TrainingMaterials(Dataset):
    """Item i: a (10, size, size) material from one of the sources, always the same for the same i
    (procedural ones drawn with the ``procedural`` generator settings; default: the defaults).

    Sources are drawn in turn by a hash of i; folder materials are cropped or resized to the
    training size and randomly flipped and turned by 90 degrees (normals turned with them).
    """

    def __init__(self, sources: tuple[str, ...], size: int, seed: int, procedural: GeneratorConfig | None = None):
        self.size, self.seed = size, seed
        self.readers = []
        self.procedural = None
        for source in sources:
            if source == "procedural":
                from ..data.datasets import ProceduralMaterials

                config = dataclasses.replace(procedural, size=size) if procedural else GeneratorConfig(size=size)
                self.procedural = ProceduralMaterials(seed, config)
                self.readers.append("procedural")
            else:
                self.readers.append(self._folder_reader(source))

    @staticmethod
    def _folder_reader(source: str):
        from ..data.datasets import DeschaintreDataset, MaterialFolderDataset, PBRFolderDataset

        path = Path(source).resolve()
        if "shared" in path.parts and "data" in path.parts:
            raise InputError(f"{source}: the shared evaluation data is never used for training")
        if not path.is_dir():
            raise InputError(f"{source}: no such data folder (use 'procedural' or a folder of materials)")
        for reader_type in (MaterialFolderDataset, PBRFolderDataset, DeschaintreDataset):
            reader = reader_type(path)
            if len(reader):
                return reader
        raise InputError(f"{source}: no materials found (material folders, PBR maps or Deschaintre strips)")

    def __len__(self) -> int:
        return 2**62

    def __getitem__(self, index: int) -> torch.Tensor:
        rng = np.random.default_rng([self.seed, index, 7])
        reader = self.readers[int(rng.integers(len(self.readers)))]
        if reader == "procedural":
            return self.procedural[index]["maps"]
        for attempt in range(len(reader)):
            material = reader.try_load(reader.sources[int(rng.integers(len(reader)))])
            if material is not None:
                if isinstance(material, tuple):
                    material = material[0]
                return augment(material.to_tensor(), self.size, rng)
        raise InputError(f"no readable material among {len(reader)} in a training folder")


def augment(maps: torch.Tensor, size: int, rng: np.random.Generator) -> torch.Tensor:
    """A random square crop (or resize) to size x size, flips and quarter turns, normals kept consistent."""
    _, height, width = maps.shape
    if min(height, width) < size:
        maps = torch.nn.functional.interpolate(maps[None], size=(size, size), mode="bilinear", align_corners=False)[0]
    else:
        top, left = int(rng.integers(height - size + 1)), int(rng.integers(width - size + 1))
        maps = maps[:, top:top + size, left:left + size]
    maps = dihedral(maps, 0, bool(rng.random() < 0.5), int(rng.integers(4)))
    maps[constants.NORMAL] = geometry.unit_vectors(maps[constants.NORMAL], dim=0)
    return maps


class PhotographedPool:
    """A pool of P photographed training materials renewed R at a time (the data of a unit trained
    alone). Before step s the pool holds materials s*R .. s*R + P - 1 of the training sources,
    material k in slot k mod P, photographed with a generator of its own: the pool at a step is
    the same whether the run got there in one go or resumed. Subclasses store what their unit
    needs (``_store``) and draw batches from it."""

    def __init__(self, materials: Dataset, config: TrainConfig, step: int, size: int, refresh: int):
        self.materials, self.config, self.size, self.refresh = materials, config, size, refresh
        self._photograph(range(step * refresh, step * refresh + size))
        self.step = step

    def _photograph(self, numbers) -> None:
        config = self.config
        for number in numbers:
            maps = self.materials[number][None]
            batch = synthesize(maps, torch.Generator().manual_seed(config.seed * 1_000_003 + number), config.synthesis,
                               config.network.extra_inputs)
            self._store(number % self.size, maps, batch, number)

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch, number: int) -> None:
        raise NotImplementedError

    def batch(self, generator: torch.Generator):
        """A training batch of the pool's unit."""
        raise NotImplementedError

    def advance(self) -> None:
        """Replace the pool's oldest materials: the pool of the next step."""
        first = self.step * self.refresh + self.size
        self._photograph(range(first, first + self.refresh))
        self.step += 1


class NormalUnitPool(PhotographedPool):
    """The training data of the normal unit alone (``TrainConfig.normal_pool``): the relief inputs
    and true normals of a pool of photographed training materials (``PhotographedPool``). A
    unit of several octaves (``NetworkConfig.normal_unit_octaves``) gets the relief inputs of
    the photo area-averaged to each (``coarse_relief``), as ``DeepBasisNet.normal_slope`` makes them.
    """

    def __init__(self, materials: Dataset, config: TrainConfig, step: int):
        size, channels = config.size, RELIEF_CHANNELS
        self.relief = torch.empty(config.normal_pool, channels, size, size)
        #: The relief inputs at octaves 1, 2, ...: (pool, channels, size / 2^k, size / 2^k) each.
        self.coarse_relief = [torch.empty(config.normal_pool, channels, size >> k, size >> k)
                              for k in range(1, len(config.network.normal_unit_octaves))]
        self.normals = torch.empty(config.normal_pool, 3, size, size)
        super().__init__(materials, config, step, config.normal_pool, config.normal_pool_refresh)

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch, number: int) -> None:
        config = self.config
        reliefs = octave_relief_inputs(decode_photo(batch.inputs), batch.lights, 1 + len(self.coarse_relief),
                                       config.synthesis.fov, config.network.convention, config.network.plane_extent)
        for stored, relief in zip([self.relief, *self.coarse_relief], reliefs, strict=True):
            stored[slot] = relief[0]
        self.normals[slot] = batch.maps[0, constants.NORMAL]  # as photographed (``supersample``: downsampled)

    def batch(self, generator: torch.Generator) -> tuple[list[torch.Tensor], torch.Tensor]:
        """A batch of random crops, each mirrored and turned at random: (the relief inputs at each
        octave, (B, relief channels, C / 2^k, C / 2^k) the k-th; true normals (B, 3, C, C)). With
        several octaves the corners fall on multiples of the coarsest octave's pixel."""
        config, crop = self.config, self.config.normal_crop
        slots = torch.randint(0, config.normal_pool, (config.batch,), generator=generator).tolist()
        step = 2**len(self.coarse_relief)
        corners = (torch.randint(0, (config.size - crop) // step + 1, (config.batch, 2), generator=generator)
                   * step).tolist()
        moves = torch.randint(0, 8, (config.batch,), generator=generator).tolist()
        reliefs, normals = [[] for _ in range(1 + len(self.coarse_relief))], []
        for slot, (top, left), move in zip(slots, corners, moves):
            for octave, stored in enumerate([self.relief, *self.coarse_relief]):
                window = (slot, slice(None), slice(top >> octave, (top + crop) >> octave),
                          slice(left >> octave, (left + crop) >> octave))
                reliefs[octave].append(dihedral(stored[window], RELIEF_DIRECTION_CHANNEL, move >= 4, move % 4))
            window = (slot, slice(None), slice(top, top + crop), slice(left, left + crop))
            normals.append(dihedral(self.normals[window], 0, move >= 4, move % 4))
        return [torch.stack(relief) for relief in reliefs], torch.stack(normals)


@dataclass
class LocalUnitBatch:
    """A batch of the local pool (``LocalUnitPool``)."""

    local_inputs: torch.Tensor
    """(B, input channels + 3 + N, H, W): what the frozen rest gives the local unit (the error map
    of the shifted global bases with ``TrainConfig.global_roughness_jitter``)."""

    weights: torch.Tensor
    """(B, N, H, W) the frozen weights."""

    global_bases: torch.Tensor
    """(B, N, 10) the frozen global bases (signed space), their lobe shifted with
    ``TrainConfig.global_roughness_jitter`` / ``global_specular_jitter``."""

    slope: torch.Tensor
    """(B, 2, H, W) the frozen normal unit's slope (zeros without one)."""

    maps: torch.Tensor
    """(B, 10, H, W) the true maps."""

    diffuse_weights: torch.Tensor | None = None
    """(B, 1, H, W) weights of the diffuse loss (``TrainConfig.highlight_weight``), or None: 1."""

    kept_signed: torch.Tensor | None = None
    """(B, 10, H, W) the blend of the init's network, signed space (``TrainConfig.local_pool_keep``;
    its maps are ``to_maps`` of it), or None."""


def shifted_lobes(global_bases: torch.Tensor, roughness_shift: torch.Tensor, specular_octaves: torch.Tensor
                  ) -> torch.Tensor:
    """Global bases (B, N, 10) signed space with every basis's roughness shifted by ``roughness_shift``
    (B,) [roughness] and its specular times 2^``specular_octaves`` (B,), both clipped to [0, 1]
    (``TrainConfig.global_roughness_jitter``)."""
    bases = global_bases.clone()
    roughness = bases[:, :, constants.ROUGHNESS] * 0.5 + 0.5 + roughness_shift.view(-1, 1, 1)
    specular = (bases[:, :, constants.SPECULAR] * 0.5 + 0.5) * torch.exp2(specular_octaves).view(-1, 1, 1)
    bases[:, :, constants.ROUGHNESS] = roughness.clamp(0.0, 1.0) * 2.0 - 1.0
    bases[:, :, constants.SPECULAR] = specular.clamp(0.0, 1.0) * 2.0 - 1.0
    return bases


class LocalUnitPool(PhotographedPool):
    """The training data of the local unit alone (``TrainConfig.local_pool``): for each material of
    the pool (``PhotographedPool``), what ``stage_of`` (network inputs, lights, field of view, the
    global lobe's shift: roughness (1,) and specular octaves (1,)) gives: the local unit's inputs and
    the global bases (both with the lobe shifted, ``TrainConfig.global_roughness_jitter``), the
    weights, the normal unit's slope, from the frozen rest of the network, and the init's blend of
    the unshifted inputs (``TrainConfig.local_pool_keep``, signed space, or None); beside the true maps."""

    def __init__(self, materials: Dataset, config: TrainConfig, step: int, stage_of):
        self.stage_of = stage_of
        network, size, count = config.network, config.size, config.local_pool
        n = network.num_bases
        self.local_inputs = torch.empty(count, network.input_channels + 3 + n, size, size)
        self.weights = torch.empty(count, n, size, size)
        self.global_bases = torch.empty(count, n, constants.BASIS_CHANNELS)
        self.slope = torch.empty(count, 2, size, size)
        self.maps = torch.empty(count, 10, size, size)
        self.diffuse_weights = torch.empty(count, 1, size, size) if config.highlight_weight else None
        self.kept_signed = torch.empty(count, 10, size, size) if config.local_pool_keep else None
        super().__init__(materials, config, step, count, config.local_pool_refresh)

    def lobe_shift(self, number: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Material ``number``'s shift of the global lobe: (roughness (1,), specular octaves (1,)),
        drawn uniformly within ``global_roughness_jitter`` and ``global_specular_jitter`` by a
        generator of the material's own (zeros when both are off)."""
        config = self.config
        if not (config.global_roughness_jitter or config.global_specular_jitter):
            return torch.zeros(1), torch.zeros(1)
        draws = np.random.default_rng([config.seed, number, 13]).uniform(-1.0, 1.0, size=2)
        return (torch.tensor([draws[0] * config.global_roughness_jitter], dtype=torch.float32),
                torch.tensor([draws[1] * config.global_specular_jitter], dtype=torch.float32))

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch, number: int) -> None:
        # Each material at the field of view it was photographed at (``SynthesisConfig.fov_range``).
        local_inputs, weights, global_bases, slope, kept_signed = self.stage_of(batch.inputs, batch.lights, batch.fov,
                                                                                *self.lobe_shift(number))
        self.local_inputs[slot], self.weights[slot], self.global_bases[slot] = local_inputs[0], weights[0], global_bases[0]
        self.slope[slot], self.maps[slot] = slope[0], batch.maps[0]
        if kept_signed is not None:
            self.kept_signed[slot] = kept_signed[0]
        if self.diffuse_weights is not None:
            config = self.config
            self.diffuse_weights[slot] = highlight_weights(batch.maps, batch.lights, config.highlight_weight,
                                                           batch.fov, config.network.convention,
                                                           config.network.plane_extent)[0]

    def batch(self, generator: torch.Generator) -> LocalUnitBatch:
        """``config.batch`` materials of the pool, drawn at random."""
        slots = torch.randint(0, self.size, (self.config.batch,), generator=generator)

        def drawn(stored: torch.Tensor | None) -> torch.Tensor | None:
            return None if stored is None else stored[slots]

        return LocalUnitBatch(self.local_inputs[slots], self.weights[slots], self.global_bases[slots],
                              self.slope[slots], self.maps[slots], drawn(self.diffuse_weights),
                              drawn(self.kept_signed))




class StepBatchSampler(Sampler):
    """Batches of material numbers in step order: step s, rank r takes s*B*R + r*B + (0..B-1)."""

    def __init__(self, batch: int, start_step: int, rank: int, world_size: int):
        self.batch, self.start_step, self.rank, self.world_size = batch, start_step, rank, world_size

    def __iter__(self):
        step = self.start_step
        while True:
            first = (step * self.world_size + self.rank) * self.batch
            yield list(range(first, first + self.batch))
            step += 1
