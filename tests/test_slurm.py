"""The CPU launcher on a real scheduler: scripts/slurm_local.sh brings up a single-node SLURM, `+ablation=tiny` is
submitted through hydra/launcher=slurm_cpu, each job writes metrics.json and the collector tables them. Skips, and
says why, where SLURM cannot be installed or started without root (.ci/run installs it)."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time

import pytest

from realityavatar.analysis.collect import collect
from tests.helpers import ROOT

SCRIPT = ROOT / "scripts" / "slurm_local.sh"
# cut shorter than the preset, as in test_sweeps.test_tiny_sweep_end_to_end: what is checked is the launcher
SHORT = ["threads=1", "iterations=4", "gaussians.num_points=300", "eval.max_frames_per_split=2", "eval.save_images=0",
         "eval.fps_frames=1", "eval.fps_warmup=0"]


def free_port_pair() -> int:
    """A port p with p and p+1 free (slurmctld, slurmd): a second cluster or test run on the machine never clashes."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port + 1))
                return port
            except OSError:
                continue
    raise RuntimeError("no two consecutive free ports")


@pytest.fixture
def slurm(tmp_path):
    """The environment of a running single-node cluster; its daemons are stopped afterwards, pass or fail."""
    state = tmp_path / "slurm"
    env = {**os.environ, "SLURM_LOCAL_PORT": str(free_port_pair()), "OMP_NUM_THREADS": "1"}
    up = subprocess.run([SCRIPT, "up", state], env=env, capture_output=True, text=True, timeout=300, check=False)
    try:
        if up.returncode == 3:
            pytest.skip(f"no single-node SLURM here: {up.stderr.strip()}")
        assert up.returncode == 0, f"scripts/slurm_local.sh up failed:\n{up.stderr[-3000:]}"
        print(up.stderr.strip())
        yield {**env, "SLURM_CONF": str(state / "slurm.conf")}
    finally:
        subprocess.run([SCRIPT, "down", state], env=env, capture_output=True, timeout=60, check=False)
        left = [d for d in ("munged", "slurmctld", "slurmd") if (state / f"{d}.pid").exists()]
        assert not left, f"still running after scripts/slurm_local.sh down: {left}"


def job_states(sweep, env, timeout: float = 30.0) -> dict[str, str]:
    """{<array job>_<task>: SLURM state} of the jobs whose folders submitit made under the sweep's .submitit/, once
    none is still running (submitit returns when a job has written its result, before the job step has ended)."""
    t0 = time.perf_counter()
    while True:
        states = _states(sweep, env)
        if time.perf_counter() - t0 > timeout or not set(states.values()) & {"PENDING", "RUNNING", "COMPLETING"}:
            return states
        time.sleep(0.5)


def _states(sweep, env) -> dict[str, str]:
    array_ids = {p.name.split("_")[0] for p in (sweep / ".submitit").iterdir() if re.fullmatch(r"\d+_\d+", p.name)}
    states = {}
    for array_id in sorted(array_ids):
        out = subprocess.run(["scontrol", "-o", "show", "job", array_id], env=env, capture_output=True, text=True,
                             check=True).stdout
        for line in out.splitlines():
            task, state = re.search(r"ArrayTaskId=(\S+)", line)[1], re.search(r"JobState=(\S+)", line)[1]
            states[f"{array_id}_{task}"] = state
    return dict(sorted(states.items()))


@pytest.mark.slow
def test_tiny_sweep_on_slurm_cpu_launcher(slurm, tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "realityavatar.train", "-m", "+ablation=tiny", "hydra/launcher=slurm_cpu",
           "hydra.launcher.cpus_per_task=1", "hydra.launcher.mem_gb=2", "hydra.launcher.timeout_min=5", *SHORT,
           f"hydra.sweep.dir={sweep}"]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, env=slurm, capture_output=True, text=True, timeout=300, check=False)
    wall = time.perf_counter() - t0
    states = job_states(sweep, slurm) if (sweep / ".submitit").is_dir() else {}
    print(f"submitted {len(states)} jobs: {', '.join(f'{j} {s}' for j, s in states.items())}; sweep {wall:.0f} s")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert len(states) == 2 and set(states.values()) == {"COMPLETED"}, states
    assert sorted(p.parent.name for p in sweep.rglob("metrics.json")) == ["0", "1"]
    csv, _ = collect(sweep, tmp_path / "table")
    assert list(csv["label"]) == ["full", "no_lstm"]
    assert csv["novel_view_psnr_mean"].notna().all()
    print((tmp_path / "table" / "table.md").read_text())
