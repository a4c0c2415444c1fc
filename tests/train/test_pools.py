"""Training data: the materials' augmentation and moves, and the photographed pools of a unit
trained alone (the normal unit's crops, the local unit's stages), each learning alone and resuming
exactly."""

from __future__ import annotations

import dataclasses
import functools
import math

import pytest
import torch

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.model.checkpoint import load_model
from mideepbasis.model.network import DeepBasisOutput
from mideepbasis.train import Trainer, augment

from .helpers import assert_the_runs_end_alike, local_pool_config, pool_config, tiny_config


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
    from mideepbasis.model.symmetry import dihedral
    from mideepbasis.render import render_flash

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
    assert_the_runs_end_alike(tmp_path)


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
    with pytest.raises(ValueError, match="normal_pool trains the normal unit alone"):
        tiny_config(tmp_path, normal_pool=3)
    with pytest.raises(ValueError, match="normal_pool trains the normal unit alone"):
        pool_config(tmp_path, train_only=("normal_unit", "local_unit"))
    with pytest.raises(ValueError, match="normal_crop 24 must be a multiple of 16"):
        pool_config(tmp_path, normal_crop=24)
    with pytest.raises(ValueError, match="normal_pool -1 must be 0"):
        tiny_config(tmp_path, normal_pool=-1)


def rebuilt_from_pool(model, pool, slot: int) -> torch.Tensor:
    """(1, 10, H, W) the maps of pool material ``slot`` rebuilt from its stored stage as a step of
    the local unit does: its deviations plus the stored normal-unit slope, blended."""
    with torch.no_grad():
        deviations = model.local_deviations(pool.local_inputs[slot:slot + 1], pool.weights[slot:slot + 1],
                                            pool.global_bases[slot:slot + 1])
    slope = pool.slope[slot:slot + 1]
    shared = torch.cat([slope, torch.zeros(1, 8, *slope.shape[-2:])], 1)
    return DeepBasisOutput.from_bases(pool.weights[slot:slot + 1], pool.global_bases[slot:slot + 1],
                                      deviations + shared[:, None], keep_bases=False).maps


def test_the_local_pool_holds_what_the_network_gives_its_local_unit(tmp_path):
    """A local-pool material, rebuilt from the stored stage as a step does, is the network's own prediction."""
    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset
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
    assert pool.slope[1].abs().max() > 0  # the normal unit's part is there
    torch.testing.assert_close(rebuilt_from_pool(model, pool, 1), expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(pool.maps[1], maps[0])


def test_the_local_pool_takes_each_material_at_its_own_field_of_view(tmp_path):
    """With ``fov_range`` each pool material is photographed at a field of view of its own, and its
    stage and highlight weights are the network's and the lobe's at that field of view."""
    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset
    from mideepbasis.train.losses import highlight_weights

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))
    config = local_pool_config(tmp_path, init=str(source), highlight_weight=4.0,
                               synthesis={"fov_range": (20.0, 75.0)})
    trainer = Trainer(config, progress=False)
    pool, model, config = trainer.unit_pool(), trainer.model, trainer.config
    fovs = []
    for slot in range(3):
        maps = trainer.materials()[slot][None]
        photographed = synthesize(maps, torch.Generator().manual_seed(config.seed * 1_000_003 + slot), config.synthesis)
        fovs.append(photographed.fov)
        with torch.no_grad():
            expected = model(photographed.inputs, photographed.lights, fov=photographed.fov).maps
            at_45 = model(photographed.inputs, photographed.lights, fov=45.0).maps
        rebuilt = rebuilt_from_pool(model, pool, slot)
        torch.testing.assert_close(rebuilt, expected, atol=1e-5, rtol=0)
        assert (rebuilt - at_45).abs().max() > 1e-4  # the field of view matters to the stage
        torch.testing.assert_close(pool.diffuse_weights[slot:slot + 1],
                                   highlight_weights(maps, photographed.lights, 4.0, photographed.fov,
                                                     config.network.convention, config.network.plane_extent))
    assert len(set(fovs)) == 3 and all(20.0 <= fov <= 75.0 for fov in fovs)
    with pytest.raises(ValueError, match="normal pool photographs at one field of view"):
        pool_config(tmp_path, synthesis={"fov_range": (20.0, 75.0)})


def test_the_local_unit_alone_learns_from_the_pool_and_resumes_exactly(tmp_path):
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))
    assert_only_the_unit_learns_and_resumes_exactly(local_pool_config, tmp_path, source, "local_unit")
    # With the global lobe shifted too (each material's own draw, the same after a resumption).
    jittered = functools.partial(local_pool_config, global_roughness_jitter=0.2, global_specular_jitter=1.0)
    assert_only_the_unit_learns_and_resumes_exactly(jittered, tmp_path / "jittered", source, "local_unit")
    # On a pool that never changes the local unit fits its materials.
    trainer = Trainer(local_pool_config(tmp_path / "c", init=str(source), steps=60, batch=3), progress=False)
    batch = next(trainer.pool_batches())
    losses = [trainer.train_step(batch)["loss"] for _ in range(60)]
    assert sum(losses[-10:]) < 0.8 * sum(losses[:10]), losses
    with pytest.raises(ValueError, match="local_pool trains the local unit alone"):
        tiny_config(tmp_path, local_pool=3)
    with pytest.raises(ValueError, match="give one of them"):
        local_pool_config(tmp_path, normal_pool=3)


def test_the_local_unit_keeps_the_maps_it_is_told_to_as_its_init_gives_them(tmp_path):
    from mideepbasis import constants
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

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


def test_the_local_pool_shows_the_local_unit_a_shifted_global_lobe_and_keeps_the_unshifted_targets(tmp_path):
    """With ``global_roughness_jitter`` and ``global_specular_jitter`` a pool material's global bases
    have their roughness shifted and their specular scaled by its own draw, within the bounds; its
    error map is the render of the shifted global blend minus the photo (the torch reference
    renderer, rebuilt here); the kept maps are still the init's answer to the unshifted photo."""
    from mideepbasis import geometry
    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.inputs import decode_photo
    from mideepbasis.model.network import DeepBasisNet, compose_bases, preset, to_maps
    from mideepbasis.render.reference import render_flash as render_flash_reference

    torch.manual_seed(0)
    source = save_checkpoint(tmp_path / "source.safetensors", DeepBasisNet(preset("tiny", normal_unit_width=4)))
    jitter = dict(global_roughness_jitter=0.3, global_specular_jitter=1.0)
    config = local_pool_config(tmp_path, init=str(source), local_pool_keep=("roughness", "specular"), **jitter)
    trainer = Trainer(config, progress=False)
    pool, model, config = trainer.unit_pool(), trainer.model, trainer.config
    channels = config.network.input_channels
    shifts, stages = [], []
    for slot in range(3):
        maps = trainer.materials()[slot][None]
        photographed = synthesize(maps, torch.Generator().manual_seed(config.seed * 1_000_003 + slot), config.synthesis)
        with torch.no_grad():
            stage = model.basis_stage(photographed.inputs, photographed.lights, config.synthesis.fov)
            unshifted = model(photographed.inputs, photographed.lights, fov=config.synthesis.fov).maps
        stages.append(stage)
        predicted, stored = to_maps(stage.global_bases, dim=2), to_maps(pool.global_bases[slot:slot + 1], dim=2)
        roughness_shift = stored[0, :, 6] - predicted[0, :, 6]
        inside = (predicted[0, :, 6] > 0.35) & (predicted[0, :, 6] < 0.65)  # bases the shift cannot clip
        assert inside.any()
        assert roughness_shift[inside].std() < 1e-5 and roughness_shift[inside].abs().max() <= 0.3 + 1e-5
        shifts.append(float(roughness_shift[inside].mean()))
        ratio = stored[0, :, 7:] / predicted[0, :, 7:]
        unclipped = (predicted[0, :, 7:] > 0.05) & (stored[0, :, 7:] < 0.95)
        assert ratio[unclipped].std() < 1e-4 and 0.5 - 1e-5 <= float(ratio[unclipped].mean()) <= 2.0 + 1e-5
        # The error map of the shifted bases, rendered by the reference renderer.
        blended = to_maps(compose_bases(stage.weights, pool.global_bases[slot:slot + 1])[1], upper_hemisphere=False)
        fov, convention = config.synthesis.fov, config.network.convention
        rendered = render_flash_reference(blended, photographed.lights.view(1, 1, 3),
                                          geometry.flash_intensity(fov, convention), convention)[:, 0]
        expected_error = rendered.clamp(0, 1) - decode_photo(photographed.inputs)
        torch.testing.assert_close(pool.local_inputs[slot:slot + 1, channels:channels + 3], expected_error,
                                   atol=2e-4, rtol=0)
        assert (pool.local_inputs[slot, channels:channels + 3] - stage.error[0]).abs().max() > 1e-3
        torch.testing.assert_close(to_maps(pool.kept_signed[slot:slot + 1])[:, 6:], unshifted[:, 6:], atol=1e-5, rtol=0)
    assert len(set(round(shift, 4) for shift in shifts)) == 3  # a draw of each material's own
    # Off, the pool holds the bases and the error map as predicted; without the pool the jitter is refused.
    plain = Trainer(local_pool_config(tmp_path / "plain", init=str(source), local_pool_keep=("roughness",)),
                    progress=False).unit_pool()
    torch.testing.assert_close(plain.global_bases[2:3], stages[2].global_bases, atol=1e-6, rtol=0)
    torch.testing.assert_close(plain.local_inputs[2:3, channels:channels + 3], stages[2].error, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="they need local_pool"):
        tiny_config(tmp_path, global_roughness_jitter=0.1)
    with pytest.raises(ValueError, match="must be 0"):
        local_pool_config(tmp_path, global_specular_jitter=-1.0)


def test_the_local_pool_stores_the_highlight_weights_of_its_materials(tmp_path):
    trainer = Trainer(local_pool_config(tmp_path, highlight_weight=4.0), progress=False)
    pool = trainer.unit_pool()
    batch = pool.batch(torch.Generator().manual_seed(0))
    assert batch.diffuse_weights.shape == (2, 1, 32, 32)
    assert float(pool.diffuse_weights[0].mean()) == pytest.approx(1.0)
    assert trainer.train_step(batch)["loss"] > 0
    assert Trainer(local_pool_config(tmp_path / "off"), progress=False).unit_pool().diffuse_weights is None
    with pytest.raises(ValueError, match="positive without normal_pool"):
        pool_config(tmp_path, highlight_weight=2.0)
    with pytest.raises(ValueError, match="positive without normal_pool"):
        local_pool_config(tmp_path, highlight_weight=-1.0)


@pytest.mark.parametrize("vc_weight", [0.0, 0.05])
def test_the_whole_network_step_weighs_the_diffuse_under_the_highlight(tmp_path, vc_weight):
    """The whole network's supervised loss with ``highlight_weight`` is the L1 with the diffuse
    pixels weighted by the true lobe under the step's own photo flashes."""
    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.network import to_signed
    from mideepbasis.train.losses import channel_weights, highlight_weights

    trainer = Trainer(tiny_config(tmp_path, highlight_weight=6.0, vc_weight=vc_weight,
                                  synthesis={"fov_range": (20.0, 75.0)}), progress=False)
    maps = torch.stack([trainer.materials()[slot] for slot in range(2)])
    state = trainer.generator.get_state()
    photographed = synthesize(maps, trainer.generator, trainer.synthesis, trainer._extra_inputs())
    trainer.generator.set_state(state)
    with torch.no_grad():
        predicted = trainer.model(photographed.inputs, photographed.lights, fov=photographed.fov).signed_maps
    weights = highlight_weights(maps, photographed.lights, 6.0, photographed.fov, trainer.config.network.convention,
                                trainer.config.network.plane_extent)
    difference = (predicted - to_signed(maps)).abs()
    difference[:, 3:6] *= weights
    expected = (difference * channel_weights(trainer.config.normal_weight)).mean()
    assert float(weights.amax()) > 1.5  # the highlight does weigh more
    assert trainer.train_step(maps)["l_sup"] == pytest.approx(float(expected), rel=1e-4)


def test_a_normal_pool_of_two_octaves_holds_the_photo_area_averaged_and_crops_both_alike(tmp_path):
    import torch.nn.functional as F

    from mideepbasis.data.synth import synthesize
    from mideepbasis.model.inputs import decode_photo, relief_inputs
    from mideepbasis.train import NormalUnitPool, TrainingMaterials

    config = pool_config(tmp_path, network={"normal_unit_width": 4, "normal_unit_blocks": (1, 1, 1), "normal_unit_octaves": (1.0, 0.5)},
                         normal_crop=32, size=64)
    materials = TrainingMaterials(config.data, config.size, config.seed)
    pool = NormalUnitPool(materials, config, 0)
    assert pool.relief.shape[-1] == 64 and [r.shape[-1] for r in pool.coarse_relief] == [32]
    # The coarse relief is that of the photo averaged over 2 x 2 pixels, made as the full one is.
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
