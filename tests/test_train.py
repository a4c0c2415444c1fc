"""Training: the loss falls, the VC loss by hand, exact resume after an interrupt, two processes under torchrun."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.synth import Variation
from mideepbasis.model.checkpoint import load_model, read_checkpoint
from mideepbasis.model.network import DeepBasisOutput
from mideepbasis.train import (TrainConfig, Trainer, augment, learning_rate_factor, rendering_loss,
                               sample_render_geometry, saturation_penalty, variation_consistency_loss)


def tiny_config(tmp_path, **overrides):
    values = dict(out=str(tmp_path / "run"), preset="tiny", steps=4, batch=2, size=32, workers=0, validate_every=0,
                  log_every=1, checkpoint_minutes=1e9, lr=3e-3, local_lr=3e-3)
    values.update(overrides)
    return TrainConfig(**values)


def test_loss_falls_on_a_fixed_batch(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, steps=60), progress=False)
    maps = torch.stack([generate(seed, config=GeneratorConfig(size=32)).to_tensor() for seed in range(2)])
    losses = [trainer.train_step(maps)["loss"] for _ in range(60)]
    assert sum(losses[-10:]) / 10 < 0.8 * sum(losses[:10]) / 10, losses


def test_variation_consistency_loss_by_hand():
    # One material, one basis, 1x1 pixel. The original prediction's basis, varied by xi, is compared
    # with the varied prediction's basis; plus the L1 of the varied maps against the varied truth.
    basis = torch.tensor([0.0, 0.0, 1.0, 0.2, -0.2, 0.0, 0.6, -1.0, -1.0, -1.0]).view(1, 1, 10, 1, 1)
    varied_basis = torch.zeros(1, 1, 10, 1, 1)
    variation = Variation(rotation=torch.tensor([0.0]), shift=torch.full((1, 7), 0.5))
    original = DeepBasisOutput(maps=torch.zeros(1, 10, 1, 1), bases=basis)
    truth = torch.zeros(1, 10, 1, 1)
    truth[:, 2] = 1.0  # flat normal, every other map 0 (signed: -1)
    varied = DeepBasisOutput(maps=truth.clone(), bases=varied_basis, signed=torch.zeros(1, 10, 1, 1))
    loss = variation_consistency_loss(original, varied, variation, truth)
    # xi on the basis: normal unchanged (rotation 0); others m -> (m + 0.5) / 1.5 in [0, 1] space.
    expected_basis = [0.0, 0.0, 1.0] + [2 * ((v * 0.5 + 0.5 + 0.5) / 1.5) - 1 for v in (0.2, -0.2, 0.0, 0.6, -1, -1, -1)]
    consistency = sum(abs(e - 0.0) for e in expected_basis) / 10
    supervised = (0 + 0 + 1 + 7 * 1) / 10  # signed maps 0 against truth [0, 0, 1, -1 x 7]
    assert loss.item() == pytest.approx(consistency + supervised, abs=1e-6)


def test_saturation_penalty_by_hand():
    raw = torch.tensor([0.5, -2.0, 3.0, -5.0], requires_grad=True).view(1, 4, 1, 1)
    penalty = saturation_penalty(raw, limit=2.0)
    assert penalty.item() == pytest.approx((0 + 0 + 1 ** 2 + 3 ** 2) / 4)
    (gradient,) = torch.autograd.grad(penalty, raw)
    # Zero inside the limit; outside, it points away from zero, so descent pulls back into range.
    assert gradient.flatten().tolist() == pytest.approx([0.0, 0.0, 2 * 1 / 4, -2 * 3 / 4])


def test_penalty_revives_a_saturated_weight_decoder(tmp_path):
    # Blow the decoder's last layer up until its outputs reach tens (tanh flat, the blend's gradient
    # gone), as a run's did; with the penalty they come back, without it they do not.
    maps = torch.stack([generate(seed, config=GeneratorConfig(size=32)).to_tensor() for seed in range(2)])
    final = {}
    for weight in (0.0, 1e-2):
        trainer = Trainer(tiny_config(tmp_path / str(weight), lr=1e-2, local_lr=1e-2, saturation_weight=weight),
                          progress=False)
        with torch.no_grad():
            trainer.model.weight_decoder.convs[-1][-1].weight.mul_(100.0)
        first = trainer.train_step(maps)["l_saturation"]
        for _ in range(40):
            final[weight] = trainer.train_step(maps)["l_saturation"]
        assert first > 100
    assert final[1e-2] < 0.15 * first and final[1e-2] < 0.05 * final[0.0], final


def test_learning_rate_decays_by_cosine():
    assert learning_rate_factor(0, 100, 0.01) == 1.0
    assert learning_rate_factor(99, 100, 0.01) == pytest.approx(0.01)
    assert learning_rate_factor(49, 100, 0.0) == pytest.approx(0.5 * (1 + math.cos(math.pi * 49 / 99)))


def test_augmentation_keeps_normals_consistent():
    import numpy as np

    maps = torch.zeros(10, 8, 8)
    maps[0], maps[2] = 0.6, 0.8  # every normal leans towards +x
    maps[3:] = torch.linspace(0, 1, 8).view(1, 1, 8)  # brighter to the right (+x)
    for seed in range(8):
        out = augment(maps, 8, np.random.default_rng(seed))
        # The normal must lean towards where the "right" side went: compare with the gradient of diffuse.
        gy, gx = torch.gradient(out[3])
        lean = torch.stack([out[0].mean(), out[1].mean()])
        direction = torch.stack([gx.mean(), -gy.mean()])  # image rows run towards -y
        assert torch.allclose(lean / lean.norm(), direction / direction.norm(), atol=1e-5), seed


def test_resume_after_an_interrupt_gives_the_same_weights(tmp_path):
    straight = Trainer(tiny_config(tmp_path / "a"), progress=False)
    straight.run()
    interrupted = Trainer(tiny_config(tmp_path / "b", steps=4), progress=False)
    interrupted.run(stop_at=2)  # stop half way, as a kill right after a checkpoint would
    resumed = Trainer(tiny_config(tmp_path / "b", steps=4), resume=True, progress=False)
    assert resumed.step == 2
    resumed.run()
    a = load_model(tmp_path / "a" / "run" / "model.safetensors").state_dict()
    b = load_model(tmp_path / "b" / "run" / "model.safetensors").state_dict()
    for name in a:
        assert torch.equal(a[name], b[name]), name
    document, _ = read_checkpoint(tmp_path / "b" / "run" / "checkpoint.safetensors")
    assert document["training_state"]["step"] == 4


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
    from mideepbasis import cli
    from mideepbasis.model.checkpoint import METADATA_KEY
    from safetensors import safe_open
    from safetensors.torch import save_file
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


def test_a_run_whose_loss_turns_non_finite_stops_and_keeps_its_last_checkpoint(tmp_path):
    from mideepbasis.train import TrainingDiverged

    run = Trainer(tiny_config(tmp_path, steps=6), progress=False)
    run.run(stop_at=2)
    path = tmp_path / "run" / "checkpoint.safetensors"
    saved = path.read_bytes()
    resumed = Trainer(tiny_config(tmp_path, steps=6, checkpoint_minutes=0.0), resume=True, progress=False)
    real_step = resumed.train_step

    def diverging(maps):
        losses = real_step(maps)
        with torch.no_grad():
            for parameter in resumed.model.parameters():
                parameter.fill_(float("nan"))
        return {**losses, "loss": float("nan")}

    resumed.train_step = diverging
    with pytest.raises(TrainingDiverged, match="diverged at step 3"):
        resumed.run()
    assert path.read_bytes() == saved  # the NaN weights never replaced it


def test_the_end_of_a_run_without_validation_names_files_that_exist(tmp_path, capsys):
    from mideepbasis import cli

    out = tmp_path / "cli"
    assert cli.main(["train", "--out", str(out), "--preset", "tiny", "--batch", "1", "--size", "32", "--workers", "0",
                     "--validate-every", "0", "--steps", "3", "--max-minutes", "1e-9"]) == 0
    printed = capsys.readouterr().out
    named = [word.rstrip(";)") for word in printed.split() if word.endswith((".safetensors", ".safetensors;"))]
    assert named and all(Path(name).exists() for name in named), printed


def test_two_processes_under_torchrun(tmp_path):
    out = tmp_path / "ddp"
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                             "29517", "-m", "mideepbasis.cli", "train", "--preset", "tiny", "--steps", "2", "--batch", "1",
                             "--size", "32", "--workers", "0", "--validate-every", "0", "--log-every", "1", "--out",
                             str(out)], capture_output=True, text=True, timeout=600, env=environment)
    assert result.returncode == 0, result.stderr[-3000:]
    document, _ = read_checkpoint(out / "model.safetensors")
    assert document["training"]["world_size"] == 2 and document["training"]["steps_done"] == 2
    assert (out / "train.jsonl").read_text().count('"loss"') == 2


def test_learning_rate_warms_up_linearly_then_decays():
    assert learning_rate_factor(0, 110, 0.01, warmup=10) == pytest.approx(0.1)
    assert learning_rate_factor(4, 110, 0.01, warmup=10) == pytest.approx(0.5)
    assert learning_rate_factor(10, 110, 0.01, warmup=10) == 1.0
    assert learning_rate_factor(109, 110, 0.01, warmup=10) == pytest.approx(0.01)


def test_mirror_pairs_put_a_highlight_on_the_sample():
    lights, views = sample_render_geometry(64, 6, torch.Generator().manual_seed(3))
    assert lights.shape == views.shape == (64, 6, 3)
    assert (lights[..., 2] >= 2.0 * 0.15 - 1e-6).all() and (views[..., 2] >= 2.0 * 0.15 - 1e-6).all()
    assert (torch.linalg.vector_norm(lights, dim=-1) <= 5.0 + 0.5 * 2**0.5 + 1e-5).all()
    # The last three pairs: the straight line from the light to the view mirrored below the plane
    # crosses the plane at q, where light and view directions are mirror images about +z.
    light, view = lights[:, 3:].reshape(-1, 3), views[:, 3:].reshape(-1, 3)
    below = view * torch.tensor([1.0, 1.0, -1.0])
    t = light[:, 2] / (light[:, 2] - below[:, 2])
    q = light + t[:, None] * (below - light)
    assert q[:, 2].abs().max() < 1e-5 and q[:, :2].abs().max() <= 0.7 + 1e-5
    to_light = torch.nn.functional.normalize(light - q, dim=-1)
    to_view = torch.nn.functional.normalize(view - q, dim=-1)
    assert torch.allclose(to_view, to_light * torch.tensor([-1.0, -1.0, 1.0]), atol=1e-5)
    # The first three are drawn independently: not mirror pairs.
    light, view = lights[:, :3].reshape(-1, 3), views[:, :3].reshape(-1, 3)
    assert ((light[:, :2] + view[:, :2]).abs().sum(-1) > 0.05).float().mean() > 0.9


@pytest.fixture
def restore_render_backend():
    from mideepbasis.render import render_backend, set_render_backend

    before = render_backend()
    yield
    set_render_backend(before)


def test_rendering_loss_against_a_hand_computed_reference(restore_render_backend):
    from mideepbasis import geometry
    from mideepbasis.render import reference, set_render_backend

    truth = torch.stack([generate(seed, config=GeneratorConfig(size=16)).to_tensor() for seed in range(2)])
    predicted = truth.clone()
    predicted[:, 3:6] *= 0.5
    lights, views = sample_render_geometry(2, 4, torch.Generator().manual_seed(0))
    intensity = geometry.flash_intensity()
    expected = (torch.log1p(reference.render_flash(predicted, lights, intensity, views=views))
                - torch.log1p(reference.render_flash(truth, lights, intensity, views=views))).abs().mean()
    for backend, tolerance in (("torch", 1e-6), ("mitsuba", 1e-4)):
        set_render_backend(backend)
        assert rendering_loss(truth, truth, lights, views).item() == 0.0
        assert rendering_loss(predicted, truth, lights, views).item() == pytest.approx(expected.item(), rel=tolerance)
    # Its gradient reaches the normals through the plugin.
    normals = truth.clone().requires_grad_(True)
    tilted = torch.cat([normals[:, :3] + torch.tensor([0.2, 0.0, 0.0]).view(1, 3, 1, 1), normals[:, 3:]], 1)
    rendering_loss(tilted, truth, lights, views).backward()
    assert normals.grad[:, :3].abs().sum() > 0


def test_render_backend_torch_works_without_mitsuba(tmp_path):
    fake = tmp_path / "mitsuba"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('no mitsuba here')\n")
    script = ("import torch\n"
              "from mideepbasis.render import render_flash, MitsubaMissingError\n"
              "maps = torch.zeros(1, 10, 4, 4); maps[:, 2] = 1; maps[:, 3:6] = 1\n"
              "image = render_flash(maps, torch.tensor([[[0.0, 0.0, 2.414213562]]]), backend='torch')\n"
              "assert abs(image[0, 0, :, 1:3, 1:3].mean().item() - 1.0) < 0.05, image\n"
              "try:\n"
              "    render_flash(maps, torch.tensor([[[0.0, 0.0, 2.0]]]))\n"
              "except MitsubaMissingError as error:\n"
              "    print('refused:', error)\n")
    environment = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=environment)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "refused: the mitsuba render backend needs Mitsuba 3 (no mitsuba here)" in result.stdout


def test_validation_keeps_the_best_weights_and_a_time_limit_stops_with_a_checkpoint(tmp_path, restore_render_backend):
    config = tiny_config(tmp_path, steps=1000, validate_every=3, validation_count=3, render_weight=1.0,
                         render_lights=2, bf16=True, warmup_steps=2, max_minutes=0.15)
    trainer = Trainer(config, progress=False)
    trainer.run()
    assert 0 < trainer.step < 1000
    records = [json.loads(line) for line in (tmp_path / "run" / "train.jsonl").read_text().splitlines()]
    validations = [r for r in records if "validation_score" in r]
    assert validations[0]["step"] == 0 and len(validations) >= 2
    assert all(r["validation_rerender_rmse"] > 0 for r in validations)
    assert all(math.isfinite(r["l_render"]) and r["grad_norm"] > 0 for r in records if "loss" in r)
    best = min(validations, key=lambda r: r["validation_score"])
    document, _ = read_checkpoint(tmp_path / "run" / "best.safetensors")
    assert document["training"]["validation"]["step"] == best["step"]
    state, _ = read_checkpoint(tmp_path / "run" / "checkpoint.safetensors")
    assert state["training_state"]["step"] == trainer.step
    assert state["training_state"]["best_validation_score"] == pytest.approx(best["validation_score"])
    assert not (tmp_path / "run" / "model.safetensors").exists()  # stopped, not finished


def test_validation_of_the_runs_own_generator_can_select_the_best_weights(tmp_path):
    from mideepbasis.train import VALIDATION_SEED, flat_normals, unit_normal_map_rmse

    procedural = {"coarse_relief_tilt_deg": (10.0, 20.0), "coarse_relief_probability": 1.0}
    config = tiny_config(tmp_path, validation_count=2, select_by="run_generator", procedural=procedural)
    trainer = Trainer(config, progress=False)
    trainer.out.mkdir(parents=True)  # run() makes it
    # The second set is drawn by the run's generator: the undulation the held-out set lacks.
    own = torch.cat([batch.maps for batch in trainer.validation_batch("run_generator")])
    expected = generate(VALIDATION_SEED + 1, config=config.procedural).to_tensor()
    torch.testing.assert_close(own[1], expected)
    held_out = torch.cat([batch.maps for batch in trainer.validation_batch("held_out")])
    assert not torch.equal(own[:, :3], held_out[:, :3])
    records = []
    for step in range(3):  # three different networks; the best by the second set's score is kept
        trainer.step = step
        with torch.no_grad():
            for parameter in trainer.model.parameters():
                parameter.add_(0.05 * torch.randn_like(parameter))
        records.append(trainer.validate())
    for record in records:
        part = record["run_generator_validation"]
        assert part["score"] == pytest.approx(sum(part["rmse"].values()) / 4)
        assert part["flat_normal_rmse"] == pytest.approx(unit_normal_map_rmse(flat_normals(own), own)["normal"])
    best = min(records, key=lambda r: r["run_generator_validation"]["score"])
    document, _ = read_checkpoint(tmp_path / "run" / "best.safetensors")
    assert document["training"]["validation"]["step"] == best["step"]
    assert trainer.best_score == best["run_generator_validation"]["score"]


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


def network_with_a_working_normal_unit():
    """A tiny network with a normal unit of width 4 whose residual scales are away from their zero
    start, so that every block computes something (seeded)."""
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    network = DeepBasisNet(preset("tiny", normal_unit_width=4)).eval()
    with torch.no_grad():
        for name, parameter in network.named_parameters():
            if name.endswith(("beta", "gamma")):
                parameter.normal_(0.0, 0.5)
    return network


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


def moved_point(point: torch.Tensor, mirror: bool, turns: int) -> torch.Tensor:
    """A point (3,) of the scene mirrored (x -> -x), then turned about z by quarter turns."""
    angle = math.pi / 2 * turns
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
                             [0.0, 0.0, 1.0]])
    mirrored = point * torch.tensor([-1.0 if mirror else 1.0, 1.0, 1.0])
    return rotation @ mirrored


@pytest.mark.parametrize("mirror,turns", [(False, 1), (True, 0), (True, 3), (False, 2)])
def test_a_moved_material_under_the_moved_flash_photographs_as_the_moved_photo(mirror, turns):
    from mideepbasis.model.inputs import RELIEF_DIRECTION_CHANNEL, relief_inputs
    from mideepbasis.render import render_flash
    from mideepbasis.model.symmetry import dihedral

    maps = generate(3, config=GeneratorConfig(size=32)).to_tensor()[None]
    light = torch.tensor([0.3, -0.5, 2.2])
    moved_light = moved_point(light, mirror, turns)
    photo = render_flash(maps, light.view(1, 1, 3))[:, 0]
    moved_photo = render_flash(dihedral(maps, 0, mirror, turns), moved_light.view(1, 1, 3))[:, 0]
    assert torch.allclose(moved_photo, dihedral(photo, None, mirror, turns), atol=1e-4)
    # So the normal unit's inputs of a moved photo are its inputs moved, flash direction included.
    relief = relief_inputs(photo.clamp(0, 1), light.view(1, 3))
    moved_relief = relief_inputs(moved_photo.clamp(0, 1), moved_light.view(1, 3))
    assert torch.allclose(moved_relief, dihedral(relief, RELIEF_DIRECTION_CHANNEL, mirror, turns), atol=1e-4)


def pool_config(tmp_path, **overrides):
    values = dict(network={"normal_unit_width": 4}, train_only=("normal_unit",), vc_weight=0.0, normal_pool=3,
                  normal_crop=16)
    return tiny_config(tmp_path, **{**values, **overrides})


def test_the_normal_pool_at_a_step_is_the_same_reached_or_rebuilt(tmp_path):
    from mideepbasis.model.inputs import RELIEF_DIRECTION_CHANNEL
    from mideepbasis.model.symmetry import dihedral
    from mideepbasis.train import NormalUnitPool, TrainingMaterials

    config = pool_config(tmp_path)
    materials = TrainingMaterials(config.data, config.size, config.seed)
    advanced = NormalUnitPool(materials, config, 0)
    first = advanced.normals.clone()
    for _ in range(4):
        advanced.advance()
    rebuilt = NormalUnitPool(materials, config, 4)
    assert torch.equal(advanced.relief, rebuilt.relief) and torch.equal(advanced.normals, rebuilt.normals)
    # Four steps of two new materials each replaced every material of the pool of three.
    assert not any(torch.equal(first[i], rebuilt.normals[j]) for i in range(3) for j in range(3))
    (relief,), normals = rebuilt.batch(torch.Generator().manual_seed(0))
    assert relief.shape == (2, 7, 16, 16) and normals.shape == (2, 3, 16, 16)
    # Each crop's relief inputs and normals come from the same material, window and move.
    for crop_relief, crop_normals in zip(relief, normals):
        matches = [(slot, top, left, move) for slot in range(3) for move in range(8)
                   for top in range(17) for left in range(17)
                   if torch.equal(dihedral(rebuilt.relief[slot, :, top:top + 16, left:left + 16],
                                           RELIEF_DIRECTION_CHANNEL, move >= 4, move % 4), crop_relief)]
        assert matches
        slot, top, left, move = matches[0]
        assert torch.equal(dihedral(rebuilt.normals[slot, :, top:top + 16, left:left + 16], 0, move >= 4, move % 4),
                           crop_normals)


def assert_only_the_unit_learns_and_resumes_exactly(make_config, tmp_path, source, unit: str) -> None:
    """A run of ``make_config`` from ``source`` changes only ``unit``, and one stopped and resumed
    ends with the same weights as one run straight through."""
    straight = Trainer(make_config(tmp_path / "a", init=str(source)), progress=False)
    before = {name: value.clone() for name, value in straight.model.state_dict().items()}
    straight.run()
    after = straight.model.state_dict()
    assert {name.split(".")[0] for name in after if not torch.equal(before[name], after[name])} == {unit}
    interrupted = Trainer(make_config(tmp_path / "b", init=str(source)), progress=False)
    interrupted.run(stop_at=2)
    resumed = Trainer(make_config(tmp_path / "b", init=str(source)), resume=True, progress=False)
    resumed.run()
    b = load_model(tmp_path / "b" / "run" / "model.safetensors").state_dict()
    for name, value in load_model(tmp_path / "a" / "run" / "model.safetensors").state_dict().items():
        assert torch.equal(value, b[name]), name


def test_the_normal_unit_alone_learns_from_the_pool_and_resumes_exactly(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny")))
    assert_only_the_unit_learns_and_resumes_exactly(pool_config, tmp_path, source, "normal_unit")
    # On a pool that never changes the unit fits the normals over a flat rest.
    trainer = Trainer(pool_config(tmp_path / "c", init=str(source), normal_pool_refresh=1, steps=80, batch=4),
                      progress=False)
    pool = trainer.pool_batches()
    crops = next(pool)
    losses = [trainer.train_step(crops)["loss"] for _ in range(80)]
    assert sum(losses[-10:]) < 0.7 * sum(losses[:10]), losses
    with pytest.raises(ValueError, match="normal_pool trains the normal units alone"):
        tiny_config(tmp_path, normal_pool=3)
    with pytest.raises(ValueError, match="needs network.normal_booster_width"):
        pool_config(tmp_path, train_only=("normal_booster",))
    with pytest.raises(ValueError, match="normal_crop 24 must be a multiple of 16"):
        pool_config(tmp_path, normal_crop=24)
    with pytest.raises(ValueError, match="normal_pool -1 must be 0"):
        tiny_config(tmp_path, normal_pool=-1)


def test_a_unit_given_the_albedo_shading_starts_as_the_checkpoint_and_learns_from_the_pool(tmp_path):
    from mideepbasis.errors import InputError
    from mideepbasis.model.checkpoint import save_checkpoint

    source_net = network_with_a_working_normal_unit()
    source = save_checkpoint(tmp_path / "source.safetensors", source_net)
    albedo = {"normal_unit_width": 4, "normal_unit_albedo": True}
    trainer = Trainer(pool_config(tmp_path / "a", init=str(source), network=albedo), progress=False)
    model = trainer.model.eval()
    assert model.normal_unit.intro.weight.shape[1] == 8 and not model.normal_unit.intro.weight[:, 7].any()
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    with torch.no_grad():
        torch.testing.assert_close(model(inputs, lights).maps, source_net(inputs, lights).maps, rtol=1e-5, atol=1e-6)
    # The pool's eighth channel is the albedo shading of the frozen network's own diffuse.
    pool = next(trainer.pool_batches())
    assert pool[0][0].shape == (2, 8, 16, 16)
    before = {name: value.clone() for name, value in trainer.model.state_dict().items()}
    trainer.run()
    changed = {name for name, value in trainer.model.state_dict().items() if not torch.equal(before[name], value)}
    assert "normal_unit.intro.weight" in changed and all(name.startswith("normal_unit.") for name in changed)
    # A unit that read the albedo shading does not go back to one that does not.
    widened = save_checkpoint(tmp_path / "widened.safetensors", trainer.model)
    with pytest.raises(InputError, match="reads the albedo shading and this run's does not"):
        Trainer(pool_config(tmp_path / "b", init=str(widened)), progress=False)


def test_a_second_normal_unit_starts_at_zero_and_learns_alone_from_the_pool(tmp_path):
    from mideepbasis.model.checkpoint import load_model, save_checkpoint
    from mideepbasis.model.network import preset

    source_net = network_with_a_working_normal_unit()
    source = save_checkpoint(tmp_path / "source.safetensors", source_net)
    boosted = {"normal_unit_width": 4, "normal_booster_width": 6}
    trainer = Trainer(pool_config(tmp_path / "a", init=str(source), network=boosted, train_only=("normal_booster",),
                                  steps=6), progress=False)
    model = trainer.model.eval()
    inputs = torch.rand(2, 9, 32, 32) * 2 - 1
    lights = torch.tensor([[0.1, 0.0, 2.4], [0.0, -0.2, 2.4]])
    with torch.no_grad():
        start = model(inputs, lights).maps
    torch.testing.assert_close(start, source_net(inputs, lights).maps, rtol=0.0, atol=0.0)  # it adds exactly zero
    before = {name: value.clone() for name, value in trainer.model.state_dict().items()}
    trainer.run()
    changed = {name for name, value in trainer.model.state_dict().items() if not torch.equal(before[name], value)}
    assert "normal_booster.ending.weight" in changed and all(name.startswith("normal_booster.") for name in changed)
    # The two units' slopes add up: the saved network reloads with its second unit and computes it.
    reloaded = load_model(save_checkpoint(tmp_path / "boosted.safetensors", trainer.model.eval()))
    assert reloaded.config.normal_booster_width == 6
    with torch.no_grad():
        relief = torch.rand(1, 7, 32, 32)
        torch.testing.assert_close(reloaded.normal_raw(relief),
                                   reloaded.normal_unit(relief) + reloaded.normal_booster(relief))
        assert not torch.equal(reloaded(inputs, lights).maps, start)
    with pytest.raises(ValueError, match="adds to the first: it needs normal_unit_width"):
        preset("tiny", normal_booster_width=4)


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


def test_the_crop_rmse_loss_is_the_mean_of_the_crops_rmse():
    from mideepbasis.train import normal_unit_loss

    truth = torch.nn.functional.normalize(torch.randn(3, 3, 8, 8) * 0.1 + torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1), dim=1)
    predicted = truth.clone()
    predicted[0] = torch.nn.functional.normalize(truth[0] + 0.3, dim=0)  # one crop wrong, two exact
    per_crop = [float(((predicted[i] - truth[i]) ** 2).mean().sqrt()) for i in range(3)]
    # Within the floor under the root: 1e-4 for an exact crop.
    assert float(normal_unit_loss(predicted, truth, "crop_rmse")) == pytest.approx(sum(per_crop) / 3, abs=1e-4)
    assert per_crop[0] > 0.05
    assert float(normal_unit_loss(predicted, truth, "mse")) == pytest.approx(float(((predicted - truth) ** 2).mean()))
    # An exact crop still gives finite gradients to the others.
    predicted.requires_grad_(True)
    normal_unit_loss(predicted, truth, "crop_rmse").backward()
    assert torch.isfinite(predicted.grad).all() and predicted.grad[0].abs().sum() > 0


def local_pool_config(tmp_path, **overrides):
    values = dict(network={"normal_unit_width": 4}, train_only=("local_unit",), vc_weight=0.0, local_pool=3)
    return tiny_config(tmp_path, **{**values, **overrides})


def test_the_local_pool_holds_what_the_network_gives_its_local_unit(tmp_path):
    """A local-pool material, rebuilt from the stored stage as a step does, is the network's own prediction."""
    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, DeepBasisOutput, preset
    from mideepbasis.train import LocalUnitPool

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))
    trainer = Trainer(local_pool_config(tmp_path, init=str(source)), progress=False)
    pool, model, config = trainer.unit_pool(), trainer.model, trainer.config
    assert isinstance(pool, LocalUnitPool)
    # Material 1 of the run's sources, photographed as the pool does (slot 1, its own generator).
    maps = trainer.materials()[1][None]
    photographed = synthesize(maps, torch.Generator().manual_seed(config.seed * 1_000_003 + 1), config.synthesis)
    with torch.no_grad():
        expected = model(photographed.inputs, photographed.lights, fov=config.synthesis.fov).maps
        deviations = model.local_deviations(pool.local_inputs[1:2], pool.weights[1:2], pool.global_bases[1:2])
    slope = pool.slope[1:2]
    assert slope.abs().max() > 0  # the normal unit's part is there
    shared = torch.cat([slope, torch.zeros(1, 8, *slope.shape[-2:])], 1)
    rebuilt = DeepBasisOutput.from_bases(pool.weights[1:2], pool.global_bases[1:2], deviations + shared[:, None],
                                         keep_bases=False).maps
    torch.testing.assert_close(rebuilt, expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(pool.maps[1], maps[0])


def test_the_local_unit_alone_learns_from_the_pool_and_resumes_exactly(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))
    assert_only_the_unit_learns_and_resumes_exactly(local_pool_config, tmp_path, source, "local_unit")
    # On a pool that never changes the local unit fits its materials.
    trainer = Trainer(local_pool_config(tmp_path / "c", init=str(source), steps=60, batch=3), progress=False)
    batch = next(trainer.pool_batches())
    losses = [trainer.train_step(batch)["loss"] for _ in range(60)]
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10]), losses
    with pytest.raises(ValueError, match="local_pool trains the local unit alone"):
        tiny_config(tmp_path, local_pool=3)
    with pytest.raises(ValueError, match="give one of them"):
        local_pool_config(tmp_path, normal_pool=3)
    with pytest.raises(ValueError, match="reads the albedo shading"):
        local_pool_config(tmp_path, network={"normal_unit_width": 4, "normal_unit_albedo": True})


def test_the_local_unit_keeps_the_maps_it_is_told_to_as_its_init_gives_them(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset
    from mideepbasis import constants

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))

    def trained(name, keep, steps=40):
        trainer = Trainer(local_pool_config(tmp_path / name, init=str(source), steps=steps, batch=3,
                                            local_pool_keep=keep), progress=False)
        batch = next(trainer.pool_batches())
        first = trainer.train_step(batch)["loss"]
        for _ in range(steps - 1):
            trainer.train_step(batch)
        model = trainer.model
        with torch.no_grad():
            deviations = model.local_deviations(batch.local_inputs, batch.weights, batch.global_bases)
            change = torch.cat([batch.slope, torch.zeros(3, 8, *batch.slope.shape[-2:])], 1)[:, None]
            maps = DeepBasisOutput.from_bases(batch.weights, batch.global_bases, deviations + change, keep_bases=False).maps
        return first, maps, batch.maps

    # Every map kept: the init's own maps are the target, so the first loss is nothing.
    first, _, _ = trained("all", tuple(constants.MAP_SLICES), steps=1)
    assert first < 1e-6
    # Roughness and specular kept: they stay near the init's while the diffuse learns the truth.
    _, start, truth = trained("start", (), steps=1)  # one step from the init: (nearly) the init's maps
    _, kept, _ = trained("kept", ("roughness", "specular"))
    _, free, _ = trained("free", ())

    def moved(maps, channels):
        return float((maps[:, channels] - start[:, channels]).abs().mean())

    rough_and_specular = [6, 7, 8, 9]
    assert moved(kept, rough_and_specular) < 0.5 * moved(free, rough_and_specular)
    diffuse_error = [float((m[:, 3:6] - truth[:, 3:6]).abs().mean()) for m in (start, kept)]
    assert diffuse_error[1] < 0.9 * diffuse_error[0], diffuse_error
    # A resumed run keeps what the init gives, not what its checkpoint holds.
    config = local_pool_config(tmp_path / "resumed", init=str(source), steps=4, local_pool_keep=("roughness",))
    Trainer(config, progress=False).run()
    resumed = Trainer(config, resume=True, progress=False)
    assert resumed.step == 4
    reference = load_model(source).state_dict()
    for name, value in resumed.kept_from.state_dict().items():
        torch.testing.assert_close(value, reference[name])
    with pytest.raises(ValueError, match="unknown maps"):
        local_pool_config(tmp_path, init=str(source), local_pool_keep=("gloss",))
    with pytest.raises(ValueError, match="needs local_pool and init"):
        local_pool_config(tmp_path, local_pool_keep=("roughness",))


def test_the_highlight_weights_peak_under_the_flash_and_keep_the_loss_scale():
    from mideepbasis.train import highlight_weights

    size = 33
    maps = torch.zeros(2, 10, size, size)
    maps[:, 2] = 1.0  # flat
    maps[:, 3:6] = 0.3
    maps[:, 6] = 0.2
    maps[0, 7:] = 0.5
    # Flash straight above the centre: a flat sample mirrors it back from the centre pixel only,
    # and less the farther a pixel is from it.
    lights = torch.tensor([[0.0, 0.0, 2.0]]).expand(2, 3)
    weights = highlight_weights(maps, lights, 8.0, fov=45.0, convention="physical")
    assert weights.shape == (2, 1, size, size)
    torch.testing.assert_close(weights.mean(dim=(2, 3)), torch.ones(2, 1))
    glossy = weights[0, 0]
    centre = size // 2
    assert glossy[centre, centre] == glossy.max()  # the brightest 1 % share the full weight
    row = glossy[centre, centre:]
    assert bool((row[1:] <= row[:-1] + 1e-6).all()) and row[-1] < 0.5 * row[0]
    # The brightest 1 % weighs 1 + 8 against 1 for an unlit pixel (before the division by the mean).
    assert float(glossy.max() / glossy.min()) == pytest.approx(9.0, rel=0.05)
    # No specular: nothing to weigh.
    torch.testing.assert_close(weights[1], torch.ones(1, size, size))


def test_the_diffuse_weights_weigh_the_diffuse_error_of_each_pixel():
    from mideepbasis.train import supervised_loss

    truth = torch.full((1, 10, 2, 2), 0.5)
    predicted = truth.clone()
    predicted[0, 3, 0, 0] += 0.1  # one diffuse error
    predicted[0, 6, 1, 1] += 0.1  # one roughness error
    output = DeepBasisOutput(maps=predicted)
    weights = torch.ones(1, 1, 2, 2)
    plain = supervised_loss(output, truth)
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), plain)
    weights[0, 0, 0, 0] = 3.0  # the diffuse error counts three times, the roughness's once
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), 2.0 * plain)
    weights[0, 0, 0, 0], weights[0, 0, 1, 1] = 1.0, 5.0  # the roughness pixel: its diffuse is right
    torch.testing.assert_close(supervised_loss(output, truth, diffuse_weights=weights), plain)


def test_the_local_pool_stores_the_highlight_weights_of_its_materials(tmp_path):
    trainer = Trainer(local_pool_config(tmp_path, highlight_weight=4.0), progress=False)
    pool = trainer.unit_pool()
    batch = pool.batch(torch.Generator().manual_seed(0))
    assert batch.diffuse_weights.shape == (2, 1, 32, 32)
    assert float(pool.diffuse_weights[0].mean()) == pytest.approx(1.0)
    assert trainer.train_step(batch)["loss"] > 0
    assert Trainer(local_pool_config(tmp_path / "off"), progress=False).unit_pool().diffuse_weights is None
    with pytest.raises(ValueError, match="positive with local_pool"):
        tiny_config(tmp_path, highlight_weight=2.0)
    with pytest.raises(ValueError, match="positive with local_pool"):
        local_pool_config(tmp_path, highlight_weight=-1.0)


def test_a_normal_pool_of_two_octaves_holds_the_photo_area_averaged_and_crops_both_alike(tmp_path):
    import torch.nn.functional as F

    from mideepbasis.model.inputs import decode_photo, relief_inputs
    from mideepbasis.train import NormalUnitPool, TrainingMaterials

    config = pool_config(tmp_path, network={"normal_unit_width": 4, "normal_unit_blocks": (1, 1, 1), "normal_unit_octaves": (1.0, 0.5)},
                         normal_crop=32, size=64)
    materials = TrainingMaterials(config.data, config.size, config.seed)
    pool = NormalUnitPool(materials, config, 0)
    assert pool.relief.shape[-1] == 64 and [r.shape[-1] for r in pool.coarse_relief] == [32]
    # The coarse relief is that of the photo averaged over 2 x 2 pixels, made as the full one is.
    from mideepbasis.train import synthesize

    photographed = synthesize(materials[0][None], torch.Generator().manual_seed(config.seed * 1_000_003),
                              config.synthesis, config.network.extra_inputs)
    photo = decode_photo(photographed.inputs)
    expected = relief_inputs(F.avg_pool2d(photo, 2), photographed.lights, config.synthesis.fov,
                             config.network.convention, config.network.plane_extent)[0]
    torch.testing.assert_close(pool.coarse_relief[0][0], expected, atol=1e-6, rtol=0)
    (full, coarse), normals = pool.batch(torch.Generator().manual_seed(1))
    assert full.shape == (2, 7, 32, 32) and coarse.shape == (2, 7, 16, 16) and normals.shape == (2, 3, 32, 32)
    for crop_full, crop_coarse in zip(full, coarse):
        matches = [(slot, top, left) for slot in range(3) for top in range(0, 33, 2) for left in range(0, 33, 2)
                   if any(torch.equal(dihedral_moves, crop_full) for dihedral_moves in moved(pool.relief[slot, :, top:top + 32, left:left + 32]))]
        assert matches
        slot, top, left = matches[0]
        assert any(torch.equal(m, crop_coarse) for m in moved(pool.coarse_relief[0][slot, :, top // 2:top // 2 + 16,
                                                                                     left // 2:left // 2 + 16]))
    trainer = Trainer(dataclasses.replace(config, steps=2), progress=False)
    trainer.run()
    assert (tmp_path / "run" / "model.safetensors").is_file()
    with pytest.raises(ValueError, match="multiples of 32"):
        pool_config(tmp_path, network={"normal_unit_width": 4, "normal_unit_blocks": (1, 1, 1), "normal_unit_octaves": (1.0, 0.5)}, normal_crop=16)


def moved(image):
    """The 8 mirrored and turned copies of a relief crop, its direction channels moved with it."""
    from mideepbasis.model.inputs import RELIEF_DIRECTION_CHANNEL
    from mideepbasis.model.symmetry import dihedral

    return [dihedral(image, RELIEF_DIRECTION_CHANNEL, move >= 4, move % 4) for move in range(8)]


def test_a_supersampled_run_makes_its_materials_larger_and_learns_from_them_downsampled(tmp_path):
    from mideepbasis.train import NormalUnitPool

    config = pool_config(tmp_path, synthesis={"supersample": 2})
    trainer = Trainer(config, progress=False)
    materials = trainer.materials()
    assert materials[0].shape == (10, 64, 64)  # twice the training size of 32
    pool = NormalUnitPool(materials, config, 0)
    assert pool.relief.shape[-1] == pool.normals.shape[-1] == 32
    assert torch.allclose(pool.normals.norm(dim=1), torch.ones(1), atol=1e-5)
    # The pool's normals are the large material's, area-averaged and made unit.
    from mideepbasis.resampling import downsample_maps

    torch.testing.assert_close(pool.normals[0], downsample_maps(materials[0][None], 32)[0, :3], atol=1e-6, rtol=0)
    trainer.run()
    assert (tmp_path / "run" / "model.safetensors").is_file()
    # Its validation photographs the fixed materials at their own size, as every run's does.
    assert trainer.validation_batch()[0].photos.shape[-1] == 32
