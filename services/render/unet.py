"""A small U-Net that fills the holes of a filtered point splat (input RGB + validity + depth -> RGB).

The published renderer uses a 31 M-parameter U-Net; this one has a few hundred thousand
parameters because it runs on every frame, on a CPU too. Inputs:

- ``rgb``   (B,3,H,W) in [0,1], zero in holes
- ``mask``  (B,1,H,W) 1 where a point survived the depth filter
- ``depth`` (B,1,H,W) metres, 0 in holes; fed as median-normalised inverse depth (scale free)

Output: (B,3,H,W) in [0,1]. The network predicts a residual on top of the input, so measured
pixels pass through nearly unchanged and the capacity goes into the holes.
Weights ship in ``services/render/weights/`` with a model card (MODEL_CARD.md).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["HoleFillNet", "SIZES", "load_holefill", "default_weights_path", "normalise_depth"]

SIZES = {"tiny": (8, 16, 24, 32), "small": (12, 24, 48, 64), "base": (16, 32, 64, 128)}
DEFAULT_SIZE = "tiny"  # as good as "small" on held-out views at 1/3.5 of the cost (benchmarks/RESULTS.md)


def normalise_depth(depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Median-normalised inverse depth in [0, 4], 0 in holes: the same for a room and a hall."""
    B = depth.shape[0]
    out = torch.zeros_like(depth)
    for b in range(B):
        v = depth[b][mask[b] > 0]
        med = v.median() if v.numel() else depth.new_tensor(1.0)
        out[b] = torch.where(mask[b] > 0, (med / depth[b].clamp_min(1e-3)).clamp(0, 4), torch.zeros_like(depth[b]))
    return out


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True))


class HoleFillNet(nn.Module):
    def __init__(self, channels: tuple[int, ...] = SIZES[DEFAULT_SIZE]):
        super().__init__()
        self.channels = tuple(channels)
        c = self.channels
        self.enc = nn.ModuleList([_block(5, c[0])] + [_block(c[i - 1], c[i]) for i in range(1, len(c))])
        self.dec = nn.ModuleList([_block(c[i] + c[i - 1], c[i - 1]) for i in range(len(c) - 1, 0, -1)])
        self.head = nn.Conv2d(c[0], 3, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    @property
    def stride(self) -> int:
        return 2 ** (len(self.channels) - 1)

    def forward(self, rgb: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        H, W = rgb.shape[-2:]
        s = self.stride
        ph, pw = (-H) % s, (-W) % s
        x = torch.cat([rgb * mask, mask, normalise_depth(depth, mask)], 1)
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        skips = []
        for i, blk in enumerate(self.enc):
            if i:
                x = F.max_pool2d(x, 2)
            x = blk(x)
            skips.append(x)
        for j, blk in enumerate(self.dec):
            skip = skips[-2 - j]
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = blk(torch.cat([x, skip], 1))
        base = F.pad(rgb * mask, (0, pw, 0, ph)) if (ph or pw) else rgb * mask
        out = base + self.head(x)
        return out[..., :H, :W].clamp(0, 1)

    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


def default_weights_path(size: str = DEFAULT_SIZE) -> Path:
    return Path(str(resources.files("services.render") / "weights" / f"holefill_{size}.pt"))


def load_holefill(path: str | Path | None = None, device: str | torch.device = "cpu") -> HoleFillNet:
    """Load shipped (or given) weights; the file stores the channel widths next to the state dict."""
    path = Path(path) if path else default_weights_path()
    if not path.exists():
        raise FileNotFoundError(f"{path}: hole-filling weights not found (train with 'cristal train-renderer')")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    net = HoleFillNet(tuple(blob["channels"]))
    net.load_state_dict(blob["state_dict"])
    return net.eval().to(device)
