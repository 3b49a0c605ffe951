"""SMPL behind the BodyModel interface, read through `smplx` from the user's licensed model files (not shipped).

Plain LBS with the shaped rest mesh (betas applied, no pose blend shapes), the same FK as every BodyModel.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from realityavatar.body.base import BodyModel

GENDERS = ("neutral", "male", "female")
CHUMPY_HELP = (
    "it holds chumpy arrays (the original SMPL release) and chumpy does not build on current Python/NumPy. "
    "Use a chumpy-free copy: the .npz files of the smplx release (SMPL_NEUTRAL.npz), or convert once on a machine "
    "with chumpy (e.g. smplx's tools/clean_ch.py) and save plain numpy arrays; 3DGS-Avatar's body_models/smpl/"
    "<gender>/model.pkl files are chumpy-free too"
)


def expected_files(gender: str) -> list[str]:
    g = gender.upper()
    return [f"SMPL_{g}.pkl", f"SMPL_{g}.npz", f"smpl/SMPL_{g}.pkl", f"smpl/SMPL_{g}.npz", f"{gender}/model.pkl",
            f"smpl/{gender}/model.pkl"]


def find_model_file(model_dir: str | Path, gender: str = "neutral") -> Path:
    """The SMPL file for `gender` in `model_dir` (or `model_dir` itself when it is a file); a clear error if absent."""
    gender = gender.lower()
    if gender not in GENDERS:
        raise ValueError(f"body.gender: expected one of {GENDERS}, got {gender!r}")
    if model_dir is None or str(model_dir) in ("", "???"):
        raise FileNotFoundError(
            "body.model_dir is not set: SMPL needs your licensed model files (https://smpl.is.tue.mpg.de), e.g. "
            f"body.model_dir=/path/to/smpl containing one of {expected_files(gender)}"
        )
    p = Path(model_dir).expanduser()
    if p.is_file():
        return p
    for rel in expected_files(gender):
        if (p / rel).is_file():
            return p / rel
    where = f"{p} does not exist" if not p.exists() else f"none of them is in {p}"
    raise FileNotFoundError(
        f"SMPL model files not found: expected one of {expected_files(gender)} ({where}). Download SMPL from "
        "https://smpl.is.tue.mpg.de (the SMPL_NEUTRAL/MALE/FEMALE files; chumpy-free .npz or model.pkl) and set "
        "body.model_dir to the folder that holds them"
    )


def load_model_data(path: Path) -> dict:
    """Arrays of an SMPL model file (.npz or chumpy-free .pkl) as a dict; chumpy pickles get an explanation."""
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=True) as z:
                data = {k: z[k] for k in z.files}
        else:
            with open(path, "rb") as f:
                data = pickle.load(f, encoding="latin1")
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] == "chumpy":
            raise RuntimeError(f"cannot read SMPL model file {path}: {CHUMPY_HELP}") from e
        raise RuntimeError(f"cannot read SMPL model file {path}: needs module {e.name!r}") from e
    except Exception as e:
        raise RuntimeError(f"cannot read SMPL model file {path}: {type(e).__name__}: {e}") from e
    if not isinstance(data, dict):
        raise RuntimeError(f"SMPL model file {path}: expected a dict of arrays, got {type(data).__name__}")  # noqa: TRY004
    needed = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "f", "kintree_table")
    missing = [k for k in needed if k not in data]
    if missing:
        raise RuntimeError(f"SMPL model file {path}: missing keys {missing}")
    out = {}
    for k, v in data.items():
        if hasattr(v, "toarray"):  # J_regressor is a scipy sparse matrix in the original files
            v = v.toarray()
        if type(v).__module__.startswith("chumpy"):
            raise RuntimeError(f"cannot read SMPL model file {path}: {CHUMPY_HELP}")
        out[k] = v
    return out


def load_betas(betas, num_betas: int = 10) -> np.ndarray:
    """betas: None | sequence of floats | path to an .npz/.npy/.json with `betas` (e.g. a ZJU models/000000.npz)."""
    if betas is None:
        return np.zeros(num_betas)
    if isinstance(betas, (str, Path)):
        p = Path(betas).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"body.betas: file {p} not found")
        if p.suffix == ".npz":
            with np.load(p) as z:
                if "betas" not in z.files:
                    raise KeyError(f"body.betas: {p} has no 'betas' array (has {z.files})")
                b = z["betas"]
        elif p.suffix == ".json":
            import json

            b = json.loads(p.read_text())["betas"]
        else:
            b = np.load(p)
    else:
        b = [float(x) for x in betas]
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if not np.isfinite(b).all():
        raise ValueError(f"body.betas: non-finite values {b.tolist()}")
    out = np.zeros(max(num_betas, b.size))
    out[: b.size] = b
    return out[:num_betas] if b.size <= num_betas else out


class SMPLBody(BodyModel):
    """SMPL (6890 vertices, 24 joints) from user files via smplx; rest mesh = template + shape blend (betas)."""

    name = "smpl"

    def __init__(self, model_dir: str | None = None, gender: str = "neutral",
                 betas: Sequence[float] | str | None = None, num_betas: int = 10) -> None:
        super().__init__()
        import smplx
        from smplx.utils import Struct

        path = find_model_file(model_dir, gender)
        data = load_model_data(path)
        b = load_betas(betas, num_betas)
        model = smplx.SMPL(model_path=str(path), data_struct=Struct(**data), gender=gender, num_betas=b.size,
                           batch_size=1)
        with torch.no_grad():
            beta_t = torch.as_tensor(b[: model.num_betas], dtype=torch.float32)[None]
            v = model.v_template + torch.einsum("vcb,b->vc", model.shapedirs, beta_t[0])  # [6890,3]
            J = model.J_regressor @ v  # [24,3]
        parents = tuple(int(p) for p in model.parents.tolist())
        parents = (-1,) + parents[1:]
        if parents != self.parents:
            raise RuntimeError(f"SMPL model file {path}: kinematic tree {parents} differs from SMPL's")
        self.model_file = str(path)
        self.gender = gender
        self.betas = b
        self._set_buffers(v, model.faces_tensor, model.lbs_weights, J)
