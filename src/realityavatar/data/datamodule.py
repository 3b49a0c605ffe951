"""The LightningDataModule over the scene readers (I3D-Human/synthetic layout, ZJU-MoCap) and its sample Dataset.

Samples follow docs/CONTRACTS.md ("Samples"): pixels, inside, background (`composite` makes image and mask of them),
mask_dist, K, viewmat, width, height, poses [T,24,3], transl [T,3], pose_features [T,D], bone_transforms [24,4,4],
frame, frame_idx, view, split.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset

from realityavatar.data.poses import PoseTable
from realityavatar.data.records import (
    SPLITS,
    ImageRecord,
    SceneData,
    SceneFormatError,
    image_size,
    load_garment,
    load_record,
    mask_distance,
)
from realityavatar.geometry import camera_centres
from realityavatar.model.avatar import pose_inputs

log = logging.getLogger(__name__)
READERS = ("i3d", "zju")


class AvatarDataset(Dataset):
    """Image records of one split -> sample dicts. Images decode lazily; `cache_images` keeps decoded uint8 copies
    (and the masks' distance fields). Every sample carries the model's pose inputs (model/avatar.py pose_inputs:
    the encoder's features of its pose window and the body's bone transforms), made here on the host by `body`, once
    per frame (the poses are fixed: every camera of a frame and every epoch reuse them). With `garment_labels` (the
    held-out splits) and records that have them (synthetic scenes), a sample carries `garment` bool [H,W,1]: the
    pixels that show the garment, which evaluation scores on their own; training samples never carry it."""

    def __init__(
        self,
        records: Sequence[ImageRecord],
        poses: PoseTable,
        split: str,
        body: torch.nn.Module,
        train_frame_index: dict[int, int],
        window_len: int,
        window_step: int,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        image_scale: float = 1.0,
        undistort: bool = True,
        cache_images: bool = False,
        garment_labels: bool = False,
    ) -> None:
        self.records = list(records)
        self.garment_labels = garment_labels and bool(self.records) and all(r.garment_path for r in self.records)
        self.poses = poses
        self.split = split
        self.body = body
        self.train_frame_index = train_frame_index
        self.window_len, self.window_step = int(window_len), int(window_step)
        self.background = torch.as_tensor(background, dtype=torch.float32).reshape(3)
        self.image_scale = float(image_scale)
        self.undistort = undistort
        self.cache_images = cache_images
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._dist_cache: dict[int, torch.Tensor] = {}
        self._garment_cache: dict[int, np.ndarray] = {}
        self._pose_cache: dict[int, tuple] = {}  # frame -> (poses, transl, pose_inputs): ~7 kB each (T=6)

    def __len__(self) -> int:
        return len(self.records)

    def _decoded(self, i: int):
        hit = self._cache.get(i)
        if hit is None:
            hit = load_record(self.records[i], self.image_scale, self.undistort)
            if self.cache_images:
                self._cache[i] = hit
        return hit

    def _distance(self, i: int, mask_b: np.ndarray) -> torch.Tensor:
        """The distance field of record i's mask (kept with the cached images: computed once per image)."""
        hit = self._dist_cache.get(i)
        if hit is None:
            hit = mask_distance(mask_b)
            if self.cache_images:
                self._dist_cache[i] = hit
        return hit

    def __getitem__(self, i: int) -> dict:
        rec = self.records[i]
        img_u8, mask_b, K = self._decoded(i)
        mask_dist = self._distance(i, mask_b)
        hit = self._pose_cache.get(rec.frame)
        if hit is None:
            poses, transl = self.poses.window(rec.frame, self.window_len, self.window_step)  # [T,24,3], [T,3]
            hit = self._pose_cache[rec.frame] = (poses, transl, pose_inputs(self.body, poses[None], transl[None]))
        poses, transl, inputs = hit
        out = {
            # the image as stored and its mask; `composite` makes the float image and mask after the batch reaches
            # the device (a quarter of the bytes to collate and copy, and the host does no per-pixel arithmetic)
            "pixels": torch.from_numpy(img_u8),  # uint8 [H,W,3]
            "inside": torch.from_numpy(mask_b)[..., None],  # bool [H,W,1]
            "background": self.background,
            "mask_dist": mask_dist,  # [H,W] pixels to the mask (losses.SilhouetteChamfer), on the host
            "K": torch.as_tensor(K, dtype=torch.float32),
            "viewmat": torch.as_tensor(rec.viewmat, dtype=torch.float32),
            "width": int(img_u8.shape[1]),
            "height": int(img_u8.shape[0]),
            "poses": poses,
            "transl": transl,
            **{k: v[0] for k, v in inputs.items()},  # pose_features [T,D], bone_transforms [24,4,4]
            "index": int(i),
            "frame": int(rec.frame),
            "frame_idx": int(self.train_frame_index.get(rec.frame, -1)),
            "view": int(rec.view),
            "split": self.split,
        }
        if self.garment_labels:
            label = self._garment_cache.get(i)
            if label is None:
                label = load_garment(rec, self.image_scale, self.undistort)
                if self.cache_images:
                    self._garment_cache[i] = label
            if label.shape != mask_b.shape:
                raise SceneFormatError(f"garment label {rec.garment_path} is {label.shape[1]}x{label.shape[0]} but "
                                       f"image {rec.image_path} is {mask_b.shape[1]}x{mask_b.shape[0]}")
            out["garment"] = torch.from_numpy(label)[..., None]  # bool [H,W,1]
        return out


def composite(batch: dict, dtype: torch.dtype = torch.float32) -> dict:
    """A collated batch of samples as the model reads it: `pixels`, `inside` and `background` become `image`
    [B,H,W,3] (the pixels in [0,1] inside the mask, the background colour outside) and `mask` [B,H,W,1], of `dtype`.
    Made where the batch is, after its transfer (AvatarModule.on_after_batch_transfer): on a GPU, 4 operations there
    instead of ~7 ms of host work per 512 px sample. The select equals image * mask + bg * (1 - mask) for a binary
    mask; the image is made in float32 whatever `dtype` is."""
    out = dict(batch)
    pixels, inside, bg = out.pop("pixels"), out.pop("inside"), out.pop("background")
    out["image"] = torch.where(inside, pixels.float() / 255.0, bg[:, None, None, :]).to(dtype)
    out["mask"] = inside.to(dtype)
    return out


def draw_seed(seed: int, epoch: int, draw: int) -> int:
    """The generator seed of draw `draw` of `epoch` (below 2**63 for any run seed)."""
    return ((seed * 1_000_003 + epoch) * 1_000_033 + draw) % (2**63 - 1)


class EpochShuffle(torch.utils.data.Sampler):
    """Random order that depends only on (seed, epoch), with a position: a resumed run continues the epoch it
    stopped in with the samples it had not seen yet, in the order the uninterrupted run would have used."""

    def __init__(self, frames: Sequence[int], seed: int) -> None:
        self.n, self.seed = len(frames), int(seed)
        self.epoch, self.consumed = 0, 0  # consumed: samples of `epoch` already handed out

    def set_epoch(self, epoch: int) -> None:  # Lightning calls this at every epoch start
        if int(epoch) != self.epoch:
            self.epoch, self.consumed = int(epoch), 0

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        if self.consumed >= self.n:  # the previous pass finished without set_epoch: next epoch
            self.epoch, self.consumed = self.epoch + 1, 0
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        order = torch.randperm(self.n, generator=g).tolist()
        while self.consumed < self.n:
            i = order[self.consumed]
            self.consumed += 1
            yield i

    def observe(self, indices: torch.Tensor, losses: torch.Tensor) -> None:
        """The uniform order ignores the training losses (HardFrameSampler draws by them)."""

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "consumed": self.consumed, "n": self.n, "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        if state.get("n") != self.n or state.get("seed") != self.seed:
            log.warning("training data changed since the checkpoint (%s samples, seed %s, now %s, %s): the resumed "
                        "epoch starts over", state.get("n"), state.get("seed"), self.n, self.seed)
            return
        self.epoch, self.consumed = int(state["epoch"]), int(state["consumed"])


class HardFrameSampler(EpochShuffle):
    """Frames drawn in proportion to their recent training loss, mixed with uniform draws (`data.sampler=hard_frames`).

    The first pass over the training images is the uniform EpochShuffle order, so every frame is seen and scored.
    From then on each draw is, with probability `mix`, a uniform image; otherwise a frame chosen with probability
    proportional to score_f ** power, then one of that frame's images (camera) uniformly. score_f is an exponential
    moving average (weight `ema` on the newest value) of the per-image training losses that `observe` receives for
    the frame's images (SamplerFeedback, conf/callbacks/default.yaml, passes them after every step), so one camera's
    loss updates the whole frame. Frames the garment flares in (the spin) and the swing after an abrupt stop have the
    highest photometric error: uniform sampling spends most steps on the easy rest frames.
    Resumable like EpochShuffle: scores, epoch and position are in the checkpoint, and draw k of epoch e comes from a
    generator seeded by (seed, e, k), so a resumed run draws what the uninterrupted run would have.
    """

    def __init__(self, frames: Sequence[int], seed: int, mix: float = 0.3, power: float = 2.0, ema: float = 0.3) -> None:
        super().__init__(frames, seed)
        if not 0.0 <= float(mix) <= 1.0:
            raise ValueError(f"data.sampler.mix must be in [0, 1], got {mix!r}")
        if not 0.0 < float(ema) <= 1.0:
            raise ValueError(f"data.sampler.ema must be in (0, 1], got {ema!r}")
        if float(power) < 0.0:
            raise ValueError(f"data.sampler.power must be >= 0, got {power!r}")
        self.mix, self.power, self.ema = float(mix), float(power), float(ema)
        ids = sorted({int(f) for f in frames})
        col = {f: j for j, f in enumerate(ids)}
        self.frame_of = torch.tensor([col[int(f)] for f in frames], dtype=torch.long)  # image -> frame column
        self.images_of = [torch.nonzero(self.frame_of == j).flatten() for j in range(len(ids))]
        self.score = torch.full((len(ids),), float("nan"), dtype=torch.float64)  # NaN: not observed yet
        self.observed = 0

    def observe(self, indices: torch.Tensor, losses: torch.Tensor) -> None:
        """Per-image training losses of the images `indices` (dataset positions) just trained on."""
        for i, v in zip(torch.as_tensor(indices).flatten().tolist(), torch.as_tensor(losses).flatten().tolist()):
            if not np.isfinite(v):
                continue
            j = int(self.frame_of[int(i)])
            old = float(self.score[j])
            self.score[j] = v if np.isnan(old) else (1.0 - self.ema) * old + self.ema * v
            self.observed += 1

    def frame_probabilities(self) -> torch.Tensor:
        """Probability of each frame column on a loss-driven draw (before mixing with the uniform draw)."""
        s = self.score.clone()
        seen = ~torch.isnan(s)
        if not bool(seen.any()):
            return torch.full_like(s, 1.0 / len(s))
        s[~seen] = s[seen].max()  # a frame nobody has scored counts as the hardest seen so far
        w = s.clamp_min(1e-12) ** self.power
        return w / w.sum()

    def __iter__(self):
        if self.epoch == 0 or self.observed == 0:
            if self.epoch >= 1 and self.consumed == 0:
                log.warning("data.sampler=hard_frames received no training losses (is callbacks.sampler_feedback "
                            "disabled?): it samples uniformly")
            yield from super().__iter__()
            return
        if self.consumed >= self.n:
            self.epoch, self.consumed = self.epoch + 1, 0
        while self.consumed < self.n:
            g = torch.Generator().manual_seed(draw_seed(self.seed, self.epoch, self.consumed))
            self.consumed += 1
            if float(torch.rand((), generator=g)) < self.mix:
                yield int(torch.randint(self.n, (), generator=g))
            else:
                j = int(torch.multinomial(self.frame_probabilities().float(), 1, generator=g))
                imgs = self.images_of[j]
                yield int(imgs[int(torch.randint(len(imgs), (), generator=g))])

    def state_dict(self) -> dict:
        return {**super().state_dict(), "score": self.score.tolist(), "observed": self.observed}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        if state.get("n") == self.n and len(state.get("score", [])) == len(self.score):
            self.score = torch.tensor(state["score"], dtype=torch.float64)
            self.observed = int(state.get("observed", 0))


class SameFrameViews(torch.utils.data.Sampler):
    """`data.views_per_step` V > 1: each image the training order (`base`) draws is followed by V-1 other training
    images of the same frame (other cameras, drawn at random), so one batch holds V views of one pose and
    Avatar.render_batch runs the networks once for them. Epochs, resume and the hard-frames feedback are the base
    order's; draw k of epoch e picks its cameras with a generator seeded by (seed, e, k)."""

    def __init__(self, base: EpochShuffle, frames: Sequence[int], views: int, seed: int) -> None:
        self.base, self.views, self.seed = base, int(views), int(seed)
        self.frame_of = [int(f) for f in frames]
        self.images_of: dict[int, list[int]] = {}
        for i, f in enumerate(self.frame_of):
            self.images_of.setdefault(f, []).append(i)
        short = sorted((len(v), f) for f, v in self.images_of.items() if len(v) < self.views)
        if short:
            n, f = short[0]
            raise ValueError(f"data.views_per_step={self.views}: frame {f} has {n} training image(s) (cameras); "
                             f"{len(short)} frame(s) have fewer than {self.views}")

    def __len__(self) -> int:
        return len(self.base) * self.views

    def __iter__(self):
        for i in self.base:
            others = [j for j in self.images_of[self.frame_of[i]] if j != i]
            g = torch.Generator().manual_seed(draw_seed(self.seed, self.base.epoch, self.base.consumed))
            yield i
            for k in torch.randperm(len(others), generator=g)[: self.views - 1].tolist():
                yield others[k]

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def observe(self, indices: torch.Tensor, losses: torch.Tensor) -> None:
        self.base.observe(indices, losses)

    def state_dict(self) -> dict:
        return self.base.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.base.load_state_dict(state)


class SamplerFeedback(pl.Callback):
    """Passes each training step's per-image losses to the training sampler (`observe`). Losses on a GPU are kept
    there and passed every `log_every_n_steps` steps (with the logging): each read of the device waits for it."""

    def __init__(self) -> None:
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        sampler = getattr(trainer.datamodule, "train_sampler", None) if trainer.datamodule is not None else None
        if sampler is None:
            return
        if not isinstance(outputs, dict) or "image_loss" not in outputs or "index" not in batch:
            return
        loss = outputs["image_loss"].detach()
        self._pending.append((batch["index"].detach(), loss))
        if loss.device.type == "cpu" or trainer.global_step % max(int(trainer.log_every_n_steps), 1) == 0:
            index, value = (torch.cat(t).cpu() for t in zip(*self._pending))  # in step order: one copy each
            sampler.observe(index, value)
            self._pending.clear()


class ResumableLoader(DataLoader):
    """A DataLoader whose position Lightning saves in the checkpoint and restores on resume (its sampler's state)."""

    def state_dict(self) -> dict:
        return self.sampler.state_dict()

    def load_state_dict(self, state: dict) -> None:
        if state:
            self.sampler.load_state_dict(state)


class DeviceSamples(Dataset):
    """A training set kept where the model trains (`data.device_cache` on a GPU): every sample's tensors are moved
    there once; the loader serves each sample's host entries (its ints and split name) and `gather` puts a batch's
    tensors together on the device. A GPU step then waits for no image collation, pinning or copy: 2.6 + 0.6 ms of a
    29.9 ms paper_scale step on the H100 machine (docs/research/2026-11-27-h100-15000-steps.md)."""

    def __init__(self, ds: Dataset, device: torch.device) -> None:
        self.host: list[dict] = []
        self.tensors: list[dict[str, torch.Tensor]] = []
        for i in range(len(ds)):
            sample = ds[i]
            self.host.append({k: v for k, v in sample.items() if not torch.is_tensor(v)})
            self.tensors.append({k: v.to(device) for k, v in sample.items() if torch.is_tensor(v)})

    def __len__(self) -> int:
        return len(self.host)

    def __getitem__(self, i: int) -> dict:
        return dict(self.host[i])

    def gather(self, index: list[int]) -> dict[str, torch.Tensor]:
        """The tensors of samples `index` (dataset positions), stacked as the loader's collation stacks them."""
        rows = [self.tensors[i] for i in index]
        if len(rows) == 1:  # views: no kernel
            return {k: v[None] for k, v in rows[0].items()}
        return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}


class AvatarDataModule(pl.LightningDataModule):
    """Train / val (a few novel-view images) / test ([novel_view, novel_pose]) loaders over one sequence.

    reader "i3d": <root>/<sequence>-train|-novelview|-novelpose (I3D-Human, synthetic scenes, converted captures);
    train_views / test_views filter the cameras of the -train and of the -novelview/-novelpose folders.
    fps: the capture's frame rate, the time base of the pose window (window_step frames) and of animations.
    reader "zju": <root>/<sequence> in the ARAH layout; splits come from train_views/test_views and the frame ranges
    zju_train_frames / zju_novel_view_frames / zju_novel_pose_frames ([start, end, step], end 0 = to the last frame).
    body: the BodyModel in use; its rest pelvis converts Rh/Th placement to the SMPL convention (`pelvis` overrides;
    with neither, canonical_joints.pkl's pelvis is used). build_preset/build_sequence/build_seed: prepare_data() calls
    realityavatar.data.synthetic.build_scene(build_preset, root, build_seed, sequence=build_sequence), which reuses an
    identical existing build; `sequence` must be the scene name it produces (<garment>_<motion>_<preset>).
    build_overrides: scene parameters over the preset's (as `realityavatar-make-scene --set KEY=VALUE`), e.g.
    {ambient: 1.0, diffuse: 0.0} for the scene without its directional light; give such a build its own `root`.
    """

    def __init__(
        self,
        root: str,
        sequence: str,
        reader: str = "i3d",
        train_views: Sequence[int] | None = None,
        test_views: Sequence[int] | None = None,
        window_len: int = 6,
        window_step: int = 1,
        fps: float | None = None,
        batch_size: int = 1,
        views_per_step: int = 1,
        num_workers: int = 0,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        image_scale: float = 1.0,
        max_train_frames: int | None = None,
        train_frame_subsample: int = 1,
        frame_subsample: int = 1,
        val_items: int = 4,
        undistort: bool = True,
        cache_images: bool = True,
        device_cache: bool = True,
        body=None,
        pelvis: Sequence[float] | None = None,
        build_preset: str | None = None,
        build_sequence: str | None = None,
        build_seed: int = 0,
        build_overrides: dict | None = None,
        zju_train_frames: Sequence[int] = (0, 0, 1),
        zju_novel_view_frames: Sequence[int] | None = None,
        zju_novel_pose_frames: Sequence[int] | None = None,
        check_images: bool = True,
        shuffle_seed: int | None = None,
        sampler: Callable[..., EpochShuffle] = EpochShuffle,
    ) -> None:
        super().__init__()
        if reader not in READERS:
            raise ValueError(f"data.reader: unknown reader {reader!r}; expected one of {READERS}")
        if window_len < 1 or window_step < 0:
            raise ValueError(f"data.window_len must be >= 1 and data.window_step >= 0, got {window_len}, {window_step}")
        if frame_subsample < 1 or train_frame_subsample < 1:
            raise ValueError("data.frame_subsample and data.train_frame_subsample must be >= 1")
        if not (isinstance(image_scale, (int, float)) and 0 < float(image_scale) < float("inf")):
            raise ValueError(f"data.image_scale must be a number > 0 (1.0 = full resolution), got {image_scale!r}")
        if max_train_frames is not None and int(max_train_frames) < 1:
            raise ValueError(f"data.max_train_frames must be null or >= 1, got {max_train_frames!r}")
        self.root, self.sequence, self.reader = str(root), str(sequence), reader
        self.train_views = None if train_views is None else [int(v) for v in train_views]
        self.test_views = None if test_views is None else [int(v) for v in test_views]
        self.window_len, self.window_step = int(window_len), int(window_step)
        if fps is not None and not float(fps) > 0:
            raise ValueError(f"data.fps: expected the capture's frame rate > 0 (frames per second), got {fps!r}")
        self.fps = None if fps is None else float(fps)  # None: a config from before data.fps (data/motion.py)
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        if int(views_per_step) < 1:
            raise ValueError(f"data.views_per_step: expected >= 1 training cameras of one frame per step, got {views_per_step!r}")
        self.views_per_step = int(views_per_step)
        self.background = [float(c) for c in background]
        if len(self.background) != 3 or not all(0.0 <= c <= 1.0 for c in self.background):
            raise ValueError(f"data.background: expected 3 values in [0,1], got {list(background)}")
        self.image_scale = float(image_scale)
        self.max_train_frames = max_train_frames
        self.train_frame_subsample, self.frame_subsample = int(train_frame_subsample), int(frame_subsample)
        self.val_items = int(val_items)
        if not isinstance(device_cache, bool):
            raise TypeError(f"data.device_cache: expected true or false, got {device_cache!r}")
        self.undistort, self.cache_images, self.device_cache = undistort, cache_images, device_cache
        self.device_samples: DeviceSamples | None = None  # the training set on the device (device_cache)
        self.training_set: str | dict = "host"  # where it is kept, for metrics.json (`_on_device`)
        self.body = body
        self.pelvis = pelvis
        self.build_preset, self.build_sequence, self.build_seed = build_preset, build_sequence, int(build_seed)
        self.build_overrides = dict(build_overrides or {})
        self.zju_frames = {
            "train": list(zju_train_frames),
            "novel_view": None if zju_novel_view_frames is None else list(zju_novel_view_frames),
            "novel_pose": None if zju_novel_pose_frames is None else list(zju_novel_pose_frames),
        }
        self.check_images = bool(check_images)
        # the training order: a sampler class (or hydra partial, conf/sampler) called with (frames, seed) at set-up
        self.sampler = sampler
        if not callable(sampler):
            raise TypeError(f"data.sampler: expected a sampler (conf/sampler, _target_ + _partial_: true), got {sampler!r}")
        self.train_sampler: EpochShuffle | None = None
        self.shuffle_seed = shuffle_seed  # None: torch.initial_seed() at set-up (the run's seed_everything seed)
        self.scene: SceneData | None = None
        self.datasets: dict[str, AvatarDataset] = {}
        self.test_split_names: list[str] = []

    # ------------------------------------------------------------------ set-up

    def _pelvis(self) -> torch.Tensor | None:
        if self.pelvis is not None:
            return torch.as_tensor([float(x) for x in self.pelvis], dtype=torch.float64).reshape(3)
        if self.body is not None:
            return self.body.rest_joints[0].detach().to("cpu", torch.float64)
        return None

    def _scene_missing(self) -> bool:
        from realityavatar.data.i3d import split_folder

        return self.reader == "i3d" and not split_folder(Path(self.root), self.sequence, "train").is_dir()

    def prepare_data(self) -> None:
        """With `build_preset` set, (re)build the synthetic scene unless an identical build exists (one process)."""
        if not self.build_preset:
            return
        from realityavatar.data.synthetic import build_scene

        log.info("scene preset %r, sequence %r under %s (seed %d)", self.build_preset, self.build_sequence, self.root,
                 self.build_seed)
        prefix = build_scene(self.build_preset, self.root, self.build_seed, sequence=self.build_sequence,
                             overrides=self.build_overrides)
        if Path(prefix).name != self.sequence or self._scene_missing():
            raise FileNotFoundError(
                f"build_scene({self.build_preset!r}, sequence={self.build_sequence!r}) wrote {prefix}, not "
                f"{self.root}/{self.sequence}-train; set data.sequence to {Path(prefix).name!r}"
            )

    def read_scene(self) -> SceneData:
        if self.reader == "i3d":
            from realityavatar.data.i3d import read_i3d

            hint = ("I3D-Human: download it (Dyco's layout, docs/data.md) and set I3D_ROOT or data.root; an embedded "
                    "scene: build it with `realityavatar-make-scene` or set data.build_preset (ci|demo|full); "
                    "otherwise check data.root and data.sequence")
            return read_i3d(self.root, self.sequence, self._pelvis(), build_hint=hint)
        from realityavatar.data.zju import read_zju

        return read_zju(
            Path(self.root) / self.sequence, self.train_views, self.test_views, self.zju_frames["train"],
            self.zju_frames["novel_view"], self.zju_frames["novel_pose"],
        )

    def _select(self, scene: SceneData) -> dict[str, list[ImageRecord]]:
        for key, splits in (("train_views", ["train"]), ("test_views", [s for s in scene.splits if s != "train"])):
            wanted, have = getattr(self, key), sorted({r.view for s in splits for r in scene.splits[s]})
            missing = sorted(set(wanted or []) - set(have))
            if missing and self.reader == "i3d":  # (the ZJU reader names its own)
                raise ValueError(f"data.{key}: camera(s) {missing} not in {scene.source}'s {', '.join(splits)} "
                                 f"images (cameras {have})")
        out = {}
        for split, records in scene.splits.items():
            views = self.train_views if split == "train" else self.test_views
            if views is not None and self.reader == "i3d":
                records = [r for r in records if r.view in views]
            frames = np.unique([r.frame for r in records])
            if split == "train":
                frames = frames[:: self.train_frame_subsample]
                if self.max_train_frames is not None:
                    frames = frames[: int(self.max_train_frames)]
            else:
                frames = frames[:: self.frame_subsample]
            keep = set(frames.tolist())
            out[split] = [r for r in records if r.frame in keep]
        if not out.get("train"):
            raise ValueError(
                f"{scene.source}: no training images left after selecting views {self.train_views} "
                f"(available {scene.views('train')})"
            )
        return out

    def setup(self, stage: str | None = None) -> None:
        if self.scene is not None:
            return
        if self.build_preset and self._scene_missing():
            self.prepare_data()
        scene = self.read_scene()
        selected = self._select(scene)
        self.scene = scene
        self.records = selected
        self.train_frame_ids = sorted({r.frame for r in selected["train"]})
        self.num_train_frames = len(self.train_frame_ids)
        frame_index = {f: i for i, f in enumerate(self.train_frame_ids)}
        first = selected["train"][0]
        w0, h0 = image_size(first.image_path)
        self.width, self.height = max(1, round(w0 * self.image_scale)), max(1, round(h0 * self.image_scale))
        self.image_size = (self.height, self.width)
        self.scene_extent = self._extent(selected["train"], scene.poses)
        kw = {"train_frame_index": frame_index, "window_len": self.window_len, "window_step": self.window_step,
              "background": self.background, "image_scale": self.image_scale, "undistort": self.undistort,
              "cache_images": self.cache_images}
        if self.body is None:
            raise ValueError(f"{scene.source}: AvatarDataModule needs the body model (body=...) to serve samples: "
                             "each carries the pose window's bone transforms")
        body = self.body.host_copy()  # the samples' pose inputs are made on the host, in the workers
        self.datasets = {s: AvatarDataset(recs, scene.poses, s, body, garment_labels=s != "train", **kw)
                         for s, recs in selected.items() if recs}
        self.test_split_names = [s for s in ("novel_view", "novel_pose") if s in self.datasets]
        if self.shuffle_seed is None:
            self.shuffle_seed = int(torch.initial_seed()) % (2**31)
        if self.check_images:
            self._check_images()
        if not self.test_split_names:
            log.warning("%s: no novel_view or novel_pose images; testing is skipped", scene.source)
        log.info(
            "%s: %s; %d training frames, image %dx%d, extent %.3f", scene.source,
            ", ".join(f"{s} {len(d)} images" for s, d in self.datasets.items()), self.num_train_frames,
            self.width, self.height, self.scene_extent,
        )

    def _check_images(self) -> None:
        """Decode every image and mask of the selected splits before training (kept in memory with cache_images),
        so a corrupt, missing or wrongly sized file stops the run before step 0; all problems are listed together."""
        import time
        from concurrent.futures import ThreadPoolExecutor
        from functools import partial

        def decode(ds: AvatarDataset, i: int):
            """Record i decoded (and with cache_images, its mask's distance field made), or the error."""
            try:
                img, mask, _ = ds._decoded(i)
                if ds.cache_images:
                    ds._distance(i, mask)
                return img
            except (OSError, ValueError) as e:
                return e

        t0 = time.perf_counter()
        problems: list[str] = []
        sizes: dict[int, tuple[tuple[int, int], Path]] = {}  # camera -> decoded (H, W) and the first file
        n = 0
        # decoding (PIL) and the distance fields (scipy) release the GIL: as many threads as torch's
        with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
            decoded = {split: list(pool.map(partial(decode, ds), range(len(ds.records))))
                       for split, ds in self.datasets.items()}
        for split, ds in self.datasets.items():
            for rec, img in zip(ds.records, decoded[split]):
                if isinstance(img, Exception):
                    problems.append(f"{split}: {img}")
                    continue
                n += 1
                hw = tuple(img.shape[:2])
                first = sizes.setdefault(rec.view, (hw, rec.image_path))
                if first[0] != hw:
                    problems.append(f"{split}: image {rec.image_path} is {hw[1]}x{hw[0]} (at data.image_scale "
                                    f"{self.image_scale}) but camera {rec.view}'s images are {first[0][1]}x"
                                    f"{first[0][0]} ({first[1]})")
        seconds = time.perf_counter() - t0
        if problems:
            source = self.scene.source
            self.scene, self.datasets, self.test_split_names = None, {}, []  # a later setup() reads again
            more = f" (and {len(problems) - 20} more)" if len(problems) > 20 else ""
            raise SceneFormatError(f"{source}: {len(problems)} bad image/mask file(s) in the selected "
                                   f"splits{more}:\n  " + "\n  ".join(problems[:20]))
        log.info("checked %d images and masks of %s in %.1f s (decodable, sizes match)%s", n,
                 ", ".join(self.datasets), seconds, "; kept in memory" if self.cache_images else "")
        self.image_check_seconds = seconds

    @staticmethod
    def _extent(train: list[ImageRecord], poses: PoseTable) -> float:
        """1.1 x the largest distance of a training camera centre from the mean body position (LR/threshold scale)."""
        E = np.stack([r.viewmat for r in {r.view: r for r in train}.values()])  # [C,4,4]
        centres = camera_centres(torch.from_numpy(E)).numpy()  # [C,3]
        body = poses.transl.double().mean(0).numpy()
        return float(1.1 * np.linalg.norm(centres - body, axis=-1).max())

    # ------------------------------------------------------------------ loaders

    def _loader(self, ds: Dataset, shuffle: bool) -> DataLoader:
        # Own generator: creating a loader's iterator draws a base seed, which must not move the global RNG (a
        # resumed run restores that RNG and must see the same stream as the uninterrupted run).
        gen = torch.Generator().manual_seed(int(self.shuffle_seed or 0))
        if shuffle:
            frames = [r.frame for r in ds.records]
            sampler = self.sampler(frames, self.shuffle_seed or 0)
            if self.views_per_step > 1:
                sampler = SameFrameViews(sampler, frames, self.views_per_step, self.shuffle_seed or 0)
            self.train_sampler = sampler
            self.device_samples = self._on_device(ds)
            workers = 0 if self.device_samples is not None else self.num_workers  # no work left for a worker
            return ResumableLoader(ds if self.device_samples is None else self.device_samples,
                                   batch_size=self.batch_size * self.views_per_step, sampler=sampler,
                                   num_workers=workers, persistent_workers=workers > 0, drop_last=False, generator=gen,
                                   pin_memory=self._pinned())
        return DataLoader(ds, batch_size=self.batch_size, shuffle=False, num_workers=self.num_workers,
                          persistent_workers=self.num_workers > 0, drop_last=False, generator=gen,
                          pin_memory=self._pinned())

    def _store_device(self) -> torch.device | None:
        """Where the training set may be kept (device_cache): the trainer's GPU; None on a CPU, where it already is."""
        if not self.device_cache or self.trainer is None:
            return None
        device = self.trainer.strategy.root_device
        return device if device.type == "cuda" else None

    def _on_device(self, ds: AvatarDataset) -> DeviceSamples | None:
        """The training set moved to the trainer's GPU (DeviceSamples) when device_cache is on and it takes at most half
        of the GPU's free memory; None otherwise (batches are then collated on the host and copied)."""
        import time

        device = self._store_device()
        if device is None or len(ds) == 0:
            return None
        need = len(ds) * sum(v.numel() * v.element_size() for v in ds[0].values() if torch.is_tensor(v))
        free = torch.cuda.mem_get_info(device)[0] if device.type == "cuda" else need * 2
        if need > free // 2:
            self.training_set = (f"host: its {len(ds)} samples would take {need / 2**30:.1f} GiB of the GPU's "
                                 f"{free / 2**30:.1f} GiB free")
            log.info("data.device_cache: the training set stays on the %s; batches are copied", self.training_set)
            return None
        t0 = time.perf_counter()
        samples = DeviceSamples(ds, device)
        self.training_set = {"device": str(device), "samples": len(ds), "gb": round(need / 2**30, 3),
                             "seconds": round(time.perf_counter() - t0, 2)}
        log.info("data.device_cache: the training set kept on the device: %s", self.training_set)
        return samples

    def transfer_batch_to_device(self, batch: dict, device: torch.device, dataloader_idx: int) -> dict:
        """The trainer's move of a batch; a batch of the training set kept on the device (device_cache) brings only
        its host entries and takes its tensors from there."""
        moved = super().transfer_batch_to_device(batch, device, dataloader_idx)
        if self.device_samples is None or "pixels" in batch:  # a batch of the host's samples
            return moved
        return {**moved, **self.device_samples.gather(batch["index"].tolist())}

    def _pinned(self) -> bool:
        """Batches in pinned host memory when the trainer moves them to a GPU: a copy from pageable memory first
        waits for every kernel queued before it (CUDA's stream sync, once per tensor of the batch); a copy from pinned
        memory is queued like a kernel."""
        return self.trainer is not None and self.trainer.strategy.root_device.type == "cuda"

    def _require(self, split: str) -> AvatarDataset:
        if not self.datasets:
            raise RuntimeError("AvatarDataModule: call setup() first")
        if split not in self.datasets:
            raise KeyError(f"{self.scene.source}: split {split!r} has no images (have {sorted(self.datasets)})")
        return self.datasets[split]

    def on_before_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        """Before a batch moves to the device, image sizes become host ints (read from a GPU tensor, each would make
        the training step wait for the device). Poses need no check here: every window comes from a PoseTable, which
        refused non-finite poses when it was built. A training batch of views_per_step cameras per frame says so
        (`views_per_frame`, checked on the host frames): Avatar.render_batch poses each frame once."""
        out = {**batch, "width": batch["width"].tolist(), "height": batch["height"].tolist()}
        V = self.views_per_step
        if V > 1 and self.trainer is not None and self.trainer.training:
            f = batch["frame"].reshape(-1, V)
            if not bool((f == f[:, :1]).all()):
                raise RuntimeError(f"data.views_per_step={V}: a training batch mixes frames {f.tolist()}")
            out["views_per_frame"] = V
        return out

    def train_dataloader(self) -> DataLoader:
        return self._loader(self._require("train"), shuffle=True)

    def val_dataloader(self) -> DataLoader:
        """A few novel-view images (evenly spaced), or training images when there is no novel-view split."""
        ds = self.datasets.get("novel_view") or self._require("train")
        n = min(self.val_items, len(ds))
        idx = np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int)).tolist() if n > 0 else []
        return self._loader(torch.utils.data.Subset(ds, idx), shuffle=False)

    def test_dataloader(self) -> list[DataLoader]:
        """[novel_view, novel_pose] loaders; dataloader_idx i is test_split_names[i]."""
        return [self._loader(self._require(s), shuffle=False) for s in self.test_split_names]

    def predict_dataloader(self) -> list[DataLoader]:
        return self.test_dataloader()

    # ------------------------------------------------------------------ poses for rollouts and animation

    def pose_sequence(self, split: str = "all") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Frame ids [F] (long), poses [F,24,3], transl [F,3] of a split ("train", "novel_view", "novel_pose", "all")."""
        if self.scene is None:
            raise RuntimeError("AvatarDataModule: call setup() first")
        table = self.scene.poses
        if split == "all":
            frames = table.frames
        elif split in SPLITS:
            frames = np.unique([r.frame for r in self.records.get(split, [])]).astype(np.int64)
        else:
            raise ValueError(f"pose_sequence: unknown split {split!r}; expected 'all' or one of {SPLITS}")
        rows = torch.as_tensor(np.searchsorted(table.frames, frames))
        return torch.as_tensor(frames), table.poses[rows], table.transl[rows]

    def window_for(self, poses_table: PoseTable | tuple, frame_id: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose window [T,24,3] and transl window [T,3] of `frame_id` in an arbitrary sequence, with this module's
        window_len/window_step and the same clamping. poses_table: a PoseTable or (poses [F,24,3], transl [F,3]) or
        (frame_ids [F], poses, transl)."""
        if not isinstance(poses_table, PoseTable):
            if len(poses_table) == 2:
                poses_table = PoseTable.from_sequence(*poses_table)
            else:
                frames, poses, transl = poses_table
                poses_table = PoseTable.from_sequence(poses, transl, frames)
        return poses_table.window(frame_id, self.window_len, self.window_step)
