"""realityavatar.runtime.tune_malloc: freed multi-MB tensors are reused from the heap instead of being mapped again."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = r"""
import ctypes, json, resource, sys, torch
# glibc's default mmap threshold (128 KiB), pinned: left alone, glibc raises it after the first free of a mapped
# block, so whether an untouched process faults depends on its allocation history; pinned, every block over it is
# mapped afresh on each allocation, which is what the tuning must undo
ctypes.CDLL("libc.so.6").mallopt(-3, 128 * 1024)
if sys.argv[1] == "tune":
    from realityavatar.runtime import tune_malloc
    print(tune_malloc(), file=sys.stderr)
def step():  # a training step's pattern: 20 activations of 5 MB alive together (forward), then all freed
    acts = [torch.ones(1_250_000) for _ in range(20)]
    del acts
for _ in range(2):                      # warm up: the heap grows once
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print(json.dumps(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before))
"""


def _faults(mode: str) -> int:
    env = {"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    import os

    env.update({k: v for k, v in os.environ.items() if k in ("PYTHONPATH", "HOME", "VIRTUAL_ENV")})
    env.pop("LD_PRELOAD", None)
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, env=env, timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    return int(json.loads(out.stdout.strip().splitlines()[-1]))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt and minor-fault counts: Linux only")
def test_tuned_malloc_stops_page_faults_of_freed_tensors():
    plain, tuned = _faults("plain"), _faults("tune")
    # untuned, each 5 MB block is mapped and faulted in afresh (~1,220 pages x 20 blocks x 10 steps); tuned, the
    # heap keeps its pages
    assert plain > 100_000, plain
    assert tuned < plain / 20, (tuned, plain)


@pytest.mark.parametrize("preload,accepted,expect", [
    ("", 1, "glibc malloc: mmap threshold 32 MiB, no trimming below 1024 MiB"),
    ("", 0, "glibc mallopt refused a setting; allocator partly tuned"),
    ("/usr/lib/libtcmalloc.so.4", 1, "allocator preloaded (LD_PRELOAD); glibc malloc not tuned")])
def test_tune_malloc_sets_glibc_once_and_says_what_it_did(monkeypatch, preload, accepted, expect):
    """tune_malloc asks glibc for the mmap threshold, trim threshold and top pad (M_MMAP_THRESHOLD -3, M_TRIM_THRESHOLD
    -1, M_TOP_PAD -2) once per process, reports what glibc accepted, and leaves a preloaded allocator alone."""
    import ctypes

    from realityavatar import runtime

    calls = []

    class Libc:
        def mallopt(self, option, value):
            calls.append((option, value))
            return accepted

    monkeypatch.setattr(runtime, "_state", {})
    monkeypatch.setattr(ctypes, "CDLL", lambda name: Libc())
    monkeypatch.setenv("LD_PRELOAD", preload)
    assert runtime.tune_malloc() == expect
    settings = [(-3, 32 << 20), (-1, 1 << 30), (-2, 64 << 20)]
    assert calls == ([] if preload else settings[: 1 if not accepted else 3])  # all() stops at the first refusal
    n = len(calls)
    assert runtime.tune_malloc() == expect and len(calls) == n  # a second call asks glibc nothing


def test_constant_is_made_once_per_device_and_dtype():
    """runtime.constant: a module-level Table or a tuple of numbers, in `like`'s dtype, made once (a step on a GPU would
    otherwise copy it from the host every time); each distinct value has its own entry."""
    import torch

    from realityavatar.runtime import Table, constant

    like = torch.zeros(2, dtype=torch.float64)
    a = constant((63.0, 31.0), like)
    assert a.dtype == torch.float64 and a.tolist() == [63.0, 31.0]
    assert constant((63.0, 31.0), like) is a and constant((63.0, 31.0), like.float()) is not a
    assert constant((127.0, 31.0), like).tolist() == [127.0, 31.0]
    for w in range(60, 70):  # tuples made at run time (an image's size): keyed by value, never by a reused id
        assert constant((w - 1.0, 31.0), like).tolist() == [w - 1.0, 31.0]
        assert constant((w - 1.0, 31.0), like) is constant((w - 1.0, 31.0), like)
    t = Table(torch.arange(3.0))
    assert constant(t, like) is constant(t, like) and constant(t, like).dtype == torch.float64
    assert constant(t, like).tolist() == [0.0, 1.0, 2.0] and t.values == (0.0, 1.0, 2.0)
    with pytest.raises(TypeError, match="runtime.Table"):  # a bare tensor: a host input of a compiled graph
        constant(torch.arange(3.0), like)


def test_a_constant_first_made_in_inference_mode_serves_training_later():
    """An evaluation (inference mode) that makes a constant first must not leave an inference tensor in the cache:
    a later training step in the same process saves it for backward (it refused to: 49 tests of one pytest worker)."""
    import torch

    from realityavatar.runtime import Table, constant

    t = Table(torch.arange(3.0, dtype=torch.float64))
    like = torch.zeros(3, dtype=torch.float32)
    with torch.inference_mode():
        constant(t, like)
        constant((5.0, 7.0), like)
    w = torch.ones(3, requires_grad=True)
    (w * constant(t, like)).sum().backward()  # mul saves the constant for backward
    assert w.grad.tolist() == [0.0, 1.0, 2.0]
    assert not constant((5.0, 7.0), like).is_inference()
