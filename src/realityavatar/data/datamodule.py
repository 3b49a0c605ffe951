"""The data of one sequence, without Lightning: a scene reader (`data.reader`: i3d.I3DReader, zju.ZJUReader), its
selection and its sample Dataset. Training wraps it for Lightning (data/lightning.py TrainingData); export, animate,
the viewer and evaluation read it as it is.

Samples follow docs/CONTRACTS.md ("Samples"): pixels, inside, background (`composite` makes image and mask of them),
mask_dist, K, viewmat, width, height, poses [T,24,3], transl [T,3], pose_features [T,D], bone_transforms [24,4,4],
frame, frame_idx, view, split.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from realityavatar.data.device_cache import DeviceSamples, keep_on_device
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
from realityavatar.data.samplers import EpochShuffle, ResumableLoader, SameFrameViews
from realityavatar.geometry import camera_centres
from realityavatar.model.avatar import pose_inputs

log = logging.getLogger(__name__)


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


class AvatarDataModule:
    """Train / val (a few novel-view images) / test ([novel_view, novel_pose]) loaders over one sequence; a plain
    object (data/lightning.py TrainingData is its Lightning face for trainer.fit).

    reader: the layout's reader (conf/data: `reader._target_`), which reads <root>/<sequence> and keeps the cameras
    train_views / test_views: i3d.I3DReader (I3D-Human, synthetic scenes, converted captures), zju.ZJUReader (ZJU-MoCap,
    with its frame ranges). This module subsamples the frames it keeps.
    fps: the capture's frame rate, the time base of the pose window (window_step frames) and of animations.
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
        reader,
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
        check_images: bool = True,
        shuffle_seed: int | None = None,
        sampler: Callable[..., EpochShuffle] = EpochShuffle,
    ) -> None:
        if not callable(getattr(reader, "read", None)):
            raise TypeError(f"data.reader: expected a scene reader (conf/data: reader._target_, e.g. "
                             f"realityavatar.data.i3d.I3DReader or realityavatar.data.zju.ZJUReader), got {reader!r}")
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
        # where training moves the batches (TrainingData sets it at fit): on a GPU the loaders pin their batches and
        # the training set is kept there (device_cache)
        self.device: torch.device | None = None
        self.device_samples: DeviceSamples | None = None  # the training set on the device (device_cache)
        self.training_set: str | dict = "host"  # where it is kept, for metrics.json (device_cache.keep_on_device)
        self.body = body
        self.pelvis = pelvis
        self.build_preset, self.build_sequence, self.build_seed = build_preset, build_sequence, int(build_seed)
        self.build_overrides = dict(build_overrides or {})
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

        return not split_folder(Path(self.root), self.sequence, "train").is_dir()  # build_preset's scenes: i3d layout

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
        """The scene as the reader selects it (train_views / test_views)."""
        return self.reader.read(self.root, self.sequence, self.train_views, self.test_views, self._pelvis())

    def _select(self, scene: SceneData) -> dict[str, list[ImageRecord]]:
        """The images of the frames kept: every train_frame_subsample-th training frame up to max_train_frames, every
        frame_subsample-th held-out frame."""
        out = {}
        for split, records in scene.splits.items():
            frames = np.unique([r.frame for r in records])
            if split == "train":
                frames = frames[:: self.train_frame_subsample]
                if self.max_train_frames is not None:
                    frames = frames[: int(self.max_train_frames)]
            else:
                frames = frames[:: self.frame_subsample]
            keep = set(frames.tolist())
            out[split] = [r for r in records if r.frame in keep]
        if not out.get("train"):  # the reader's selection left none (I3DReader names the cameras it had)
            raise ValueError(f"{scene.source}: the reader selected no training images (data.train_views "
                             f"{self.train_views}, data.reader {type(self.reader).__name__})")
        return out

    def setup(self, stage: str | None = None) -> None:
        if self.scene is not None:
            return
        if self.build_preset and self._scene_missing():
            self.prepare_data()
        scene = self.read_scene()
        if self.fps is None and scene.meta.get("fps"):  # a converted capture's or a built scene's -meta.json
            self.fps = float(scene.meta["fps"])
        elif self.fps is None:
            log.warning("%s: no frame rate (data.fps, or fps in its -meta.json): motion phases are off and animations "
                        "need data.fps=<frames per second>", scene.source)
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
            device = self._store_device()
            if device is not None and len(ds):
                self.device_samples, self.training_set = keep_on_device(ds, device)
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
        if not self.device_cache or self.device is None:
            return None
        return self.device if self.device.type == "cuda" else None

    def _pinned(self) -> bool:
        """Batches in pinned host memory when the trainer moves them to a GPU: a copy from pageable memory first
        waits for every kernel queued before it (CUDA's stream sync, once per tensor of the batch); a copy from pinned
        memory is queued like a kernel."""
        return self.device is not None and self.device.type == "cuda"

    def _require(self, split: str) -> AvatarDataset:
        if not self.datasets:
            raise RuntimeError("AvatarDataModule: call setup() first")
        if split not in self.datasets:
            raise KeyError(f"{self.scene.source}: split {split!r} has no images (have {sorted(self.datasets)})")
        return self.datasets[split]

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
