"""The training loop (``Trainer``, ``train``): one run, resumable, on one process or several under
torchrun; its checkpoints (the optimiser's state as named tensors), its log and its validations."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader

from .. import constants
from ..configs import differences
from ..data.synth import PHONE_LEVERS, SynthesisConfig, TrainingBatch, Variation, synthesize
from ..errors import InputError, MideepbasisError
from ..model.checkpoint import CheckpointError, non_finite_tensors, previous_path, read_checkpoint, save_checkpoint
from ..model.network import DeepBasisNet, DeepBasisOutput, add_slope, local_unit_inputs, to_maps, to_signed
from .config import LOCAL_UNIT_FIELDS, NORMAL_UNIT_FIELDS, RESUMABLE_CHANGES, WEIGHTLESS_FIELDS, TrainConfig
from .data import (LocalUnitBatch, LocalUnitPool, NormalUnitPool, PhotographedPool, StepBatchSampler, TrainingMaterials,
                   shifted_lobes)
from .losses import (global_blend_loss, highlight_weights, learning_rate_factor, lobe_loss, normal_unit_loss,
                     normals_over_flat, rendering_loss, sample_render_geometry, saturation_penalty, specular_colour_loss,
                     supervised_loss, variation_consistency_loss)


class TrainingDiverged(MideepbasisError):
    """The loss became NaN or infinite; the last checkpoint on disk is kept."""


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
        from ..render import set_render_backend

        set_render_backend(config.render_backend)
        self.model = DeepBasisNet(network_config).to(self.device)
        for name, parameter in self.model.named_parameters():
            if config.train_only and name.split(".")[0] not in config.train_only:
                parameter.requires_grad_(False)
        trained = [(n, p) for n, p in self.model.named_parameters() if p.requires_grad]
        if not trained:
            raise InputError(f"this network has none of the parts {list(config.train_only)} to train")
        # The per-pixel units learn faster (the paper trains its local unit faster too).
        per_pixel = ("local_unit.", "normal_unit.")
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
        self.kept_from = self._frozen(config.init) if config.local_pool_keep else None
        self.anchor = None
        if config.anchor:
            self.anchor = self._frozen(config.anchor)
            if self.anchor.config != self.model.config:
                raise InputError(f"{config.anchor}: the anchor's network configuration differs from this run's")
        if resume:
            self._resume()
        if self.world_size > 1:
            self.model = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None)

    # --- checkpoints ---------------------------------------------------------------------------

    def _frozen(self, path: str) -> DeepBasisNet:
        """The network of checkpoint ``path`` on this run's device, in eval mode, without gradients."""
        from ..model.checkpoint import load_model

        return load_model(path).to(self.device).eval().requires_grad_(False)

    def _extra_inputs(self) -> tuple[str, ...]:
        return getattr(self.model, "module", self.model).config.extra_inputs

    def _initialise_from(self, path: str) -> None:
        """Start from a checkpoint's weights. It may differ from this run's network in the optional
        inputs (their weights start at zero: ``widen_inputs``) and in the sizes of the local and the
        normal units (a unit whose size differs, or that the checkpoint lacks, starts afresh;
        everything else is loaded), except that a normal unit of the same width and levels with more
        blocks keeps the checkpoint's blocks, the added ones starting as the identity. How the
        network runs (``WEIGHTLESS_FIELDS``: the normal unit's octaves and slope scaling, the local
        unit's error map) may differ too: it needs no weights."""
        from dataclasses import replace

        from ..model.checkpoint import load_model

        source = load_model(path)
        config = self.model.config
        local_fields = {name: getattr(config, name) for name in LOCAL_UNIT_FIELDS}
        free = {name: getattr(config, name) for name in ("extra_inputs",) + NORMAL_UNIT_FIELDS + WEIGHTLESS_FIELDS}
        if replace(source.config, **free, **local_fields) != config:
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
        if fresh:  # those units start afresh
            state = {name: value for name, value in state.items() if not name.startswith(tuple(fresh))}
            state.update({name: value for name, value in target.items() if name.startswith(tuple(fresh))})
        # A deepened normal unit keeps its blocks; the added ones start as they are built (the identity).
        state.update({name: value for name, value in target.items() if name not in state})
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
        diffuse_weights = None
        if config.highlight_weight:
            diffuse_weights = highlight_weights(target, batch.lights.to(self.device), config.highlight_weight, batch.fov,
                                                config.network.convention, config.network.plane_extent)
        if use_vc:
            original, varied = output.split(maps.shape[0])
            variation = Variation(batch.variation.rotation.to(self.device), batch.variation.shift.to(self.device))
            sup = supervised_loss(original, target, config.normal_weight, diffuse_weights=diffuse_weights,
                                  diffuse_encoded=config.diffuse_loss_encoded)
            vc = variation_consistency_loss(original, varied, variation, batch.varied_maps.to(self.device),
                                            config.normal_weight)
        else:
            sup = supervised_loss(output, target, config.normal_weight, diffuse_weights=diffuse_weights,
                                  diffuse_encoded=config.diffuse_loss_encoded)
            vc = torch.zeros((), device=self.device)
        saturation = saturation_penalty(output.extras["decoder_raw"].float())
        taken = original if use_vc else output  # the answer to the photos as taken
        predicted = taken.maps
        anchored = self._anchor_loss(taken, batch)
        # The optional terms (``WHOLE_STEP_WEIGHTS``), each computed and logged only when weighed.
        terms = {}
        if config.lobe_weight:
            terms["l_lobe"] = config.lobe_weight, lobe_loss(predicted, target, batch.lights.to(self.device), batch.fov,
                                                            config.network.convention, config.network.plane_extent)
        if config.global_weight:
            terms["l_global"] = config.global_weight, global_blend_loss(taken, target)
        if config.colour_weight:
            terms["l_colour"] = config.colour_weight, specular_colour_loss(predicted, target)
        loss, losses = self._with_rendering_loss(sup + config.vc_weight * vc + config.saturation_weight * saturation
                                                 + config.anchor_weight * anchored
                                                 + sum(weight * value for weight, value in terms.values()),
                                                 predicted, target)
        norm = self._optimise(loss)
        anchor_log = {"l_anchor": anchored.item()} if self.anchor is not None else {}
        return {"loss": loss.item(), "l_sup": sup.item(), "l_vc": vc.item(), "l_saturation": saturation.item(),
                **anchor_log, **{key: value.item() for key, (_, value) in terms.items()}, **losses,
                "grad_norm": norm.item()}

    def _anchor_loss(self, output: DeepBasisOutput, batch: TrainingBatch) -> torch.Tensor:
        """The supervised L1 between ``output`` (of ``batch.inputs``) and the anchor's maps of the
        same photos, the diffuse compared as the run's supervised loss compares it
        (``diffuse_loss_encoded``), on a plain batch (``TrainConfig.anchor``); zero on the others
        and without an anchor."""
        if self.anchor is None or not batch.plain:
            return torch.zeros((), device=self.device)
        with torch.no_grad(), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.bf16):
            answer = self.anchor(batch.inputs.to(self.device), batch.lights.to(self.device), fov=batch.fov)
        return supervised_loss(output, answer.maps.float(), self.config.normal_weight,
                               signed_target=answer.signed_maps.float(),
                               diffuse_encoded=self.config.diffuse_loss_encoded)

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
        loss = normal_unit_loss(normals_over_flat(slope.float()), truth)
        norm = self._optimise(loss)  # the frozen rest has no gradient
        return {"loss": loss.item(), "l_sup": loss.item(), "l_vc": 0.0, "l_saturation": 0.0, "grad_norm": norm.item()}

    def _local_unit_step(self, batch: LocalUnitBatch) -> dict:
        """One step of the local unit alone (``TrainConfig.local_pool``) on a batch of the pool."""
        config, model = self.config, getattr(self.model, "module", self.model)
        weights, global_bases, maps = (t.to(self.device) for t in (batch.weights, batch.global_bases, batch.maps))
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=config.bf16):
            deviations = model.local_deviations(batch.local_inputs.to(self.device), weights, global_bases)
        output = self._local_blend(weights, global_bases, deviations.float(), batch.slope.to(self.device))
        signed_target = None
        if batch.kept_signed is not None:
            # The blend itself (signed space) for the map loss, its maps for the rendering loss.
            kept_signed = batch.kept_signed.to(self.device)
            kept_maps = to_maps(kept_signed)
            maps, signed_target = maps.clone(), to_signed(maps)
            for name in config.local_pool_keep:
                channels = constants.MAP_SLICES[name]
                maps[:, channels], signed_target[:, channels] = kept_maps[:, channels], kept_signed[:, channels]
        diffuse_weights = None if batch.diffuse_weights is None else batch.diffuse_weights.to(self.device)
        sup = supervised_loss(output, maps, config.normal_weight, signed_target, diffuse_weights,
                              config.diffuse_loss_encoded)
        loss, losses = self._with_rendering_loss(sup, output.maps, maps)
        norm = self._optimise(loss)  # the frozen rest has no gradient
        return {"loss": loss.item(), "l_sup": sup.item(), "l_vc": 0.0, "l_saturation": 0.0, **losses,
                "grad_norm": norm.item()}

    def _local_blend(self, weights: torch.Tensor, global_bases: torch.Tensor, deviations: torch.Tensor,
                     slope: torch.Tensor) -> DeepBasisOutput:
        """The local unit's deviations (B, N, 10, H, W) blended with the frozen weights (B, N, H, W)
        and global bases (B, N, 10) (signed space), the normal unit's slope (B, 2, H, W) added."""
        scaled = getattr(self.model, "module", self.model).config.normal_slope_scaled
        return DeepBasisOutput.from_bases(weights, global_bases, add_slope(global_bases, deviations, slope, scaled),
                                          keep_bases=False)

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
        if self.config.local_pool:
            @torch.no_grad()
            def stage_of(inputs: torch.Tensor, lights: torch.Tensor, fov: float, roughness_shift: torch.Tensor,
                         specular_octaves: torch.Tensor):
                inputs, lights = inputs.to(self.device), lights.to(self.device)
                stage = model.basis_stage(inputs, lights, fov)
                slope = torch.zeros_like(stage.error[:, :2])
                if hasattr(model, "normal_unit"):
                    slope = model.normal_slope(stage, lights, fov)
                kept_signed = None
                if self.kept_from is not None:  # the init's answer to the bases as predicted
                    blend = self._local_blend(stage.weights, stage.global_bases, self.kept_from.local_deviations(
                        stage.local_inputs, stage.weights, stage.global_bases), slope)
                    kept_signed = blend.signed_maps.float().cpu()
                local_inputs, global_bases = stage.local_inputs, stage.global_bases
                if bool(roughness_shift.any() or specular_octaves.any()):
                    global_bases = shifted_lobes(global_bases, roughness_shift.to(self.device),
                                                 specular_octaves.to(self.device))
                    error = model.error_map(stage.weights, global_bases, stage.photo, lights, fov)
                    local_inputs = local_unit_inputs(inputs, error, stage.weights)
                return (local_inputs.float().cpu(), stage.weights.float().cpu(), global_bases.float().cpu(),
                        slope.float().cpu(), kept_signed)

            return LocalUnitPool(self.materials(), self.config, self.step, stage_of)
        return NormalUnitPool(self.materials(), self.config, self.step)

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
        from ..reporting import plot_training_log

        plot_training_log(self.out / "train.jsonl", self.out / "loss.png")

    def validation_batch(self, of: str = "held_out"):
        """The validation materials and their photos (fixed seeds; made once): ``held_out`` or
        ``run_generator`` (``TrainConfig.select_by``)."""
        if of not in self._validation_batches:
            from ..data.procedural import GeneratorConfig, generate

            # held_out: the generator with relief by a factor, not scaled to a drawn tilt, the same
            # for every run, so that the validations of every run compare.
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
        from ..evaluation.metrics import flat_normals, mean_tilt_deg, unit_normal_map_rmse
        from ..reporting import validation_sheet

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
        if self.config.keep_validated:
            save_checkpoint(self.out / f"step_{self.step:07d}.safetensors", model, metadata={"training": {
                **self.training_record(), "validation": record}})
        validation_sheet(batches[0].photos[:4], predicted[:4], maps[:4],
                         self.out / "validation" / f"step_{self.step:07d}.png")
        self.plot_losses()
        return record

    def _validation_rerender_rmse(self, predicted: torch.Tensor, maps: torch.Tensor, count: int = 8) -> float:
        """Mean RMSE of clipped sRGB re-renderings under ``count`` seeded lights and views (the
        evaluation's metric, on the validation materials)."""
        from ..evaluation import random_lights_and_views, rerender_rmse
        from ..render import render_backend

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

def train(config: TrainConfig, resume: bool = False, progress: bool = True) -> Path:
    """Run (or resume) a training run; returns the final model file."""
    Trainer(config, resume=resume, progress=progress).run()
    return Path(config.out) / "model.safetensors"
