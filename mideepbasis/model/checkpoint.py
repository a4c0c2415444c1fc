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

import dataclasses
import json
import os
from importlib import resources
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from ..errors import InputError
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
    fields = {f.name: f for f in dataclasses.fields(NetworkConfig)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise CheckpointError(f"{source}: unknown network settings {unknown}")
    converted = {key: tuple(value) if isinstance(value, list) else value for key, value in values.items()}
    return NetworkConfig(**converted)


def save_checkpoint(path: str | os.PathLike, model: torch.nn.Module, metadata: dict | None = None,
                    extra_tensors: dict[str, torch.Tensor] | None = None) -> Path:
    """Write ``model``'s weights, its configuration and ``metadata`` (JSON-able) atomically.

    Args:
        path: the ``.safetensors`` file.
        model: a DeepBasisNet (or a DDP wrapper of one).
        metadata: more JSON for the document (``training``, ``convention`` overrides, ...).
        extra_tensors: more tensors (optimiser state, generator states), by name.
    """
    network = getattr(model, "module", model)
    document = {"format": FORMAT, "version": FORMAT_VERSION, "network": network_config_to_dict(network.config),
                "convention": network.config.convention, **(metadata or {})}
    tensors = {WEIGHTS_PREFIX + name: value.detach().contiguous().cpu() for name, value in network.state_dict().items()}
    for name, value in (extra_tensors or {}).items():
        tensors[name] = value.detach().contiguous().cpu()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        save_file(tensors, str(temporary), metadata={METADATA_KEY: json.dumps(document)})
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


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
    return document, tensors


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
    model.checkpoint = document
    return model.to(device).eval()


def shipped_model_path() -> Path:
    """The model file shipped inside the package."""
    path = Path(str(resources.files("mideepbasis") / "models" / SHIPPED_MODEL))
    if not path.is_file():
        raise CheckpointError(f"{path}: the shipped model is missing from this installation")
    return path
