//! Does a rotation before product quantisation help (issue 14, "OPQ if it measurably helps")?
//! A throwaway measurement (removed in the next commit): `cargo run --release --features
//! colmap,localize,fuzzing --example opq_check -- COPY_OF_database.db 64 8`. SIFT rows in the
//! uncentred PCA basis (first `dims`), PQ with M subspaces on the PCA order, on dimension
//! orders (round robin, snake, eigenvalue allocation), and OPQ (Procrustes) iterations.
use nalgebra::DMatrix;
use sfpmap::build::basis::Basis;
use sfpmap::build::pq::Quantiser;
use sfpmap::colmap::Database;
use sfpmap::localize::internals::{normalise_rows, sgemm_abt};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let db = Database::open(std::path::Path::new(&args[1])).unwrap();
    let dims: usize = args[2].parse().unwrap();
    let m: usize = args[3].parse().unwrap();
    let mut rows: Vec<f32> = Vec::new();
    for f in db.iter_features().unwrap() {
        let f = f.unwrap();
        if let Some(d) = f.descriptors {
            for i in 0..d.len() {
                rows.extend(d.row(i).unwrap().iter().map(|&v| v as f32));
            }
        }
        if rows.len() >= 104_000 * 128 {
            break;
        }
    }
    let n = rows.len() / 128;
    normalise_rows(&mut rows, 128);
    let basis = Basis::fit(&rows[..30_000.min(n) * 128], 128);
    let mut x = vec![0.0f32; n * dims];
    let mut full = vec![0.0f32; 128];
    for (r, o) in rows.chunks_exact(128).zip(x.chunks_exact_mut(dims)) {
        basis.project(r, &mut full);
        o.copy_from_slice(&full[..dims]);
    }
    normalise_rows(&mut x, dims);
    let nq = 2000;
    let (queries, database) = x.split_at(nq * dims);
    let nd = database.len() / dims;
    eprintln!("{n} rows, {nd} database, {nq} queries, {dims} dims, M {m}");
    let exact_top = top1(queries, database, dims);
    // Variance per dim -> eigenvalue allocation (Ge et al. 2013, OPQ_P).
    let mut var = vec![0.0f64; dims];
    for r in database.chunks_exact(dims) {
        for (v, &x) in var.iter_mut().zip(r) {
            *v += f64::from(x * x);
        }
    }
    let mean = var.iter().sum::<f64>() / dims as f64;
    let per = dims / m;
    let mut buckets: Vec<(f64, Vec<usize>)> = vec![(0.0, vec![]); m];
    for d in 0..dims {
        let key = |b: usize| if buckets[b].1.is_empty() { f64::NEG_INFINITY } else { buckets[b].0 };
        let b = (0..m)
            .filter(|&b| buckets[b].1.len() < per)
            .min_by(|&a, &b| key(a).total_cmp(&key(b)))
            .unwrap();
        buckets[b].0 += (var[d] * database.len() as f64 / dims as f64 / mean / 64.0).max(1e-12).ln();
        buckets[b].1.push(d);
    }
    let perm: Vec<usize> = buckets.iter().flat_map(|b| b.1.clone()).collect();
    let ident: Vec<usize> = (0..dims).collect();
    let eval = |name: &str, rot: &DMatrix<f32>| -> DMatrix<f32> {
        let apply = |v: &[f32]| -> Vec<f32> {
            let mut o = vec![0.0f32; v.len()];
            let nr = v.len() / dims;
            let a = DMatrix::from_row_slice(nr, dims, v);
            let b = &a * rot.transpose();
            for i in 0..nr {
                for j in 0..dims {
                    o[i * dims + j] = b[(i, j)];
                }
            }
            o
        };
        let db_r = apply(database);
        let q_r = apply(queries);
        let t = std::time::Instant::now();
        let q = Quantiser::train(&db_r[..16_384 * dims], dims, m, 256).unwrap();
        let mut codes = vec![0u8; nd * m];
        let err = q.encode_rows(&db_r, &mut codes);
        let secs = t.elapsed().as_secs_f64();
        let cb = q.codebook();
        let d = dims / m;
        let mut recon = vec![0.0f32; nd * dims];
        for (r, o) in codes.chunks_exact(m).zip(recon.chunks_exact_mut(dims)) {
            for (s, &c) in r.iter().enumerate() {
                let at = (s * 256 + c as usize) * d;
                o[s * d..(s + 1) * d].copy_from_slice(&cb[at..at + d]);
            }
        }
        normalise_rows(&mut recon, dims);
        let got = top1(&q_r, &recon, dims);
        let hit = got.iter().zip(&exact_top).filter(|(a, b)| a == b).count();
        println!(
            "{name:>28}: mse {:.5}  recall@1 of the exact NN {:.3}  ({secs:.2} s train+encode)",
            err / nd as f64,
            hit as f64 / nq as f64
        );
        // Y for OPQ's Procrustes step: reconstructions (unnormalised) in the rotated space.
        let mut y = vec![0.0f32; nd * dims];
        for (r, o) in codes.chunks_exact(m).zip(y.chunks_exact_mut(dims)) {
            for (s, &c) in r.iter().enumerate() {
                let at = (s * 256 + c as usize) * d;
                o[s * d..(s + 1) * d].copy_from_slice(&cb[at..at + d]);
            }
        }
        DMatrix::from_row_slice(nd, dims, &y)
    };
    let perm_matrix = |p: &[usize]| {
        let mut r = DMatrix::<f32>::zeros(dims, dims);
        for (i, &j) in p.iter().enumerate() {
            r[(i, j)] = 1.0;
        }
        r
    };
    eval("PQ on the PCA basis", &perm_matrix(&ident));
    let rr: Vec<usize> = (0..m).flat_map(|b| (0..per).map(move |i| i * m + b)).collect();
    eval("round robin", &perm_matrix(&rr));
    let snake: Vec<usize> = (0..m)
        .flat_map(|b| (0..per).map(move |i| if i % 2 == 0 { i * m + b } else { i * m + m - 1 - b }))
        .collect();
    eval("snake", &perm_matrix(&snake));
    let mut rot = perm_matrix(&perm);
    let mut y = eval("eigenvalue allocation", &rot);
    let xm = DMatrix::from_row_slice(nd, dims, database);
    for it in 0..6 {
        // min ‖X Rᵀ − Y‖: Rᵀ = U Vᵀ with Xᵀ Y = U S Vᵀ.
        let svd = (xm.transpose() * &y).svd(true, true);
        let rt = svd.u.unwrap() * svd.v_t.unwrap();
        rot = rt.transpose();
        y = eval(&format!("OPQ iteration {}", it + 1), &rot);
    }
}

fn top1(q: &[f32], db: &[f32], dims: usize) -> Vec<usize> {
    let nq = q.len() / dims;
    let nd = db.len() / dims;
    let mut best = vec![(f32::NEG_INFINITY, 0usize); nq];
    let block = 4096;
    let mut out = vec![0.0f32; nq * block];
    for start in (0..nd).step_by(block) {
        let len = block.min(nd - start);
        sgemm_abt(q, &db[start * dims..(start + len) * dims], &mut out[..nq * len], nq, len, dims);
        for i in 0..nq {
            for j in 0..len {
                let v = out[i * len + j];
                if v > best[i].0 {
                    best[i] = (v, start + j);
                }
            }
        }
    }
    best.into_iter().map(|b| b.1).collect()
}
