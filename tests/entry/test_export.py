"""realityavatar-export: the PLY format, read back by our reader and by plyfile."""

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


def test_ply_reads_in_plyfile_as_3dgs_writes_it(tmp_path):
    """The exported file read by plyfile (the reader 3DGS's own loader uses), checked against 3DGS's layout computed
    here from the inputs: names and order of the vertex properties, float32, and every value (logit opacity, log
    scales, unit wxyz quaternions, SH DC then the rest channel-major)."""
    from plyfile import PlyData

    from realityavatar.export import write_ply

    rng = np.random.default_rng(1)
    N, K = 40, 16
    means, quats = rng.normal(size=(N, 3)), rng.normal(size=(N, 4))
    scales, op = rng.uniform(0.01, 0.1, (N, 3)), rng.uniform(0.05, 0.95, N)
    sh = rng.normal(size=(N, K, 3))
    write_ply(tmp_path / "g.ply", means, quats, scales, op, sh=sh)
    ply = PlyData.read(str(tmp_path / "g.ply"))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    rest = [f"f_rest_{i}" for i in range(3 * (K - 1))]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest, "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert [p.name for p in v.properties] == names
    assert {p.val_dtype for p in v.properties} == {"f4"} and v.count == N
    col = {n: np.asarray(v[n], np.float64) for n in names}
    expected = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2], "opacity": np.log(op / (1 - op))}
    expected |= {f"n{a}": np.zeros(N) for a in "xyz"}
    expected |= {f"f_dc_{c}": sh[:, 0, c] for c in range(3)}
    expected |= {f"f_rest_{c * (K - 1) + k}": sh[:, 1 + k, c] for c in range(3) for k in range(K - 1)}
    expected |= {f"scale_{i}": np.log(scales[:, i]) for i in range(3)}
    unit = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    expected |= {f"rot_{i}": unit[:, i] for i in range(4)}
    for n in names:
        np.testing.assert_allclose(col[n], expected[n], rtol=1e-5, atol=1e-6, err_msg=n)


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
