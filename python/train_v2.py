#!/usr/bin/env python3
"""Train SFP v2 on CPU, resumably (issue 17). Same network and ONNX contract as v1
(sfp-extractor/1: python/sfp/model.py); see python/TRAINING-v2.md.

Per step, one forward pass over n_hom homography pairs + n_mv multi-view pairs (crops of side `size`)
and, every `glob_every` steps, n_glob (anchor, co-visible positive) full images for the global
descriptor. Loss (weights in python/train_v2.json "w"; weight 0 switches a term off):
  rec     L1(recon, input)                        paper: reconstruction
  comp    sum_i (d_i/D) mean(p_i)                  paper: compression (expected floats kept)
  rate    sum_i (mean(p_i) - t_i)^2                keep-rate control per level (anti-collapse)
  alive   sum_i relu(alive_std - std(p_i))         no flat score map on any level
  h_desc  InfoNCE, cells of A vs homography-warped positions in B, per level
  h_rep   1 - local cosine(p_A, warped p_B)        homography repeatability
  h_peak  1 - (maxpool5 p - avgpool5 p)            peakiness
  h_rel   balanced BCE: p predicts a correct mutual-NN match (homography)
  mv_desc InfoNCE on true track correspondences of two map images, per level (negatives closer
          than one cell to the positive in either image are masked)
  mv_rep  (p_A - p_B)^2 at the two observations of each shared 3D point (detector repeatability)
  mv_rel  balanced BCE: p at track points predicts a correct mutual-NN match (multi-view)
  mv_trk  -log p at track points (SfM points are what a map keeps: score >= threshold)
  glob    InfoNCE of GeM global descriptors: anchor vs most co-visible database image, negatives =
          hardest non-co-visible images from a descriptor cache (memory bank)

Resumable: python/checkpoints/sfp-v2-state.pt (weights, AdamW moments in bf16, step, RNG states)
is written atomically every `ckpt_minutes` and on exit / SIGTERM, and read on start. The first run
starts from the encoder of models/sfp-v1.onnx (the decoder is not exported: it starts fresh and the
encoder gets no reconstruction gradient for `dec_warmup_steps`).

  nohup nice -n 19 python3 python/train_v2.py --minutes 150 > python/runs/v2-$(date +%Y%m%d-%H%M).log 2>&1 &
"""
from __future__ import annotations

import argparse
import copy
import csv
import glob
import json
import math
import os
import signal
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import train as T  # noqa: E402  (v1 helpers: warping, sampling, patch cosine, peakiness, validate)
from sfp import data as D  # noqa: E402
from sfp import multiview as MV  # noqa: E402
from sfp.config import apply_sets  # noqa: E402
from sfp.model import SFP  # noqa: E402

REPO = os.path.normpath(os.path.join(HERE, ".."))
DATA = D.DATA
STATE = os.path.join(HERE, "checkpoints", "sfp-v2-state.pt")
KITTI_SCENE = os.path.join(REPO, "target", "scenes", "kitti06")

STOP = {"flag": False, "sig": None}


def _on_signal(sig, _frame):
    STOP["flag"] = True
    STOP["sig"] = sig


# ----------------------------------------------------------------------------------------------
# data

def scene_dirs():
    """(name, scene dir) of the localization scenes whose map images are trained on."""
    out = [(os.path.basename(d), d) for d in sorted(glob.glob(os.path.join(DATA, "scenes", "*")))
           if os.path.exists(os.path.join(d, "sparse-map"))]
    if os.path.exists(os.path.join(KITTI_SCENE, "sparse-map")):
        out.append(("kitti06", KITTI_SCENE))
    else:
        raise SystemExit(f"{KITTI_SCENE} missing: build it with ../shared/data/tools/make_posed_scene.py "
                         "(see ../shared/data/sequences/README.md)")
    return out


def query_paths():
    """Every query image file: the scenes' queries.txt, and the KITTI 06 query frames in the
    original sequence folder too."""
    out = []
    for name, d in scene_dirs():
        for q in MV.read_queries(os.path.join(d, "queries.txt")):
            out.append(os.path.join(d, "images", q))
            if name == "kitti06":
                out.append(os.path.join(DATA, "sequences", "kitti06", "images", q))
    return [p for p in out if os.path.exists(p)]


FIXTURE_MODELS = [  # (name, model dir, images dir) of the COLMAP fixtures with sound models
    ("lund_door", "colmap/gtsfm_lund_door/colmap_ground_truth", "colmap/gtsfm_lund_door/images"),
    ("yding121", "colmap/yding121_video_frames/sparse/0", "colmap/yding121_video_frames/images"),
    ("bartoszek", "colmap/bartoszek_test_colmap/dense/0/sparse", "colmap/bartoszek_test_colmap/dense/0/images"),
]
VAL_MODEL = ("kapture", "colmap/kapture_maupertuis/reconstruction", "colmap/kapture_maupertuis/images")


def hom_files():
    """Images for homography pairs: train/, the scenes' map images, the COLMAP fixtures except the
    validation one."""
    files = []
    for root in sorted(glob.glob(os.path.join(DATA, "train", "*"))):
        files += D._list_images(root)
    for name, d in scene_dirs():
        q = set(MV.read_queries(os.path.join(d, "queries.txt")))
        files += [p for p in D._list_images(os.path.join(d, "images")) if os.path.basename(p) not in q]
    val = os.path.join(DATA, "colmap", "kapture_maupertuis")
    for root in sorted(glob.glob(os.path.join(DATA, "colmap", "*"))):
        if root == val or root.endswith("malformed"):
            continue
        files += D._list_images(root)
    return files


def load_scenes(max_side=1024):
    scenes = []
    for name, d in scene_dirs():
        q = MV.read_queries(os.path.join(d, "queries.txt"))
        scenes.append(MV.SfMScene(name, os.path.join(d, "sparse-map"), os.path.join(d, "images"),
                                  exclude=q, max_side=max_side))
    for name, m, i in FIXTURE_MODELS:
        scenes.append(MV.SfMScene(name, os.path.join(DATA, m), os.path.join(DATA, i), max_side=max_side))
    return scenes


# ----------------------------------------------------------------------------------------------
# model

def load_v1_encoder(net: SFP, onnx_path: str):
    import onnx
    from onnx import numpy_helper

    m = onnx.load(onnx_path)
    sd = net.state_dict()
    n = 0
    for init in m.graph.initializer:
        if init.name.startswith("net.") and init.name[4:] in sd:
            k = init.name[4:]
            v = torch.from_numpy(numpy_helper.to_array(init).copy())
            assert sd[k].shape == v.shape, (k, sd[k].shape, v.shape)
            sd[k] = v
            n += 1
    # Every exported tensor both ways, or the stems differ (a strided student's ONNX has its stem conv
    # and first BN folded together): load its .pt state instead (SFP.for_state_dict).
    names = {i.name for i in m.graph.initializer}
    unused = sorted(k[4:] for k in names if k.startswith("net.") and k[4:] not in sd)
    missing = sorted(k for k in sd if k.startswith(("stem", "pre.", "enc.", "score_heads."))
                     and not k.endswith("num_batches_tracked") and "net." + k not in names)
    if unused or missing:
        raise ValueError(f"{onnx_path} does not hold this network's encoder: unused {unused[:4]}, "
                         f"missing {missing[:4]}")
    net.load_state_dict(sd)
    return n


def forward_train(net: SFP, x, detach_dec=False):
    """SFP.forward (training, Bernoulli masks with straight-through) with the option to keep the
    reconstruction gradient out of the encoder (fresh decoder warm-up)."""
    feats, logits = net.encode(x)
    probs = [torch.sigmoid(l) for l in logits]
    masks = []
    for p in probs:
        m = (torch.rand_like(p) < p).to(p.dtype)
        m = m + p - p.detach()
        masks.append(m)
    sparse = [f * m for f, m in zip(feats, masks)]
    if detach_dec:
        sparse = [s.detach() for s in sparse]
    y = sparse[-1]
    for i, blk in enumerate(net.dec):
        lvl = len(net.dims) - 2 - i
        y = blk(y, sparse[lvl], sparse[lvl].shape[-2:])
    y = net.dec_full(y, None, x.shape[-2:])
    recon = torch.sigmoid(net.out(y))
    return dict(feats=feats, logits=logits, probs=probs, recon=recon)


class BNEval:
    """Context: BatchNorm layers in eval mode (running stats), gradients still flow."""

    def __init__(self, net):
        self.bns = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]

    def __enter__(self):
        self.was = [b.training for b in self.bns]
        for b in self.bns:
            b.eval()

    def __exit__(self, *a):
        for b, w in zip(self.bns, self.was):
            b.train(w)


def freeze_bn(net):
    """BatchNorm in eval mode (running statistics of v1, not updated; affine parameters still
    trained): training then optimises exactly the network that is exported (eval mode). With
    batch statistics in training, eval-mode behaviour drifted away within 250 steps (first try,
    python/curves/v2-run-20261201-2036*: level-3 keep rate 0.26 in training, 0.73 in eval)."""
    for m in net.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()


def global_of(net, im):
    x = torch.from_numpy(im)[None, None]
    feats, _ = net.encode(x)
    return net.global_desc(feats[-1])[0]


# ----------------------------------------------------------------------------------------------
# losses

def hom_terms(net, out, sl, A, B, H, V, cfg, logs):
    """v1's homography terms on the sub-batch `sl` = (A rows, B rows) of the forward pass."""
    ia, ib = sl
    N, S = A.shape[0], A.shape[-1]
    tot = dict(h_desc=0.0, h_rep=0.0, h_peak=0.0, h_rel=0.0)
    for i, s in enumerate(net.strides):
        f, p = out["feats"][i], out["probs"][i]
        fA, fB, pA, pB = f[ia], f[ib], p[ia], p[ib]
        h, w = fA.shape[-2:]
        grid = T.level_grid_coords(h, w, s, f.device).reshape(1, -1, 2).expand(N, -1, -1)
        q = T.warp_points(H, grid)
        vB = T.sample_map(V, q, 1)[..., 0] > 0.99
        ok = T.in_bounds(q, S, margin=s) & vB
        K = min(cfg["kpts_hom"], h * w)
        idx = (torch.rand(ok.shape) + ok.float() * 2).topk(K, dim=1).indices
        okk = torch.gather(ok, 1, idx)
        dA = F.normalize(torch.gather(fA.flatten(2).transpose(1, 2), 1, idx[..., None].expand(-1, -1, fA.shape[1])), dim=-1)
        qk = torch.gather(q, 1, idx[..., None].expand(-1, -1, 2))
        dB = F.normalize(T.sample_map(fB, qk, s), dim=-1)
        sim = dA @ dB.transpose(1, 2) / cfg["tau"]
        big = torch.finfo(sim.dtype).max / 4
        sim = sim.masked_fill(~okk[:, None, :], -big)
        tgt = torch.arange(K)[None].expand(N, -1)
        ce1 = F.cross_entropy(sim.reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        ce2 = F.cross_entropy(sim.transpose(1, 2).reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        okf = okk.float()
        desc = ((ce1 + ce2) * 0.5 * okf).sum() / okf.sum().clamp(min=1)
        with torch.no_grad():
            correct = ((sim.argmax(2) == tgt) & (sim.argmax(1) == tgt)).float()
        pAk = torch.gather(pA.flatten(1), 1, idx).clamp(1e-4, 1 - 1e-4)
        cm = (correct * okf).sum() / okf.sum().clamp(min=1)
        rel = -(correct * torch.log(pAk) * (1 - cm) + (1 - correct) * torch.log(1 - pAk) * cm)
        rel = (rel * okf).sum() / okf.sum().clamp(min=1)
        pBA, qq = T.warp_map_to_A(pB, H, s, h, w)
        vmap = (T.in_bounds(qq, S, margin=s) &
                (T.sample_map(V, qq.reshape(N, -1, 2), 1)[..., 0].reshape(N, h, w) > 0.99)).float()[:, None]
        rep = 1 - T.patch_cos(pA, pBA, vmap, max(2, min(8, h // 4)))
        pk = T.peaky(torch.cat([pA, pB], 0))
        lw = cfg["level_w"][i]
        tot["h_desc"] = tot["h_desc"] + lw * desc
        tot["h_rep"] = tot["h_rep"] + lw * rep
        tot["h_peak"] = tot["h_peak"] + lw * pk
        tot["h_rel"] = tot["h_rel"] + lw * rel
        logs[f"hacc{i}"] = cm.item()
    return tot


def mv_terms(net, out, sl, PA, PB, VV, cfg, logs):
    """Multi-view terms on true track correspondences (pixel-index positions PA, PB [N,K,2])."""
    ia, ib = sl
    N, K = VV.shape
    tot = dict(mv_desc=0.0, mv_rep=0.0, mv_rel=0.0, mv_trk=0.0)
    vf = VV.float()
    nv = vf.sum().clamp(min=1)
    eye = torch.eye(K, dtype=torch.bool)[None]
    dA2 = torch.cdist(PA, PA)
    dB2 = torch.cdist(PB, PB)
    for i, s in enumerate(net.strides):
        f, p = out["feats"][i], out["probs"][i]
        dA = F.normalize(T.sample_map(f[ia], PA, s), dim=-1)
        dB = F.normalize(T.sample_map(f[ib], PB, s), dim=-1)
        sim = dA @ dB.transpose(1, 2) / cfg["tau"]
        big = torch.finfo(sim.dtype).max / 4
        # exclude padding and "negatives" within one cell of the positive in either image
        near = ((dA2 < s) | (dB2 < s)) & ~eye
        bad = near | ~VV[:, None, :] | ~VV[:, :, None]
        sim = sim.masked_fill(bad, -big)
        tgt = torch.arange(K)[None].expand(N, -1)
        ce1 = F.cross_entropy(sim.reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        ce2 = F.cross_entropy(sim.transpose(1, 2).reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        desc = ((ce1 + ce2) * 0.5 * vf).sum() / nv
        with torch.no_grad():
            correct = ((sim.argmax(2) == tgt) & (sim.argmax(1) == tgt)).float() * vf
        pa = T.sample_map(p[ia], PA, s)[..., 0].clamp(1e-4, 1 - 1e-4)
        pb = T.sample_map(p[ib], PB, s)[..., 0].clamp(1e-4, 1 - 1e-4)
        rep = (((pa - pb) ** 2) * vf).sum() / nv
        cm = correct.sum() / nv
        pp = torch.cat([pa, pb], 1)
        cc = torch.cat([correct, correct], 1)
        v2 = torch.cat([vf, vf], 1)
        rel = -(cc * torch.log(pp) * (1 - cm) + (1 - cc) * torch.log(1 - pp) * cm)
        rel = (rel * v2).sum() / v2.sum().clamp(min=1)
        trk = (-torch.log(pp) * v2).sum() / v2.sum().clamp(min=1)
        lw = cfg["level_w"][i]
        tot["mv_desc"] = tot["mv_desc"] + lw * desc
        tot["mv_rep"] = tot["mv_rep"] + lw * rep
        tot["mv_rel"] = tot["mv_rel"] + lw * rel
        tot["mv_trk"] = tot["mv_trk"] + lw * trk
        logs[f"mvacc{i}"] = cm.item()
        logs[f"mvtrk{i}"] = (pp * v2).sum().item() / max(v2.sum().item(), 1)
    return tot


class GlobalTrainer:
    def __init__(self, cidx: MV.CovisIndex, cfg, seed):
        self.c = cidx
        self.cfg = cfg
        self.rng = np.random.default_rng(seed + 7)
        self.cache = None

    @torch.no_grad()
    def refresh(self, net):
        was = net.training
        net.eval()
        self.cache = torch.stack([global_of(net, im) for im in self.c.images])
        net.train(was)

    def loss(self, net):
        c, cfg = self.c, self.cfg
        anchors = self.rng.choice(c.anchors, size=cfg["n_glob"], replace=False)
        losses, r1 = [], 0
        with BNEval(net):
            for g in anchors:
                p = int(self.rng.choice(c.pos[g]))
                ga = global_of(net, c.images[g])
                gp = global_of(net, c.images[p])
                negs = np.nonzero(c.neg[g])[0]
                with torch.no_grad():
                    sims = self.cache[negs] @ ga
                    hard = negs[sims.topk(min(cfg["glob_hard_negs"], len(negs))).indices.numpy()]
                logits = torch.cat([(ga * gp).sum()[None], self.cache[hard] @ ga]) / cfg["glob_tau"]
                losses.append(F.cross_entropy(logits[None], torch.zeros(1, dtype=torch.long)))
                r1 += int(logits.argmax().item() == 0)
                self.cache[g] = ga.detach()
                self.cache[p] = gp.detach()
        return torch.stack(losses).mean(), r1 / len(anchors)

    @torch.no_grad()
    def recall_train(self):
        """Leave-one-out on the (training) database images: is a co-visibility positive the top-1 /
        within the top 5 by the cached descriptors?  A training-set sanity check, not the issue's
        evaluation (that is on the queries)."""
        S = self.cache @ self.cache.t()
        S.fill_diagonal_(-2)
        r1 = r5 = 0
        for g in self.c.anchors:
            top = S[g].topk(5).indices.tolist()
            r1 += int(top[0] in self.c.pos[g])
            r5 += int(any(t in self.c.pos[g] for t in top))
        n = max(len(self.c.anchors), 1)
        return r1 / n, r5 / n


# ----------------------------------------------------------------------------------------------
# checkpoint

def compact_opt_state(sd):
    sd = copy.deepcopy(sd)
    for st in sd["state"].values():
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k] = st[k].to(torch.bfloat16)
    return sd


def expand_opt_state(sd):
    for st in sd["state"].values():
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k] = st[k].float()
    return sd


def save_state(path, net, opt, step, samplers, meta, extra=None):
    """`extra`: more top-level entries (python/distill_v2.py: format, model_name, export_metadata)."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    ck = dict(format="sfp-v2-state/1", model=net.state_dict(), opt=compact_opt_state(opt.state_dict()),
              step=step, torch_rng=torch.get_rng_state(),
              np_rng={k: s.rng.bit_generator.state for k, s in samplers.items()}, meta=meta)
    ck.update(extra or {})
    tmp = path + ".tmp"
    torch.save(ck, tmp)
    os.replace(tmp, path)
    return os.path.getsize(path)


# ----------------------------------------------------------------------------------------------

def lr_at(step, cfg):
    if step < cfg["warmup_steps"]:
        return cfg["lr"] * (step + 1) / cfg["warmup_steps"]
    fr = min(1.0, step / cfg["total_steps"])
    return cfg["lr"] * (cfg["lr_min_frac"] + (1 - cfg["lr_min_frac"]) * 0.5 * (1 + math.cos(math.pi * fr)))


@torch.no_grad()
def validate_mv(net, batches):
    net.eval()
    L = len(net.strides)
    acc = np.zeros(L)
    n = 0
    for A, B, PA, PB, VV in batches:
        x = torch.cat([A[:, None], B[:, None]], 0)
        feats, _ = net.encode(x)
        N = A.shape[0]
        out = dict(feats=feats, probs=[torch.zeros(2 * N, 1, *f.shape[-2:]) for f in feats])
        logs = {}
        mv_terms(net, out, (slice(0, N), slice(N, 2 * N)), PA, PB, VV,
                 dict(tau=0.1, level_w=[1.0] * L), logs)
        acc += np.array([logs[f"mvacc{i}"] for i in range(L)])
        n += 1
    net.train()
    return acc / max(n, 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=os.path.join(HERE, "train_v2.json"))
    ap.add_argument("--set", action="append", default=[], help="override: key=json_value (w.mv_trk=0)")
    ap.add_argument("--minutes", type=float, default=150)
    ap.add_argument("--max-steps", type=int, default=None, help="stop at this global step")
    ap.add_argument("--state", default=STATE, help="training-state file (read if present, written)")
    ap.add_argument("--init", default=os.path.join(REPO, "models", "sfp-v1.onnx"),
                    help="ONNX model whose encoder initialises a fresh run")
    ap.add_argument("--fresh", action="store_true", help="ignore an existing --state (start from --init)")
    ap.add_argument("--curves", default=os.path.join(HERE, "curves"))
    ap.add_argument("--run-name", default=None)
    ap.add_argument("--best", default=os.path.join(HERE, "runs", "v2-best.pt"),
                    help="weights of the best validation score (not committed)")
    args = ap.parse_args()
    with open(args.config) as f:
        cfg = apply_sets(json.load(f), args.set)
    W = cfg["w"]
    torch.set_num_threads(cfg["threads"])
    t_start = time.time()
    run = args.run_name or time.strftime("v2-run-%Y%m%d-%H%M")

    # --- data
    import pycolmap  # noqa: F401  (glog installs a SIGTERM handler on import: ours must come after it)
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    qpaths = query_paths()
    hfiles = hom_files()
    scenes = load_scenes()
    mv_paths = [p for sc in scenes for p in sc.paths]
    MV.assert_disjoint(hfiles + mv_paths, qpaths)
    print(f"queries excluded (asserted by path and md5): {len(qpaths)} files", flush=True)
    himgs = [D.load_gray(p, 640) for p in hfiles] + D.skimage_images()
    print(f"homography images: {len(hfiles)} files + {len(himgs) - len(hfiles)} skimage", flush=True)
    for sc in scenes:
        print(f"  sfm {sc.name}: {len(sc)} map images, {int((sc.covis >= cfg['mv_min_shared']).sum())} "
              f"ordered pairs >= {cfg['mv_min_shared']} shared points", flush=True)
    hs = D.PairSampler(himgs, size=cfg["size"], seed=cfg["seed"])
    mvs = MV.MVPairSampler(scenes, size=cfg["size"], kmax=cfg["kmax_mv"], min_shared=cfg["mv_min_shared"],
                           min_corr=cfg["mv_min_corr"], seed=cfg["seed"] + 1)
    cidx = MV.CovisIndex(scenes, glob_side=cfg["glob_side"])
    gt = GlobalTrainer(cidx, cfg, cfg["seed"])
    print(f"multi-view pairs: {len(mvs.pairs)}; global: {len(cidx)} images, {len(cidx.anchors)} anchors", flush=True)
    # validation: v1's homography pairs on kapture + multi-view pairs of the kapture model
    vs = D.PairSampler([D.load_gray(p, 640) for p in D.val_files()], size=256, seed=1234)
    val_h = []
    for _ in range(4):
        val_h.append(tuple(torch.from_numpy(a) for a in vs.batch(4)))
    vsc = MV.SfMScene(VAL_MODEL[0], os.path.join(DATA, VAL_MODEL[1]), os.path.join(DATA, VAL_MODEL[2]))
    vmv = MV.MVPairSampler([vsc], size=256, kmax=256, min_shared=30, seed=4321, photo=0.0)
    val_mv = [tuple(torch.from_numpy(a) for a in vmv.batch(4)) for _ in range(4)]

    # --- model / state
    net = SFP()
    opt = torch.optim.AdamW(net.parameters(), lr=cfg["lr"], weight_decay=cfg["weight_decay"])
    samplers = dict(hom=hs, mv=mvs, glob=gt)
    step, meta = 0, dict(runs=[], total_minutes=0.0, init=None, best=-2.0)
    if os.path.exists(args.state) and not args.fresh:
        ck = torch.load(args.state, map_location="cpu", weights_only=False)
        net.load_state_dict(ck["model"])
        opt.load_state_dict(expand_opt_state(ck["opt"]))
        step = ck["step"]
        meta = ck["meta"]
        torch.set_rng_state(ck["torch_rng"])
        for k, s in samplers.items():
            if k in ck["np_rng"]:
                s.rng.bit_generator.state = ck["np_rng"][k]
        print(f"resumed {args.state} at step {step} ({meta['total_minutes']:.1f} min trained before)", flush=True)
    else:
        n = load_v1_encoder(net, args.init)
        meta["init"] = f"{os.path.relpath(args.init, REPO)} ({n} encoder tensors; decoder fresh)"
        print(f"fresh run from {meta['init']}", flush=True)
    meta["runs"].append(dict(name=run, start_step=step, started=time.strftime("%Y-%m-%d %H:%M"), cfg=cfg))
    print(f"params: {sum(p.numel() for p in net.parameters())}", flush=True)
    net.train()
    gt.refresh(net)

    os.makedirs(args.curves, exist_ok=True)
    os.makedirs(os.path.dirname(args.best), exist_ok=True)
    curve_path = os.path.join(args.curves, f"{run}.csv")
    val_path = os.path.join(args.curves, f"{run}-val.csv")
    L = len(net.strides)
    terms = ["rec", "comp", "rate", "alive", "h_desc", "h_rep", "h_peak", "h_rel",
             "mv_desc", "mv_rep", "mv_rel", "mv_trk", "glob"]
    cols = (["step", "run_minutes", "total_minutes", "lr", "sec_per_step", "loss"] + terms +
            [f"rate{i}" for i in range(L)] + [f"std{i}" for i in range(L)] + [f"hacc{i}" for i in range(L)] +
            [f"mvacc{i}" for i in range(L)] + [f"mvtrk{i}" for i in range(L)] + ["glob_r1_batch"])
    cf = open(curve_path, "w", newline="")
    cw = csv.DictWriter(cf, fieldnames=cols)
    cw.writeheader()
    vf = open(val_path, "w", newline="")
    vw = csv.writer(vf)
    vw.writerow(["step", "total_minutes"] + [f"hom_acc{i}" for i in range(L)] + [f"mv_acc{i}" for i in range(L)] +
                [f"rate{i}" for i in range(L)] + [f"std{i}" for i in range(L)] +
                ["glob_r1_train", "glob_r5_train", "score"])
    total0 = meta["total_minutes"]
    budget = args.minutes * 60
    last_ck = time.time()
    acc_rows = []
    t_loop = time.time()
    start_step = step

    def do_save(reason):
        meta["total_minutes"] = total0 + (time.time() - t_loop) / 60
        meta["runs"][-1].update(end_step=step, minutes=round((time.time() - t_loop) / 60, 2))
        sz = save_state(args.state, net, opt, step, samplers, meta)
        print(f"checkpoint ({reason}) step {step}: {args.state} {sz} bytes", flush=True)

    def do_val():
        accs, vr, vsd = T.validate(net, val_h)
        mva = validate_mv(net, val_mv)
        gt.refresh(net)
        r1, r5 = gt.recall_train()
        alive = all(r > 0.01 and sd > 0.02 for r, sd in zip(vr, vsd))
        score = float(np.mean(accs) + np.mean(mva)) / 2 if alive else -1.0
        vw.writerow([step, round(total0 + (time.time() - t_loop) / 60, 2)] + list(np.round(accs, 4)) +
                    list(np.round(mva, 4)) + list(np.round(vr, 4)) + list(np.round(vsd, 4)) +
                    [round(r1, 4), round(r5, 4), round(score, 4)])
        vf.flush()
        print(f"VAL step {step} hom_acc={np.round(accs, 3)} mv_acc={np.round(mva, 3)} rates={np.round(vr, 3)} "
              f"std={np.round(vsd, 3)} glob_train r1={r1:.3f} r5={r5:.3f} score={score:.4f}", flush=True)
        if score > meta.get("best", -2.0):
            meta["best"] = score
            torch.save(dict(model=net.state_dict(), step=step, score=score, val_hom=accs.tolist(),
                            val_mv=mva.tolist()), args.best)

    if step == 0:
        do_val()
    while not STOP["flag"] and time.time() - t_start < budget and (args.max_steps is None or step < args.max_steps):
        ts = time.time()
        net.train()
        if cfg.get("bn_frozen", False):
            freeze_bn(net)
        lr = lr_at(step, cfg)
        for g in opt.param_groups:
            g["lr"] = lr
        A, B, H, V = map(torch.from_numpy, hs.batch(cfg["n_hom"]))
        MA, MB, PA, PB, VV = map(torch.from_numpy, mvs.batch(cfg["n_mv"]))
        nh, nm = cfg["n_hom"], cfg["n_mv"]
        x = torch.cat([A, B, MA[:, None], MB[:, None]], 0)
        out = forward_train(net, x, detach_dec=meta["init"] is not None and step < cfg["dec_warmup_steps"])
        logs = {}
        Ls = {}
        Ls["rec"] = (out["recon"] - x).abs().mean()
        Dsum = float(sum(net.dims))
        Ls["comp"] = sum((d / Dsum) * p.mean() for d, p in zip(net.dims, out["probs"]))
        Ls["rate"] = sum((p.mean() - t) ** 2 for p, t in zip(out["probs"], cfg["targets"]))
        Ls["alive"] = sum(F.relu(cfg["alive_std"] - p.std()) for p in out["probs"])
        if any(W[k] > 0 for k in ("h_desc", "h_rep", "h_peak", "h_rel")):
            Ls.update(hom_terms(net, out, (slice(0, nh), slice(nh, 2 * nh)), A, B, H, V, cfg, logs))
        if any(W[k] > 0 for k in ("mv_desc", "mv_rep", "mv_rel", "mv_trk")):
            o = 2 * nh
            Ls.update(mv_terms(net, out, (slice(o, o + nm), slice(o + nm, o + 2 * nm)), PA, PB, VV, cfg, logs))
        if W["glob"] > 0 and step % cfg["glob_every"] == 0:
            Ls["glob"], logs["glob_r1_batch"] = gt.loss(net)
        loss = sum(W[k] * v for k, v in Ls.items() if W.get(k, 0) > 0)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
        opt.step()
        if step > 0 and step % cfg["glob_cache_every"] == 0:
            gt.refresh(net)
        row = dict(step=step, lr=lr, sec_per_step=time.time() - ts, loss=loss.item())
        row.update({k: float(v.detach()) if torch.is_tensor(v) else float(v) for k, v in Ls.items()})
        row.update({f"rate{i}": p.mean().item() for i, p in enumerate(out["probs"])})
        row.update({f"std{i}": p.std().item() for i, p in enumerate(out["probs"])})
        row.update(logs)
        acc_rows.append(row)
        step += 1
        if len(acc_rows) >= cfg["log_every"]:
            agg = {k: float(np.mean([r[k] for r in acc_rows if k in r])) for k in cols
                   if any(k in r for r in acc_rows)}
            agg["step"] = step - 1
            agg["run_minutes"] = round((time.time() - t_loop) / 60, 3)
            agg["total_minutes"] = round(total0 + (time.time() - t_loop) / 60, 3)
            cw.writerow({k: (round(v, 5) if isinstance(v, float) else v) for k, v in agg.items()})
            cf.flush()
            acc_rows = []
            if (step // cfg["log_every"]) % 5 == 0:
                print(f"step {step - 1} t={agg['run_minutes']:.1f}m {agg['sec_per_step']:.2f}s/step loss={agg['loss']:.3f} "
                      + " ".join(f"{k}={agg[k]:.3f}" for k in terms if k in agg)
                      + " rates=" + ",".join(f"{agg[f'rate{i}']:.3f}" for i in range(L))
                      + " mvacc=" + ",".join(f"{agg.get(f'mvacc{i}', 0):.2f}" for i in range(L)), flush=True)
        if step % cfg["val_every"] == 0:
            do_val()
        if time.time() - last_ck >= cfg["ckpt_minutes"] * 60:
            do_save("periodic")
            last_ck = time.time()
    if STOP["flag"]:
        print(f"signal {STOP['sig']}: stopping cleanly", flush=True)
    do_save("end")
    cf.close()
    vf.close()
    print(f"done: steps {start_step}..{step} in {(time.time() - t_loop) / 60:.1f} min "
          f"(total {meta['total_minutes']:.1f} min); curves {curve_path}", flush=True)


if __name__ == "__main__":
    main()
