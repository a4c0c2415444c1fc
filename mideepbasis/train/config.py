"""The settings of a training run (``TrainConfig``) and the tables that go with them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from .. import constants
from ..configs import drop_removed_fields, positive_int
from ..data.procedural import GeneratorConfig
from ..data.synth import SynthesisConfig
from ..errors import InputError
from ..model.network import NetworkConfig, preset


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

    keep_validated: bool = False
    """Keep the weights of every validated step too (``step_NNNNNNN.safetensors`` in ``out``), to
    judge a run's steps by what its validation does not measure (``evaluate`` on real photos)."""

    select_by: str = field(default="held_out", metadata={"choices": ("held_out", "run_generator")})
    """Which validation set keeps ``best.safetensors``. Each validation predicts two: ``held_out``,
    materials of the generator with the families' relief times a factor (``relief_tilt_deg`` None),
    the same for every run (its figures compare across all runs); ``run_generator``, as many
    materials drawn by this run's own generator (``procedural``), which sees what a change of the
    training materials teaches (e.g. the broad undulation of ``coarse_relief_tilt_deg``, which the
    first set lacks)."""

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
    (``vc_weight``, ``saturation_weight`` and ``workers`` do not apply). The stage is computed in
    float32 (as ``capture`` runs).
    Validation runs the whole network. One process only."""

    local_pool_refresh: int = field(default=1, metadata={"parse": positive_int})
    """Materials of the local pool replaced by new ones each step."""

    local_pool_keep: tuple[str, ...] = ()
    """Maps (``constants.MAP_SLICES``: normal, diffuse, roughness, specular) the local unit alone keeps as the run's start (``init``) gives them:
    on their channels the target is not the true map but the map of the network with the init's
    local unit, so the unit learns the other maps without moving these. Trained alone on
    procedural materials the unit trades the roughness for the diffuse on the shared test set
    (MODEL.md); kept, the roughness cannot drift. Costs one more local-unit pass for each material
    the pool photographs."""

    global_roughness_jitter: float = 0.0
    """With ``local_pool``: the largest shift of the global bases' roughness [roughness, the map's
    units] before they reach the local unit. Each material of the pool draws one shift, uniform in
    +- this, for all its bases (clipped to [0, 1]), and the local unit's error map is rendered from
    the shifted bases; the targets stay those of the bases as predicted (the true maps, and
    ``local_pool_keep``'s maps as the init answers the unshifted inputs). On real photos the global
    unit's lobe misses the highlight and the local unit turns the difference into the diffuse map
    (dark holes under the highlight, benchmarks/README.md); so it learns to answer such a miss with
    the lobe's maps. 0: off."""

    global_specular_jitter: float = 0.0
    """With ``local_pool``: the largest change of the global bases' specular [octaves]: each material
    draws one factor 2^u, u uniform in +- this, for all its bases' specular (clipped to [0, 1]),
    as ``global_roughness_jitter`` shifts their roughness. 0: off."""

    highlight_weight: float = 0.0
    """Extra weight of the diffuse map's loss under the flash's highlight (the whole network's
    step, or the local unit's with ``local_pool``; not the normal pool's, which has no diffuse):
    each pixel's diffuse error weighs 1 + w * (the true specular lobe's
    brightness under the photo's flash, over its 99th percentile, at most 1), divided by the
    material's mean of that (``highlight_weights``). The
    highlight covers a few percent of a photo, so the plain loss hardly minds a highlight baked
    into the diffuse map (issue 11's demo smudge); 0: off."""

    lobe_weight: float = 0.0
    """Weight of the specular lobe's loss (the whole network's step; ``losses.lobe_loss``): the
    predicted maps' lobe, rendered alone under the photo's flash, against the truth's, in log
    ratios where either shows. One photo fixes the sum of diffuse and lobe under the highlight,
    so the diffuse takes up the lobe's miss (the leak follows it); the map losses hardly see a
    lobe ten times too faint, a small roughness error. 0: off."""

    global_weight: float = 0.0
    """Weight of the global blend's loss (the whole network's step; ``losses.global_blend_loss``):
    the blending weights times the global bases alone, without the local deviations, against the
    truth's reflectance, so that the global bases are a material of their own, the local unit's
    error map measures what they miss, and the refinement moves a material. 0: off."""

    colour_weight: float = 0.0
    """Weight of the specular colour's loss (the whole network's step;
    ``losses.specular_colour_loss``): the predicted specular's chromaticity against the truth's, in
    log ratios of its channels, so that a dark dielectric's tinted specular costs as a bright one's.
    0: off."""

    diffuse_loss_encoded: bool = False
    """Compare the diffuse map in the supervised loss as sRGB-encoded albedo rather than linear
    (its pixels still weighed by ``highlight_weight``): a blob in the diffuse is seen against the
    albedo beside it, and in linear values a dark material's blob costs little. On the held-out
    phone scenes the leak relative to the albedo is largest on the darkest third of materials,
    though smallest in albedo units (``benchmarks/highlight_leak.py``, ``leak_by``)."""

    anchor: str | None = None
    """A checkpoint whose answers the run keeps on the plain camera's batches (those that
    ``synthesis.plain_probability`` draws): there the loss adds ``anchor_weight`` times the
    supervised L1 between this network's maps and the anchor's, as "learning without forgetting"
    does. A fine-tune towards phone photos then learns them from the other batches without
    drifting from what the anchor does on the plain camera (the shared test set's). Costs one
    forward pass of the anchor on those batches. None: off."""

    anchor_weight: float = 1.0
    """Weight of the anchor's L1 (``anchor``) against the supervised loss's 1."""

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
        if self.normal_pool and self.synthesis.fov_range is not None:
            raise ValueError("the normal pool photographs at one field of view: synthesis.fov_range needs the local "
                             "pool or the whole network")
        if self.normal_pool and self.local_pool:
            raise ValueError("local_pool and normal_pool train different units: give one of them")
        if self.normal_pool:
            if set(self.train_only) != {"normal_unit"} or not self.network.normal_unit_width:
                raise ValueError("normal_pool trains the normal unit alone: it needs train_only = normal_unit "
                                 "and a network with a normal unit (network.normal_unit_width)")
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
        if self.global_roughness_jitter < 0 or self.global_specular_jitter < 0:
            raise ValueError(f"global_roughness_jitter {self.global_roughness_jitter} and global_specular_jitter "
                             f"{self.global_specular_jitter} must be 0 (off) or positive")
        for name in WHOLE_STEP_WEIGHTS:
            weight = getattr(self, name)
            if weight < 0:
                raise ValueError(f"{name} {weight} must be 0 (off) or positive")
            if weight and (self.local_pool or self.normal_pool):
                raise ValueError(f"{name} weighs the whole network's step: the unit pools do not take it")
        if self.global_weight and not self.network.use_bases:
            raise ValueError("global_weight holds the global bases' blend: it needs a network with bases")
        if (self.global_roughness_jitter or self.global_specular_jitter) and not self.local_pool:
            raise ValueError("global_roughness_jitter and global_specular_jitter change what the local pool gives "
                             "the local unit: they need local_pool")
        unknown = [name for name in self.local_pool_keep if name not in constants.MAP_SLICES]
        if unknown:
            raise ValueError(f"local_pool_keep: unknown maps {unknown}; known: {list(constants.MAP_SLICES)}")
        if self.highlight_weight < 0 or (self.highlight_weight and self.normal_pool):
            raise ValueError(f"highlight_weight {self.highlight_weight} must be 0, or positive without normal_pool "
                             "(the normal unit's loss has no diffuse map)")
        if self.anchor is not None:
            if self.anchor_weight <= 0:
                raise ValueError(f"anchor_weight {self.anchor_weight} must be positive")
            if self.normal_pool or self.local_pool or not self.synthesis.plain_probability:
                raise ValueError("anchor keeps the anchor's answers on plain batches: it needs the whole network "
                                 "(no normal_pool or local_pool) and synthesis.plain_probability > 0")
        if self.keep_validated and not self.validate_every:
            raise ValueError("keep_validated keeps the weights of validated steps: it needs validate_every")
        if self.local_pool_keep and not (self.local_pool and self.init):
            raise ValueError("local_pool_keep keeps maps as the init gives them: it needs local_pool and init")

    @classmethod
    def from_dict(cls, values: dict, source: str = "checkpoint", network: dict | None = None) -> TrainConfig:
        """The config a checkpoint stores. A checkpoint may store the network as overrides of its
        preset and the synthesis as overrides of the defaults: the network is then the one the
        checkpoint's weights were saved with (``network``, its document's), not this version's preset.
        Stored settings this version lacks (``configs.REMOVED_FIELDS``), here or in the nested
        network and procedural settings, are dropped where they are off and refused otherwise."""
        from ..model.checkpoint import network_config_from_dict

        values = drop_removed_fields("TrainConfig", values, source, InputError)
        stored = values.get("network")
        complete = {f.name for f in dataclasses.fields(NetworkConfig)} <= set(stored or {})
        if isinstance(stored, dict) and (complete or network is not None):
            values["network"] = network_config_from_dict(stored if complete else network, source)
        elif isinstance(stored, dict):
            values["network"] = drop_removed_fields("NetworkConfig", stored, source, InputError)
        for key, kind in (("synthesis", "SynthesisConfig"), ("procedural", "GeneratorConfig")):
            if isinstance(values.get(key), dict):
                values[key] = drop_removed_fields(kind, values[key], source, InputError)
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

#: NetworkConfig fields of the normal unit's size: ``--init`` from a network with another normal unit
#: loads everything else; the unit starts afresh, unless it only gained blocks (``Trainer``).
NORMAL_UNIT_FIELDS = ("normal_unit_width", "normal_unit_blocks", "normal_unit_middle_blocks")

#: NetworkConfig fields that change how the network runs but none of its weights: ``--init`` may
#: change them freely.
WEIGHTLESS_FIELDS = ("normal_unit_octaves", "normal_slope_scaled", "error_map")

#: Weights of the optional terms of the whole network's step (``Trainer``), each 0 (off) or positive.
WHOLE_STEP_WEIGHTS = ("lobe_weight", "colour_weight", "global_weight")

#: Parts of DeepBasisNet (its top-level modules) that ``train_only`` may name.
TRAINABLE_PARTS = ("encoder", "weight_decoder", "global_unit", "local_unit", "normal_unit")

#: Settings a resumed run may change: where and how it runs, not what it learns.
RESUMABLE_CHANGES = frozenset({"out", "workers", "checkpoint_minutes", "log_every", "validate_every", "device",
                               "max_minutes", "render_backend", "keep_validated"})
