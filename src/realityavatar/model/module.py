"""The LightningModule: the avatar (model/avatar.py) trained with its loss terms and density control, evaluated."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytorch_lightning as pl
import torch
from pytorch_lightning.utilities import move_data_to_device
from torch import nn

from realityavatar.data.datamodule import composite
from realityavatar.losses import LossTerm, TrainingRender, total_loss
from realityavatar.model.avatar import PER_POINT, Avatar, Schedule

# Networks whose gradient norm optim.grad_clip bounds (not the Gaussians', nor the sheet's), in this order.
CLIPPED = ("encoder", "temporal", "deformer", "skinning", "color", "shading")
# torch.compile modes of the `compile` setting (AvatarModule.compile_path); "none": eager.
COMPILE_MODES = ("none", "default", "reduce-overhead", "max-autotune")
# Dynamo's settings for it. Density control replaces the Gaussians' parameters with more or fewer rows, so their first
# dimension must be allowed to vary (compile_path marks it dynamic from the first call); the LSTM is traced too
# (experimental in dynamo; without it the networks are 3 graphs around an eager LSTM, with it one: values and gradients
# equal eager to 1e-9 on the CPU). Training traces each graph once (the step-dependent state is in tensors:
# set_progress); evaluation adds versions for its grad mode and inference tensors (TORCH_LOGS=recompiles shows them).
DYNAMO_CONFIG = {"force_parameter_static_shapes": False, "allow_rnn": True}
# The sheet's optimizer groups take the free Gaussians' rates of the same name, its motion basis the decoder's.
SHEET_RATES = {"sheet_normal_offset": "means", "sheet_basis": "deformer", "sheet_coeff": "deformer"}


class AvatarModule(pl.LightningModule):
    """Lightning's training and test loop around an avatar (model/avatar.py: its components and its one forward path,
    held as `self.avatar`): loss terms (losses.py), density control, optimizer groups and LR decay, checkpoint hooks,
    metrics."""

    def __init__(
        self,
        avatar: Avatar,
        density: Any,
        losses: dict[str, nn.Module],
        optimizer: Callable[..., torch.optim.Optimizer],
        lr: dict,
        final_factor: dict,
        schedule: Schedule,
        grad_clip: float | None,
        max_steps: int,
        scene_extent: float,
        lpips: nn.Module | None = None,
        eval_supersample: int = 1,
    ):
        super().__init__()
        self.avatar = avatar
        self.automatic_optimization = False  # density control edits parameters between optimizer steps
        self.density = density
        self.losses = nn.ModuleDict(losses)  # summed in this order (losses.total_loss)
        for name, term in self.losses.items():
            if not isinstance(term, LossTerm):
                raise TypeError(f"loss.{name}: {type(term).__name__} is not a realityavatar.losses.LossTerm")
            term.bind(avatar)  # what the term draws from the avatar, before any step (and outside torch.compile)
        self.optimizer_factory = optimizer
        self.lr = dict(lr)
        self.final_factor = dict(final_factor)
        self.schedule = schedule
        self.grad_clip = grad_clip
        self.max_steps = max(int(max_steps), 1)
        self.scene_extent = float(scene_extent)
        self.lpips = lpips
        self.eval_supersample = int(eval_supersample)  # eval.supersample: test images rendered at k x, averaged
        self.lpips_status = "computed" if lpips is not None else "not computed"  # build_module sets the reason
        self.test_records: list[dict] = []
        self.log_every = 1  # the trainer's log_every_n_steps (set in setup)
        # The sum of the losses since the last log step, on the device: finite iff every one of them was (a NaN or an
        # infinity stays in a sum). One addition per step; read on log steps only.
        self._loss_sum: torch.Tensor | None = None
        self._loss_sum_since = 0  # the first step in that sum
        # Facts needed to rebuild the run from its checkpoint (num_train_frames, scene_extent, ...).
        self.run_info: dict = {"scene_extent": self.scene_extent}
        # Frozen networks from weight files (LPIPS, the perceptual loss's VGG19) stay out of the checkpoint, so a run
        # trained with or without them loads strictly into a module built with or without them.
        self._register_state_dict_hook(_drop_frozen_networks)
        self.register_load_state_dict_post_hook(_ignore_frozen_networks)

    def set_progress(self, step: int | None) -> None:
        """Put the step-dependent state where training step `step` has it (None: a finished run): the decoder's
        coarse-to-fine window (schedule.deform_anneal) and the loss terms' scheduled weights. Called every training
        step, and by `load_run` with the checkpoint's step, so a checkpoint saved mid-anneal renders as it trained.
        Outside the compiled graphs: they read tensors this writes, and are not traced again as the step advances."""
        self.avatar.deformer.set_window(self.schedule.deform_window(step))
        for term in self.losses.values():
            term.set_progress(step)

    # ------------------------------------------------------------------ training
    def setup(self, stage: str) -> None:
        check_single_process(self.trainer)
        self.log_every = max(int(self.trainer.log_every_n_steps), 1)

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """A dataset batch on the module's device -> the batch the model reads: the image over its background and the
        mask made there (data.datamodule.composite); floating-point tensors in the module's dtype (float32 images
        feed a float64 module)."""
        batch = composite(batch, self.dtype)
        return {k: v.to(self.dtype) if torch.is_tensor(v) and v.is_floating_point() else v for k, v in batch.items()}

    def device_batch(self, batch: dict) -> dict:
        """A collated dataset batch as a training or test step reads it (outside a Trainer: the probes, `measure_fps`):
        moved to the module's device, then `on_after_batch_transfer`."""
        return self.on_after_batch_transfer(move_data_to_device(batch, self.device), 0)

    def on_fit_start(self) -> None:
        self.run_info["device"] = str(self.device)  # Lightning's teardown moves the module back to the CPU
        if not bool(self.avatar.shading.built):  # the normal grid of shading=irradiance (a checkpoint restores it)
            t0 = time.perf_counter()
            record = self.avatar.shading.init_from_body(self.avatar.body.canonical_vertices().detach(), self.avatar.body.faces)
            self.run_info["shading_grid"] = {**record, "seconds": time.perf_counter() - t0}
        # The skinning field starts from the body's weights: the MLP is pre-fitted for schedule.skin_pretrain_steps
        # cheap steps on surface samples (learnt from scratch at the paper's small LR it is still far from them after
        # a short CPU run, which blurs every frame); the grid is built from them. Once per run: a resumed run restores
        # run_info["skin_pretrain"] from its checkpoint (on_load_checkpoint runs before this hook, while global_step
        # is still 0) and keeps the checkpoint's skinning weights.
        if "skin_pretrain" in self.run_info:
            return
        t0 = time.perf_counter()
        record = self.avatar.skinning.init_from_body(self.avatar.body.canonical_vertices().detach(), self.avatar.body.faces,
                                              self.avatar.body.skin_weights, steps=self.schedule.skin_pretrain_steps)
        if record is not None:
            self.run_info["skin_pretrain"] = {**record, "seconds": time.perf_counter() - t0}
        record = self.avatar.sheet.canonicalise(self.avatar.body, self.avatar.skinning)  # sheet.profile=rest, once per run
        self.run_info["sheet"] = {**self.avatar.sheet.layout, **({"canonicalise": record} if record else {})}

    def training_loss(self, batch: dict, step: int, check: bool = True
                      ) -> tuple[torch.Tensor, dict, TrainingRender, list[dict]]:
        """Render the batch and sum the loss terms: (total, {term: detached value}, the render, rasterizer metas).
        check: the rasterizer's input checks, which read the device (training runs them on log steps only)."""
        self.set_progress(step)
        rgb, alpha, metas, posed = self.avatar.render_batch(batch, deform=self.schedule.deform_on(step), check_finite=check)
        out = TrainingRender(rgb, alpha, batch, posed, self.avatar)
        total, terms = self.loss(out)
        return total, terms, out, metas

    def loss(self, out: TrainingRender) -> tuple[torch.Tensor, dict]:
        """The run's loss terms summed over a render (losses.total_loss): one graph for torch.compile (numpy and numba
        paths step aside while it traces)."""
        return total_loss(self.losses, out)

    def compile_path(self, mode: str) -> None:
        """torch.compile (`mode`, one of COMPILE_MODES) the networks' path, the avatar's `deform` and `shade`, and the losses,
        `loss`: one graph each (DYNAMO_CONFIG); the rasterizer and the optimizer stay eager. "none" leaves them eager.
        reduce-overhead replays the graphs as CUDA graphs: each training step then marks a new iteration of them."""
        if mode not in COMPILE_MODES:
            raise ValueError(f"compile: expected one of {', '.join(COMPILE_MODES)}, got {mode!r}")
        if mode == "none":
            return
        for key, value in DYNAMO_CONFIG.items():
            setattr(torch._dynamo.config, key, value)
        kw = {} if mode == "default" else {"mode": mode}
        a = self.avatar  # its render_batch calls the compiled deform and shade
        a.deform, a.shade, self.loss = (torch.compile(f, **kw) for f in (a.deform, a.shade, self.loss))
        if self.density.changes_count:
            a.deform, a.shade, self.loss = self._count_dynamic(a.deform, a.shade, self.loss)
        if mode == "reduce-overhead":
            self.mark_step = torch.compiler.cudagraph_mark_step_begin

    def _count_dynamic(self, compiled_deform, compiled_shade, compiled_loss):
        """`deform`, `shade` and `loss` with the Gaussian count marked dynamic in their inputs (the free Gaussians'
        parameters, the posed Gaussians' per-point entries) before each call, so that dynamo traces them for any count
        from the first call. Otherwise the first refinement that changes the count traces all three again (45 s on an
        H100). A graph traced with marked inputs is traced again for unmarked ones: every caller's are marked here."""
        mark = torch._dynamo.maybe_mark_dynamic

        def mark_posed(posed: dict) -> None:
            for k, v in posed.items():
                if k in PER_POINT:
                    mark(v, 1)  # [B,N,...]
            mark(posed["opacities"], 0)  # [N]

        def deform_any_count(inputs: dict, deform: bool = True) -> dict:
            for p in self.avatar.gaussians.parameters():
                mark(p, 0)
            return compiled_deform(inputs, deform=deform)

        def shade_any_count(posed: dict, viewmats: torch.Tensor, frame_idx: torch.Tensor) -> torch.Tensor:
            mark_posed(posed)
            return compiled_shade(posed, viewmats, frame_idx)

        def loss_any_count(out: TrainingRender) -> tuple[torch.Tensor, dict]:
            mark_posed(out.posed)
            return compiled_loss(out)

        return deform_any_count, shade_any_count, loss_any_count

    def mark_step(self) -> None:
        """A new training iteration begins (compile=reduce-overhead: of the CUDA graphs; eager: nothing)."""

    def training_step(self, batch, batch_idx):
        """One step without a read of the device, except every `log_every` steps (logging, the finiteness checks):
        on a GPU each read waits for every kernel queued before it."""
        self.mark_step()
        step = self.global_step
        log_now = (step + 1) % self.log_every == 0  # the steps Lightning writes the logs of
        if log_now:
            self._check_finite(step - 1, "")  # the steps since the last log step, before this one renders
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        total, terms, out, metas = self.training_loss(batch, step, check=log_now)
        # A non-finite loss is remembered on the device and raised on the next log step (ModelCheckpoint saves
        # after this hook: no checkpoint is written between a non-finite step and the error).
        if self._loss_sum is None:  # a copy: with compile=reduce-overhead `total` is a CUDA graph's output, which
            self._loss_sum, self._loss_sum_since = total.detach().clone(), step  # the next step's replay overwrites
        else:
            self._loss_sum = self._loss_sum + total.detach()
        if log_now:  # the logged values, read from the device in one copy (host tensors: see below)
            logged = dict(zip(["loss", *terms], torch.stack([total.detach(), *terms.values()]).cpu()))
            self._check_finite(step, f": {logged}")  # before this step's update
        self.manual_backward(total)
        if self.grad_clip:
            nets = [p for n in CLIPPED for p in self.components()[n].parameters() if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(nets, self.grad_clip)
        opt.step()
        self.lr_schedulers().step()
        rgb, alpha = out.rgb, out.alpha
        H, W = rgb.shape[1:3]
        # What actually rendered (gsplat may have fallen back to torch), reported in metrics.json.
        self.run_info["render"] = {"backend": metas[0]["backend"], "device": str(rgb.device), "dtype": str(rgb.dtype),
                                   "resolution": [W, H]}  # the training images' (evaluate: eval.supersample)
        raw = getattr(opt, "optimizer", opt)  # the torch optimizer under Lightning's wrapper
        stats = self.density.step_post_backward(self.avatar.gaussians, raw, metas, step, (W, H))
        # Logged values are host tensors: Lightning turns progress-bar values into numbers after every step (a read of a
        # GPU tensor waits for the GPU), and a number it is given becomes a tensor on the module's device (a copy that
        # waits too).
        bs = rgb.shape[0]
        if log_now:
            for name, v in logged.items():
                self.log(f"train/{name}", v, prog_bar=name == "loss", batch_size=bs)
            self.log("train/num_gaussians", torch.tensor(float(self.avatar.gaussians.num_points)), prog_bar=True, batch_size=bs)
        # Density control's counts are host ints: a refinement's (cloned / split / pruned / reset) is logged at its step.
        for k, v in stats.items():
            if isinstance(v, (int, float)) and (log_now or k != "num_points"):
                self.log(f"train/density_{k}", torch.tensor(float(v)), batch_size=bs)
        # Per-image error for samplers that draw hard frames more often (data.sampler=hard_frames, SamplerFeedback):
        # colour L1 plus the mask disagreement, both means over the image.
        with torch.no_grad():
            image_loss = (rgb - batch["image"]).abs().mean((1, 2, 3)) + (alpha - batch["mask"]).abs().mean((1, 2, 3))
        return {"loss": total.detach(), "image_loss": image_loss}

    def _check_finite(self, last_step: int, detail: str) -> None:
        """Raise if a loss since the sum was last cleared was non-finite (one read of the device), then clear it."""
        if self._loss_sum is not None and not bool(torch.isfinite(self._loss_sum)):
            raise FloatingPointError(f"training loss became non-finite between steps {self._loss_sum_since} and "
                                     f"{last_step}{detail}")
        self._loss_sum = None

    def components(self) -> dict[str, nn.Module]:
        """The trained components, in optimizer-group order."""
        a = self.avatar
        return {"gaussians": a.gaussians, "encoder": a.encoder, "temporal": a.temporal, "deformer": a.deformer,
                "skinning": a.skinning, "color": a.color, "shading": a.shading, "sheet": a.sheet}

    def param_groups(self) -> list[dict]:
        """Optimizer groups as each component names them (`param_groups()`); a group without its own entry in
        optim.lr takes its component's rate (the sheet's: SHEET_RATES, else the free Gaussians' of the same name)."""
        groups = []
        for name, comp in self.components().items():
            for gname, params in comp.param_groups().items():
                params = [p for p in params if p.requires_grad]
                if not params:  # an ablated component (e.g. SH colour) contributes no group
                    continue
                base = SHEET_RATES.get(gname, gname.removeprefix("sheet_"))
                lr = self.lr.get(gname, self.lr.get(base, self.lr.get(name)))
                if gname in ("means", "sheet_normal_offset"):
                    lr = lr * self.scene_extent
                groups.append({"params": params, "lr": lr, "name": gname})
        return groups

    def configure_optimizers(self):
        opt = self.optimizer_factory(self.param_groups())
        T = self.max_steps

        def decay(name):
            f = self.final_factor.get(name, self.final_factor.get("default", 1.0))
            return lambda s: f ** min(s / T, 1.0)

        sched = torch.optim.lr_scheduler.LambdaLR(opt, [decay(g["name"]) for g in opt.param_groups])
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["density_state"] = self.density.state_dict()
        checkpoint["num_gaussians"] = self.avatar.gaussians.num_points
        checkpoint["realityavatar"] = dict(self.run_info)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if checkpoint.get("density_state"):
            self.density.load_state_dict(checkpoint["density_state"])
        saved = checkpoint.get("realityavatar", {})
        if "skin_pretrain" in saved:  # done in an earlier part of this run (or checkpoint without a pre-fit: none)
            self.run_info["skin_pretrain"] = saved["skin_pretrain"]
        elif checkpoint.get("global_step", 0) > 0:
            self.run_info["skin_pretrain"] = {"steps": 0, "note": "checkpoint predates pre-fit records; not repeated"}

    # ------------------------------------------------------------------ evaluation
    def test_step(self, batch, batch_idx, dataloader_idx: int = 0):
        from realityavatar.metrics import image_metrics

        split = batch["split"][0]
        with torch.no_grad():
            rgb, alpha, _, _ = self.avatar.render_batch(batch, supersample=self.eval_supersample)
        rgb = rgb.clamp(0, 1)
        garment = batch.get("garment")  # synthetic scenes: the pixels that show the garment
        for b in range(rgb.shape[0]):
            pred, gt = rgb[b], batch["image"][b]
            rec = image_metrics(pred, gt, alpha[b], batch["mask"][b], None if garment is None else garment[b],
                                self.lpips)
            for k, v in rec.items():
                self.log(f"test/{split}/{k}", v, add_dataloader_idx=False, batch_size=1)
            rec = {"split": split, "frame": int(batch["frame"][b]), "view": int(batch["view"][b]), **rec}
            self.test_records.append({**rec, "_pred": pred.cpu(), "_gt": gt.cpu()})

    @torch.no_grad()
    def measure_fps(self, batch: dict, warmup: int = 3, repeats: int = 20) -> float:
        """Frames per second of the full path (encoder .. rasterize) for one camera, synchronised on CUDA."""
        one = {k: (v[:1] if torch.is_tensor(v) else v[:1] if isinstance(v, list) else v) for k, v in batch.items()}
        one = self.device_batch(one)
        _, _, metas, _ = self.avatar.render_batch(one)
        self.run_info["fps"] = {"backend": metas[0]["backend"], "device": str(self.device)}
        for _ in range(warmup):
            self.avatar.render_batch(one)
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(repeats):
            self.avatar.render_batch(one)
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        return repeats / (time.perf_counter() - t0)


FROZEN_NETWORKS = ("lpips.", "losses.perceptual.vgg.")  # state-dict prefixes of networks loaded from weight files


def _drop_frozen_networks(module: nn.Module, state_dict: dict, prefix: str, local_metadata: dict) -> None:
    for key in [k for k in state_dict if k[len(prefix):].startswith(FROZEN_NETWORKS)]:
        del state_dict[key]


def _ignore_frozen_networks(module: nn.Module, incompatible) -> None:
    for keys in (incompatible.missing_keys, incompatible.unexpected_keys):
        keys[:] = [k for k in keys if not k.startswith(FROZEN_NETWORKS)]


def check_single_process(trainer: Any) -> None:
    """One avatar trains in one process: density control adds Parameters after each refinement (DDP would not see
    them), the deformer is unused before deform_start, and per-rank densification would diverge."""
    if trainer is not None and trainer.world_size > 1:
        raise ValueError(
            f"trainer: {trainer.world_size} processes (devices={trainer.num_devices}, num_nodes={trainer.num_nodes}) "
            "for one run; RealityAvatar trains one avatar per process. Scale with one run per GPU through a hydra "
            "launcher (hydra/launcher=joblib, hydra/launcher=slurm_gpu) and keep trainer.devices=1"
        )
