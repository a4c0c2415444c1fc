"""The training loop: the loss falls, exact resume after an interrupt, a diverged run keeps its
checkpoint, two processes under torchrun, the torch render backend, validation and the best weights."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mideepbasis.data.procedural import generate
from mideepbasis.model.checkpoint import load_model, read_checkpoint
from mideepbasis.train import Trainer

from .helpers import procedural_maps, tiny_config


def test_loss_falls_on_a_fixed_batch(tmp_path):
    trainer = Trainer(tiny_config(tmp_path, steps=60), progress=False)
    maps = procedural_maps()
    losses = [trainer.train_step(maps)["loss"] for _ in range(60)]
    assert sum(losses[-10:]) / 10 < 0.8 * sum(losses[:10]) / 10, losses


def test_penalty_revives_a_saturated_weight_decoder(tmp_path):
    # Blow the decoder's last layer up until its outputs reach tens (tanh flat, the blend's gradient
    # gone), as a run's did; with the penalty they come back, without it they do not.
    maps = procedural_maps()
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
    from mideepbasis.evaluation.metrics import flat_normals, unit_normal_map_rmse
    from mideepbasis.train import VALIDATION_SEED

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


def test_keep_validated_keeps_the_weights_of_every_validated_step(tmp_path):
    from mideepbasis.model.checkpoint import load_model

    config = tiny_config(tmp_path, steps=4, validate_every=2, validation_count=2, keep_validated=True)
    trainer = Trainer(config, progress=False)
    trainer.run()
    out = tmp_path / "run"
    assert sorted(path.name for path in out.glob("step_*.safetensors")) == [
        "step_0000000.safetensors", "step_0000002.safetensors", "step_0000004.safetensors"]
    for step in (0, 2, 4):
        document, _ = read_checkpoint(out / f"step_{step:07d}.safetensors")
        assert document["training"]["validation"]["step"] == step
    final, first = load_model(out / "model.safetensors").state_dict(), load_model(out / "step_0000000.safetensors")
    last = load_model(out / "step_0000004.safetensors").state_dict()
    assert all(torch.equal(last[name], value) for name, value in final.items())
    assert any(not torch.equal(first.state_dict()[name], value) for name, value in final.items())
    Trainer(tiny_config(tmp_path / "plain", steps=2, validate_every=2, validation_count=2), progress=False).run()
    assert not list((tmp_path / "plain").glob("**/step_*.safetensors"))
    with pytest.raises(ValueError, match="needs validate_every"):
        tiny_config(tmp_path, keep_validated=True, validate_every=0)
