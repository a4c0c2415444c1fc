"""Training DeepBasisNet: L = L_sup + 0.05 L_vc on synthesised flash photos, resumable, DDP-ready.

    mideepbasis train --preset compact --data procedural --steps 20000 --batch 8 --out runs/compact
    torchrun --nproc_per_node 2 -m mideepbasis.cli train ...          # several processes, no change

Every step draws a batch of materials (procedural, or folders of materials), synthesises their
photos and the photos of their variations M + xi under hand-held flashes (``data.synth``),
predicts both and minimises

    L_sup = |maps(M) - M|_1                                  (signed space, as the paper)
    L_vc  = |xi(bases(M)) - bases(M + xi)|_1 + |maps(M + xi) - (M + xi)|_1

with Adam and a cosine learning-rate decay. Material number i of the run is always the same
material and the synthesis generator's state is saved, so ``--resume`` continues exactly where a
killed run stopped. Rank 0 writes ``OUT/train.jsonl`` (losses, learning rate, speed),
``OUT/loss.png``, validation sheets ``OUT/validation/step_XXXXXXX.png``, ``OUT/checkpoint.safetensors``
every few minutes (atomically) and ``OUT/model.safetensors`` at the end.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, Sampler

from . import constants, geometry
from .configs import differences, positive_int
from .data.procedural import GeneratorConfig
from .data.synth import PHONE_LEVERS, SynthesisConfig, TrainingBatch, Variation, synthesize
from .errors import InputError, MideepbasisError
from .model.checkpoint import CheckpointError, non_finite_tensors, previous_path, read_checkpoint, save_checkpoint
from .model.inputs import RELIEF_DIRECTION_CHANNEL, decode_photo, octave_relief_inputs, relief_channels
from .model.network import DeepBasisNet, DeepBasisOutput, NetworkConfig, add_slope, preset, to_signed
from .model.symmetry import dihedral


class TrainingDiverged(MideepbasisError):
    """The loss became NaN or infinite; the last checkpoint on disk is kept."""


@dataclass
class TrainConfig:
    """A training run. Stored, resolved, in every checkpoint of the run."""

    out: str = "runs/default"
    """Output folder of the run [path]."""

    preset: str = "compact"
    """Network preset the network's settings start from: ``compact``, ``paper`` or ``tiny`` (tests)."""

    network: NetworkConfig | dict | None = None
    """The network (None: the preset's; a dict: fields of the preset's replaced, e.g. the ablations'
    use_local, use_global, use_bases, num_bases). Stored resolved."""

    data: tuple[str, ...] = ("procedural",)
    """Material sources: ``procedural`` and/or folders (material folders, PBR folders, Deschaintre strips)."""

    steps: int = field(default=1000, metadata={"parse": positive_int})
    """Optimisation steps."""

    batch: int = field(default=8, metadata={"parse": positive_int})
    """Materials per step and process (each seen twice: M and M + xi)."""

    size: int = field(default=constants.DEFAULT_RESOLUTION, metadata={"parse": positive_int})
    """Training resolution [pixels]; a multiple of the network's stride."""

    lr: float = 1e-3
    """Adam learning rate of the encoder, weight decoder and global unit."""

    local_lr: float = 3e-3
    """Adam learning rate of the local unit (the paper trains it faster too)."""

    final_lr_fraction: float = 0.01
    """The cosine decay ends at this fraction of the learning rates."""

    vc_weight: float = constants.VC_LOSS_WEIGHT
    """Weight of the variation-consistency loss; 0 turns it off (and halves the work)."""

    normal_weight: float = 4.0
    """Weight of the normal channels in the supervised L1 (the others weigh 1; the mean weight is
    kept at 1). The paper weighs all ten equally; on a CPU budget the normals, whose signal in a
    flash photo is faint, stay flat for thousands of steps unless they weigh more."""

    saturation_weight: float = 1e-3
    """Weight of a penalty on the weight decoder's pre-tanh outputs beyond +-2 (not in the paper).
    Without it a run at these learning rates drove them to +-30 within a few hundred steps: the
    tanh saturated, every pixel got the same blend of five bases, the blend's gradient vanished
    and the normals stayed flat for good. The penalty's gradient bypasses the tanh, so it also
    revives a saturated network."""

    seed: int = 0
    """Seed of the run: materials, network initialisation, synthesis."""

    workers: int = 2
    """DataLoader worker processes generating materials."""

    checkpoint_minutes: float = 5.0
    """Write the resumable checkpoint this often [minutes]."""

    log_every: int = field(default=10, metadata={"parse": positive_int})
    """Log the losses every this many steps."""

    validate_every: int = 250
    """Write validation renders and metrics every this many steps (0: never)."""

    device: str = field(default="auto", metadata={"choices": ("auto", "cpu", "cuda")})
    """``auto`` (CUDA when available), ``cpu`` or ``cuda``."""

    synthesis: SynthesisConfig | dict | None = None
    """How the training photos are made (None: the defaults; a dict: fields replaced). Its shading
    convention is always the network's. Stored resolved."""

    procedural: GeneratorConfig | dict | None = None
    """The procedural materials (None: the defaults; a dict: fields replaced, e.g.
    ``coarse_relief_tilt_deg``). Its size is always the run's. Stored resolved."""

    init: str | None = None
    """Start from the weights of this checkpoint (same network configuration), e.g. to fine-tune
    at a higher resolution; the optimiser and the schedule start afresh."""

    render_weight: float = 0.0
    """Weight of the re-rendering loss (0: off): L1 of log(1 + x) between renders of the predicted
    and the true material under random lights and views, as Deschaintre et al. 2018. Under a
    flash beside the camera the normals change the photo little; under grazing and mirror
    configurations they change it a lot."""

    render_lights: int = field(default=6, metadata={"parse": positive_int})
    """Light-and-view pairs per material of the re-rendering loss; half of them (rounded down)
    are mirror pairs that put a highlight on the sample."""

    render_backend: str = field(default="mitsuba", metadata={"choices": ("mitsuba", "torch")})
    """Renderer of the training photos, the error map and the re-rendering loss: ``mitsuba`` (the
    ``svbrdf`` plugin) or ``torch`` (the reference, equal to float precision; for a GPU server
    without Mitsuba)."""

    bf16: bool = False
    """bfloat16 autocast of the network's forward pass; renders and losses stay float32."""

    grad_clip: float = 1.0
    """Largest global norm of the gradient; larger ones are scaled down (0: no clipping)."""

    warmup_steps: int = 0
    """Linear learning-rate warm-up over this many steps before the cosine decay."""

    validation_count: int = field(default=32, metadata={"parse": positive_int})
    """Held-out procedural materials (fixed seeds, never drawn in training) of each validation set."""

    select_by: str = field(default="held_out", metadata={"choices": ("held_out", "run_generator")})
    """Which validation set keeps ``best.safetensors``. Each validation predicts two: ``held_out``,
    materials of the generator as it was when the learning curve began (its figures compare across
    all runs); ``run_generator``, as many materials drawn by this run's own generator
    (``procedural``), which sees what a change of the training materials teaches (e.g. the broad
    undulation of ``coarse_relief_tilt_deg``, which the first set lacks)."""

    train_only: tuple[str, ...] = ()
    """Train only these parts of the network (``TRAINABLE_PARTS``: e.g. ``normal_unit``); the
    others keep the weights the run starts with (``init``) and get no gradient. Empty: all."""

    max_minutes: float = 0.0
    """Stop after this much training wall time in this process [minutes], with a resumable
    checkpoint (0: no limit); the schedule still runs to ``steps``."""

    normal_pool: int = 0
    """0: every part learns inside the whole network. N > 0: the normal unit alone learns the normal
    from its relief inputs (``--train-only normal_unit``), with no pass of the rest of the network:
    random crops (``normal_crop``), mirrored and turned, of a pool of N photographed training
    materials (``NormalUnitPool``) of which ``normal_pool_refresh`` are replaced each step. Its
    prediction is taken over a flat rest, as ``DeepBasisNet`` adds it to the bases' normals (the
    shipped rest predicts nearly flat normals), and its loss is the mean squared error of the unit
    normals: the losses and weights of the whole network (``normal_weight``, ``vc_weight``,
    ``render_weight``, ``saturation_weight``) and ``workers`` do not apply. Validation runs the
    whole network. One process only (not under torchrun)."""

    normal_pool_refresh: int = field(default=2, metadata={"parse": positive_int})
    """Materials of the normal pool replaced by new ones each step."""

    normal_crop: int = field(default=64, metadata={"parse": positive_int})
    """Side of the normal pool's training crops [pixels]."""

    local_pool: int = 0
    """0: off. N > 0: the local unit alone learns (``--train-only local_unit``) on a pool of N
    photographed training materials (``LocalUnitPool``), of which ``local_pool_refresh`` are
    replaced each step. Each is stored with what the frozen rest of the network gives the local
    unit (its inputs: the photo, the error map of the global bases, the weights; the global bases)
    and the normal unit's slope, so a step runs the local unit alone. The loss is the whole
    network's (``normal_weight``, ``render_weight``), without the variation pair
    (``vc_weight``, ``saturation_weight`` and ``workers`` do not apply). Not with a normal unit
    that reads the albedo shading: its slope would depend on the local unit being trained, so a
    resumed run's pool would differ. The stage is computed in float32 (as ``capture`` runs).
    Validation runs the whole network. One process only."""

    local_pool_refresh: int = field(default=1, metadata={"parse": positive_int})
    """Materials of the local pool replaced by new ones each step."""

    local_pool_keep: tuple[str, ...] = ()
    """Maps (``constants.MAP_SLICES``: normal, diffuse, roughness, specular) the local unit alone keeps as the run's start (``init``) gives them:
    on their channels the target is not the true map but the map of the network with the init's
    local unit, so the unit learns the other maps without moving these. Trained alone on
    procedural materials the unit trades the roughness for the diffuse on the shared test set
    (MODEL.md); kept, the roughness cannot drift. Costs one more local-unit pass a step."""

    highlight_weight: float = 0.0
    """Extra weight of the diffuse map's loss under the flash's highlight, for the local unit alone
    (``local_pool``): each pixel's diffuse error weighs 1 + w * (the true specular lobe's
    brightness under the photo's flash, over its 99th percentile, at most 1), divided by the
    material's mean of that (``highlight_weights``). The
    highlight covers a few percent of a photo, so the plain loss hardly minds a highlight baked
    into the diffuse map (issue 11's demo smudge); 0: off."""

    normal_pool_loss: str = field(default="mse", metadata={"choices": ("mse", "crop_rmse")})
    """Loss of the normal pool (``normal_unit_loss``): ``mse``, the mean squared error over the
    batch; ``crop_rmse``, the mean over crops of each crop's RMSE, as ``evaluate`` averages the
    per-material RMSE: a nearly flat crop weighs as much as a deep one, where the squared error lets
    the deep ones decide."""

    def __post_init__(self):
        # Resolve the network and the synthesis now, so that what is stored is what ran.
        if self.network is None or isinstance(self.network, dict):
            overrides = {key: value for key, value in _fields(self.network).items() if key != "input_channels"}
            self.network = preset(self.preset, **overrides)
        synthesis = self.synthesis
        if synthesis is None or isinstance(synthesis, dict):
            synthesis = SynthesisConfig(**_fields(synthesis))
        self.synthesis = dataclasses.replace(synthesis, convention=self.network.convention)
        procedural = self.procedural
        if procedural is None or isinstance(procedural, dict):
            procedural = GeneratorConfig(**_fields(procedural))
        self.procedural = dataclasses.replace(procedural, size=self.size)
        self.data = tuple(self.data)
        if not self.data:
            raise ValueError("no material sources (data): give procedural and/or folders")
        self.train_only = tuple(self.train_only)
        self.local_pool_keep = tuple(self.local_pool_keep)
        unknown = sorted(set(self.train_only) - set(TRAINABLE_PARTS))
        if unknown:
            raise ValueError(f"unknown network parts {unknown} to train; expected some of {list(TRAINABLE_PARTS)}")
        if self.normal_pool < 0:
            raise ValueError(f"normal_pool {self.normal_pool} must be 0 (off) or a number of materials")
        if (self.normal_pool or self.local_pool) and self.synthesis.fov_range is not None:
            raise ValueError("the unit pools photograph at one field of view: synthesis.fov_range needs the whole network")
        if self.normal_pool and self.local_pool:
            raise ValueError("local_pool and normal_pool train different units: give one of them")
        if self.normal_pool:
            if not self.train_only or not set(self.train_only) <= set(NORMAL_PARTS) or not self.network.normal_unit_width:
                raise ValueError("normal_pool trains the normal units alone: it needs train_only = normal_unit "
                                 "and/or normal_booster, and a network with a normal unit (network.normal_unit_width)")
            if "normal_booster" in self.train_only and not self.network.normal_booster_width:
                raise ValueError("train_only names normal_booster: it needs network.normal_booster_width")
            if self.normal_crop > self.size or self.normal_crop % 16:
                raise ValueError(f"normal_crop {self.normal_crop} must be a multiple of 16 and at most size {self.size}")
            coarsest = 2 ** (len(self.network.normal_unit_octaves) - 1)
            if self.normal_crop % (16 * coarsest) or self.size % coarsest:
                raise ValueError(f"normal_crop {self.normal_crop} and size {self.size} must be multiples of "
                                 f"{16 * coarsest} and {coarsest}: the normal unit's coarsest octave sees them "
                                 f"at 1/{coarsest}")
            if self.normal_pool_refresh > self.normal_pool:
                raise ValueError("normal_pool_refresh cannot exceed normal_pool")
        if self.local_pool < 0:
            raise ValueError(f"local_pool {self.local_pool} must be 0 (off) or a number of materials")
        if self.local_pool:
            if self.train_only != ("local_unit",) or not (self.network.use_bases and self.network.use_local):
                raise ValueError("local_pool trains the local unit alone: it needs train_only = local_unit "
                                 "and a network with a local unit")
            if self.local_pool_refresh > self.local_pool:
                raise ValueError("local_pool_refresh cannot exceed local_pool")
            if self.network.normal_unit_albedo:
                raise ValueError("local_pool cannot train under a normal unit that reads the albedo shading "
                                 "(its slope would follow the local unit being trained)")
        unknown = [name for name in self.local_pool_keep if name not in constants.MAP_SLICES]
        if unknown:
            raise ValueError(f"local_pool_keep: unknown maps {unknown}; known: {list(constants.MAP_SLICES)}")
        if self.highlight_weight < 0 or (self.highlight_weight and not self.local_pool):
            raise ValueError(f"highlight_weight {self.highlight_weight} must be 0, or positive with local_pool")
        if self.local_pool_keep and not (self.local_pool and self.init):
            raise ValueError("local_pool_keep keeps maps as the init gives them: it needs local_pool and init")

    @classmethod
    def from_dict(cls, values: dict, source: str = "checkpoint", network: dict | None = None) -> TrainConfig:
        """The config a checkpoint stores. Older checkpoints store the network as overrides of its
        preset and the synthesis as overrides of the defaults: the network is then the one the
        checkpoint's weights were saved with (``network``, its document's), not today's preset."""
        from .model.checkpoint import network_config_from_dict

        values = dict(values)
        stored = values.get("network")
        complete = {f.name for f in dataclasses.fields(NetworkConfig)} <= set(stored or {})
        if isinstance(stored, dict) and (complete or network is not None):
            values["network"] = network_config_from_dict(stored if complete else network, source)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(f"{source}: unknown training settings {unknown}")
        return cls(**{key: tuple(value) if key == "data" else value for key, value in values.items()})


def _fields(values: dict | None) -> dict:
    """A nested config's fields as given (None: none), lists (as JSON stores tuples) made tuples."""
    return {key: tuple(value) if isinstance(value, list) else value for key, value in (values or {}).items()}


#: NetworkConfig fields of the local unit's size: ``--init`` from a network with another local unit
#: loads everything else and starts the local unit afresh.
LOCAL_UNIT_FIELDS = ("local_width", "local_encoder_blocks", "local_middle_blocks", "local_decoder_blocks",
                     "local_ending_kernel")

#: Parts of DeepBasisNet (its top-level modules) that ``train_only`` may name.
TRAINABLE_PARTS = ("encoder", "weight_decoder", "global_unit", "local_unit", "normal_unit", "normal_booster")

#: The parts the normal pool trains (either or both).
NORMAL_PARTS = ("normal_unit", "normal_booster")

#: Settings a resumed run may change: where and how it runs, not what it learns.
RESUMABLE_CHANGES = frozenset({"out", "workers", "checkpoint_minutes", "log_every", "validate_every", "device",
                               "max_minutes", "render_backend"})


# --- data --------------------------------------------------------------------------------------


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
                from .data.datasets import ProceduralMaterials

                config = dataclasses.replace(procedural, size=size) if procedural else GeneratorConfig(size=size)
                self.procedural = ProceduralMaterials(seed, config)
                self.readers.append("procedural")
            else:
                self.readers.append(self._folder_reader(source))

    @staticmethod
    def _folder_reader(source: str):
        from .data.datasets import DeschaintreDataset, MaterialFolderDataset, PBRFolderDataset

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
            self._store(number % self.size, maps, batch)

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch) -> None:
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
    unit that reads the albedo shading (``NetworkConfig.normal_unit_albedo``) gets the diffuse
    that ``diffuse_of`` (network inputs, lights) predicts: the frozen rest of the network's. A
    unit of several octaves (``NetworkConfig.normal_unit_octaves``) gets the relief inputs of
    the photo area-averaged to each (``coarse_relief``), as ``DeepBasisNet.normal_slope`` makes them.
    """

    def __init__(self, materials: Dataset, config: TrainConfig, step: int, diffuse_of=None):
        if config.network.normal_unit_albedo and diffuse_of is None:
            raise ValueError("a unit that reads the albedo shading needs the network's diffuse (diffuse_of)")
        self.diffuse_of = diffuse_of
        size, channels = config.size, relief_channels(config.network.normal_unit_albedo)
        self.relief = torch.empty(config.normal_pool, channels, size, size)
        #: The relief inputs at octaves 1, 2, ...: (pool, channels, size / 2^k, size / 2^k) each.
        self.coarse_relief = [torch.empty(config.normal_pool, channels, size >> k, size >> k)
                              for k in range(1, len(config.network.normal_unit_octaves))]
        self.normals = torch.empty(config.normal_pool, 3, size, size)
        super().__init__(materials, config, step, config.normal_pool, config.normal_pool_refresh)

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch) -> None:
        config = self.config
        diffuse = self.diffuse_of(batch.inputs, batch.lights) if config.network.normal_unit_albedo else None
        reliefs = octave_relief_inputs(decode_photo(batch.inputs), batch.lights, 1 + len(self.coarse_relief),
                                       config.synthesis.fov, config.network.convention, config.network.plane_extent,
                                       diffuse=diffuse)
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
    """(B, input channels + 3 + N, H, W): what the frozen rest gives the local unit."""

    weights: torch.Tensor
    """(B, N, H, W) the frozen weights."""

    global_bases: torch.Tensor
    """(B, N, 10) the frozen global bases (signed space)."""

    slope: torch.Tensor
    """(B, 2, H, W) the frozen normal unit's slope (zeros without one)."""

    maps: torch.Tensor
    """(B, 10, H, W) the true maps."""

    diffuse_weights: torch.Tensor | None = None
    """(B, 1, H, W) weights of the diffuse loss (``TrainConfig.highlight_weight``), or None: 1."""


class LocalUnitPool(PhotographedPool):
    """The training data of the local unit alone (``TrainConfig.local_pool``): for each material of
    the pool (``PhotographedPool``), what ``stage_of`` (network inputs, lights) gives: the local
    unit's inputs, the weights, the global bases and the normal unit's slope, from the frozen rest
    of the network; beside the true maps."""

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
        super().__init__(materials, config, step, count, config.local_pool_refresh)

    def _store(self, slot: int, maps: torch.Tensor, batch: TrainingBatch) -> None:
        local_inputs, weights, global_bases, slope = self.stage_of(batch.inputs, batch.lights)
        self.local_inputs[slot], self.weights[slot], self.global_bases[slot] = local_inputs[0], weights[0], global_bases[0]
        self.slope[slot], self.maps[slot] = slope[0], batch.maps[0]
        if self.diffuse_weights is not None:
            config = self.config
            self.diffuse_weights[slot] = highlight_weights(batch.maps, batch.lights, config.highlight_weight,
                                                           config.synthesis.fov, config.network.convention,
                                                           config.network.plane_extent)[0]

    def batch(self, generator: torch.Generator) -> LocalUnitBatch:
        """``config.batch`` materials of the pool, drawn at random."""
        slots = torch.randint(0, self.size, (self.config.batch,), generator=generator)
        return LocalUnitBatch(self.local_inputs[slots], self.weights[slots], self.global_bases[slots],
                              self.slope[slots], self.maps[slots],
                              None if self.diffuse_weights is None else self.diffuse_weights[slots])


def specular_lobe(maps: torch.Tensor, lights: torch.Tensor, fov: float, convention: str,
                  extent: float = 1.0) -> torch.Tensor:
    """The luminance (B, 1, H, W) of the maps' (B, 10, H, W) specular lobe alone (their diffuse
    set to zero) rendered under the flashes at ``lights`` (B, 3): where the highlight is."""
    from .render import render_flash

    specular_only = maps.clone()
    specular_only[:, constants.DIFFUSE] = 0.0
    with torch.no_grad():
        rgb = render_flash(specular_only, lights.view(-1, 1, 3), fov=fov, convention=convention, extent=extent)[:, 0]
    return sum(weight * rgb[:, channel] for channel, weight in enumerate(constants.LUMINANCE_WEIGHTS))[:, None]


#: The lobe's brightness that weighs fully in ``highlight_weights``: its 99th percentile.
HIGHLIGHT_PEAK_QUANTILE = 0.99


def highlight_weights(maps: torch.Tensor, lights: torch.Tensor, weight: float, fov: float, convention: str,
                      extent: float = 1.0) -> torch.Tensor:
    """Per-pixel weights (B, 1, H, W) of the diffuse loss: 1 + ``weight`` * the specular lobe alone
    (the maps (B, 10, H, W) with their diffuse set to zero) rendered under the flashes at
    ``lights`` (B, 3), as luminance over its ``HIGHLIGHT_PEAK_QUANTILE`` (at most 1); then divided
    by their mean, so that the highlight moves the loss within a material, not its scale. A
    material without specular weighs 1 everywhere."""
    lobe = specular_lobe(maps, lights, fov, convention, extent)
    # A percentile rather than the maximum: the glints of a bumpy glossy sample would set the scale.
    peak = torch.quantile(lobe.flatten(1), HIGHLIGHT_PEAK_QUANTILE, dim=1).view(-1, 1, 1, 1)
    share = torch.where(peak > 0, lobe / peak.clamp_min(1e-12), torch.zeros_like(lobe)).clamp(max=1.0)
    weights = 1.0 + weight * share
    return weights / weights.mean(dim=(2, 3), keepdim=True)


def normals_over_flat(slope: torch.Tensor) -> torch.Tensor:
    """The normals (B, 3, H, W) that the normal unit's slope (B, 2, H, W) gives a flat material:
    unit-normal(slope, 1), as ``DeepBasisNet`` adds it to the bases."""
    return geometry.unit_vectors(torch.cat([slope, torch.ones_like(slope[:, :1])], dim=1), dim=1)


def normal_unit_loss(normals: torch.Tensor, truth: torch.Tensor, kind: str = "mse") -> torch.Tensor:
    """The normal pool's loss (``TrainConfig.normal_pool_loss``) of unit normals (B, 3, H, W)
    against the true ones: ``mse`` over everything, or ``crop_rmse``, the mean of the crops' RMSE."""
    squared = (normals - truth) ** 2
    if kind == "mse":
        return squared.mean()
    if kind == "crop_rmse":
        # The small floor keeps the gradient of a crop predicted exactly finite.
        return (squared.mean(dim=(1, 2, 3)) + 1e-8).sqrt().mean()
    raise ValueError(f"unknown normal pool loss {kind!r}")


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


# --- losses ------------------------------------------------------------------------------------


def vary_signed(variation: Variation, signed: torch.Tensor) -> torch.Tensor:
    """Apply xi to signed-space parameters (B, 10, ...) (maps or bases with channels at dim 1)."""
    normal, rest = signed.split(constants.NORMAL_AND_REFLECTANCE, dim=1)
    varied = variation.apply(torch.cat([normal, rest * 0.5 + 0.5], dim=1))
    return torch.cat([varied[:, constants.NORMAL], varied[:, constants.REFLECTANCE] * 2.0 - 1.0], dim=1)


def channel_weights(normal_weight: float, device=None) -> torch.Tensor:
    """(1, 10, 1, 1) weights of the map channels: ``normal_weight`` for the normal, 1 for the rest,
    scaled so that their mean is 1."""
    weights = torch.tensor([normal_weight] * 3 + [1.0] * 7, device=device)
    return (weights * 10 / weights.sum()).view(1, 10, 1, 1)


def supervised_loss(output: DeepBasisOutput, maps: torch.Tensor, normal_weight: float = 1.0,
                    signed_target: torch.Tensor | None = None,
                    diffuse_weights: torch.Tensor | None = None) -> torch.Tensor:
    """(Weighted) L1 between the predicted blend and the ground truth ``maps`` (or, given, the
    target already in signed space), in signed space; ``diffuse_weights`` (B, 1, H, W) weigh the
    diffuse channels' pixels (``highlight_weights``)."""
    target = to_signed(maps) if signed_target is None else signed_target
    difference = (output.signed_maps - target).abs()
    if diffuse_weights is not None:
        difference = torch.cat([difference[:, :constants.DIFFUSE.start],
                                difference[:, constants.DIFFUSE] * diffuse_weights,
                                difference[:, constants.DIFFUSE.stop:]], dim=1)
    return (difference * channel_weights(normal_weight, maps.device)).mean()


def saturation_penalty(raw: torch.Tensor, limit: float = 2.0) -> torch.Tensor:
    """mean(max(|raw| - limit, 0)^2) of pre-tanh outputs (B, C, H, W): zero where tanh still has slope."""
    return torch.relu(raw.abs() - limit).square().mean()


def variation_consistency_loss(original: DeepBasisOutput, varied: DeepBasisOutput, variation: Variation,
                               varied_maps: torch.Tensor, normal_weight: float = 1.0) -> torch.Tensor:
    """|xi(bases(M)) - bases(M + xi)|_1 + |maps(M + xi) - (M + xi)|_1 (DeepBasis's L_vc).

    Without bases (the direct ablation) the maps stand in for the bases.
    """
    if original.bases is not None:
        source, target = original.bases.transpose(1, 2), varied.bases.transpose(1, 2)  # (B, 10, N, H, W)
    elif original.global_bases is not None:
        source, target = original.global_bases.transpose(1, 2), varied.global_bases.transpose(1, 2)
    else:
        source, target = original.signed_maps, varied.signed_maps
    consistency = (vary_signed(variation, source) - target).abs().mean()
    return consistency + supervised_loss(varied, varied_maps, normal_weight)


def sample_render_geometry(batch: int, count: int, generator: torch.Generator,
                           distance: tuple[float, float] = (2.0, 5.0), min_cos: float = 0.15,
                           jitter: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Random light and view positions of the re-rendering loss.

    Every position is ``d * dir + (jx, jy, 0)``: ``dir`` on the upper hemisphere with its cosine
    to +z uniform in [min_cos, 1] (down to grazing, 81 deg by default), uniform azimuth, ``d``
    uniform in ``distance``, a lateral jitter uniform in [-jitter, jitter]. The first
    ``count - count // 2`` pairs draw light and view independently; the other ``count // 2`` are
    mirror pairs: the view is the light mirrored about the normal of a random point q of the
    sample (at its own distance), so a flat, smooth sample shows a highlight at q.

    Returns:
        lights, views: (B, K, 3) positions [patch half-widths].
    """
    def positions():
        """(B, K, 3) positions drawn as the docstring says."""
        n = batch * count
        cos = min_cos + (1 - min_cos) * torch.rand(n, generator=generator)
        sin = torch.sqrt(1 - cos**2)
        phi = 2 * math.pi * torch.rand(n, generator=generator)
        length = distance[0] + (distance[1] - distance[0]) * torch.rand(n, generator=generator)
        lateral = (2 * torch.rand(n, 2, generator=generator) - 1) * jitter
        direction = torch.stack([sin * torch.cos(phi), sin * torch.sin(phi), cos], dim=-1)
        return (length[:, None] * direction + torch.cat([lateral, torch.zeros(n, 1)], dim=-1)).view(batch, count, 3)

    mirrored = count // 2
    lights = positions()
    views = positions()
    if mirrored:
        target = torch.cat([(2 * torch.rand(batch, mirrored, 2, generator=generator) - 1) * 0.7,
                            torch.zeros(batch, mirrored, 1)], dim=-1)
        to_light = lights[:, -mirrored:] - target
        mirror = to_light * torch.tensor([-1.0, -1.0, 1.0])
        length = distance[0] + (distance[1] - distance[0]) * torch.rand(batch, mirrored, 1, generator=generator)
        views = torch.cat([views[:, :-mirrored], target + mirror / mirror.norm(dim=-1, keepdim=True) * length], dim=1)
    return lights, views


def rendering_loss(predicted: torch.Tensor, truth: torch.Tensor, lights: torch.Tensor, views: torch.Tensor,
                   convention: str = constants.DEFAULT_CONVENTION) -> torch.Tensor:
    """Mean |log(1 + render(predicted)) - log(1 + render(truth))| over K lights and views.

    Args:
        predicted, truth: (B, 10, H, W) maps (unit normals, the rest in [0, 1]).
        lights, views: (B, K, 3) positions [patch half-widths] (``sample_render_geometry``).

    The render is the renderer interface's (its current backend), in float32, with the physical
    flash intensity of the default field of view.
    """
    from .render import render_flash

    with torch.autocast(predicted.device.type, enabled=False):
        rendered = render_flash(predicted.float(), lights, views=views, convention=convention)
        with torch.no_grad():
            reference = render_flash(truth.float(), lights, views=views, convention=convention)
        return (torch.log1p(rendered.clamp(min=0.0)) - torch.log1p(reference.clamp(min=0.0))).abs().mean()


# --- the loop ------------------------------------------------------------------------------------


def _single_threaded_worker(worker_id: int) -> None:
    """Material workers use one thread each (OpenCV would start a pool per worker otherwise)."""
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)


def _distributed() -> tuple[int, int]:
    """(rank, world size); initialises the process group when launched by torchrun."""
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        if not dist.is_initialized():
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _device(name: str, rank: int) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        index = int(os.environ.get("LOCAL_RANK", rank)) % max(1, torch.cuda.device_count())
        torch.cuda.set_device(index)
        return torch.device("cuda", index)
    return torch.device(name)


def learning_rate_factor(step: int, steps: int, final_fraction: float, warmup: int = 0) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay from 1 to ``final_fraction`` at the last step."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, steps - warmup - 1))
    return final_fraction + (1 - final_fraction) * 0.5 * (1 + math.cos(math.pi * progress))


def _optimizer_tensors(optimizer: torch.optim.Optimizer, names: dict) -> tuple[dict, dict]:
    """Adam's state as named tensors (no pickling) and the small numbers as JSON."""
    tensors, steps = {}, {}
    for parameter, state in optimizer.state.items():
        name = names[parameter]
        tensors[f"optimizer/{name}/exp_avg"] = state["exp_avg"]
        tensors[f"optimizer/{name}/exp_avg_sq"] = state["exp_avg_sq"]
        steps[name] = float(state["step"])
    return tensors, steps


def _restore_optimizer(optimizer, names: dict, tensors: dict, steps: dict) -> None:
    for parameter, name in names.items():
        if name in steps:
            optimizer.state[parameter] = {"step": torch.tensor(steps[name]),
                                          "exp_avg": tensors[f"optimizer/{name}/exp_avg"].to(parameter),
                                          "exp_avg_sq": tensors[f"optimizer/{name}/exp_avg_sq"].to(parameter)}


class Trainer:
    """One training run (see the module docstring)."""

    def __init__(self, config: TrainConfig, resume: bool = False, progress: bool = True):
        self.config = config
        self.rank, self.world_size = _distributed()
        self.device = _device(config.device, self.rank)
        self.out = Path(config.out)
        self.progress = progress and self.rank == 0
        torch.manual_seed(config.seed)
        if (config.normal_pool or config.local_pool) and self.world_size > 1:
            raise InputError("train --normal-pool and --local-pool run in one process: start them without torchrun")
        network_config = config.network
        if config.size % network_config.stride:
            raise InputError(f"training size {config.size} is not a multiple of the {config.preset} network's "
                             f"stride {network_config.stride}")
        self.synthesis = config.synthesis
        from .render import set_render_backend

        set_render_backend(config.render_backend)
        self.model = DeepBasisNet(network_config).to(self.device)
        for name, parameter in self.model.named_parameters():
            if config.train_only and name.split(".")[0] not in config.train_only:
                parameter.requires_grad_(False)
        trained = [(n, p) for n, p in self.model.named_parameters() if p.requires_grad]
        if not trained:
            raise InputError(f"this network has none of the parts {list(config.train_only)} to train")
        # The per-pixel units learn faster (the paper trains its local unit faster too).
        per_pixel = ("local_unit.", "normal_unit.", "normal_booster.")
        local = [p for n, p in trained if n.startswith(per_pixel)]
        rest = [p for n, p in trained if not n.startswith(per_pixel)]
        groups = [{"params": rest, "lr": config.lr, "initial_lr": config.lr}] if rest else []
        if local:
            groups.append({"params": local, "lr": config.local_lr, "initial_lr": config.local_lr})
        self.optimizer = torch.optim.Adam(groups)
        self.parameter_names = {p: n for n, p in trained}
        self.generator = torch.Generator().manual_seed(config.seed * 1_000_003 + self.rank)
        self.step = 0
        self.elapsed = 0.0
        self.best_score = math.inf
        self._validation_batches = {}
        if config.init and not resume:
            self._initialise_from(config.init)
        # The local unit the kept maps come from: the init's, also when the run resumes.
        self.kept_from = None
        if config.local_pool_keep:
            from .model.checkpoint import load_model

            self.kept_from = load_model(config.init).to(self.device).eval().requires_grad_(False)
        if resume:
            self._resume()
        if self.world_size > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None)

    # --- checkpoints ---------------------------------------------------------------------------

    def _extra_inputs(self) -> tuple[str, ...]:
        return getattr(self.model, "module", self.model).config.extra_inputs

    def _initialise_from(self, path: str) -> None:
        """Start from a checkpoint's weights. It may differ from this run's network in the optional
        inputs (their weights start at zero: ``widen_inputs``) and in the sizes of the local and the
        normal units (a unit whose size differs, or that the checkpoint lacks, starts afresh;
        everything else is loaded), except that a normal unit of the same width and levels with more
        blocks keeps the checkpoint's blocks, the added ones starting as the identity, and that a
        second normal unit (``normal_booster_width``) the checkpoint lacks starts at zero: the
        network computes what the checkpoint's did. A run without one drops the checkpoint's. How
        the normal unit runs (``normal_unit_octaves``, ``normal_slope_scaled``) may differ too: it
        needs no weights."""
        from dataclasses import replace

        from .model.checkpoint import load_model

        source = load_model(path)
        config = self.model.config
        local_fields = {name: getattr(config, name) for name in LOCAL_UNIT_FIELDS}
        if replace(source.config, extra_inputs=config.extra_inputs, normal_unit_width=config.normal_unit_width,
                   normal_booster_width=config.normal_booster_width,
                   normal_unit_blocks=config.normal_unit_blocks, normal_unit_albedo=config.normal_unit_albedo,
                   normal_unit_middle_blocks=config.normal_unit_middle_blocks,
                   normal_unit_octaves=config.normal_unit_octaves, normal_slope_scaled=config.normal_slope_scaled,
                   **local_fields) != config:
            raise InputError(f"{path}: its network configuration differs from this run's ({self.config.preset} "
                             "preset) in more than the optional inputs and the sizes of the local and normal units")
        state, target = source.state_dict(), self.model.state_dict()
        fresh = []
        if any(getattr(source.config, name) != value for name, value in local_fields.items()):
            fresh.append("local_unit.")
        before, after = source.config, config
        if (before.normal_unit_width != after.normal_unit_width
                or len(before.normal_unit_blocks) != len(after.normal_unit_blocks)
                or any(b > a for b, a in zip(before.normal_unit_blocks, after.normal_unit_blocks))
                or before.normal_unit_middle_blocks > after.normal_unit_middle_blocks):
            fresh.append("normal_unit.")
        if "normal_unit." in fresh or before.normal_booster_width != after.normal_booster_width:
            fresh.append("normal_booster.")  # (one the checkpoint lacks starts at zero: the same network)
        if fresh:  # those units start afresh
            state = {name: value for name, value in state.items() if not name.startswith(tuple(fresh))}
            state.update({name: value for name, value in target.items() if name.startswith(tuple(fresh))})
        # A deepened normal unit keeps its blocks; the added ones start as they are built (the identity).
        state.update({name: value for name, value in target.items() if name not in state})
        intro = "normal_unit.intro.weight"
        if "normal_unit." not in fresh and intro in state and state[intro].shape != target[intro].shape:
            if before.normal_unit_albedo or not after.normal_unit_albedo:
                raise InputError(f"{path}: its normal unit reads the albedo shading and this run's does not")
            # The albedo shading, the last input, enters with zero weights: the unit computes what it did.
            state[intro] = widen_inputs({intro: state[intro]}, target, relief_channels(False))[intro]
        if source.config.extra_inputs != config.extra_inputs:
            state = widen_inputs(state, target, source.config.input_channels)
        self.model.load_state_dict(state)

    def _resume(self) -> None:
        path = self.out / "checkpoint.safetensors"
        document, tensors = read_checkpoint(path)
        state = document.get("training_state")
        if state is None:
            raise InputError(f"{path}: has no training state to resume from")
        stored = TrainConfig.from_dict(document["training"]["config"], str(path), document.get("network"))
        processes = document["training"].get("world_size", 1)
        if processes != self.world_size:
            raise InputError(f"{path}: this run was started in {processes} process(es), not {self.world_size}: "
                             "resume it with as many")
        changed = differences(stored, self.config, ignore=RESUMABLE_CHANGES)
        if changed:
            name, before, now = changed[0]
            raise InputError(f"{path}: this run was started with {name} = {before!r}, not {now!r} "
                             f"({len(changed)} setting(s) differ); resume with the run's settings, or start a "
                             "new run with --init")
        broken = non_finite_tensors(tensors)
        if broken:
            raise CheckpointError(f"{path}: {len(broken)} of {len(tensors)} tensors hold NaN or infinite values "
                                  f"(e.g. {broken[0]}): the file is damaged; the one saved before it is "
                                  f"{previous_path(path).name}, if there (copy it over to resume from there)")
        weights = {k[len("model/"):]: v for k, v in tensors.items() if k.startswith("model/")}
        self.model.load_state_dict(weights)
        _restore_optimizer(self.optimizer, self.parameter_names, tensors, state["optimizer_steps"])
        self.step, self.elapsed = state["step"], state["elapsed_seconds"]
        self.best_score = state.get("best_validation_score", math.inf)
        self.generator.set_state(tensors[f"state/generator_rank{self.rank}"])
        self._set_learning_rate()

    def save(self, final: bool = False) -> None:
        """Write the resumable checkpoint (and the plain model at the end); rank 0 only."""
        generator_states = [self.generator.get_state()]
        if self.world_size > 1:
            gathered = [torch.empty_like(generator_states[0]) for _ in range(self.world_size)]
            dist.all_gather_object(gathered, generator_states[0])
            generator_states = gathered
        if self.rank != 0:
            return
        model = getattr(self.model, "module", self.model)
        optimizer_tensors, optimizer_steps = _optimizer_tensors(self.optimizer, self.parameter_names)
        extra = {f"state/generator_rank{r}": s for r, s in enumerate(generator_states)}
        training = self.training_record()
        save_checkpoint(self.out / "checkpoint.safetensors", model, metadata={
            "training": training, "training_state": {"step": self.step, "elapsed_seconds": self.elapsed,
                                                     "optimizer_steps": optimizer_steps,
                                                     "best_validation_score": self.best_score}},
            extra_tensors={**optimizer_tensors, **extra}, keep_previous=True)
        if final:
            save_checkpoint(self.out / "model.safetensors", model, metadata={"training": training})

    def training_record(self) -> dict:
        return {"config": dataclasses.asdict(self.config), "steps_done": self.step, "world_size": self.world_size,
                "device": str(self.device), "wall_seconds": round(self.elapsed, 1),
                "data": list(self.config.data), "command": " ".join(sys.argv)}

    # --- one step --------------------------------------------------------------------------------

    def _set_learning_rate(self) -> None:
        factor = learning_rate_factor(self.step, self.config.steps, self.config.final_lr_fraction,
                                      self.config.warmup_steps)
        for group in self.optimizer.param_groups:
            group["lr"] = group["initial_lr"] * factor

    def train_step(self, maps) -> dict:
        config = self.config
        if config.normal_pool:
            return self._normal_unit_step(maps)
        if config.local_pool:
            return self._local_unit_step(maps)
        maps = maps.to(self.device, non_blocking=True)
        batch = synthesize(maps, self.generator, self.synthesis, self._extra_inputs())
        use_vc = config.vc_weight > 0
        inputs = torch.cat([batch.inputs, batch.varied_inputs]) if use_vc else batch.inputs
        lights = torch.cat([batch.lights, batch.lights]) if use_vc else batch.lights
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=config.bf16):
            output = self.model(inputs.to(self.device), lights.to(self.device), fov=batch.fov)
        target = batch.maps.to(self.device)
        if use_vc:
            original, varied = output.split(maps.shape[0])
            variation = Variation(batch.variation.rotation.to(self.device), batch.variation.shift.to(self.device))
            sup = supervised_loss(original, target, config.normal_weight)
            vc = variation_consistency_loss(original, varied, variation, batch.varied_maps.to(self.device),
                                            config.normal_weight)
        else:
            sup, vc = supervised_loss(output, target, config.normal_weight), torch.zeros((), device=self.device)
        saturation = saturation_penalty(output.extras["decoder_raw"].float())
        loss, losses = self._with_rendering_loss(sup + config.vc_weight * vc + config.saturation_weight * saturation,
                                                 (original if use_vc else output).maps, target)
        norm = self._optimise(loss)
        return {"loss": loss.item(), "l_sup": sup.item(), "l_vc": vc.item(), "l_saturation": saturation.item(),
                **losses, "grad_norm": norm.item()}

    def _with_rendering_loss(self, loss: torch.Tensor, predicted: torch.Tensor, target: torch.Tensor
                             ) -> tuple[torch.Tensor, dict]:
        """``loss`` plus ``render_weight`` times the rendering loss of the predicted maps (B, 10, H, W)
        under random lights and views, and the logged terms ({} when the weight is 0)."""
        config = self.config
        if config.render_weight <= 0:
            return loss, {}
        render_lights, render_views = sample_render_geometry(target.shape[0], config.render_lights, self.generator)
        rendering = rendering_loss(predicted, target, render_lights.to(self.device), render_views.to(self.device),
                                   self.synthesis.convention)
        return loss + config.render_weight * rendering, {"l_render": rendering.item()}

    def _optimise(self, loss: torch.Tensor) -> torch.Tensor:
        """Backward, the gradient clipped to ``grad_clip``, one Adam step, the next learning rate;
        returns the gradient's global norm before clipping."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.config.grad_clip > 0:
            norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        else:
            norm = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in self.model.parameters()
                                                         if p.grad is not None]))
        self.optimizer.step()
        self.step += 1
        self._set_learning_rate()
        return norm

    def _normal_unit_step(self, crops: tuple[list[torch.Tensor], torch.Tensor]) -> dict:
        """One step of the normal unit alone (``TrainConfig.normal_pool``) on crops of the pool."""
        reliefs, truth = [tensor.to(self.device) for tensor in crops[0]], crops[1].to(self.device)
        model = getattr(self.model, "module", self.model)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.bf16):
            slope = model.octave_slope(reliefs)
        loss = normal_unit_loss(normals_over_flat(slope.float()), truth, self.config.normal_pool_loss)
        norm = self._optimise(loss)  # the frozen rest has no gradient
        return {"loss": loss.item(), "l_sup": loss.item(), "l_vc": 0.0, "l_saturation": 0.0, "grad_norm": norm.item()}

    def _local_unit_step(self, batch: LocalUnitBatch) -> dict:
        """One step of the local unit alone (``TrainConfig.local_pool``) on a batch of the pool."""
        config, model = self.config, getattr(self.model, "module", self.model)
        weights, global_bases, maps = (t.to(self.device) for t in (batch.weights, batch.global_bases, batch.maps))
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=config.bf16):
            deviations = model.local_deviations(batch.local_inputs.to(self.device), weights, global_bases)
        slope = batch.slope.to(self.device)

        def blended(local_deviations: torch.Tensor) -> DeepBasisOutput:  # the normal unit's slope added
            return DeepBasisOutput.from_bases(weights, global_bases,
                                              add_slope(global_bases, local_deviations, slope,
                                                        model.config.normal_slope_scaled), keep_bases=False)

        output = blended(deviations.float())
        signed_target = None
        if self.kept_from is not None:
            with torch.no_grad():
                kept = blended(self.kept_from.local_deviations(batch.local_inputs.to(self.device), weights, global_bases))
            # The blend itself (signed space) for the map loss, its maps for the rendering loss.
            maps, signed_target = maps.clone(), to_signed(maps)
            for name in config.local_pool_keep:
                channels = constants.MAP_SLICES[name]
                maps[:, channels], signed_target[:, channels] = kept.maps[:, channels], kept.signed_maps[:, channels]
        diffuse_weights = None if batch.diffuse_weights is None else batch.diffuse_weights.to(self.device)
        sup = supervised_loss(output, maps, config.normal_weight, signed_target, diffuse_weights)
        loss, losses = self._with_rendering_loss(sup, output.maps, maps)
        norm = self._optimise(loss)  # the frozen rest has no gradient
        return {"loss": loss.item(), "l_sup": sup.item(), "l_vc": 0.0, "l_saturation": 0.0, **losses,
                "grad_norm": norm.item()}

    # --- the loop ----------------------------------------------------------------------------------

    def pool_batches(self):
        """Batches of the unit trained alone from this step on (``TrainConfig.normal_pool``: crops
        of the normal pool; ``local_pool``: materials of the local pool), then the pool moves on."""
        pool = self.unit_pool()
        while True:
            yield pool.batch(self.generator)
            pool.advance()

    def unit_pool(self) -> PhotographedPool:
        """The pool of the unit trained alone (``normal_pool`` or ``local_pool``) at this step."""
        model = getattr(self.model, "module", self.model)
        fov = self.config.synthesis.fov
        if self.config.local_pool:
            @torch.no_grad()
            def stage_of(inputs: torch.Tensor, lights: torch.Tensor):
                inputs, lights = inputs.to(self.device), lights.to(self.device)
                stage = model.basis_stage(inputs, lights, fov)
                slope = torch.zeros_like(stage.error[:, :2])
                if hasattr(model, "normal_unit"):
                    deviations = model.local_deviations(stage.local_inputs, stage.weights, stage.global_bases)
                    slope = model.normal_slope(stage, deviations, lights, fov)
                return (stage.local_inputs.float().cpu(), stage.weights.float().cpu(),
                        stage.global_bases.float().cpu(), slope.float().cpu())

            return LocalUnitPool(self.materials(), self.config, self.step, stage_of)

        @torch.no_grad()
        def diffuse_of(inputs: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
            # The unit changes only the normal: the diffuse is the frozen rest's, without a pass of the unit.
            output = model(inputs.to(self.device), lights.to(self.device), fov=self.config.synthesis.fov,
                           with_normal_unit=False)
            return output.maps[:, constants.DIFFUSE].float().cpu()

        return NormalUnitPool(self.materials(), self.config, self.step, diffuse_of)

    def materials(self) -> TrainingMaterials:
        """The run's training materials by number."""
        # Photographed at ``supersample`` times the training size and downsampled (``synthesize``).
        return TrainingMaterials(self.config.data, self.config.size * self.config.synthesis.supersample,
                                 self.config.seed, self.config.procedural)

    def loader(self) -> DataLoader:
        dataset = self.materials()
        sampler = StepBatchSampler(self.config.batch, self.step, self.rank, self.world_size)
        workers = self.config.workers
        return DataLoader(dataset, batch_sampler=sampler, num_workers=workers, worker_init_fn=_single_threaded_worker,
                          prefetch_factor=4 if workers else None, persistent_workers=workers > 0,
                          pin_memory=self.device.type == "cuda")

    def run(self, stop_at: int | None = None) -> None:
        """Train to ``config.steps``; ``stop_at`` ends early after a checkpoint, as a kill would."""
        from tqdm import tqdm

        config = self.config
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
        last_checkpoint = started_run = time.monotonic()
        # disable=None: no bar where stderr is not a terminal (a log file).
        bar = tqdm(total=config.steps, initial=self.step, desc="training", unit="step",
                   disable=None if self.progress else True)
        iterator = None
        if self.step < config.steps:
            iterator = self.pool_batches() if config.normal_pool or config.local_pool else iter(self.loader())
        if config.validate_every and self.step == 0 and self.rank == 0:
            # The starting point of the learning curve; after the workers start, since forking a
            # process whose OpenMP threads have run can deadlock the child.
            self.validate()
        window_start, window_steps = time.monotonic(), 0
        first_step_done, process_start_step = None, self.step
        while self.step < config.steps:
            out_of_time = config.max_minutes > 0 and time.monotonic() - started_run > 60 * config.max_minutes
            if out_of_time or (stop_at is not None and self.step >= stop_at):
                if out_of_time:
                    self._log_process_rate(process_start_step, first_step_done)
                    self._final_validation()
                self.save()
                bar.close()
                return
            started = time.monotonic()
            losses = self.train_step(next(iterator))
            if not math.isfinite(losses["loss"]):  # the weights are lost: stop before they are saved
                bar.close()
                raise TrainingDiverged(f"{self.out}: training diverged at step {self.step}: the loss is not finite; "
                                       f"{self.out / 'checkpoint.safetensors'} keeps the last good weights (resume "
                                       "it, perhaps with a lower --lr)")
            self.elapsed += time.monotonic() - started
            if first_step_done is None:
                first_step_done, process_start_step = time.monotonic(), self.step
            window_steps += 1
            bar.update(1)
            bar.set_postfix(loss=f"{losses['loss']:.4f}")
            if self.rank == 0 and (self.step % config.log_every == 0 or self.step == config.steps):
                rate = window_steps / max(1e-9, time.monotonic() - window_start)
                self.log({"step": self.step, **losses, "lr": self.optimizer.param_groups[0]["lr"],
                          "steps_per_second": round(rate, 4), "elapsed_seconds": round(self.elapsed, 1)})
                window_start, window_steps = time.monotonic(), 0
            if config.validate_every and self.step % config.validate_every == 0 and self.rank == 0:
                self.validate()
            if time.monotonic() - last_checkpoint > 60 * config.checkpoint_minutes:
                self.save()
                last_checkpoint = time.monotonic()
        bar.close()
        self._log_process_rate(process_start_step, first_step_done)
        self._final_validation()
        self.save(final=True)
        if self.rank == 0:
            self.plot_losses()
        if self.world_size > 1:
            dist.barrier()

    def _log_process_rate(self, start_step: int, start_time: float | None) -> None:
        """Log this process's steps per second, from its first step (start-up excluded) to now."""
        if self.rank == 0 and start_time is not None and self.step > start_step:
            rate = (self.step - start_step) / max(1e-9, time.monotonic() - start_time)
            self.log({"step": self.step, "process_steps_per_second": round(rate, 4)})

    def _final_validation(self) -> None:
        """Validate the last weights too, unless this step was just validated."""
        if self.config.validate_every and self.rank == 0 and self.step % self.config.validate_every:
            self.validate()

    def log(self, record: dict) -> None:
        with open(self.out / "train.jsonl", "a") as log:
            log.write(json.dumps(record) + "\n")

    def plot_losses(self) -> None:
        from .reporting import plot_training_log

        plot_training_log(self.out / "train.jsonl", self.out / "loss.png")

    def validation_batch(self, of: str = "held_out"):
        """The validation materials and their photos (fixed seeds; made once): ``held_out`` or
        ``run_generator`` (``TrainConfig.select_by``)."""
        if of not in self._validation_batches:
            from .data.procedural import GeneratorConfig, generate

            # held_out: the generator as it was when the learning curve began (relief by a factor,
            # not scaled to a drawn tilt), so that validations of every session compare.
            config = (GeneratorConfig(size=self.config.size, relief_tilt_deg=None) if of == "held_out"
                      else self.config.procedural)
            maps = torch.stack([generate(VALIDATION_SEED + i, config=config).to_tensor()
                                for i in range(self.config.validation_count)])
            # Photographed at their own size whatever the run's ``supersample``, the held-out set as
            # the learning curve began (one 45 deg camera, plain sRGB), the run's own as it trains:
            # in chunks of a field of view each where it draws them.
            synthesis = dataclasses.replace(self.synthesis, supersample=1)
            if of == "held_out":
                defaults = SynthesisConfig()
                synthesis = dataclasses.replace(synthesis, **{name: getattr(defaults, name) for name in PHONE_LEVERS})
            generator = torch.Generator().manual_seed(12345)
            chunk = VALIDATION_CHUNK if synthesis.fov_range is not None else len(maps)
            self._validation_batches[of] = [synthesize(maps[start:start + chunk], generator, synthesis,
                                                       self._extra_inputs())
                                            for start in range(0, len(maps), chunk)]
        return self._validation_batches[of]

    def _predict_validation(self, batches: list[TrainingBatch], chunk: int = 16) -> torch.Tensor:
        """The whole network's maps (B, 10, H, W) of a validation set's batches, in chunks."""
        model = getattr(self.model, "module", self.model)
        model.eval()
        predicted = []
        with torch.no_grad(), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.bf16):
            for batch in batches:
                for start in range(0, batch.maps.shape[0], chunk):
                    output = model(batch.inputs[start:start + chunk].to(self.device),
                                   batch.lights[start:start + chunk].to(self.device), fov=batch.fov)
                    predicted.append(output.maps.float().cpu())
        model.train()
        return torch.cat(predicted)

    def validate(self) -> dict:
        """Predict both validation sets; log their map RMSE (and the flat-normal RMSE beside the
        normal's), keep ``best.safetensors`` by the mean of the ``select_by`` set's, and write a
        sheet of four of the held-out set."""
        from .reporting import validation_sheet

        batches = self.validation_batch("held_out")
        model = getattr(self.model, "module", self.model)
        predicted, maps = self._predict_validation(batches), torch.cat([b.maps for b in batches])
        rmse = unit_normal_map_rmse(predicted, maps)
        score = sum(rmse.values()) / len(rmse)
        own_batches = self.validation_batch("run_generator")
        own_maps = torch.cat([b.maps for b in own_batches])
        own_rmse = unit_normal_map_rmse(self._predict_validation(own_batches), own_maps)
        own_score = sum(own_rmse.values()) / len(own_rmse)
        record = {"step": self.step, "validation_rmse": rmse, "validation_score": score,
                  "validation_rerender_rmse": self._validation_rerender_rmse(predicted, maps),
                  "validation_flat_normal_rmse": unit_normal_map_rmse(flat_normals(maps), maps)["normal"],
                  "validation_tilt_deg": {"predicted": mean_tilt_deg(predicted), "truth": mean_tilt_deg(maps)},
                  "run_generator_validation": {
                      "rmse": own_rmse, "score": own_score,
                      "flat_normal_rmse": unit_normal_map_rmse(flat_normals(own_maps), own_maps)["normal"]}}
        self.log(record)
        if self.config.select_by == "run_generator":
            score = own_score
        if score < self.best_score:
            self.best_score = score
            save_checkpoint(self.out / "best.safetensors", model, metadata={"training": {
                **self.training_record(), "validation": record}})
        validation_sheet(batches[0].photos[:4], predicted[:4], maps[:4],
                         self.out / "validation" / f"step_{self.step:07d}.png")
        self.plot_losses()
        return record

    def _validation_rerender_rmse(self, predicted: torch.Tensor, maps: torch.Tensor, count: int = 8) -> float:
        """Mean RMSE of clipped sRGB re-renderings under ``count`` seeded lights and views (the
        evaluation's metric, on the validation materials)."""
        from .evaluation import random_lights_and_views, rerender_rmse
        from .render import render_backend

        lights, views = random_lights_and_views(count, seed=0)
        device = self.device
        errors = [rerender_rmse(predicted[start:start + 16].to(device), maps[start:start + 16].to(device),
                                lights.to(device), views.to(device), self.synthesis.convention, render_backend())
                  for start in range(0, maps.shape[0], 16)]
        return torch.cat(errors).mean().item()


def widen_inputs(source: dict, target: dict, source_inputs: int) -> dict:
    """Weights of a network with ``source_inputs`` input channels for one with more (extra inputs):
    every tensor whose input dimension (1) grew gets zero weights for the new channels, which the
    wider network's input holds right after the first ``source_inputs`` ones; the rest is copied.
    The wider network then computes exactly what the narrower one did, and learns to use the rest."""
    widened = {}
    for name, value in source.items():
        shape = target[name].shape
        if value.shape == shape:
            widened[name] = value
            continue
        added = shape[1] - value.shape[1]
        if value.ndim < 2 or added <= 0 or value.shape[0] != shape[0] or value.shape[2:] != shape[2:]:
            raise InputError(f"cannot widen the inputs of {name}: {tuple(value.shape)} -> {tuple(shape)}")
        zeros = value.new_zeros(value.shape[0], added, *value.shape[2:])
        widened[name] = torch.cat([value[:, :source_inputs], zeros, value[:, source_inputs:]], dim=1)
    return widened


#: Seed of the first held-out validation material (training draws material numbers from 0 up).
VALIDATION_SEED = 10**9

#: Validation photos of a run that draws its field of view per batch are made in chunks of this many,
#: a field of view each.
VALIDATION_CHUNK = 8


def unit_normal_map_rmse(predicted: torch.Tensor, truth: torch.Tensor) -> dict:
    """RMSE of each map over a batch (B, 10, H, W), in the in-memory encoding (unit normals, so the
    normal's figure is twice ``evaluation.map_rmse``'s, which is in the stored encoding)."""
    rmse = ((predicted - truth) ** 2).mean(dim=(0, 2, 3)).sqrt()
    return {name: rmse[channels].mean().item() for name, channels in constants.MAP_SLICES.items()}


def flat_normals(maps: torch.Tensor) -> torch.Tensor:
    """A copy of maps (B, 10, H, W) with flat normals (+z): the baseline of the normal's RMSE."""
    flat = maps.clone()
    flat[:, constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0], dtype=maps.dtype).view(1, 3, 1, 1)
    return flat


def mean_tilt_deg(maps: torch.Tensor) -> float:
    """Mean angle between the normals of (B, 10, H, W) maps and +z [deg]: how much relief there is."""
    return torch.rad2deg(torch.acos(maps[:, constants.NORMAL][:, 2].clamp(-1.0, 1.0))).mean().item()


def train(config: TrainConfig, resume: bool = False, progress: bool = True) -> Path:
    """Run (or resume) a training run; returns the final model file."""
    Trainer(config, resume=resume, progress=progress).run()
    return Path(config.out) / "model.safetensors"
