"""Checkpoints: safetensors files with the weights, the resolved configuration and what made them.

A checkpoint holds tensors only (safetensors never unpickles anything) and one JSON document in
the file's metadata under the key ``mideepbasis``::

    {"format": "mideepbasis-checkpoint", "version": 1, "network": {NetworkConfig fields},
     "convention": "physical", "training": {...what data, steps, command...}, ...}

Training checkpoints add the optimiser's moments and the random-generator states as tensors
(``optimizer/...``, ``state/...``) and the loop's position in the metadata, so that a resumed run
continues exactly where it stopped. Every write goes to a temporary file that is renamed into place.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import zlib
from importlib import resources
from pathlib import Path

import torch
from safetensors import SafetensorError
from torch import nn
from safetensors.torch import load_file, save_file

from ..configs import drop_removed_fields
from ..errors import InputError
from .inputs import ModelInfo
from .network import DeepBasisNet, NetworkConfig

FORMAT = "mideepbasis-checkpoint"
FORMAT_VERSION = 1
METADATA_KEY = "mideepbasis"
WEIGHTS_PREFIX = "model/"

#: The model that ships with the package (see MODEL.md), loaded by ``load_model()``.
SHIPPED_MODEL = "deepbasis_compact.safetensors"


class CheckpointError(InputError):
    """A file is not a usable mideepbasis checkpoint; the message names it and the problem."""


def network_config_to_dict(config: NetworkConfig) -> dict:
    return {key: list(value) if isinstance(value, tuple) else value
            for key, value in dataclasses.asdict(config).items()}


def network_config_from_dict(values: dict, source: str = "checkpoint") -> NetworkConfig:
    """The ``NetworkConfig`` a checkpoint stores. A stored setting this version lacks
    (``configs.REMOVED_FIELDS``) is dropped where it is off and refused otherwise."""
    fields = {f.name: f for f in dataclasses.fields(NetworkConfig)}
    values = drop_removed_fields("NetworkConfig", values, source, CheckpointError)
    # A checkpoint may store the input width, which the optional inputs determine.
    stored_inputs = values.pop("input_channels", None)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise CheckpointError(f"{source}: unknown network settings {unknown}")
    converted = {key: tuple(value) if isinstance(value, list) else value for key, value in values.items()}
    config = NetworkConfig(**converted)
    if stored_inputs is not None and stored_inputs != config.input_channels:
        raise CheckpointError(f"{source}: input_channels {stored_inputs} does not match the optional inputs "
                              f"{list(config.extra_inputs)} ({config.input_channels} channels)")
    return config


def save_checkpoint(path: str | os.PathLike, model: torch.nn.Module, metadata: dict | None = None,
                    extra_tensors: dict[str, torch.Tensor] | None = None, keep_previous: bool = False) -> Path:
    """Write ``model``'s weights, its configuration, ``metadata`` (JSON-able) and the tensors'
    checksum atomically; never weights that are not finite (the file on disk stays as it was).

    Args:
        path: the ``.safetensors`` file.
        model: a DeepBasisNet (or a DDP wrapper of one).
        metadata: more JSON for the document (``training``, ``convention`` overrides, ...).
        extra_tensors: more tensors (optimiser state, generator states), by name.
        keep_previous: keep the file being replaced as ``previous_path(path)`` (a training run's
            last good checkpoint, should this one be damaged on disk).

    Raises:
        CheckpointError: a tensor holds NaN or infinite values.
    """
    network = getattr(model, "module", model)
    tensors = {WEIGHTS_PREFIX + name: value.detach().contiguous().cpu() for name, value in network.state_dict().items()}
    for name, value in (extra_tensors or {}).items():
        tensors[name] = value.detach().contiguous().cpu()
    path = Path(path)
    broken = non_finite_tensors(tensors)
    if broken:
        raise CheckpointError(f"{path}: not written: {len(broken)} of {len(tensors)} tensors hold NaN or infinite "
                              f"values (e.g. {broken[0]}); the file there is kept as it was")
    document = {"format": FORMAT, "version": FORMAT_VERSION, "network": network_config_to_dict(network.config),
                "convention": network.config.convention, **(metadata or {}), "checksum": tensor_checksum(tensors)}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    kept = path.with_name(f".{path.name}.previous-{os.getpid()}")
    try:
        save_file(tensors, str(temporary), metadata={METADATA_KEY: json.dumps(document)})
        if keep_previous and path.exists():
            # A second name for the old file first: at every instant ``path`` is the old file or the new one.
            os.link(path, kept)
            os.replace(kept, previous_path(path))
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
        kept.unlink(missing_ok=True)
    return path


def previous_path(path: str | os.PathLike) -> Path:
    """Where ``save_checkpoint(keep_previous=True)`` keeps the checkpoint it replaced."""
    path = Path(path)
    return path.with_name(f"{path.stem}.previous{path.suffix}")


def tensor_checksum(tensors: dict[str, torch.Tensor]) -> str:
    """CRC-32 of the tensors' names, shapes, types and bytes, in the order of their names (hex)."""
    checksum = 0
    for name in sorted(tensors):
        tensor = tensors[name].detach().contiguous().cpu()
        checksum = zlib.crc32(f"{name}{tuple(tensor.shape)}{tensor.dtype}".encode(), checksum)
        checksum = zlib.crc32(tensor.view(-1).view(torch.uint8).numpy() if tensor.numel() else b"", checksum)
    return f"{checksum:08x}"


def non_finite_tensors(tensors: dict[str, torch.Tensor]) -> list[str]:
    """The names of the floating-point tensors that hold NaN or infinite values."""
    return [name for name, tensor in tensors.items()
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all())]


def read_checkpoint(path: str | os.PathLike) -> tuple[dict, dict[str, torch.Tensor]]:
    """(document, tensors) of a checkpoint file, checked for format and version; never unpickles."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as handle:
            raw = (handle.metadata() or {}).get(METADATA_KEY)
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as error:
        raise CheckpointError(f"{path}: not a safetensors checkpoint ({' '.join(str(error).split())})") from None
    if raw is None:
        raise CheckpointError(f"{path}: a safetensors file without mideepbasis metadata (not a mideepbasis checkpoint)")
    try:
        document = json.loads(raw)
    except json.JSONDecodeError:
        raise CheckpointError(f"{path}: its mideepbasis metadata is not valid JSON") from None
    if document.get("format") != FORMAT:
        raise CheckpointError(f"{path}: format {document.get('format')!r} is not {FORMAT!r}")
    if document.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {document.get('version')} is not supported "
                              f"(this mideepbasis reads version {FORMAT_VERSION})")
    if "checksum" in document and tensor_checksum(tensors) != document["checksum"]:
        raise CheckpointError(f"{path}: its tensors do not match their checksum: the file is damaged")
    return document, tensors


#: The layers whose random initialisation ``parameters_left_uninitialised`` skips: nearly all of
#: the shipped network's parameters, and 55 of a ``load_model``'s 135 ms on two AVX2 cores.
RANDOMLY_INITIALISED = (nn.Conv2d, nn.Linear)


@contextlib.contextmanager
def parameters_left_uninitialised():
    """Inside, ``RANDOMLY_INITIALISED`` layers are built without drawing their random initial
    parameters (their memory is left as it is): for a network whose every parameter a checkpoint
    then replaces. A setting of the classes, so of every thread, while it lasts (a few ms);
    restored after."""
    saved = {layer: layer.__dict__.get("reset_parameters") for layer in RANDOMLY_INITIALISED}
    try:
        for layer in RANDOMLY_INITIALISED:
            layer.reset_parameters = lambda self: None
        yield
    finally:
        for layer, method in saved.items():
            if method is None:  # inherited (Conv2d's is _ConvNd's)
                del layer.reset_parameters
            else:
                layer.reset_parameters = method


def load_model(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> DeepBasisNet:
    """A DeepBasisNet with the weights of a checkpoint, in eval mode.

    Args:
        path: the checkpoint; None loads the model shipped with the package.
        device: where to put it.

    Raises:
        CheckpointError: not a checkpoint, wrong version, or a tensor missing, unexpected or of
            the wrong shape (the message names the first one).
    """
    path = Path(path) if path is not None else shipped_model_path()
    document, tensors = read_checkpoint(path)
    config = network_config_from_dict(document.get("network", {}), str(path))
    with parameters_left_uninitialised():  # every tensor is replaced below, or the load fails
        model = DeepBasisNet(config)
    weights = {name[len(WEIGHTS_PREFIX):]: value for name, value in tensors.items() if name.startswith(WEIGHTS_PREFIX)}
    expected = model.state_dict()
    missing = [name for name in expected if name not in weights]
    if missing:
        raise CheckpointError(f"{path}: tensor {WEIGHTS_PREFIX}{missing[0]} is missing ({len(missing)} missing in all)")
    unexpected = [name for name in weights if name not in expected]
    if unexpected:
        raise CheckpointError(f"{path}: unexpected tensor {WEIGHTS_PREFIX}{unexpected[0]} for this network configuration")
    for name, value in expected.items():
        if tuple(weights[name].shape) != tuple(value.shape):
            raise CheckpointError(f"{path}: tensor {WEIGHTS_PREFIX}{name} has shape {tuple(weights[name].shape)}, "
                                  f"the network expects {tuple(value.shape)}")
    model.load_state_dict(weights)
    model.info = ModelInfo.from_document(document, config, str(path))
    return model.to(device).eval()


def shipped_model_path() -> Path:
    """The model file shipped inside the package."""
    path = Path(str(resources.files("mideepbasis") / "models" / SHIPPED_MODEL))
    if not path.is_file():
        raise CheckpointError(f"{path}: the shipped model is missing from this installation")
    return path


# --- the authors' published weights ------------------------------------------------------------------

#: Half-width of the sample the authors' networks see [patch half-widths]: their 256-pixel crops of
#: a 384-pixel grid over [-1.5, 1.5] put pixels 3 / 383 apart.
AUTHORS_PLANE_EXTENT = 384.0 / 383.0


def authors_name_map(config: NetworkConfig) -> dict[str, str]:
    """Our state-dict name for every tensor of the authors' GlobalNet and LocalNet state dicts.

    Their global network nests everything under ``basisNet``: ``en_convs`` (the first a bare
    convolution, the others after a leaky ReLU), ``en_fcs`` / ``en_g2e_fcs`` / ``en_ins_norms``
    (the global track and instance norms), ``weight_net.{deconv,fcs,f2c,ins}`` (the decoder) and
    ``basis_net`` (the MLP). Their local network is a NAFNet with the same names as ours.
    """
    names = {}
    levels = len(config.encoder_channels)
    for i in range(levels):
        source = f"basisNet.en_convs.{i}." if i == 0 else f"basisNet.en_convs.{i}.1."
        for kind in ("weight", "bias"):
            names[source + kind] = f"encoder.convs.{i}.{kind}"
            names[f"basisNet.en_fcs.{i}.0.{kind}"] = f"encoder.global_fcs.{i}.{kind}"
    for i in range(levels - 1):
        names[f"basisNet.en_g2e_fcs.{i}.weight"] = f"encoder.global_to_maps.{i}.weight"
    for i in range(levels - 2):
        for kind in ("weight", "bias"):
            names[f"basisNet.en_ins_norms.{i}.{kind}"] = f"encoder.norms.{i}.{kind}"
    for i in range(levels):
        for kind in ("weight", "bias"):
            names[f"basisNet.weight_net.deconv.{i}.1.{kind}"] = f"weight_decoder.convs.{i}.0.{kind}"
            names[f"basisNet.weight_net.deconv.{i}.2.{kind}"] = f"weight_decoder.convs.{i}.1.{kind}"
        names[f"basisNet.weight_net.f2c.{i}.weight"] = f"weight_decoder.global_to_maps.{i}.weight"
    for i in range(levels - 1):
        for kind in ("weight", "bias"):
            names[f"basisNet.weight_net.fcs.{i}.0.{kind}"] = f"weight_decoder.global_fcs.{i}.{kind}"
            names[f"basisNet.weight_net.ins.{i}.{kind}"] = f"weight_decoder.norms.{i}.{kind}"
    for i in range(config.mlp_hidden_layers + 1):
        for kind in ("weight", "bias"):
            names[f"basisNet.basis_net.{i}.0.{kind}"] = f"global_unit.{2 * i}.{kind}"
    return names


def _first_sentence(error: BaseException, most: int = 200) -> str:
    """An error's telling sentence, on one line, without terminal escapes or other control
    characters: torch's unpickler's own reason where its message holds one, else the first."""
    text = re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", str(error))
    text = " ".join("".join(c if c.isprintable() else " " for c in text).split())
    text = text.split("WeightsUnpickler error: ", 1)[-1]
    sentence = re.split(r"(?<=[.!?])\s", text, maxsplit=1)[0]
    return sentence if len(sentence) <= most else sentence[:most].rsplit(" ", 1)[0] + " ..."


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """A state dict from a .pth file, without ever unpickling anything but tensors and containers."""
    import pickle

    if not path.is_file():
        raise CheckpointError(f"{path}: no such weight file")
    try:
        loaded = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError) as error:
        raise CheckpointError(f"{path}: not a PyTorch state dict that loads without unpickling code "
                              f"({_first_sentence(error)})") from None
    if isinstance(loaded, dict) and "params" in loaded and isinstance(loaded["params"], dict):
        loaded = loaded["params"]
    if not isinstance(loaded, dict) or not all(isinstance(v, torch.Tensor) for v in loaded.values()):
        raise CheckpointError(f"{path}: not a state dict (a mapping of names to tensors)")
    return {k[len("module."):] if k.startswith("module.") else k: v for k, v in loaded.items()}


def _sha256(path: Path) -> str:
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def import_authors_weights(global_path: str | os.PathLike, local_path: str | os.PathLike, fov: float,
                           output: str | os.PathLike) -> Path:
    """Map the authors' GlobalNet and LocalNet weights onto our ``paper`` preset and save a checkpoint.

    Every tensor must land on a tensor of the same shape: none left over, none missing (the error
    names the first). The checkpoint records the ``deepbasis`` shading convention, their framed
    sample, the field of view the weights were trained for and the source files' SHA-256.

    Args:
        global_path, local_path: their ``net_g_*.pth`` and ``net_l_*.pth``.
        fov: field of view the weights belong to [deg] (their ``fovZ`` 2.414 is 45 deg, 4 is 28.07).
        output: the ``.safetensors`` file to write.
    """
    from .network import preset

    global_path, local_path = Path(global_path), Path(local_path)
    config = preset("paper", convention="deepbasis", plane_extent=AUTHORS_PLANE_EXTENT)
    model = DeepBasisNet(config)
    expected = model.state_dict()
    names = authors_name_map(config)
    mapped = {}
    for path, prefix in ((global_path, None), (local_path, "local_unit.")):
        state = _load_state_dict(path)
        for name, tensor in state.items():
            target = names.get(name) if prefix is None else prefix + name
            if target is None or target not in expected:
                raise CheckpointError(f"{path}: tensor {name} has no place in the paper network")
            if tuple(tensor.shape) != tuple(expected[target].shape):
                raise CheckpointError(f"{path}: tensor {name} has shape {tuple(tensor.shape)}, the paper network's "
                                      f"{target} has {tuple(expected[target].shape)}")
            mapped[target] = tensor.float()
    missing = [name for name in expected if name not in mapped]
    if missing:
        inverse = {ours: theirs for theirs, ours in names.items()}
        first = inverse.get(missing[0], missing[0].removeprefix("local_unit."))
        source = local_path if missing[0].startswith("local_unit.") else global_path
        raise CheckpointError(f"{source}: tensor {first} is missing ({len(missing)} missing in all)")
    model.load_state_dict(mapped)
    provenance = {"source": "DeepBasis authors' published weights", "global_file": global_path.name,
                  "local_file": local_path.name, "global_sha256": _sha256(global_path),
                  "local_sha256": _sha256(local_path)}
    return save_checkpoint(output, model, metadata={"fov_deg": float(fov), "photo_decoding": "gamma2.2",
                                                    "provenance": provenance,
                                                    "training": {"data": ["DeepBasis authors' training set"]}})
