"""Process-level settings for CPU training (the C allocator), and `OpCount`: the tensor operations and device reads
of a piece of code, counted on any device.

Each training step allocates and frees dozens of 1-5 MB tensors (per-Gaussian activations, images). glibc serves
blocks over its mmap threshold (128 KiB, rising only as far as 32 MiB on its own) with fresh mmap calls and returns
them on free, so every step pays page faults to zero them again: ~10% of a step at 10k Gaussians / 256^2 here
(benchmarks/step.py, process CPU time, 0.113 s -> 0.100 s). `tune_malloc` keeps such blocks in the heap and stops
trimming it, as tcmalloc does (the Makefile preloads tcmalloc where it is installed; then this is not needed).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
_state: dict = {}


def tune_malloc(mmap_threshold: int = 32 << 20, trim_threshold: int = 1 << 30, top_pad: int = 64 << 20) -> str:
    """Raise glibc's mmap and trim thresholds for this process (once). Returns what was done, for the run log."""
    if "result" in _state:
        return _state["result"]
    if "tcmalloc" in os.environ.get("LD_PRELOAD", "") or "jemalloc" in os.environ.get("LD_PRELOAD", ""):
        result = "allocator preloaded (LD_PRELOAD); glibc malloc not tuned"
    else:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):
            result = "no glibc mallopt on this platform; allocator not tuned"
        else:
            ok = all(mallopt(opt, val) == 1 for opt, val in ((_M_MMAP_THRESHOLD, mmap_threshold),
                                                            (_M_TRIM_THRESHOLD, trim_threshold),
                                                            (_M_TOP_PAD, top_pad)))
            result = (f"glibc malloc: mmap threshold {mmap_threshold >> 20} MiB, no trimming below "
                      f"{trim_threshold >> 20} MiB" if ok else "glibc mallopt refused a setting; allocator partly tuned")
    _state["result"] = result
    return result


def set_threads(threads, where: str = "threads") -> int:
    """The one rule for threads of every entry point (train, evaluate, export, animate, view, the analysis tools):
    `threads=N` sets torch's intra-op threads to N before anything is loaded, and the numba renderer and the image
    decoders follow torch's count; null or absent keeps torch's default (one per core). Where other jobs share the
    cores give threads=1: OpenMP threads that wait for one another stall when a core is taken. Returns the count."""
    if threads is None or str(threads).strip().lower() in ("", "null", "none"):
        return torch.get_num_threads()
    try:
        n = int(str(threads).strip())
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{where}={threads}: expected a whole number >= 1 (or null: torch's default, one per core)")
    torch.set_num_threads(n)
    return n


def add_threads_option(parser, default: int | None = 1) -> None:
    """`--threads N` of the analysis tools' command lines, applied with `set_threads`."""
    parser.add_argument("--threads", type=int, default=default,
                        help="torch CPU threads (1: safe on a shared CPU; runtime.set_threads)")


# Ops whose output size depends on the data: on a GPU each waits for the device, like a scalar read.
DATA_DEPENDENT = ("nonzero", "masked_select", "unique", "_unique2", "unique_consecutive", "argwhere",
                  "boolean_mask_index")
_METADATA = ("detach", "alias", "lift_fresh", "_unsafe_view")


class OpCount(TorchDispatchMode):
    """Counts the tensor operations run inside it (forward, backward, optimizer; views and other metadata-only ops
    left out) by name in `ops`, and the host syncs among them: `reads` = scalar reads (`.item()`, `float()`, `bool()`
    of a tensor: aten._local_scalar_dense) plus ops whose output size depends on the data (nonzero, indexing with a
    boolean mask, ...). The same counts on a CPU as on a GPU: the kernel launches and waits a GPU step would make.

        with OpCount() as c:
            module.training_step(batch, 0)
        c.total, c.reads
    """

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.__name__.split(".")[0]
        if not (func.is_view or name in _METADATA):
            self.ops[name] += 1
            if name in ("index", "index_put", "index_put_") and any(
                    torch.is_tensor(i) and i.dtype == torch.bool for i in args[1] if i is not None):
                self.ops["boolean_mask_index"] += 1  # output size = the mask's count (not an op of its own)
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(v for k, v in self.ops.items() if k != "boolean_mask_index")

    @property
    def reads(self) -> int:
        return self.ops["_local_scalar_dense"] + sum(self.ops[k] for k in DATA_DEPENDENT)


_CONSTANTS: dict[tuple, torch.Tensor] = {}


def host_path(t: torch.Tensor) -> bool:
    """Whether a numpy or numba path may take tensor t: a CPU tensor, outside torch.compile's tracing (dynamo cannot
    trace those calls; while it traces, the torch path runs and becomes part of the graph)."""
    return t.device.type == "cpu" and not torch.compiler.is_compiling()


class Table:
    """A table of numbers defined at import (a basis, a stencil, a sign pattern), for `constant`. Its numbers are kept
    as Python floats too: under torch.compile they become a literal of the graph on its device. A module-level
    tensor would be a host input of the graph, copied to the GPU at every call (a copy and a wait each: the 13
    syncs per compiled step on an H200), and CUDA graphs skip a graph with a host input."""

    def __init__(self, t: torch.Tensor) -> None:
        self.tensor = t.detach().clone()
        self.values = _nested_tuple(self.tensor.tolist())


def _nested_tuple(v):
    return tuple(_nested_tuple(x) for x in v) if isinstance(v, list) else v


def constant(t: Table | tuple[float, ...], like: torch.Tensor) -> torch.Tensor:
    """A constant in `like`'s device and dtype, made there once: a module-level `Table`, or a tuple of numbers
    (e.g. an image's size). A `t.to(like)` or `like.new_tensor(values)` in the training step would copy it from the
    host at every step on a GPU (and wait for the copy)."""
    if not isinstance(t, (Table, tuple)):
        raise TypeError(f"constant: expected a runtime.Table or a tuple of numbers, got {type(t).__name__}")
    values = t.values if isinstance(t, Table) else t
    if torch.compiler.is_compiling():  # traced by torch.compile: a literal of the graph (not cached: a side effect)
        return torch.tensor(values, dtype=like.dtype, device=like.device)
    key = (id(t) if isinstance(t, Table) else t, like.device, like.dtype)
    if key not in _CONSTANTS:
        # made outside inference mode even when first asked for inside it (an evaluation, the viewer): an inference
        # tensor in the cache would refuse to be saved for backward by every later training step in the process
        with torch.inference_mode(False):
            _CONSTANTS[key] = (t.tensor.to(like) if isinstance(t, Table) else
                               torch.tensor(values, dtype=like.dtype, device=like.device))
    return _CONSTANTS[key]
