"""Training settings: stored resolved, checked on resume (by the API and the command line), those
this version lacks read where off; a run's start from another network's weights (``--init``)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig
from mideepbasis.model.checkpoint import load_model, read_checkpoint
from mideepbasis.train import TrainConfig, Trainer

from .helpers import assert_the_runs_end_alike, network_with_a_working_normal_unit, tiny_config


def test_checkpoints_store_the_resolved_config_and_a_resume_must_agree_with_it(tmp_path):
    from mideepbasis.errors import InputError
    from mideepbasis.model.network import preset

    run = Trainer(tiny_config(tmp_path, steps=4, network={"num_bases": 3}), progress=False)
    run.run(stop_at=2)
    path = tmp_path / "run" / "checkpoint.safetensors"
    document, _ = read_checkpoint(path)
    stored = document["training"]["config"]
    # Resolved: the whole network and synthesis, not the overrides given, the photos' convention the network's.
    assert stored["network"] == {**json.loads(json.dumps(dataclasses.asdict(preset("tiny")))), "num_bases": 3}
    assert stored["synthesis"]["convention"] == stored["network"]["convention"] == "physical"
    assert TrainConfig.from_dict(stored) == run.config
    # Where the run is written and how often may change; what it learns may not, and the error names it.
    Trainer(tiny_config(tmp_path, steps=4, network={"num_bases": 3}, workers=1, log_every=5), resume=True,
            progress=False)
    with pytest.raises(InputError, match=r"checkpoint.safetensors: this run was started with lr = 0.003, not 0.01"):
        Trainer(tiny_config(tmp_path, steps=4, network={"num_bases": 3}, lr=1e-2), resume=True, progress=False)
    with pytest.raises(InputError, match=r"started with network.num_bases = 3, not 10"):
        Trainer(tiny_config(tmp_path, steps=4), resume=True, progress=False)


def test_the_command_line_resumes_with_the_stored_settings(tmp_path):
    from mideepbasis import cli

    out = tmp_path / "cli"
    common = ["train", "--out", str(out), "--preset", "tiny", "--batch", "1", "--size", "32", "--workers", "0",
              "--validate-every", "0", "--log-every", "1", "--network-num-bases", "2", "--synthesis-read-noise",
              "1e-4,2e-4"]
    assert cli.main(common + ["--steps", "2", "--max-minutes", "1e-9"]) == 0
    # Only how long it may run is given: everything else is the run's own.
    assert cli.main(["train", "--out", str(out), "--resume", "--max-minutes", "0"]) == 0
    document, _ = read_checkpoint(out / "model.safetensors")
    config = document["training"]["config"]
    assert (config["steps"], config["network"]["num_bases"], config["synthesis"]["read_noise"]) == (2, 2, [1e-4, 2e-4])
    assert cli.main(["train", "--out", str(out), "--resume", "--steps", "3"]) == 2


def test_a_resume_refuses_a_damaged_checkpoint_in_one_line(tmp_path, capsys):
    """64 KiB of the tensor data overwritten with 0xFF (NaN in float32), the size kept: with its
    checksum, and without one (as a checkpoint of an earlier version), the resume refuses."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from mideepbasis import cli
    from mideepbasis.model.checkpoint import METADATA_KEY
    from tests.model.test_checkpoint import damage

    out = tmp_path / "cli"
    common = ["train", "--out", str(out), "--preset", "tiny", "--batch", "1", "--size", "32", "--workers", "0",
              "--validate-every", "0", "--log-every", "1"]
    assert cli.main(common + ["--steps", "3", "--max-minutes", "1e-9"]) == 0
    path = out / "checkpoint.safetensors"
    good = path.read_bytes()
    for checksum in (True, False):
        path.write_bytes(good)
        if not checksum:  # the same file as an earlier version wrote it: no checksum in the metadata
            with safe_open(str(path), framework="pt") as handle:
                document = json.loads(handle.metadata()[METADATA_KEY])
                tensors = {name: handle.get_tensor(name) for name in handle.keys()}
            del document["checksum"]
            save_file(tensors, str(path), metadata={METADATA_KEY: json.dumps(document)})
        damage(path)
        damaged = path.read_bytes()
        capsys.readouterr()
        assert cli.main(["train", "--out", str(out), "--resume", "--max-minutes", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mideepbasis: error:") and "\n" not in err and str(path) in err
        assert ("checksum" if checksum else "NaN or infinite") in err
        assert path.read_bytes() == damaged and not (out / "model.safetensors").exists()


def test_training_materials_follow_the_runs_procedural_settings(tmp_path):
    from mideepbasis.train import TrainingMaterials

    settings = {"coarse_relief_tilt_deg": [20.0, 20.0], "coarse_relief_probability": 1.0}
    config = tiny_config(tmp_path, procedural=settings)
    assert config.procedural == GeneratorConfig(size=32, coarse_relief_tilt_deg=(20.0, 20.0), coarse_relief_probability=1.0)
    materials = TrainingMaterials(config.data, config.size, config.seed, config.procedural)
    plain = TrainingMaterials(config.data, config.size, config.seed)
    assert not torch.equal(materials[3], plain[3])
    assert torch.equal(materials[3][3:], plain[3][3:])  # only the relief differs
    # Stored resolved, and a run started before the setting existed resumes with the defaults.
    stored = dataclasses.asdict(config)
    assert TrainConfig.from_dict(stored) == config
    del stored["procedural"]
    assert TrainConfig.from_dict(stored).procedural == GeneratorConfig(size=32)


def test_a_stored_setting_this_version_lacks_is_dropped_where_off_and_refused_otherwise(tmp_path):
    """Checkpoints and runs of earlier versions store settings this version lacks (``configs.REMOVED_FIELDS``):
    at their off value they read as if absent; at another value the error names them, in one line."""
    from mideepbasis.configs import REMOVED_FIELDS
    from mideepbasis.errors import InputError

    config = tiny_config(tmp_path)
    stored = json.loads(json.dumps(dataclasses.asdict(config)))
    # As an earlier version wrote them: every removed setting at its off value (JSON: lists for tuples).
    earlier = json.loads(json.dumps({**stored, **REMOVED_FIELDS["TrainConfig"],
                                     "network": {**stored["network"], **REMOVED_FIELDS["NetworkConfig"]},
                                     "procedural": {**stored["procedural"], **REMOVED_FIELDS["GeneratorConfig"]}}))
    assert earlier["procedural"]["low_relief_tilt_deg"] == [0.3, 2.4]
    assert TrainConfig.from_dict(earlier) == config
    # The network stored as overrides of the preset (older runs), without the checkpoint's own network.
    assert TrainConfig.from_dict({**earlier, "network": {"normal_booster_width": 0}}) == config
    refused = [("", "normal_pool_loss", "crop_rmse"), ("network", "normal_booster_width", 16),
               ("network", "normal_unit_albedo", True), ("procedural", "low_relief_probability", 0.3),
               ("procedural", "relief_inversion_probability", 0.5), ("procedural", "low_relief_tilt_deg", [0.5, 1.0])]
    for part, name, value in refused:
        changed = json.loads(json.dumps(earlier))
        (changed[part] if part else changed)[name] = value
        with pytest.raises(InputError) as error:
            TrainConfig.from_dict(changed, "runs/old/checkpoint.safetensors")
        message = str(error.value)
        assert message.startswith(f"runs/old/checkpoint.safetensors: uses {name} = {value!r}, a setting this "
                                  "version does not have") and "\n" not in message, message
    with pytest.raises(InputError, match="uses normal_booster_width = 16"):
        TrainConfig.from_dict({**earlier, "network": {"normal_booster_width": 16}})


def test_a_checkpoint_with_settings_this_version_lacks_resumes(tmp_path):
    """A run's checkpoint as an earlier version wrote it (the removed settings at their off values,
    in its network and in its run's settings) resumes, and ends as a run straight through does."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from mideepbasis.configs import REMOVED_FIELDS
    from mideepbasis.model.checkpoint import METADATA_KEY

    Trainer(tiny_config(tmp_path / "a"), progress=False).run()
    Trainer(tiny_config(tmp_path / "b"), progress=False).run(stop_at=2)
    path = tmp_path / "b" / "run" / "checkpoint.safetensors"
    with safe_open(str(path), framework="pt") as handle:
        document = json.loads(handle.metadata()[METADATA_KEY])
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    document["network"].update(REMOVED_FIELDS["NetworkConfig"])
    training = document["training"]["config"]
    training.update(REMOVED_FIELDS["TrainConfig"])
    training["network"].update(REMOVED_FIELDS["NetworkConfig"])
    training["procedural"].update({key: list(value) if isinstance(value, tuple) else value
                                   for key, value in REMOVED_FIELDS["GeneratorConfig"].items()})
    save_file(tensors, str(path), metadata={METADATA_KEY: json.dumps(document)})
    resumed = Trainer(tiny_config(tmp_path / "b"), resume=True, progress=False)
    assert resumed.step == 2
    resumed.run()
    assert_the_runs_end_alike(tmp_path)


def test_init_from_a_network_with_another_local_unit_loads_the_rest(tmp_path):
    from mideepbasis.errors import InputError
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = DeepBasisNet(preset("tiny"))
    path = save_checkpoint(tmp_path / "source.safetensors", source)
    wider = Trainer(tiny_config(tmp_path / "w", init=str(path), network={"local_width": 8}), progress=False)
    loaded, original = wider.model.state_dict(), source.state_dict()
    rest = [name for name in original if not name.startswith("local_unit.")]
    assert rest and all(torch.equal(loaded[name], original[name]) for name in rest)
    assert loaded["local_unit.intro.weight"].shape[0] == 8 != original["local_unit.intro.weight"].shape[0]
    with pytest.raises(InputError, match="differs from this run's"):
        Trainer(tiny_config(tmp_path / "n", init=str(path), network={"num_bases": 3}), progress=False)


def test_init_with_another_error_map_loads_every_weight(tmp_path):
    from mideepbasis.model.checkpoint import load_model, save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = DeepBasisNet(preset("tiny"))
    path = save_checkpoint(tmp_path / "source.safetensors", source)
    trainer = Trainer(tiny_config(tmp_path / "r", init=str(path), network={"error_map": "log_ratio"}), progress=False)
    assert trainer.model.config.error_map == "log_ratio" and source.config.error_map == "clipped"
    loaded, original = trainer.model.state_dict(), source.state_dict()
    assert all(torch.equal(loaded[name], original[name]) for name in original)
    saved = load_model(save_checkpoint(tmp_path / "saved.safetensors", trainer.model))
    assert saved.config.error_map == "log_ratio"  # the checkpoint keeps it


def test_widened_inputs_start_as_the_narrow_network():
    from mideepbasis.model.network import DeepBasisNet, preset
    from mideepbasis.train import widen_inputs

    torch.manual_seed(0)
    narrow = DeepBasisNet(preset("tiny")).eval()
    wide = DeepBasisNet(preset("tiny", extra_inputs=("shading", "highpass"))).eval()
    wide.load_state_dict(widen_inputs(narrow.state_dict(), wide.state_dict(), 9))
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    extra = torch.rand(2, 6, 32, 32) * 2 - 1
    with torch.no_grad():
        a = narrow(inputs, lights, ).maps
        b = wide(torch.cat([inputs, extra], 1), lights).maps
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    # The input width follows from the optional inputs; an unknown one is refused by name.
    assert preset("tiny", extra_inputs=("shading",)).input_channels == 12
    with pytest.raises(ValueError, match="unknown extra inputs \\['shadow'\\]"):
        preset("tiny", extra_inputs=("shadow",))


def test_train_only_the_normal_unit_from_a_network_without_one(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = DeepBasisNet(preset("tiny"))
    path = save_checkpoint(tmp_path / "source.safetensors", source)
    trainer = Trainer(tiny_config(tmp_path, init=str(path), network={"normal_unit_width": 4},
                                  train_only=("normal_unit",), vc_weight=0.0), progress=False)
    before = {name: value.clone() for name, value in trainer.model.state_dict().items()}
    trainer.run()
    after = trainer.model.state_dict()
    changed = {name.split(".")[0] for name in after if not torch.equal(before[name], after[name])}
    assert changed == {"normal_unit"}
    assert all(torch.equal(after[name], value) for name, value in source.state_dict().items())
    assert load_model(tmp_path / "run" / "model.safetensors").config.normal_unit_width == 4
    with pytest.raises(ValueError, match="unknown network parts \\['decoder'\\]"):
        tiny_config(tmp_path, train_only=("decoder",))


def test_a_deepened_normal_unit_starts_as_the_checkpoint_it_grew_from(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint

    source = network_with_a_working_normal_unit()
    path = save_checkpoint(tmp_path / "source.safetensors", source)
    deeper = {"normal_unit_width": 4, "normal_unit_blocks": (1, 1, 2, 2), "normal_unit_middle_blocks": 3}
    model = Trainer(tiny_config(tmp_path / "d", init=str(path), network=deeper), progress=False).model.eval()
    assert len(model.normal_unit.middle_blks) == 3 and len(model.normal_unit.encoders[3]) == 2
    assert len(model.normal_unit.decoders[0]) == 2 and len(model.normal_unit.decoders[3]) == 1
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    with torch.no_grad():
        torch.testing.assert_close(model(inputs, lights).maps, source(inputs, lights).maps, rtol=1e-5, atol=1e-6)
    # A shallower unit cannot keep what the checkpoint's computed: it starts afresh, the rest loaded.
    shallower = {"normal_unit_width": 4, "normal_unit_blocks": (1, 1, 1, 1), "normal_unit_middle_blocks": 1}
    loaded = Trainer(tiny_config(tmp_path / "s", init=str(path), network=shallower), progress=False).model.state_dict()
    original = source.state_dict()
    assert all(torch.equal(loaded[name], value) for name, value in original.items() if not name.startswith("normal_unit."))
    fresh_scales = [value for name, value in loaded.items() if name.startswith("normal_unit.") and name.endswith("beta")]
    assert fresh_scales and all(not value.any() for value in fresh_scales)
