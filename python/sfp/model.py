"""Sparse Feature Pyramid (SFP) network: a U-Net autoencoder whose skip connections are
sparsified by per-pixel score heads (Potapov et al., see ../shared/PAPER.md).

Geometry (the contract relies on it, see spec/extractor.md):
every encoder block starts with MaxPool2d(3, 2, 1), which maps a size n to ceil(n / 2), so level i
(stride s_i) has size ceil(H / s_i) x ceil(W / s_i) for ANY H, W -- no padding is needed. Cell (r, c)
of a stride-s level is centred on input pixel index (s*r, s*c) (pixel-centre convention where the
first pixel's centre is 0; add 0.5 for COLMAP's convention).
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

# Default configuration of sfp-v1.
STRIDES = (2, 4, 8, 16)
DIMS = (16, 32, 64, 128)
STEM = 16


def conv3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


class EncoderBlock(nn.Module):
    """Paper block MaxPool(3,2,1) -> BN -> ReLU -> Conv, followed by one more BN -> ReLU -> Conv."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.pool = nn.MaxPool2d(3, 2, 1)
        self.bn1 = nn.BatchNorm2d(cin)
        self.conv1 = conv3(cin, cout)
        self.bn2 = nn.BatchNorm2d(cout)
        self.conv2 = conv3(cout, cout)

    def forward(self, x):
        x = self.conv1(F.relu(self.bn1(self.pool(x))))
        return self.conv2(F.relu(self.bn2(x))) + x


class DecoderBlock(nn.Module):
    """Upsample (to the skip's exact size) + conv, conv, ReLU."""

    def __init__(self, cin: int, cskip: int, cout: int):
        super().__init__()
        self.conv1 = conv3(cin + cskip, cout)
        self.conv2 = conv3(cout, cout)

    def forward(self, x, skip, size):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        if skip is not None:
            x = torch.cat([x, skip], 1)
        return F.relu(self.conv2(F.relu(self.conv1(x))))


STEM_MODES = ("full", "strided", "strided1")


class SFP(nn.Module):
    """stem_mode "full" (sfp-v1): two 3x3 convolutions at full resolution, then the first encoder
    block's MaxPool (about 40 % of the MACs at 640x480). The students of python/distill_v2.py skip
    full resolution: "strided" = a 3x3 stride-2 conv straight from the image, ReLU, one 3x3 conv at
    stride 2 (receptive field 7 px, as v1's MaxPool output); "strided1" = the stride-2 conv alone.
    Both drop the first block's MaxPool; a 3x3 stride-2 conv with padding 1 maps n to ceil(n / 2) and
    centres cell r on pixel 2r, so level sizes and the cell <-> pixel rule are v1's. Their weights are
    named `stem_s2.*`: a student state dict never loads silently into a full-stem net or vice versa
    (SFP.for_state_dict picks the mode from the names)."""

    def __init__(self, strides=STRIDES, dims=DIMS, stem=STEM, rate_init=(0.1, 0.15, 0.2, 0.3),
                 stem_mode: str = "full", glob_head: bool = False):
        super().__init__()
        assert len(strides) == len(dims)
        for a, b in zip(strides, strides[1:]):
            assert b == 2 * a
        assert stem_mode in STEM_MODES, stem_mode
        self.strides = tuple(strides)
        self.dims = tuple(dims)
        self.stem_mode = stem_mode
        if stem_mode == "full":
            self.stem = nn.Sequential(conv3(1, stem), nn.ReLU(inplace=True), conv3(stem, stem))
        elif stem_mode == "strided":
            self.stem_s2 = nn.Sequential(nn.Conv2d(1, stem, 3, stride=2, padding=1), nn.ReLU(inplace=True),
                                         conv3(stem, stem))
        else:  # the first block's BN -> ReLU follows: no ReLU of its own
            self.stem_s2 = nn.Sequential(nn.Conv2d(1, stem, 3, stride=2, padding=1))
        # blocks from full resolution down to strides[0]
        n_pre = int(math.log2(strides[0])) - 1  # blocks before the first level (strides[0]=2 -> 0)
        pre = []
        c = stem
        for _ in range(n_pre):
            pre.append(EncoderBlock(c, c))
        self.pre = nn.Sequential(*pre)
        enc = []
        for d in dims:
            enc.append(EncoderBlock(c, d))
            c = d
        self.enc = nn.ModuleList(enc)
        if stem_mode != "full":  # the stem already halved the size: the first pooling block doesn't
            self.first_block().pool = nn.Identity()
        self.score_heads = nn.ModuleList([nn.Conv2d(d, 1, 1) for d in dims])
        for h, r in zip(self.score_heads, rate_init):
            nn.init.normal_(h.weight, std=0.01)
            nn.init.constant_(h.bias, float(torch.logit(torch.tensor(r))))
        # decoder: deepest level -> ... -> level 0 -> full resolution
        dec = []
        cin = dims[-1]
        for d in reversed(dims[:-1]):
            dec.append(DecoderBlock(cin, d, d))
            cin = d
        self.dec = nn.ModuleList(dec)
        self.dec_full = DecoderBlock(cin, 0, stem)
        self.out = nn.Conv2d(stem, 1, 3, padding=1)
        # Optional retrieval head (`glob_head.*`): 1x1 conv to 2x the deepest dims, ReLU, GeM, a
        # linear whitening back to the deepest dims, L2. It reads the deepest features detached,
        # so training it for retrieval leaves every local descriptor and score as it was
        # (python/distill_v2.py --set glob_head=true). Without it: GeM of the features (v1).
        self.glob_head = None
        if glob_head:
            d = dims[-1]
            self.glob_head = nn.ModuleDict(dict(conv=nn.Conv2d(d, 2 * d, 1), white=nn.Linear(2 * d, d)))

    @classmethod
    def for_state_dict(cls, sd: dict, **kw) -> "SFP":
        """An SFP whose stem mode matches the state dict's weight names (loaded, strict)."""
        mode = ("strided" if "stem_s2.2.weight" in sd else "strided1" if "stem_s2.0.weight" in sd
                else "full")
        net = cls(stem_mode=mode, glob_head=any(k.startswith("glob_head.") for k in sd), **kw)
        net.load_state_dict(sd)
        return net

    def first_block(self) -> EncoderBlock:
        """The block whose MaxPool the strided stems replace: its bn1 input is at stride 2 in every
        stem mode (the distillation's stem hint)."""
        return self.pre[0] if len(self.pre) else self.enc[0]

    # -- encoder / scores ---------------------------------------------------------------------
    def encode(self, x):
        x = self.pre(self.stem(x) if self.stem_mode == "full" else self.stem_s2(x))
        feats = []
        for blk in self.enc:
            x = blk(x)
            feats.append(x)
        logits = [h(f) for h, f in zip(self.score_heads, feats)]
        return feats, logits

    @staticmethod
    def gem(f, p: float = 3.0):
        """GeM pooling of the (ReLU'd) features over the image, [N, C]."""
        return F.relu(f).clamp(min=1e-6).pow(p).mean(dim=(2, 3)).pow(1.0 / p)

    def global_desc(self, f_deep):
        """The global descriptor of the deepest features: the retrieval head's if the net has one,
        else their GeM; L2-normalised."""
        if self.glob_head is None:
            return F.normalize(self.gem(f_deep), dim=1)
        g = self.gem(self.glob_head["conv"](f_deep.detach()))
        return F.normalize(self.glob_head["white"](g), dim=1)

    # -- full autoencoder pass (training) --------------------------------------------------------
    def forward(self, x, hard: bool | None = None):
        """Returns dict(feats, logits, probs, masks, recon, global).

        Training: m ~ Bernoulli(p) with a straight-through estimator (forward uses the hard sample,
        backward the gradient of p). Eval: m = p.
        """
        feats, logits = self.encode(x)
        probs = [torch.sigmoid(l) for l in logits]
        if hard is None:
            hard = self.training
        masks = []
        for p in probs:
            if hard:
                m = (torch.rand_like(p) < p).to(p.dtype)
                m = m + p - p.detach()
            else:
                m = p
            masks.append(m)
        sparse = [f * m for f, m in zip(feats, masks)]
        y = sparse[-1]
        for i, blk in enumerate(self.dec):
            lvl = len(self.dims) - 2 - i
            y = blk(y, sparse[lvl], sparse[lvl].shape[-2:])
        y = self.dec_full(y, None, x.shape[-2:])
        recon = torch.sigmoid(self.out(y))
        return dict(feats=feats, logits=logits, probs=probs, masks=masks, recon=recon,
                    glob=self.global_desc(feats[-1]))


class SFPExtractor(nn.Module):
    """The inference graph shipped as ONNX: image -> (feat_i, score_i)_i, global. No decoder."""

    def __init__(self, net: SFP):
        super().__init__()
        self.net = net

    def forward(self, image):
        feats, logits = self.net.encode(image)
        outs = []
        for f, l in zip(feats, logits):
            outs.append(f)
            outs.append(torch.sigmoid(l))
        outs.append(self.net.global_desc(feats[-1]))
        return tuple(outs)


def output_names(n_levels: int):
    names = []
    for i in range(n_levels):
        names += [f"feat_{i}", f"score_{i}"]
    return names + ["global"]
