"""The SMPL body from its model files: clear errors, the npz through smplx, chumpy pickles refused."""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import torch


def fake_smpl_arrays(n_verts: int = 40, seed: int = 0) -> dict:
    from realityavatar.body.base import SMPL_PARENTS

    rng = np.random.default_rng(seed)
    w = rng.random((n_verts, 24))
    return {
        "v_template": rng.normal(0, 0.3, (n_verts, 3)), "shapedirs": rng.normal(0, 0.01, (n_verts, 3, 10)),
        "posedirs": np.zeros((n_verts, 3, 207)), "J_regressor": rng.random((24, n_verts)) / n_verts,
        "weights": w / w.sum(1, keepdims=True), "f": rng.integers(0, n_verts, (30, 3)),
        "kintree_table": np.array([[4294967295] + list(SMPL_PARENTS[1:]), list(range(24))]),
    }


def test_smpl_missing_files_names_expected_files(tmp_path):
    from realityavatar.body.smpl import SMPLBody

    with pytest.raises(FileNotFoundError, match=r"SMPL_NEUTRAL\.pkl.*SMPL_NEUTRAL\.npz.*smpl\.is\.tue\.mpg\.de"):
        SMPLBody(model_dir=str(tmp_path))
    with pytest.raises(FileNotFoundError, match=r"SMPL_FEMALE\.pkl"):
        SMPLBody(model_dir=str(tmp_path / "nope"), gender="female")
    with pytest.raises(FileNotFoundError, match="body.model_dir is not set"):
        SMPLBody(model_dir=None)


def test_smpl_npz_loads_through_smplx(tmp_path):
    from realityavatar.body.smpl import SMPLBody

    a = fake_smpl_arrays()
    np.savez(tmp_path / "SMPL_NEUTRAL.npz", **a)
    betas = np.linspace(-1, 1, 10)
    np.savez(tmp_path / "000000.npz", betas=betas[None])  # ZJU models/*.npz store betas as [1,10]
    b = SMPLBody(model_dir=str(tmp_path), betas=str(tmp_path / "000000.npz"))
    v = a["v_template"] + a["shapedirs"] @ betas
    np.testing.assert_allclose(b.rest_vertices.numpy(), v, atol=1e-5)
    np.testing.assert_allclose(b.rest_joints.numpy(), a["J_regressor"] @ v, atol=1e-5)
    assert b.skin_weights.shape == (40, 24) and b.faces.shape == (30, 3)
    A = b(torch.zeros(24, 3), torch.zeros(3))
    torch.testing.assert_close(A, torch.eye(4).expand(24, 4, 4), atol=1e-5, rtol=0)


def test_smpl_chumpy_pickle_gives_clear_error(tmp_path, monkeypatch):
    from realityavatar.body.smpl import SMPLBody

    fake = types.ModuleType("chumpy")

    class Ch:  # stands in for chumpy.Ch inside an original SMPL pickle
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy", "Ch"
    fake.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", fake)
    data = {**fake_smpl_arrays(), "v_template": Ch()}
    (tmp_path / "SMPL_MALE.pkl").write_bytes(pickle.dumps(data))
    monkeypatch.delitem(sys.modules, "chumpy")
    with pytest.raises(RuntimeError, match=r"SMPL_MALE\.pkl: .*chumpy.*\.npz"):
        SMPLBody(model_dir=str(tmp_path), gender="male")


def test_canonical_vertices_follow_the_buffers():
    from realityavatar.body import build_body

    body = build_body("mannequin").double()
    # a pose built on the default device/dtype and multiplied with moved buffers: the CUDA crash of on_fit_start
    assert body.canonical_pose().dtype == torch.float64
    assert body.canonical_vertices().dtype == torch.float64
