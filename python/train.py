#!/usr/bin/env python3
"""Train the Sparse Feature Pyramid network on CPU.

Loss ("sfp", default):
  w_rec * L1(recon, input)                                  paper: reconstruction
+ lam * sum_i (d_i / D) * mean(p_i)                         paper: compression (expected floats kept)
+ w_rate * sum_i (mean(p_i) - t_i)^2                        per-level rate targets (anti-collapse)
+ w_desc * InfoNCE(level-i descriptors of A vs B)           homography pairs: descriptor consistency
+ w_rep * (1 - patch-cos(p_A, warp(p_B)))                   detector repeatability
+ w_peak * (1 - (maxpool(p) - avgpool(p)))                  peakiness (local maxima for NMS)
+ w_rel * BCE(p at sampled cells, [descriptor matched correctly])   reliability
+ w_glob * InfoNCE(global A vs global B across the batch)
Loss "paper": reconstruction + lam * compression only (the ablation).
Loss "rate": "paper" + the per-level rate targets (anti-collapse alone, no homography-pair terms).

Example:  nice -n 10 python3 python/train.py --out python/runs/main --minutes 70
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp import data as D  # noqa: E402
from sfp.model import SFP  # noqa: E402


def level_grid_coords(h, w, s, device):
    ys, xs = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32),
                            torch.arange(w, device=device, dtype=torch.float32), indexing="ij")
    return torch.stack([xs * s, ys * s], -1)  # pixel coords of cell centres [h,w,2] (x,y)


def warp_points(H, pts):
    """H [N,3,3], pts [N,K,2] -> [N,K,2]"""
    ph = torch.cat([pts, torch.ones_like(pts[..., :1])], -1)
    q = ph @ H.transpose(1, 2)
    return q[..., :2] / q[..., 2:3].clamp(min=1e-6)


def sample_map(fmap, pts_pix, s):
    """Bilinear sample fmap [N,C,h,w] at pixel coords pts [N,K,2]; cell c <-> pixel s*c."""
    h, w = fmap.shape[-2:]
    gx = pts_pix[..., 0] / s / max(w - 1, 1) * 2 - 1
    gy = pts_pix[..., 1] / s / max(h - 1, 1) * 2 - 1
    g = torch.stack([gx, gy], -1)[:, :, None]  # N,K,1,2
    out = F.grid_sample(fmap, g, mode="bilinear", align_corners=True, padding_mode="border")
    return out[..., 0].transpose(1, 2)  # N,K,C


def in_bounds(pts, size, margin=0.0):
    return (pts[..., 0] >= margin) & (pts[..., 1] >= margin) & \
           (pts[..., 0] <= size - 1 - margin) & (pts[..., 1] <= size - 1 - margin)


def warp_map_to_A(mapB, H, s, hA, wA):
    """Resample a level map of B at the positions of A's level cells (through H)."""
    N = mapB.shape[0]
    grid = level_grid_coords(hA, wA, s, mapB.device).reshape(1, -1, 2).expand(N, -1, -1)
    q = warp_points(H, grid)
    v = sample_map(mapB, q, s)  # N,K,C
    return v.transpose(1, 2).reshape(N, -1, hA, wA), q.reshape(N, hA, wA, 2)


def patch_cos(a, b, valid, k):
    a = a * valid
    b = b * valid
    st = max(k // 2, 1)
    ab = F.avg_pool2d(a * b, k, st)
    aa = F.avg_pool2d(a * a, k, st)
    bb = F.avg_pool2d(b * b, k, st)
    vv = F.avg_pool2d(valid, k, st)
    cos = ab / (aa * bb).clamp(min=1e-12).sqrt()
    w = (vv > 0.99).float()
    return (cos * w).sum() / w.sum().clamp(min=1)


def peaky(p, k=5):
    return 1 - (F.max_pool2d(p, k, 1, k // 2) - F.avg_pool2d(p, k, 1, k // 2, count_include_pad=False)).mean()


def compute_losses(net, A, B, H, V, args, step, cfg):
    S = A.shape[-1]
    if args.loss in ("paper", "rate"):
        out = net(A)
        rec = (out["recon"] - A).abs().mean()
        Dsum = float(sum(net.dims))
        comp = sum((d / Dsum) * p.mean() for d, p in zip(net.dims, out["probs"]))
        total = args.w_rec * rec + args.lam * comp
        logs = dict(rec=rec.item(), comp=comp.item())
        if args.loss == "rate":  # paper loss + per-level rate targets (anti-collapse only, no pair terms)
            warm = min(1.0, step / max(args.warmup, 1))
            rate = sum((p.mean() - t) ** 2 for p, t in zip(out["probs"], args.targets))
            total = total + warm * args.w_rate * rate
            logs["rate"] = rate.item()
        return total, logs, out
    x = torch.cat([A, B], 0)
    out = net(x)
    N = A.shape[0]
    rec = (out["recon"] - x).abs().mean()
    Dsum = float(sum(net.dims))
    comp = sum((d / Dsum) * p.mean() for d, p in zip(net.dims, out["probs"]))
    warm = min(1.0, step / max(args.warmup, 1))
    rate = sum((p.mean() - t) ** 2 for p, t in zip(out["probs"], args.targets))
    desc_l, rep_l, peak_l, rel_l = 0.0, 0.0, 0.0, 0.0
    logs = {}
    for i, s in enumerate(net.strides):
        f = out["feats"][i]
        p = out["probs"][i]
        fA, fB = f[:N], f[N:]
        pA, pB = p[:N], p[N:]
        h, w = fA.shape[-2:]
        grid = level_grid_coords(h, w, s, f.device).reshape(1, -1, 2).expand(N, -1, -1)
        q = warp_points(H, grid)
        # validity of the warped point in B (inside the patch and inside the warped source image)
        vB = sample_map(V, q, 1)[..., 0] > 0.99
        ok = in_bounds(q, S, margin=s) & vB
        K = min(args.kpts, h * w)
        # pick K random valid cells per image
        score_rand = torch.rand(ok.shape, device=f.device) + ok.float() * 2
        idx = score_rand.topk(K, dim=1).indices
        okk = torch.gather(ok, 1, idx)
        dA = F.normalize(torch.gather(fA.flatten(2).transpose(1, 2), 1, idx[..., None].expand(-1, -1, fA.shape[1])), dim=-1)
        qk = torch.gather(q, 1, idx[..., None].expand(-1, -1, 2))
        dB = F.normalize(sample_map(fB, qk, s), dim=-1)
        sim = dA @ dB.transpose(1, 2) / args.tau  # N,K,K
        big = torch.finfo(sim.dtype).max / 4
        sim = sim.masked_fill(~okk[:, None, :], -big)
        tgt = torch.arange(K, device=f.device)[None].expand(N, -1)
        ce1 = F.cross_entropy(sim.reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        ce2 = F.cross_entropy(sim.transpose(1, 2).reshape(N * K, K), tgt.reshape(-1), reduction="none").reshape(N, K)
        okf = okk.float()
        desc = ((ce1 + ce2) * 0.5 * okf).sum() / okf.sum().clamp(min=1)
        # reliability: score should predict a correct (mutual best) match
        with torch.no_grad():
            correct = ((sim.argmax(2) == tgt) & (sim.argmax(1) == tgt)).float()
        pAk = torch.gather(pA.flatten(1), 1, idx).clamp(1e-4, 1 - 1e-4)
        # rebalance so that the reliability term does not move the mean rate
        rel = -(correct * torch.log(pAk) * (1 - correct.mean()) +
                (1 - correct) * torch.log(1 - pAk) * correct.mean())
        rel = (rel * okf).sum() / okf.sum().clamp(min=1)
        # repeatability
        pBA, qq = warp_map_to_A(pB, H, s, h, w)
        vmap = (in_bounds(qq, S, margin=s) & (sample_map(V, qq.reshape(N, -1, 2), 1)[..., 0].reshape(N, h, w) > 0.99)).float()[:, None]
        kk = max(2, min(8, h // 4))
        rep = 1 - patch_cos(pA, pBA, vmap, kk)
        pk = peaky(p)
        lw = cfg["level_w"][i]
        desc_l = desc_l + lw * desc
        rep_l = rep_l + lw * rep
        peak_l = peak_l + lw * pk
        rel_l = rel_l + lw * rel
        logs[f"acc{i}"] = (correct * okf).sum().item() / max(okf.sum().item(), 1)
    gA, gB = out["glob"][:N], out["glob"][N:]
    gs = gA @ gB.t() / 0.1
    t = torch.arange(N)
    glob = 0.5 * (F.cross_entropy(gs, t) + F.cross_entropy(gs.t(), t))
    total = (args.w_rec * rec + args.lam * comp + warm * args.w_rate * rate + args.w_desc * desc_l
             + warm * args.w_rep * rep_l + warm * args.w_peak * peak_l + warm * args.w_rel * rel_l
             + args.w_glob * glob)
    logs.update(rec=rec.item(), comp=comp.item(), rate=float(rate), desc=float(desc_l), rep=float(rep_l),
                peak=float(peak_l), rel=float(rel_l), glob=glob.item())
    return total, logs, out


@torch.no_grad()
def validate(net, val_batches):
    """Mutual-NN accuracy (within one cell) of the top-scored cells per level, on fixed pairs."""
    net.eval()
    accs = np.zeros(len(net.strides))
    rates = np.zeros(len(net.strides))
    stds = np.zeros(len(net.strides))
    n = 0
    for A, B, H, V in val_batches:
        feA, lgA = net.encode(A)
        feB, lgB = net.encode(B)
        N, S = A.shape[0], A.shape[-1]
        for i, s in enumerate(net.strides):
            pA = torch.sigmoid(lgA[i])
            pB = torch.sigmoid(lgB[i])
            rates[i] += pA.mean().item()
            stds[i] += pA.std().item()
            h, w = pA.shape[-2:]
            K = max(8, h * w // 16)
            for b in range(N):
                grid = level_grid_coords(h, w, s, A.device).reshape(-1, 2)
                kA = pA[b].flatten().topk(K).indices
                kB = pB[b].flatten().topk(K).indices
                xA, xB = grid[kA], grid[kB]
                dA = F.normalize(feA[i][b].flatten(1).t()[kA], dim=1)
                dB = F.normalize(feB[i][b].flatten(1).t()[kB], dim=1)
                sim = dA @ dB.t()
                m1 = sim.argmax(1)
                m2 = sim.argmax(0)
                mutual = m2[m1] == torch.arange(K)
                proj = warp_points(H[b:b + 1], xA[None])[0]
                err = (proj - xB[m1]).norm(dim=1)
                good = (err <= s * 1.0) & mutual
                accs[i] += good.float().sum().item() / max(mutual.float().sum().item(), 1)
        n += 1
    net.train()
    nb = sum(b[0].shape[0] for b in val_batches)
    return accs / nb, rates / n, stds / n


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--loss", choices=["sfp", "paper", "rate"], default="sfp")
    ap.add_argument("--minutes", type=float, default=70)
    ap.add_argument("--max-steps", type=int, default=10 ** 9)
    ap.add_argument("--batch", type=int, default=6)
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lam", type=float, default=0.05)
    ap.add_argument("--w-rec", type=float, default=5.0)
    ap.add_argument("--w-rate", type=float, default=20.0)
    ap.add_argument("--w-desc", type=float, default=1.0)
    ap.add_argument("--w-rep", type=float, default=0.5)
    ap.add_argument("--w-peak", type=float, default=0.5)
    ap.add_argument("--w-rel", type=float, default=0.3)
    ap.add_argument("--w-glob", type=float, default=0.1)
    ap.add_argument("--tau", type=float, default=0.1)
    ap.add_argument("--kpts", type=int, default=128)
    ap.add_argument("--warmup", type=int, default=150)
    ap.add_argument("--targets", type=str, default="0.08,0.12,0.18,0.25")
    ap.add_argument("--val-every", type=int, default=100)
    args = ap.parse_args()
    args.targets = [float(t) for t in args.targets.split(",")]
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "args.json"), "w") as f:
        json.dump(vars(args), f, indent=1)

    files = D.train_files()
    imgs = [D.load_gray(p, 640) for p in files] + D.skimage_images()
    print(f"train images: {len(files)} files + {len(imgs) - len(files)} skimage; "
          f"queries excluded: {len(D.query_names())}", flush=True)
    sampler = D.PairSampler(imgs, size=args.size, seed=args.seed)
    vimgs = [D.load_gray(p, 640) for p in D.val_files()]
    vs = D.PairSampler(vimgs, size=256, seed=1234)
    val_batches = []
    for _ in range(4):
        A, B, H, V = vs.batch(4)
        val_batches.append((torch.from_numpy(A), torch.from_numpy(B), torch.from_numpy(H), torch.from_numpy(V)))

    net = SFP()
    nparam = sum(p.numel() for p in net.parameters())
    print(f"params: {nparam}", flush=True)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    cfg = dict(level_w=[1.0] * len(net.strides))
    t0 = time.time()
    budget = args.minutes * 60
    logf = open(os.path.join(args.out, "log.csv"), "w", newline="")
    logw = None
    valf = open(os.path.join(args.out, "val.csv"), "w", newline="")
    valw = csv.writer(valf)
    valw.writerow(["step", "minutes"] + [f"acc{i}" for i in range(4)] + [f"rate{i}" for i in range(4)] +
                  [f"std{i}" for i in range(4)] + ["score"])
    best = -2.0
    step = 0
    ema = None
    while step < args.max_steps and time.time() - t0 < budget:
        frac = (time.time() - t0) / budget
        lr = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))
        for g in opt.param_groups:
            g["lr"] = lr if step >= 50 else lr * (step + 1) / 50
        A, B, H, V = sampler.batch(args.batch)
        A, B, H, V = map(torch.from_numpy, (A, B, H, V))
        loss, logs, out = compute_losses(net, A, B, H, V, args, step, cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
        opt.step()
        rates = [p.mean().item() for p in out["probs"]]
        row = dict(step=step, minutes=round((time.time() - t0) / 60, 3), lr=lr, loss=loss.item(), **logs,
                   **{f"rate{i}": r for i, r in enumerate(rates)})
        if logw is None:
            logw = csv.DictWriter(logf, fieldnames=list(row.keys()))
            logw.writeheader()
        logw.writerow(row)
        ema = loss.item() if ema is None else 0.98 * ema + 0.02 * loss.item()
        if step % 20 == 0:
            logf.flush()
            print(f"step {step} t={row['minutes']:.1f}m loss={loss.item():.4f} ema={ema:.4f} rec={logs['rec']:.4f} "
                  f"rates={[round(r, 3) for r in rates]} " +
                  " ".join(f"{k}={v:.3f}" for k, v in logs.items() if k not in ('rec',)), flush=True)
        step += 1
        if step % args.val_every == 0 or time.time() - t0 >= budget:
            accs, vr, vsd = validate(net, val_batches)
            alive = all(r > 0.01 and sd > 0.02 for r, sd in zip(vr, vsd))
            score = float(np.mean(accs)) if alive else -1.0
            valw.writerow([step, round((time.time() - t0) / 60, 2)] + list(np.round(accs, 4)) +
                          list(np.round(vr, 4)) + list(np.round(vsd, 4)) + [round(score, 4)])
            valf.flush()
            print(f"VAL step {step} acc={np.round(accs, 3)} rates={np.round(vr, 3)} std={np.round(vsd, 3)} "
                  f"score={score:.4f}", flush=True)
            ck = dict(model=net.state_dict(), step=step, args=vars(args), val_acc=accs.tolist(),
                      val_rates=vr.tolist(), val_std=vsd.tolist(), minutes=(time.time() - t0) / 60)
            torch.save(ck, os.path.join(args.out, "last.pt"))
            if score > best:
                best = score
                torch.save(ck, os.path.join(args.out, "best.pt"))
            if step in (300, 600, 1000, 1500, 2000):
                torch.save(ck, os.path.join(args.out, f"step{step}.pt"))
    print(f"done: {step} steps in {(time.time() - t0) / 60:.1f} min, best val score {best:.4f}", flush=True)


if __name__ == "__main__":
    main()
