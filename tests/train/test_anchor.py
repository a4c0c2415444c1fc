"""The anchor (``TrainConfig.anchor``): on the plain camera's batches the run keeps an anchor
network's answers; on the others it learns from the truth alone."""

from __future__ import annotations

import pytest
import torch

from mideepbasis.data.synth import SynthesisConfig, synthesize
from mideepbasis.errors import InputError
from mideepbasis.model.checkpoint import load_model
from mideepbasis.train import Trainer
from mideepbasis.train.losses import supervised_loss

from .helpers import procedural_maps, tiny_config

#: Phone levers on, the plain camera drawn for every batch or none.
PHONE = {"fov_range": (25.0, 70.0), "white_balance_sigma": 0.08}


@pytest.fixture(scope="module")
def anchor_file(tmp_path_factory):
    """A tiny network trained a few steps away from its initialisation, saved as a checkpoint."""
    out = tmp_path_factory.mktemp("anchor")
    trainer = Trainer(tiny_config(out, steps=3), progress=False)
    trainer.run()
    return out / "run" / "model.safetensors"


def test_synthesis_says_which_batches_the_plain_camera_took():
    maps = procedural_maps()
    for probability, expected in ((1.0, True), (0.0, False)):
        config = SynthesisConfig(plain_probability=probability, **PHONE)
        batch = synthesize(maps, torch.Generator().manual_seed(1), config)
        assert batch.plain is expected
        if expected:  # the plain camera's one field of view
            assert batch.fov == SynthesisConfig().fov
    drawn = [synthesize(maps, torch.Generator().manual_seed(seed), SynthesisConfig(plain_probability=0.5, **PHONE))
             for seed in range(12)]
    assert {batch.plain for batch in drawn} == {True, False}
    for batch in drawn:
        assert (batch.fov == SynthesisConfig().fov) or not batch.plain


@pytest.mark.parametrize("encoded", [False, True])
def test_the_anchor_term_is_the_l1_to_the_anchors_maps_on_plain_batches_only(tmp_path, anchor_file, encoded):
    """The anchor's term is the run's supervised loss against the anchor's maps, the diffuse
    compared sRGB-encoded where the run's is (``diffuse_loss_encoded``)."""
    maps = procedural_maps()
    trainer = Trainer(tiny_config(tmp_path, anchor=str(anchor_file), synthesis={"plain_probability": 0.5, **PHONE},
                                  diffuse_loss_encoded=encoded), progress=False)
    anchor = load_model(anchor_file).eval()
    for seed in range(6):
        batch = synthesize(maps, torch.Generator().manual_seed(seed), trainer.synthesis)
        with torch.no_grad():
            output = trainer.model(batch.inputs, batch.lights, fov=batch.fov)
            term = trainer._anchor_loss(output, batch)
            if batch.plain:
                answer = anchor(batch.inputs, batch.lights, fov=batch.fov)
                expected = supervised_loss(output, answer.maps, trainer.config.normal_weight,
                                           signed_target=answer.signed_maps, diffuse_encoded=encoded)
                assert float(term) == pytest.approx(float(expected), rel=1e-5)
                assert float(term) > 0  # the run's fresh network differs from the trained anchor
            else:
                assert float(term) == 0.0


def test_an_anchor_holds_the_plain_answers_that_training_would_move(tmp_path, anchor_file):
    """From the anchor's own weights, thirty steps move the plain answers; the anchor's term keeps
    them nearer to the anchor's. The rate is low: Adam's first steps move every weight by about
    the rate, and at 1e-2 that moves the tiny network's answers as far with the anchor as without."""
    maps = procedural_maps()
    probe = synthesize(maps, torch.Generator().manual_seed(99), SynthesisConfig())
    anchor = load_model(anchor_file).eval()
    with torch.no_grad():
        reference = anchor(probe.inputs, probe.lights, fov=probe.fov).maps
    drift = {}
    for weight in (None, 20.0):
        extra = {"anchor": str(anchor_file), "anchor_weight": weight} if weight else {}
        trainer = Trainer(tiny_config(tmp_path / str(weight), init=str(anchor_file), lr=3e-4, local_lr=3e-4,
                                      synthesis={"plain_probability": 1.0}, **extra), progress=False)
        for _ in range(30):
            trainer.train_step(maps)
        with torch.no_grad():
            answer = trainer.model.eval()(probe.inputs, probe.lights, fov=probe.fov).maps
        drift[weight] = float((answer - reference).abs().mean())
    assert drift[None] > 0.01, drift
    assert drift[20.0] < 0.5 * drift[None], drift


@pytest.mark.parametrize("overrides, message", [
    ({"synthesis": {"plain_probability": 0.0}}, "plain_probability"),
    ({"anchor_weight": 0.0}, "must be positive"),
])
def test_an_anchor_that_could_not_act_is_refused(tmp_path, overrides, message):
    with pytest.raises(ValueError, match=message):
        tiny_config(tmp_path, anchor="x.safetensors", **overrides)


def test_an_anchor_of_another_network_is_refused_in_one_line(tmp_path, anchor_file):
    with pytest.raises(InputError, match="anchor's network configuration differs"):
        Trainer(tiny_config(tmp_path, anchor=str(anchor_file), network={"normal_unit_width": 4},
                            synthesis={"plain_probability": 1.0}), progress=False)
