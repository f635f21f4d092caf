"""A small random stand-in for training.data.dataset.LightStageDataset (same keys, shapes and
units), for the training tests only: fast, deterministic, and independent of the light stage."""

import numpy as np

from addon import contract

K = len(contract.PARSING_CLASSES)


def sample(res: int = 64, seed: int = 0, shift: int = 1) -> dict:
    """One pair of frames: frame t+1 is frame t moved ``shift`` pixels right, with exact flows."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:res, 0:res].astype(np.float32) / res
    mask = (((xx - 0.5) ** 2 + (yy - 0.5) ** 2) < 0.12).astype(np.float32)[None]
    base = 0.2 + rng.random((3, res, res), dtype=np.float32) * 0.5

    def move(a):
        return np.roll(a, shift, axis=-1)

    light = lambda: rng.random((16, 16, 3), dtype=np.float32) * 2.0  # noqa: E731
    li, lj, lk = light(), light(), light()
    img_t = base * mask * 3.0
    gt_t = img_t * 0.7
    parsing = np.concatenate([mask] + [mask * (rng.random((1, res, res)) > 0.5)
                                       for _ in range(K - 1)]).astype(np.float32)
    flow_fw = np.zeros((2, res, res), np.float32)
    flow_fw[0] = shift
    valid = np.ones((1, res, res), np.float32)
    valid[..., -shift:] = 0
    valid_bw = np.ones((1, res, res), np.float32)
    valid_bw[..., :shift] = 0
    return {"img_t_i": img_t, "img_t1_j": move(img_t) * 1.1, "gt_t_k": gt_t, "gt_t1_k": move(gt_t),
            "light_i": li, "light_j": lj, "light_k": lk, "mask_t": mask, "mask_t1": move(mask),
            "parsing_t": parsing, "parsing_t1": move(parsing), "flow_fw": flow_fw,
            "flow_bw": -flow_fw, "valid_fw": valid, "valid_bw": valid_bw}


class StandinDataset:
    def __init__(self, split="train", resolution=64, seed=0, n=4):
        self.res, self.seed, self.n = resolution, seed, n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return sample(self.res, self.seed * 1000 + i)


def perturbed_net(cfg, seed: int = 0, scale: float = 0.05):
    """A RelightNet of ``cfg`` in eval mode, its weights moved off the identity start by
    ``scale`` * N(0, 1) (seeded), so every output depends on the weights and the light."""
    import torch

    from training.model import network

    torch.manual_seed(seed)
    net = network.RelightNet(cfg)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(scale * torch.randn_like(p))
    return net.eval()
