"""The training order: samplers that draw the training images (conf/sampler), the views of one frame per step, and
the loader that saves their position in the checkpoint. The loss feedback that the hard-frames order draws by is a
training callback (data/lightning.py SamplerFeedback)."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader

log = logging.getLogger(__name__)


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
    the frame's images (data/lightning.py SamplerFeedback, conf/callbacks/default.yaml, passes them after every
    step), so one camera's loss updates the whole frame. Frames the garment flares in (the spin) and the swing after
    an abrupt stop have the highest photometric error: uniform sampling spends most steps on the easy rest frames.
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


class ResumableLoader(DataLoader):
    """A DataLoader whose position Lightning saves in the checkpoint and restores on resume (its sampler's state)."""

    def state_dict(self) -> dict:
        return self.sampler.state_dict()

    def load_state_dict(self, state: dict) -> None:
        if state:
            self.sampler.load_state_dict(state)
