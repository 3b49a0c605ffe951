"""realityavatar-export: the PLY format round trip."""

from __future__ import annotations

import numpy as np
import pytest


def test_ply_round_trip(tmp_path):
    from realityavatar.export import read_ply, write_ply

    rng = np.random.default_rng(0)
    N = 50
    means, quats = rng.normal(size=(N, 3)), rng.normal(size=(N, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales, op = rng.uniform(0.01, 0.1, (N, 3)), rng.uniform(0.05, 0.95, N)
    sh = rng.normal(size=(N, 16, 3))
    write_ply(tmp_path / "g.ply", means, quats, scales, op, sh=sh)
    back = read_ply(tmp_path / "g.ply")
    for k, v in (("means", means), ("quats", quats), ("scales", scales), ("opacities", op), ("sh", sh)):
        np.testing.assert_allclose(back[k], v, rtol=1e-4, atol=1e-5, err_msg=k)
    with pytest.raises(ValueError, match="means"):
        write_ply(tmp_path / "bad.ply", means[:, :2], quats, scales, op, sh=sh)


@pytest.mark.parametrize("argv, named", [
    (["frme=3"], "frme=: unknown argument"),
    (["poses=walk.npz"], "poses= apply to frames=a:b"),        # without frames=: the canonical Gaussians were written
    (["frames=0:4", "fps=30"], "fps= apply to frames=a:b"),    # fps= without poses=: ignored
])
def test_export_refuses_arguments_it_would_ignore(argv, named, capsys):
    """Exit 2 naming the argument, before the run folder (here absent) is read."""
    from realityavatar.export import main as export_main

    assert export_main(["run_dir=/nonexistent/run", *argv]) == 2
    assert named in capsys.readouterr().err
