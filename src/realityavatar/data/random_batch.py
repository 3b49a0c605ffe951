"""A DataModule-shaped batch of random targets for a body model: what benchmarks/step.py times a training step on and
the model's tests step with (a scene to read is not needed)."""

from __future__ import annotations

import math

import torch

from realityavatar.data.records import mask_distance
from realityavatar.model.avatar import pose_inputs


def look_at(campos, target, up):
    """World-to-camera OpenCV matrix (z forward, y down) for a camera at campos looking at target."""
    z = torch.nn.functional.normalize(target - campos, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, up), dim=0)
    y = torch.linalg.cross(z, x)
    vm = torch.eye(4)
    vm[:3, :3] = torch.stack([x, y, z])
    vm[:3, 3] = -vm[:3, :3] @ campos
    return vm


def make_batch_fn(body, size: int, window: int, views: int = 1, device: str = "cpu"):
    """A DataModule-shaped batch: one pose window seen by `views` cameras framing the body (turned about the up axis),
    random target images and masks; made on `device` (a GPU: as training keeps the training set there)."""
    verts = body.canonical_vertices().detach().float().cpu()
    lo, hi = verts.min(0).values, verts.max(0).values
    centre, ext = 0.5 * (lo + hi), hi - lo
    up_axis = int(torch.argmax(ext))
    up = torch.zeros(3)
    up[up_axis] = 1.0
    side = (up_axis + 1) % 3
    campos = centre.clone()
    campos[side] -= 3.0
    vms = []
    for v in range(views):
        a = 2 * math.pi * v / views
        c, s_ = math.cos(a), math.sin(a)
        d = campos - centre
        k = torch.nn.functional.normalize(up, dim=0)
        d = d * c + torch.linalg.cross(k, d) * s_ + k * (k @ d) * (1 - c)  # Rodrigues about the up axis
        vms.append(look_at(centre + d, centre, up))
    vm = torch.stack(vms)
    f = 0.92 * size * 3.0 / float(ext[up_axis])
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    g = torch.Generator().manual_seed(0)
    # the images, masks and distance fields a dataset with cache_images (the demo's) holds: made once
    images = [torch.rand(views, size, size, 3, generator=g) for _ in range(4)]
    masks = [(torch.rand(views, size, size, 1, generator=g) > 0.5).float() for _ in images]
    dists = [torch.stack([mask_distance(m[..., 0]) for m in ms]) for ms in masks]
    host = body.host_copy()  # the dataset's copy, on the host
    windows = []  # pose windows and their pose inputs, made once per frame as the dataset makes them
    for _ in images:
        poses = (torch.randn(1, window, 24, 3, generator=g) * 0.1).expand(views, -1, -1, -1).clone()
        transl = torch.zeros(views, window, 3)
        windows.append({"poses": poses, "transl": transl, **pose_inputs(host, poses, transl)})

    if device != "cpu":  # the training set kept on the GPU, as training keeps it there (data.device_cache)
        images, masks, dists = ([t.to(device) for t in ts] for ts in (images, masks, dists))
        windows = [{name: x.to(device) for name, x in w.items()} for w in windows]
        vm, K = vm.to(device), K.to(device)

    def make():
        """Per sample, as the DataModule serves it: a frame's cached pose window and inputs, a cached image. On the
        CPU collation copies them; on a GPU they are the kept set's tensors, and only the frame index travels."""
        V = views
        k = int(torch.randint(len(images), (), generator=g))
        copy = (lambda x: x.clone()) if device == "cpu" else (lambda x: x)
        batch = {
            **{name: copy(x) for name, x in windows[k].items()},
            "frame_idx": torch.full((V,), 3),
            "viewmat": copy(vm),
            "K": K[None] if device != "cpu" and V == 1 else K[None].repeat(V, 1, 1),
            "image": images[k],
            "mask": masks[k],
            "mask_dist": dists[k],
        }
        if device != "cpu":  # the host entry (the frame index) pinned, copied without waiting for a kernel
            batch["frame_idx"] = batch["frame_idx"].pin_memory().to(device, non_blocking=True)
        # host ints and the views of one frame (data/lightning.py TrainingData, views_per_step=V)
        return {**batch, "width": [size] * V, "height": [size] * V, **({"views_per_frame": V} if V > 1 else {})}

    return make
