"""The datamodule: the sample contract, selection, windows, caching, every data config, samplers, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict
from torch.utils.data import default_collate

from realityavatar.data.datamodule import AvatarDataModule, composite
from realityavatar.data.i3d import I3DReader
from realityavatar.data.poses import PoseTable
from tests.fixtures_data import SIZE, RandomBody, project, write_i3d, write_zju
from tests.helpers import CONF

KEYS = {"pixels", "inside", "background", "mask_dist", "K", "viewmat", "width", "height", "poses", "transl",
        "pose_features", "bone_transforms", "index", "frame", "frame_idx", "view", "split"}


@pytest.fixture(scope="module")
def body():
    return RandomBody()


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory, body):
    root = tmp_path_factory.mktemp("scenes")
    write_i3d(root, "seq", body, train_frames=tuple(range(8)), pose_frames=(8, 9, 10), train_views=(0, 1, 3),
              test_views=(2, 5))
    return root


def compose_data(option: str):
    """The data group's option as the command line composes it (option files may inherit from another)."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", overrides=[f"data={option}"]).data


def make(scene_root, body, **kw):
    dm = AvatarDataModule(str(scene_root), "seq", I3DReader(1), body=body, **{"window_len": 3, "window_step": 2, **kw})
    dm.setup("fit")
    return dm


def test_sample_dict_follows_the_contract(scene_root, body):
    dm = make(scene_root, body, batch_size=2)
    assert dm.num_train_frames == 8 and dm.train_frame_ids == list(range(8))
    assert dm.image_size == (SIZE, SIZE) and (dm.width, dm.height) == (SIZE, SIZE)
    assert 2.5 < dm.scene_extent < 4.5  # cameras 3 m from the subject, x1.1
    assert dm.test_split_names == ["novel_view", "novel_pose"]
    s = dm.datasets["train"][0]
    assert set(s) == KEYS
    assert s["pixels"].shape == (SIZE, SIZE, 3) and s["pixels"].dtype == torch.uint8
    assert s["inside"].shape == (SIZE, SIZE, 1) and s["inside"].dtype == torch.bool and s["inside"].any()
    c = composite(default_collate([s]))  # what the model reads, made after the transfer
    assert c["image"].shape == (1, SIZE, SIZE, 3) and c["image"].dtype == torch.float32
    assert c["mask"].shape == (1, SIZE, SIZE, 1) and set(c["mask"].unique().tolist()) == {0.0, 1.0}
    assert not {"pixels", "inside", "background"} & set(c)
    assert s["poses"].shape == (3, 24, 3) and s["transl"].shape == (3, 3)
    # the model's pose inputs, made by the dataset from the sample's own window with the body
    from realityavatar.model.encoders import pose_features

    torch.testing.assert_close(s["pose_features"], pose_features(s["poses"][None], s["transl"][None])[0])
    torch.testing.assert_close(s["bone_transforms"], body.canonical_transforms(s["poses"][-1], s["transl"][-1]))
    b = next(iter(dm.train_dataloader()))
    assert b["pixels"].shape == (2, SIZE, SIZE, 3) and b["poses"].shape == (2, 3, 24, 3)
    assert b["K"].shape == (2, 3, 3) and b["viewmat"].shape == (2, 4, 4) and b["frame_idx"].shape == (2,)
    nv, npose = dm.test_dataloader()
    assert all(set(x["split"]) == {"novel_view"} and torch.equal(x["frame_idx"], x["frame"]) for x in nv)
    assert all(set(x["split"]) == {"novel_pose"} and (x["frame_idx"] == -1).all() for x in npose)
    assert len(nv.dataset) == 8 * 2 and len(npose.dataset) == 3 * 2
    val = [s for x in dm.val_dataloader() for s in x["split"]]
    assert len(val) == 4 and set(val) == {"novel_view"}


def test_views_per_step_batches_cameras_of_one_frame(scene_root, body):
    """data.views_per_step=V: every training batch holds V different cameras of one frame (batch_size frames), the
    hook marks it for the model (training only), the order resumes, and too few cameras per frame is an error."""
    from types import SimpleNamespace

    from realityavatar.data.lightning import TrainingData

    dm = make(scene_root, body, views_per_step=3, batch_size=2)
    loader = dm.train_dataloader()
    batches = list(loader)
    assert len(batches) == 12  # 24 training images drawn once each by the base order, each with its frame's others
    for b in batches:
        f, v = b["frame"].reshape(2, 3), b["view"].reshape(2, 3)
        assert (f == f[:, :1]).all() and all(len(set(row)) == 3 for row in v.tolist())
    assert {int(i) for b in batches for i in b["index"][::3]} == set(range(24))
    hooks = TrainingData(dm)
    hooks.trainer = SimpleNamespace(training=True)
    assert hooks.on_before_batch_transfer(batches[0], 0)["views_per_frame"] == 3
    hooks.trainer = SimpleNamespace(training=False)  # evaluation batches: one sample each
    assert "views_per_frame" not in hooks.on_before_batch_transfer(batches[0], 0)
    mixed = {**batches[0], "frame": torch.arange(6)}
    hooks.trainer = SimpleNamespace(training=True)
    with pytest.raises(RuntimeError, match="views_per_step=3: a training batch mixes frames"):
        hooks.on_before_batch_transfer(mixed, 0)
    # resume: the state after 4 batches continues with the uninterrupted order's batches 5..
    dm2 = make(scene_root, body, views_per_step=3, batch_size=2, shuffle_seed=dm.shuffle_seed)
    it = iter(dm2.train_dataloader())
    for _ in range(4):
        next(it)
    state = dm2.train_sampler.state_dict()
    dm3 = make(scene_root, body, views_per_step=3, batch_size=2, shuffle_seed=dm.shuffle_seed)
    loader3 = dm3.train_dataloader()
    loader3.load_state_dict(state)
    assert torch.equal(next(iter(loader3))["index"], batches[4]["index"])
    with pytest.raises(ValueError, match=r"views_per_step=4: frame \d+ has 3 training image"):
        make(scene_root, body, views_per_step=4).train_dataloader()


def test_joint_projects_inside_mask_in_samples(scene_root, body):
    dm = make(scene_root, body, image_scale=0.5)
    assert dm.image_size == (SIZE // 2, SIZE // 2)
    for split, ds in dm.datasets.items():
        for i in range(len(ds)):
            s = ds[i]
            pelvis = body.joints(s["poses"][-1], s["transl"][-1])[0].double().numpy()
            u, v = project(s["K"].double().numpy(), s["viewmat"].double().numpy(), pelvis)
            assert s["inside"][int(v), int(u), 0], (split, s["frame"], s["view"])


def test_background_is_composited(scene_root, body):
    """`composite` puts the pixels over data.background outside the mask: the values of image * mask + bg * (1 -
    mask), bit for bit, made in float32 for a float64 module too."""
    dm = make(scene_root, body, background=[1.0, 0.5, 0.0])
    s = dm.datasets["train"][0]
    c = composite(default_collate([s]))
    outside = c["mask"][0, ..., 0] == 0
    assert torch.allclose(c["image"][0][outside], torch.tensor([1.0, 0.5, 0.0]))
    assert not torch.allclose(c["image"][0][~outside].mean(0), torch.tensor([1.0, 0.5, 0.0]))
    m = s["inside"].float()
    assert torch.equal(c["image"][0], s["pixels"].float() / 255.0 * m + torch.tensor([1.0, 0.5, 0.0]) * (1 - m))
    c64 = composite(default_collate([s]), torch.float64)
    assert c64["image"].dtype == c64["mask"].dtype == torch.float64 and torch.equal(c64["image"], c["image"].double())


def test_view_and_frame_selection(scene_root, body):
    dm = make(scene_root, body, train_views=[0, 3], test_views=[5], max_train_frames=5, frame_subsample=2)
    assert sorted({r.view for r in dm.records["train"]}) == [0, 3]
    assert dm.train_frame_ids == [0, 1, 2, 3, 4] and dm.num_train_frames == 5
    assert sorted({r.view for r in dm.records["novel_pose"]}) == [5]
    assert sorted({r.frame for r in dm.records["novel_pose"]}) == [8, 10]
    # novel-view frames beyond max_train_frames are not training frames: frame_idx -1
    idx = {s["frame"]: s["frame_idx"] for s in (dm.datasets["novel_view"][i] for i in range(len(dm.datasets["novel_view"])))}
    assert idx[0] == 0 and idx[2] == 2 and idx[6] == -1
    with pytest.raises(ValueError, match=r"data\.train_views: camera\(s\) \[7\] not in .*seq's train images "
                                         r"\(cameras \[0, 1, 3\]\)"):
        make(scene_root, body, train_views=[0, 7])
    # a test camera the scene has not: the splits were read without it, and evaluation tested fewer images or none
    with pytest.raises(ValueError, match=r"data\.test_views: camera\(s\) \[7\] not in .*seq's novel_view, novel_pose "
                                         r"images \(cameras \[2, 5\]\)"):
        make(scene_root, body, test_views=[5, 7])
    with pytest.raises(ValueError, match=r"no training images left after selecting views \[\]"):
        make(scene_root, body, train_views=[])
    with pytest.raises(ValueError, match=r"data\.background: expected 3 values in \[0,1\], got \[2, 0, 0\]"):
        make(scene_root, body, background=[2, 0, 0])


def test_novel_pose_window_looks_back_into_training_frames(scene_root, body):
    dm = make(scene_root, body, window_len=4, window_step=3)
    table = dm.scene.poses
    s = next(dm.datasets["novel_pose"][i] for i in range(len(dm.datasets["novel_pose"]))
             if dm.datasets["novel_pose"][i]["frame"] == 9)
    for k, f in enumerate([0, 3, 6, 9]):  # 9-9, 9-6, 9-3, 9: three of them are training frames
        torch.testing.assert_close(s["poses"][k], table.get(f)[0])
        torch.testing.assert_close(s["transl"][k], table.get(f)[1])
    s0 = dm.datasets["train"][0]  # frame 0: every window entry clamps to the first frame
    assert s0["frame"] == 0 and torch.equal(s0["poses"], table.get(0)[0].expand(4, 24, 3))


def test_pose_sequence_and_window_for(scene_root, body):
    dm = make(scene_root, body)
    f, p, t = dm.pose_sequence("novel_pose")
    assert f.tolist() == [8, 9, 10] and p.shape == (3, 24, 3) and t.shape == (3, 3)
    f_all, _, _ = dm.pose_sequence("all")
    assert f_all.tolist() == list(range(11))
    seq_p, seq_t = torch.randn(5, 24, 3), torch.randn(5, 3)
    wp, wt = dm.window_for((seq_p, seq_t), 3)  # T=3, s=2: frames 0 (clamped from -1), 1, 3
    torch.testing.assert_close(wp, seq_p[[0, 1, 3]])
    torch.testing.assert_close(wt, seq_t[[0, 1, 3]])
    wp2, _ = dm.window_for(PoseTable.from_sequence(seq_p, seq_t, frame_ids=[10, 11, 12, 13, 14]), 14)
    torch.testing.assert_close(wp2, seq_p[[0, 2, 4]])  # frames 10, 12, 14
    with pytest.raises(ValueError, match="unknown split"):
        dm.pose_sequence("valid")


def test_cache_images_keeps_decoded_images(tmp_path, body):
    write_i3d(tmp_path, "c", body, train_frames=(0, 1), pose_frames=(2,), train_views=(0,), test_views=(1,))
    dm = AvatarDataModule(str(tmp_path), "c", I3DReader(1), body=body, cache_images=True)
    dm.setup()
    dm2 = AvatarDataModule(str(tmp_path), "c", I3DReader(1), body=body, cache_images=False)
    dm2.setup()
    first = dm.datasets["train"][0]["pixels"]
    dm.datasets["train"].records[0].image_path.unlink()
    torch.testing.assert_close(dm.datasets["train"][0]["pixels"], first)  # served from memory
    with pytest.raises(FileNotFoundError, match="frame_000000_view_00.png not found"):
        dm2.datasets["train"][0]
    # the image check also made every cached mask's distance field (in threads), the values a sample would make
    from realityavatar.data.records import mask_distance

    for ds in dm.datasets.values():
        assert sorted(ds._dist_cache) == list(range(len(ds)))
        for i in range(len(ds)):
            torch.testing.assert_close(ds._dist_cache[i], mask_distance(ds._decoded(i)[1]), rtol=0, atol=0)
    assert not dm2.datasets["train"]._dist_cache  # not cached: made when a sample is read


def test_pose_inputs_are_made_once_per_frame(scene_root, body, monkeypatch):
    """Every camera of a frame and every epoch reuse the frame's pose inputs (2 ms of host time per sample on the
    sweep scene), and a collated batch does not share memory with them."""
    from realityavatar.data import datamodule

    calls = []
    real = datamodule.pose_inputs
    monkeypatch.setattr(datamodule, "pose_inputs", lambda *a: calls.append(1) or real(*a))
    dm = make(scene_root, body)
    ds = dm.datasets["train"]  # 8 frames x 3 cameras
    first = [ds[i] for i in range(len(ds))]
    assert len(calls) == 8
    again = ds[5]
    assert len(calls) == 8 and torch.equal(again["pose_features"], first[5]["pose_features"])
    b = next(iter(dm.train_dataloader()))
    b["pose_features"].zero_()
    assert not torch.equal(ds[int(b["index"][0])]["pose_features"], b["pose_features"][0])


def test_missing_scene_folder_error_says_how_to_get_it(tmp_path):
    """The folder could be I3D-Human's (downloaded) or an embedded scene's (built): the error says both."""
    dm = AvatarDataModule(str(tmp_path), "demo_skirt_spin", I3DReader(1))
    with pytest.raises(FileNotFoundError, match=r"scene folder .*demo_skirt_spin-train not found; I3D-Human: download "
                                                r"it .* set I3D_ROOT or data\.root; an embedded scene: build it with"):
        dm.setup()


def test_bad_arguments_fail_fast():
    with pytest.raises(TypeError, match=r"data\.reader: expected a scene reader .*, got 'i3d'"):
        AvatarDataModule("x", "y", reader="i3d")  # a config from before the readers were components
    with pytest.raises(ValueError, match="background"):
        AvatarDataModule("x", "y", I3DReader(1), background=[0, 0])
    with pytest.raises(TypeError, match=r"data.device_cache: expected true or false, got .no."):
        AvatarDataModule("x", "y", I3DReader(1), device_cache="no")
    with pytest.raises(ValueError, match=r"data\.reader\.frame_interval: expected a whole number >= 1"):
        I3DReader(0)


def test_build_preset_builds_missing_scene(tmp_path, body, monkeypatch):
    from realityavatar.data import synthetic

    calls = []

    def fake_build(preset, root, seed=0, *, sequence=None, **_):
        calls.append((preset, str(root), seed, sequence))
        write_i3d(root, f"{sequence}_{preset}", body, train_frames=(0, 1), pose_frames=(2,), train_views=(0,),
                  test_views=(1,))
        return Path(root) / f"{sequence}_{preset}"

    monkeypatch.setattr(synthetic, "build_scene", fake_build)
    dm = AvatarDataModule(str(tmp_path), "skirt_spin_ci", I3DReader(1), body=body, build_preset="ci",
                          build_sequence="skirt_spin")
    dm.prepare_data()
    dm.setup()
    assert calls == [("ci", str(tmp_path), 0, "skirt_spin")] and dm.num_train_frames == 2
    bad = AvatarDataModule(str(tmp_path), "other_name", I3DReader(1), body=body, build_preset="ci",
                           build_sequence="skirt_spin")
    with pytest.raises(FileNotFoundError, match="set data.sequence to 'skirt_spin_ci'"):
        bad.prepare_data()


def test_zju_datamodule(tmp_path, body):
    write_zju(tmp_path, "CoreView_377", body, n_frames=6, cams=("1", "2", "3"))
    from realityavatar.data.zju import ZJUReader

    reader = ZJUReader(train_frames=[0, 4, 1], novel_view_frames=[0, 4, 2], novel_pose_frames=[4, 0, 1])
    dm = AvatarDataModule(str(tmp_path), "CoreView_377", reader, body=body, train_views=[1], test_views=[2, 3],
                          window_len=2, window_step=1, background=[1, 1, 1], image_scale=0.5)
    dm.setup()
    assert dm.train_frame_ids == [0, 1, 2, 3] and dm.image_size == (SIZE // 2, SIZE // 2)
    s = dm.datasets["novel_pose"][0]
    assert s["frame"] == 4 and s["frame_idx"] == -1 and s["view"] == 2
    c = composite(default_collate([s]))
    assert torch.allclose(c["image"][0][c["mask"][0, ..., 0] == 0], torch.ones(3))  # the jpg's background is replaced
    # a frame range that selects no training frame: the data module says so, naming the reader
    empty = ZJUReader(train_frames=[3, 3, 1], novel_view_frames=None, novel_pose_frames=[4, 0, 1])
    with pytest.raises(ValueError, match=r"CoreView_377: the reader selected no training images .*ZJUReader"):
        AvatarDataModule(str(tmp_path), "CoreView_377", empty, body=body, train_views=[1], test_views=[2]).setup()


def _datasets(pattern: str) -> list[Path]:
    """conf/data options that are datasets: the *_base files hold shared settings only."""
    return sorted(p for p in (CONF / "data").glob(pattern) if not p.stem.endswith("_base"))


@pytest.mark.parametrize("path", _datasets("*.yaml"), ids=lambda p: p.stem)
def test_every_data_config_instantiates(path, body, monkeypatch):
    """Invariants each data config must keep (no YAML value re-typed here): disjoint train/test cameras, and for
    ZJU-MoCap every one of its 23 cameras used once."""
    from realityavatar.data.zju import ZJUReader

    monkeypatch.delenv("I3D_ROOT", raising=False)
    dm = instantiate(compose_data(path.stem), body=body)
    assert isinstance(dm, AvatarDataModule) and dm.body is body
    if dm.train_views is not None and dm.test_views is not None:
        assert not set(dm.train_views) & set(dm.test_views), "a camera is in both the training and the test split"
    if isinstance(dm.reader, ZJUReader):
        assert sorted(dm.train_views + dm.test_views) == list(range(1, 24))


@pytest.mark.parametrize("path", _datasets("synthetic_*.yaml"), ids=lambda p: p.stem)
def test_synthetic_configs_build_the_scene_they_read(path, monkeypatch):
    """A synthetic data config's build settings (preset, sequence, overrides such as synthetic_sweep_soft's cloth)
    resolve to valid scene parameters whose scene name is the `sequence` the reader opens, so prepare_data builds the
    scene the run reads instead of failing after the build."""
    from realityavatar.data.synthetic.cloth import garment_params
    from realityavatar.data.synthetic.scene import resolve_params

    monkeypatch.delenv("REALITYAVATAR_SCENES", raising=False)
    cfg = compose_data(path.stem)
    overrides = cfg.get("build_overrides")
    overrides = OmegaConf.to_container(overrides, resolve=True) if overrides is not None else {}
    p = resolve_params(cfg.build_preset, cfg.build_sequence, overrides)
    assert p["name"] == cfg.sequence
    garment_params(p["garment"], p["cloth_params"])  # unknown or bad cloth keys raise here


@pytest.mark.parametrize("path", _datasets("i3d_*.yaml"), ids=lambda p: p.stem)
def test_i3d_configs_read_their_layout(path, body, tmp_path):
    """Each I3D-Human config, pointed at a fixture folder in the published layout holding every camera 0..10, reads
    exactly its own training and test cameras and gives pose windows of its own length."""
    cfg = compose_data(path.stem)
    write_i3d(tmp_path, cfg.sequence, body, train_frames=(0, 1), pose_frames=(2,), train_views=tuple(range(11)),
              test_views=tuple(range(11)))
    cfg.root = str(tmp_path)
    dm = instantiate(cfg, body=body)
    dm.setup("fit")
    seen = {split: {int(r.view) for r in ds.records} for split, ds in dm.datasets.items()}
    assert seen["train"] == set(cfg.train_views)
    assert seen["novel_view"] == seen["novel_pose"] == set(cfg.test_views)
    assert dm.datasets["train"][0]["poses"].shape == (cfg.window_len, 24, 3)


@pytest.mark.parametrize("path", sorted((CONF / "data").glob("*_base.yaml")), ids=lambda p: p.stem)
def test_base_data_configs_are_not_datasets(path, body):
    """`data=i3d_base` (or another *_base) without a sequence stops at once, naming the missing key."""
    from omegaconf.errors import MissingMandatoryValue

    with pytest.raises(MissingMandatoryValue, match="data.sequence"):
        instantiate(compose_data(path.stem), body=body)


def test_paper_camera_splits():
    """The camera splits of the paper's I3D-Human protocol (transcribed from its experiments section), which the
    configs must reproduce: the one place the expected numbers come from outside the YAML."""
    splits = {"ID1_1": ([1, 3, 6, 8], [2, 4, 7, 9]), "ID1_2": ([0, 2, 5, 7], [1, 6, 8, 9]),
              "ID2_1": ([1, 3, 5, 7, 9], [2, 4, 6, 10]), "ID3_1": ([1, 3, 5, 7, 9], [2, 4, 6, 8, 10])}
    for seq, (tr, te) in splits.items():
        cfg = compose_data(f"i3d_{seq}")
        assert (cfg.sequence, list(cfg.train_views), list(cfg.test_views)) == (seq, tr, te)


@pytest.mark.slow
def test_synthetic_ci_scene_joints_inside_masks(scenes_root):
    """The generator's real ci scene (the session's, built once) read through synthetic_ci.yaml: every sampled joint
    lands inside its mask."""
    from realityavatar.body.mannequin import MannequinBody

    body = MannequinBody()
    cfg = compose_data("synthetic_ci")
    cfg.root = str(scenes_root)
    dm = instantiate(cfg, body=body)
    dm.prepare_data()
    dm.setup()
    for ds in dm.datasets.values():
        for i in range(0, len(ds), 5):
            s = ds[i]
            J = body.joints(s["poses"][-1], s["transl"][-1]).double().numpy()
            for j in (0, 3, 6, 9, 12, 15):
                u, v = project(s["K"].double().numpy(), s["viewmat"].double().numpy(), J[j])
                assert s["inside"][int(v), int(u), 0]
    assert np.isfinite(dm.scene_extent)


def test_hard_frame_sampler_draws_frames_in_proportion_to_their_loss():
    """After a uniform first pass, a frame whose images had 9x the loss of the others is drawn about as often as
    mix/n + (1-mix) * 9/(9 + n_frames - 1) predicts; every draw is one of that frame's cameras; a resumed sampler
    continues with the draws the uninterrupted one makes."""
    from realityavatar.data.samplers import HardFrameSampler

    frames = [f for f in range(10) for _ in range(4)]  # 10 frames x 4 cameras, image i belongs to frame i // 4
    s = HardFrameSampler(frames, seed=3, mix=0.5, power=1.0, ema=1.0)
    first = list(s)
    assert sorted(first) == list(range(40))  # the first epoch is a plain permutation
    s.observe(torch.arange(40), torch.tensor([9.0 if frames[i] == 7 else 1.0 for i in range(40)]))
    p = s.frame_probabilities()
    assert p[7] == pytest.approx(9 / 18) and p[0] == pytest.approx(1 / 18)
    draws = [i for _ in range(50) for i in s]
    share = np.mean([frames[i] == 7 for i in draws])
    expected = 0.5 / 10 + 0.5 * 9 / 18
    assert abs(share - expected) < 0.03, (share, expected)
    cams = {i % 4 for i in draws if frames[i] == 7}
    assert cams == {0, 1, 2, 3}
    # resume mid-epoch from the state dict
    state = s.state_dict()
    it = iter(s)
    head = [next(it) for _ in range(7)]
    state_mid = s.state_dict()
    rest = list(it)
    t = HardFrameSampler(frames, seed=3, mix=0.5, power=1.0, ema=1.0)
    t.load_state_dict(state_mid)
    assert list(t) == rest and len(head) + len(rest) == 40
    assert state["score"][7] == 9.0


def test_sampler_feedback_passes_per_image_losses_to_the_sampler():
    """SamplerFeedback hands the training step's per-image losses to the sampler by dataset index."""
    from types import SimpleNamespace

    from realityavatar.data.lightning import SamplerFeedback
    from realityavatar.data.samplers import HardFrameSampler

    s = HardFrameSampler([0, 0, 1, 1], seed=0)
    trainer = SimpleNamespace(datamodule=SimpleNamespace(train_sampler=s))
    batch = {"index": torch.tensor([2, 0])}
    SamplerFeedback().on_train_batch_end(trainer, None, {"loss": 1.0, "image_loss": torch.tensor([4.0, 2.0])},
                                         batch, 0)
    assert s.observed == 2 and s.score.tolist() == [2.0, 4.0]


def test_sampler_feedback_on_a_gpu_reads_once_per_log_step():
    """Losses on a GPU wait on the device until a log step, then reach the sampler in step order, in one copy."""
    from types import SimpleNamespace

    from realityavatar.data.lightning import SamplerFeedback
    from realityavatar.data.samplers import HardFrameSampler

    class OnGpu(torch.Tensor):  # reports a GPU device: the callback keeps it until a log step
        @property
        def device(self):
            return torch.device("cuda")

    steps = [([0, 2], [1.0, 3.0]), ([2, 1], [5.0, 2.0]), ([3, 0], [4.0, 6.0])]
    s, reference = HardFrameSampler([0, 0, 1, 1], seed=0), HardFrameSampler([0, 0, 1, 1], seed=0)
    feedback = SamplerFeedback()
    trainer = SimpleNamespace(datamodule=SimpleNamespace(train_sampler=s), log_every_n_steps=3)
    for step, (index, loss) in enumerate(steps):
        trainer.global_step = step + 1
        feedback.on_train_batch_end(trainer, None, {"image_loss": torch.tensor(loss).as_subclass(OnGpu)},
                                    {"index": torch.tensor(index)}, 0)
        assert s.observed == (6 if step == 2 else 0)
        reference.observe(torch.tensor(index), torch.tensor(loss))
    assert torch.equal(s.score, reference.score)


def test_unknown_sampler_option_names_the_field(scene_root, body):
    """The sampler is built from conf/sampler like every other group (_target_ + _partial_, called with the training
    images' frames and the seed): each option gives its class, a value that is not a sampler names data.sampler, an
    unknown option names itself, an unknown sampler names the group."""
    from realityavatar.config import compose
    from realityavatar.data.samplers import EpochShuffle, HardFrameSampler

    for name, cls in (("uniform", EpochShuffle), ("hard_frames", HardFrameSampler)):
        dm = make(scene_root, body, sampler=instantiate(compose([f"sampler={name}"]).data.sampler))
        dm.train_dataloader()
        assert type(dm.train_sampler) is cls
    with pytest.raises(TypeError, match="data.sampler"):
        make(scene_root, body, sampler={"kind": "hard_frames"})
    bad = compose(["sampler=hard_frames", "+data.sampler.temperature=2"]).data.sampler
    dm = make(scene_root, body, sampler=instantiate(bad))
    with pytest.raises(TypeError, match="temperature"):
        dm.train_dataloader()
    with pytest.raises(Exception, match="sampler"):
        compose(["sampler=hardest"])


def test_reader_options_belong_to_their_reader(body):
    """Each layout's options are its reader's: a key the chosen reader does not take, or one left at the data
    module's level from before the readers were components, is an error naming it."""
    from hydra.errors import InstantiationException

    from realityavatar.config import compose

    for override, name in (("+data.reader.train_frames=[0,4,1]", "train_frames"),
                           ("+data.zju_train_frames=[0,4,1]", "zju_train_frames"),
                           ("+data.frame_interval=3", "frame_interval")):
        with pytest.raises(InstantiationException, match=f"unexpected keyword argument '{name}'"):
            instantiate(compose(["data=synthetic_ci", override]).data, body=body)
    with pytest.raises(InstantiationException, match="unexpected keyword argument 'frame_interval'"):
        instantiate(compose(["data=zju_377_mono", "+data.reader.frame_interval=3"]).data, body=body)


def test_missing_scene_folder_is_named(tmp_path, body):
    from realityavatar.config import compose

    cfg = compose(["data=synthetic_ci", f"data.root={tmp_path / 'nowhere'}"])
    with open_dict(cfg):
        cfg.data.build_preset = None
    dm = instantiate(cfg.data, body=body)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        dm.prepare_data()
        dm.setup("fit")


def test_batches_are_pinned_when_the_trainer_runs_on_a_gpu(scene_root, body):
    """Every loader pins its batches when the trainer's device is a GPU (their copies then wait for no kernel), not
    on a CPU or without a trainer (TrainingData.setup gives the data the trainer's device)."""
    dm = make(scene_root, body, device_cache=False)  # a GPU's training set would move there (needs CUDA)
    assert not dm.train_dataloader().pin_memory
    for device, pinned in (("cpu", False), ("cuda", True)):
        dm.device = torch.device(device)
        loaders = [dm.train_dataloader(), dm.val_dataloader(), *dm.test_dataloader()]
        assert [loader.pin_memory for loader in loaders] == [pinned] * len(loaders)


def test_device_cache_serves_the_host_batches_from_the_device(scene_root, body, monkeypatch):
    """data.device_cache: the training set kept on the device gives the trainer the batches the host path gives (every
    entry, value and dtype; one and three views per frame), its loader carries the host entries only, test batches
    keep the host path, and a set larger than half the GPU's free memory stays on the host. The set is made for a
    GPU; here it is kept on the CPU to compare."""
    from types import SimpleNamespace

    from realityavatar.data.lightning import TrainingData

    trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device("cpu")), training=True)
    cpu = torch.device("cpu")
    for kw in ({}, {"views_per_step": 3, "batch_size": 2}):
        host = make(scene_root, body, device_cache=False, **kw)
        dev = make(scene_root, body, shuffle_seed=host.shuffle_seed, **kw)
        monkeypatch.setattr(dev, "_store_device", lambda: cpu)
        th, td = TrainingData(host), TrainingData(dev)
        th.trainer = td.trainer = trainer
        a_batches, b_batches = list(host.train_dataloader()), list(dev.train_dataloader())
        assert host.device_samples is None and len(dev.device_samples) == len(dev.datasets["train"])
        assert len(a_batches) == len(b_batches)
        for a, b in zip(a_batches, b_batches):
            assert "pixels" not in b and not any(torch.is_tensor(v) and v.ndim > 1 for v in b.values())
            a = th.transfer_batch_to_device(th.on_before_batch_transfer(a, 0), cpu, 0)
            b = td.transfer_batch_to_device(td.on_before_batch_transfer(b, 0), cpu, 0)
            assert a.keys() == b.keys()
            for k, v in a.items():
                if torch.is_tensor(v):
                    assert v.dtype == b[k].dtype and torch.equal(v, b[k]), k
                else:
                    assert v == b[k], k
    test_batch = next(iter(dev.test_dataloader()[0]))
    moved = td.transfer_batch_to_device(test_batch, cpu, 0)
    assert torch.equal(moved["pixels"], test_batch["pixels"]) and torch.equal(moved["index"], test_batch["index"])
    full = make(scene_root, body)
    monkeypatch.setattr(full, "_store_device", lambda: torch.device("cuda"))
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (1 << 20, 1 << 30))  # 1 MiB free
    full.train_dataloader()
    assert full.device_samples is None and full.training_set.startswith("host: its 24 samples would take")


@pytest.mark.gpu
def test_device_cache_on_a_gpu_keeps_the_set_there_and_serves_the_host_batches(scene_root, body):
    """On a GPU trainer the training set moves there (data.device_cache): each batch's tensors come from it, equal to
    the pinned host batch moved there, and its entries are the host path's."""
    from types import SimpleNamespace

    from realityavatar.data.lightning import TrainingData

    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    gpu = torch.device("cuda")
    trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=gpu), training=True)
    host = make(scene_root, body, device_cache=False)
    dev = make(scene_root, body, shuffle_seed=host.shuffle_seed)
    host.device = dev.device = gpu
    th, td = TrainingData(host), TrainingData(dev)
    th.trainer = td.trainer = trainer
    a_loader, b_loader = host.train_dataloader(), dev.train_dataloader()
    assert dev.training_set["device"].startswith("cuda") and host.device_samples is None
    for a, b in zip(a_loader, b_loader):
        a = th.transfer_batch_to_device(th.on_before_batch_transfer(a, 0), gpu, 0)
        b = td.transfer_batch_to_device(td.on_before_batch_transfer(b, 0), gpu, 0)
        assert a.keys() == b.keys()
        for k, v in a.items():
            if torch.is_tensor(v):
                assert b[k].device.type == "cuda" and v.dtype == b[k].dtype and torch.equal(v, b[k]), k
            else:
                assert v == b[k], k
