"""The training set kept where the model trains (`data.device_cache` on a GPU)."""

from __future__ import annotations

import logging
import time

import torch
from torch.utils.data import Dataset

log = logging.getLogger(__name__)


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


def keep_on_device(ds: Dataset, device: torch.device) -> tuple[DeviceSamples | None, str | dict]:
    """The training set moved to `device` (DeviceSamples) when it takes at most half of the GPU's free memory, else
    None (batches are then collated on the host and copied); with where it is kept, for metrics.json."""
    need = len(ds) * sum(v.numel() * v.element_size() for v in ds[0].values() if torch.is_tensor(v))
    free = torch.cuda.mem_get_info(device)[0] if device.type == "cuda" else need * 2
    if need > free // 2:
        where = f"host: its {len(ds)} samples would take {need / 2**30:.1f} GiB of the GPU's {free / 2**30:.1f} GiB free"
        log.info("data.device_cache: the training set stays on the %s; batches are copied", where)
        return None, where
    t0 = time.perf_counter()
    samples = DeviceSamples(ds, device)
    where = {"device": str(device), "samples": len(ds), "gb": round(need / 2**30, 3),
             "seconds": round(time.perf_counter() - t0, 2)}
    log.info("data.device_cache: the training set kept on the device: %s", where)
    return samples, where
