#!/usr/bin/env python3
"""Distil SFP v1 into a faster student on CPU, resumably (issue 17's speed target: <= 15 ms per
640x480 image on 2 cores, <= 25 ms on 1). Same ONNX contract (sfp-extractor/1: 4 levels, strides
2/4/8/16, dims 16/32/64/128, GeM global), so the Rust extractor runs the student unchanged.

Student: SFP(stem_mode="strided") of python/sfp/model.py -- a 3x3 stride-2 conv from the image and one
3x3 conv at stride 2 instead of v1's two full-resolution convs + MaxPool (`--stem strided1`: the
stride-2 conv alone, faster still). Everything after the stem (encoder blocks, score heads, their
frozen BN statistics) starts as the teacher's; the stem starts fresh.
Teacher: models/sfp-v1.onnx's weights in torch (train_v2.load_v1_encoder; or a .pt state with
"model", e.g. a v2 run), eval mode, no gradient.
Data: train_v2.py's homography images (train/, the scenes' map images without their queries, the
COLMAP fixtures except the validation one) + scikit-image, query files excluded and asserted exactly
as there (multiview.assert_disjoint: by path and md5). A step: n_img random crops A of side `size`
and their random-homography warps B (sfp/data.PairSampler) = 2 n_img images for both networks.

Loss (weights `w`, per level `level_w`; weight 0 switches a term off):
  score  Bernoulli KL(p_t || p_s) per cell = BCE(logit_s, p_t) - H(p_t): 0 when the maps agree
  desc   1 - cos(f_s, f_t) per cell, weighted by p_t + desc_floor: the extractor L2-normalises
         descriptors (only the direction counts), and the cells a map keeps matter most
  glob   1 - cos(g_s, g_t) of the GeM global descriptors
  hint   |h_s - h_t|^2 / mean(h_t^2) at the first block's input (student stem vs v1's pooled stem)
Multi-view fine-tuning (weights `mv_*`, `glob_ret`; 0 by default): train_v2's InfoNCE on true track
correspondences, detector repeatability/reliability/track terms on n_mv pairs of co-visible map images,
and the co-visibility InfoNCE of the global descriptor (train_v2.GlobalTrainer), with the distillation
terms kept as an anchor to the teacher on the same images (train_v2's multi-view runs alone drifted
from v1's validation accuracy within 250 steps). `--from STATE` starts such a run from a trained
student's weights (with `--set stem_steps=0`).
For the first `stem_steps` steps only the stem learns (the other parameters get lr 0), so the fresh
stem's early output does not pull the teacher-initialised blocks away. BatchNorm is frozen as in
train_v2 (eval mode, affine parameters trained): training optimises the exported network.

Resumable: python/checkpoints/sfp-v2s-state.pt (train_v2.save_state's layout + model_name and
export_metadata) is written atomically every `ckpt_minutes`, at the end and on SIGTERM/SIGINT, and
read on start (`--fresh` ignores it). Curves: python/curves/<run>.csv (means over log_every steps),
<run>-val.csv (held-out colmap/kapture_maupertuis: distillation loss and train.validate's
homography accuracy; the teacher's is in the first line).

  mkdir -p python/runs
  nohup nice -n 19 python3 python/distill_v2.py --minutes 150 > python/runs/v2s-$(date +%Y%m%d-%H%M).log 2>&1 &
  kill -TERM <pid>                     # clean stop: writes the state first
  python3 python/export.py python/checkpoints/sfp-v2s-state.pt -o models/sfp-v2s.onnx
  python3 python/bench_onnx.py models/sfp-v1.onnx models/sfp-v2s.onnx
"""
from __future__ import annotations

import argparse
import copy
import csv
import json
import os
import signal
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import train as T  # noqa: E402  (validate: homography mutual-NN accuracy)
import train_v2 as V  # noqa: E402  (data lists, teacher loading, state file, lr schedule, BN freezing)
from sfp import data as D  # noqa: E402
from sfp import multiview as MV  # noqa: E402
from sfp.config import apply_sets  # noqa: E402
from sfp.model import SFP  # noqa: E402

REPO = V.REPO
STATE = os.path.join(HERE, "checkpoints", "sfp-v2s-state.pt")

CFG = {
    "seed": 0,
    "threads": 1,
    "stem": "strided",
    "model_name": None,  # sfp.model_name of the export; None: MODEL_NAMES[stem]
    "size": 256,
    "n_img": 4,
    "lr": 1e-3,
    "weight_decay": 1e-4,
    "warmup_steps": 100,
    "total_steps": 20000,
    "lr_min_frac": 0.05,
    "stem_steps": 300,
    "desc_floor": 0.02,
    "level_w": [1.0, 1.0, 1.0, 1.0],
    "w": {"score": 1.0, "desc": 1.0, "glob": 1.0, "hint": 0.1,
          # multi-view terms on top of the distillation (0: off; train_v2.mv_terms / GlobalTrainer)
          "mv_desc": 0.0, "mv_rep": 0.0, "mv_rel": 0.0, "mv_trk": 0.0, "glob_ret": 0.0},
    # multi-view and retrieval data (used only when one of those weights is > 0)
    "n_mv": 2,
    "kmax_mv": 160,
    "mv_min_shared": 30,
    "mv_min_corr": 16,
    "tau": 0.1,
    "n_glob": 2,
    "glob_side": 288,
    "glob_tau": 0.05,
    "glob_hard_negs": 8,
    "glob_cache_every": 300,
    # a retrieval head on the deepest features (SFP(glob_head=True); fresh in a run --from a state
    # without one) and which parameters train: "" = all, else a name prefix ("glob_head.")
    "glob_head": False,
    "train_only": "",
    "ckpt_minutes": 5.0,
    "val_every": 250,
    "log_every": 10,
}
MODEL_NAMES = {"strided": "sfp-v2s", "strided1": "sfp-v2s1"}  # maps are tied to the name: one per net
INIT_PREFIXES = ("pre.", "enc.", "score_heads.")  # the exported layers after the stem

STOP = {"flag": False, "sig": None}


def _on_signal(sig, _frame):
    STOP["flag"] = True
    STOP["sig"] = sig


# ----------------------------------------------------------------------------------------------
# networks

def load_teacher(path: str) -> SFP:
    if path.endswith(".onnx"):
        net = SFP()
        n = V.load_v1_encoder(net, path)
        assert n > 0, f"no SFP weights in {path}"
    else:
        net = SFP.for_state_dict(torch.load(path, map_location="cpu", weights_only=False)["model"])
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def init_from_teacher(student: SFP, teacher: SFP) -> int:
    """Copy the teacher's layers after the stem (same names and shapes in every stem mode)."""
    sd = student.state_dict()
    n = 0
    for k, v in teacher.state_dict().items():
        if k.startswith(INIT_PREFIXES) and k in sd:
            assert sd[k].shape == v.shape, (k, sd[k].shape, v.shape)
            sd[k] = v.clone()
            n += 1
    student.load_state_dict(sd)
    return n


class Hint:
    """Captures the input of the first block's bn1 (stride 2 in every stem mode) on each encode."""

    def __init__(self, net: SFP):
        self.x = None
        net.first_block().bn1.register_forward_pre_hook(self._grab)

    def _grab(self, _mod, args):
        self.x = args[0]


def run_net(net: SFP, hint: Hint, x):
    feats, logits = net.encode(x)
    return dict(feats=feats, logits=logits, glob=net.global_desc(feats[-1]), hint=hint.x)


# ----------------------------------------------------------------------------------------------
# loss

def bernoulli_kl(logit_s, p_t):
    """KL(p_t || sigmoid(logit_s)) per cell, without log(0) at saturated teacher scores."""
    pt = p_t.clamp(1e-6, 1 - 1e-6)
    ent = -(pt * pt.log() + (1 - pt) * (1 - pt).log())
    return F.binary_cross_entropy_with_logits(logit_s, pt, reduction="none") - ent


def distill_terms(s, t, cfg, logs):
    L = len(t["feats"])
    tot = dict(score=0.0, desc=0.0)
    for i in range(L):
        pt = torch.sigmoid(t["logits"][i])
        kl = bernoulli_kl(s["logits"][i], pt).mean()
        cos = F.cosine_similarity(s["feats"][i], t["feats"][i], dim=1, eps=1e-6)[:, None]
        w = pt + cfg["desc_floor"]
        desc = ((1 - cos) * w).sum() / w.sum()
        lw = cfg["level_w"][i]
        tot["score"] = tot["score"] + lw * kl
        tot["desc"] = tot["desc"] + lw * desc
        with torch.no_grad():
            logs[f"kl{i}"] = kl.item()
            logs[f"cos{i}"] = 1 - desc.item()
            logs[f"rate_s{i}"] = torch.sigmoid(s["logits"][i]).mean().item()
            logs[f"rate_t{i}"] = pt.mean().item()
    gcos = (s["glob"] * t["glob"]).sum(1)
    tot["glob"] = (1 - gcos).mean()
    ht = t["hint"]
    tot["hint"] = (s["hint"] - ht).pow(2).mean() / ht.pow(2).mean().clamp(min=1e-8)
    logs["gcos"] = gcos.mean().item()
    return tot


def total_loss(terms, cfg):
    W = cfg["w"]
    return sum(W[k] * v for k, v in terms.items() if W.get(k, 0) > 0)


# ----------------------------------------------------------------------------------------------

@torch.no_grad()
def validate(student, sh, teacher, th, val_batches, cfg):
    """Distillation loss on the held-out pairs (eval mode) and `student`'s homography accuracy
    (`student` may be the teacher itself: its reference line)."""
    was = student.training
    student.eval()
    acc = {}
    n = 0
    for A, B, _H, _V in val_batches:
        x = torch.cat([A, B], 0)
        logs = {}
        terms = distill_terms(run_net(student, sh, x), run_net(teacher, th, x), cfg, logs)
        logs.update({k: float(v) for k, v in terms.items()})
        logs["loss"] = float(total_loss(terms, cfg))
        for k, v in logs.items():
            acc[k] = acc.get(k, 0.0) + v
        n += 1
    out = {k: v / n for k, v in acc.items()}
    hacc, rates, _ = T.validate(student, val_batches)
    student.train(was)  # T.validate leaves train mode: the teacher's BN must never see it
    out.update({f"hom_acc{i}": a for i, a in enumerate(hacc)})
    out.update({f"rate{i}": r for i, r in enumerate(rates)})
    return out


def parse_cfg(sets):
    return apply_sets(copy.deepcopy(CFG), sets)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", action="append", default=[], help="override: key=json_value (w.hint=0)")
    ap.add_argument("--minutes", type=float, default=150)
    ap.add_argument("--max-steps", type=int, default=None, help="stop at this global step")
    ap.add_argument("--state", default=STATE, help="training-state file (read if present, written)")
    ap.add_argument("--teacher", default=os.path.join(REPO, "models", "sfp-v1.onnx"),
                    help=".onnx (SFP weights) or .pt state with 'model'")
    ap.add_argument("--fresh", action="store_true", help="ignore an existing --state")
    ap.add_argument("--from", dest="from_state", default=None,
                    help="a fresh run starts from this student state's weights (.pt with 'model')")
    ap.add_argument("--curves", default=os.path.join(HERE, "curves"))
    ap.add_argument("--run-name", default=None)
    ap.add_argument("--best", default=os.path.join(HERE, "runs", "v2s-best.pt"),
                    help="weights of the lowest validation loss (not committed)")
    args = ap.parse_args()
    cfg = parse_cfg(args.set)
    torch.set_num_threads(cfg["threads"])
    t_start = time.time()
    run = args.run_name or time.strftime("v2s-run-%Y%m%d-%H%M")
    W = cfg["w"]
    use_mv = any(W[k] > 0 for k in ("mv_desc", "mv_rep", "mv_rel", "mv_trk"))
    use_gret = W["glob_ret"] > 0
    distill_on = any(W[k] > 0 for k in ("score", "desc", "glob", "hint"))
    if use_mv or use_gret:
        import pycolmap  # noqa: F401  (glog installs a SIGTERM handler on import: ours must come after it)
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)

    # --- data (the query exclusion exactly as train_v2.py)
    qpaths = V.query_paths()
    hfiles = V.hom_files()
    scenes = V.load_scenes() if use_mv or use_gret else []
    MV.assert_disjoint(hfiles + [p for sc in scenes for p in sc.paths], qpaths)
    print(f"queries excluded (asserted by path and md5): {len(qpaths)} files", flush=True)
    imgs = [D.load_gray(p, 640) for p in hfiles] + D.skimage_images()
    print(f"images: {len(hfiles)} files + {len(imgs) - len(hfiles)} skimage", flush=True)
    hs = D.PairSampler(imgs, size=cfg["size"], seed=cfg["seed"])
    vs = D.PairSampler([D.load_gray(p, 640) for p in D.val_files()], size=256, seed=1234)
    val_h = [tuple(torch.from_numpy(a) for a in vs.batch(4)) for _ in range(4)]  # train_v2's val pairs
    mvs = gt = None
    val_mv = []
    if use_mv:
        mvs = MV.MVPairSampler(scenes, size=cfg["size"], kmax=cfg["kmax_mv"], min_shared=cfg["mv_min_shared"],
                               min_corr=cfg["mv_min_corr"], seed=cfg["seed"] + 1)
        vsc = MV.SfMScene(V.VAL_MODEL[0], os.path.join(V.DATA, V.VAL_MODEL[1]), os.path.join(V.DATA, V.VAL_MODEL[2]))
        vmv = MV.MVPairSampler([vsc], size=256, kmax=256, min_shared=30, seed=4321, photo=0.0)
        val_mv = [tuple(torch.from_numpy(a) for a in vmv.batch(4)) for _ in range(4)]  # train_v2's
        print(f"multi-view pairs: {len(mvs.pairs)}", flush=True)
    if use_gret:
        gt = V.GlobalTrainer(MV.CovisIndex(scenes, glob_side=cfg["glob_side"]), cfg, cfg["seed"])
        print(f"global: {len(gt.c)} images, {len(gt.c.anchors)} anchors", flush=True)

    # --- networks / state
    teacher = load_teacher(args.teacher)
    th = Hint(teacher)
    samplers = dict(hom=hs)
    if mvs is not None:
        samplers["mv"] = mvs
    if gt is not None:
        samplers["glob"] = gt
    step, meta = 0, dict(runs=[], total_minutes=0.0, init=None, best=float("inf"))
    if os.path.exists(args.state) and not args.fresh:
        ck = torch.load(args.state, map_location="cpu", weights_only=False)
        net = SFP.for_state_dict(ck["model"])
        if net.stem_mode != cfg["stem"]:
            raise SystemExit(f"{args.state} holds a {net.stem_mode!r} stem, config says {cfg['stem']!r}")
        step, meta = ck["step"], ck["meta"]
        torch.set_rng_state(ck["torch_rng"])
        for k, smp in samplers.items():
            if k in ck["np_rng"]:
                smp.rng.bit_generator.state = ck["np_rng"][k]
    elif args.from_state:
        ck = None
        sd = torch.load(args.from_state, map_location="cpu", weights_only=False)["model"]
        net = SFP.for_state_dict(sd)
        if cfg["glob_head"] and net.glob_head is None:
            net = SFP(stem_mode=net.stem_mode, glob_head=True)
            missing, unexpected = net.load_state_dict(sd, strict=False)
            assert not unexpected and all(k.startswith("glob_head.") for k in missing), (missing, unexpected)
        if net.stem_mode != cfg["stem"]:
            raise SystemExit(f"{args.from_state} holds a {net.stem_mode!r} stem, config says {cfg['stem']!r}")
        meta["init"] = f"{os.path.relpath(args.from_state, REPO)} (student weights; optimiser fresh)"
        print(f"fresh run: {meta['init']}", flush=True)
    else:
        ck = None
        net = SFP(stem_mode=cfg["stem"])
        n = init_from_teacher(net, teacher)
        meta["init"] = f"{os.path.relpath(args.teacher, REPO)} ({n} tensors after the stem; stem fresh)"
        print(f"fresh run: {meta['init']}", flush=True)
    sh = Hint(net)
    if cfg["train_only"]:
        for k, p in net.named_parameters():
            p.requires_grad_(k.startswith(cfg["train_only"]))
    stem_p = [p for k, p in net.named_parameters() if k.startswith("stem_s2.")]
    rest_p = [p for k, p in net.named_parameters() if not k.startswith("stem_s2.")]
    opt = torch.optim.AdamW([dict(params=stem_p), dict(params=rest_p)], lr=cfg["lr"],
                            weight_decay=cfg["weight_decay"])
    if ck is not None:
        opt.load_state_dict(V.expand_opt_state(ck["opt"]))
        print(f"resumed {args.state} at step {step} ({meta['total_minutes']:.1f} min trained before)", flush=True)
    meta["runs"].append(dict(name=run, start_step=step, started=time.strftime("%Y-%m-%d %H:%M"), cfg=cfg,
                             teacher=os.path.relpath(args.teacher, REPO)))
    extra = dict(format="sfp-v2s-state/1", model_name=cfg["model_name"] or MODEL_NAMES[net.stem_mode],
                 export_metadata={"sfp.teacher": os.path.basename(args.teacher), "sfp.stem": net.stem_mode,
                                  "sfp.train_loss": "distillation (python/distill_v2.py)"})
    print(f"student {cfg['stem']}: {sum(p.numel() for p in net.parameters())} params "
          f"({sum(p.numel() for p in stem_p)} in the stem)", flush=True)

    os.makedirs(args.curves, exist_ok=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.best)), exist_ok=True)
    L = len(net.strides)
    terms = ["score", "desc", "glob", "hint"] + [k for k in ("mv_desc", "mv_rep", "mv_rel", "mv_trk", "glob_ret")
                                                 if W[k] > 0]
    per_level = ["kl", "cos", "rate_s", "rate_t"] + (["mvacc"] if use_mv else [])
    cols = (["step", "run_minutes", "total_minutes", "lr", "sec_per_step", "loss"] + terms + ["gcos"] +
            [f"{k}{i}" for k in per_level for i in range(L)] + (["glob_r1_batch"] if use_gret else []))
    vcols = (["step", "total_minutes", "who", "loss"] + terms + ["gcos"] + [f"cos{i}" for i in range(L)] +
             [f"kl{i}" for i in range(L)] + [f"hom_acc{i}" for i in range(L)] + [f"rate{i}" for i in range(L)] +
             ([f"mv_acc{i}" for i in range(L)] if use_mv else []) +
             (["glob_r1_train", "glob_r5_train"] if use_gret else []) + ["score_acc"])
    curve_path = os.path.join(args.curves, f"{run}.csv")
    val_path = os.path.join(args.curves, f"{run}-val.csv")
    cf = open(curve_path, "w", newline="")
    cw = csv.DictWriter(cf, fieldnames=cols)
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
        meta["runs"][-1].update(end_step=step, minutes=round((time.time() - t_loop) / 60, 2))
        sz = V.save_state(args.state, net, opt, step, samplers, meta, extra)
        print(f"checkpoint ({reason}) step {step}: {args.state} {sz} bytes", flush=True)

    def do_val(who="student"):
        m = teacher if who == "teacher" else net
        h = th if who == "teacher" else sh
        r = validate(m, h, teacher, th, val_h, cfg)
        accs = [r[f"hom_acc{i}"] for i in range(L)]
        if use_mv:
            mva = V.validate_mv(m, val_mv)
            if who == "teacher":
                m.eval()  # validate_mv leaves train mode: the teacher's BN must never see it
            r.update({f"mv_acc{i}": float(a) for i, a in enumerate(mva)})
            accs = [(a + b) / 2 for a, b in zip(accs, mva)]
        if use_gret and who == "student":
            gt.refresh(net)
            r["glob_r1_train"], r["glob_r5_train"] = gt.recall_train()
        r["score_acc"] = float(np.mean(accs))  # train_v2's score: mean held-out accuracy
        r.update(step=step, who=who, total_minutes=round(total0 + (time.time() - t_loop) / 60, 2))
        vw.writerow({k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()})
        vf.flush()
        print(f"VAL {who} step {step}: loss={r['loss']:.4f} cos=" +
              ",".join(f"{r[f'cos{i}']:.3f}" for i in range(L)) + f" gcos={r['gcos']:.3f} hom_acc=" +
              ",".join(f"{r[f'hom_acc{i}']:.3f}" for i in range(L)) +
              ("" if not use_mv else " mv_acc=" + ",".join(f"{r[f'mv_acc{i}']:.3f}" for i in range(L))) +
              ("" if not use_gret or who != "student" else
               f" glob_train r1={r['glob_r1_train']:.3f} r5={r['glob_r5_train']:.3f}") +
              f" score_acc={r['score_acc']:.4f}", flush=True)
        # best: the lowest distillation loss, or with multi-view terms the highest held-out accuracy
        # (the anchor's loss rises by design there)
        better = (r["score_acc"] > meta.get("best_acc", -1.0)) if use_mv else \
            (r["loss"] < meta.get("best", float("inf")))
        if who == "student" and better:
            meta["best"] = r["loss"]
            meta["best_acc"] = r["score_acc"]
            torch.save(dict(model=net.state_dict(), step=step, val=r, model_name=extra["model_name"],
                            export_metadata=extra["export_metadata"]), args.best)  # export.py reads it

    do_val("teacher")  # the reference line: what the student's accuracies should reach
    if gt is not None:
        gt.refresh(net)
    if step == 0:
        do_val()
    while not STOP["flag"] and time.time() - t_start < args.minutes * 60 and \
            (args.max_steps is None or step < args.max_steps):
        ts = time.time()
        net.train()
        V.freeze_bn(net)
        lr = V.lr_at(step, cfg)
        opt.param_groups[0]["lr"] = lr
        opt.param_groups[1]["lr"] = lr if step >= cfg["stem_steps"] else 0.0
        logs = {}
        if distill_on or use_mv:
            A, B, _H, _V = map(torch.from_numpy, hs.batch(cfg["n_img"]))
            x = torch.cat([A, B], 0)
            if use_mv:
                MA, MB, PA, PB, VV = map(torch.from_numpy, mvs.batch(cfg["n_mv"]))
                x = torch.cat([x, MA[:, None], MB[:, None]], 0)
            with torch.no_grad():
                t_out = run_net(teacher, th, x)
            s_out = run_net(net, sh, x)
            Ls = distill_terms(s_out, t_out, cfg, logs)  # the anchor, on the multi-view crops too
        else:  # the retrieval head alone: no crops to distil
            Ls = {}
        if use_mv:
            o, nm = 2 * cfg["n_img"], cfg["n_mv"]
            out = dict(feats=s_out["feats"], probs=[torch.sigmoid(lg) for lg in s_out["logits"]])
            Ls.update(V.mv_terms(net, out, (slice(o, o + nm), slice(o + nm, o + 2 * nm)), PA, PB, VV, cfg, logs))
        if use_gret:
            Ls["glob_ret"], logs["glob_r1_batch"] = gt.loss(net)
        loss = total_loss(Ls, cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([p for p in net.parameters() if p.requires_grad], 5.0)
        opt.step()
        if use_gret and step > 0 and step % cfg["glob_cache_every"] == 0:
            gt.refresh(net)
        row = dict(step=step, lr=lr, sec_per_step=time.time() - ts, loss=loss.item())
        row.update({k: float(v.detach()) if torch.is_tensor(v) else float(v) for k, v in Ls.items()})
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
            print(f"step {step - 1} t={agg['run_minutes']:.1f}m {agg['sec_per_step']:.2f}s/step "
                  f"loss={agg['loss']:.4f} " + " ".join(f"{k}={agg[k]:.4f}" for k in terms if k in agg) +
                  " cos=" + ",".join(f"{agg.get(f'cos{i}', 0):.3f}" for i in range(L)) + f" gcos={agg.get('gcos', 0):.3f}",
                  flush=True)
        if step % cfg["val_every"] == 0:
            do_val()
        if time.time() - last_ck >= cfg["ckpt_minutes"] * 60:
            do_save("periodic")
            last_ck = time.time()
    if STOP["flag"]:
        print(f"signal {STOP['sig']}: stopping cleanly", flush=True)
    elif step % cfg["val_every"] != 0:
        do_val()
    do_save("end")
    cf.close()
    vf.close()
    print(f"done: steps {start_step}..{step} in {(time.time() - t_loop) / 60:.1f} min "
          f"(total {meta['total_minutes']:.1f} min); curves {curve_path}", flush=True)


if __name__ == "__main__":
    main()
