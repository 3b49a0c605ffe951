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
