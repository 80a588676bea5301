//! Integration tests of the tile rasterizer against a brute-force reference renderer
//! written independently here (f64 projection, no tiles, every Gaussian against every
//! pixel of its 3-sigma tile set, identical f32 per-pixel arithmetic).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::sync::OnceLock;

use profuse_formats::rng::SplitMix64;
use profuse_formats::{Cameras, Gaussians};
use splat_raster::{
    camera, DepthMode, ListScratch, RasterError, Rasterizer, RenderOptions, Simd, ViewCamera,
    ViewRender, MAX_TOP_K, NO_GAUSSIAN, TILE,
};

// ---------------------------------------------------------------------------------------
// Small deterministic RNG (SplitMix64).

struct Rng(SplitMix64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0.unit()
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

// ---------------------------------------------------------------------------------------
// Brute-force reference.

const SH_C0: f64 = 0.28209479177387814;
const SH_C1: f64 = 0.4886025119029199;
const SH_C2: [f64; 5] = [
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
];
const SH_C3: [f64; 7] = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
];

type M3 = [[f64; 3]; 3];

fn matmul(a: &M3, b: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            for (k, bk) in b.iter().enumerate() {
                c[i][j] += a[i][k] * bk[j];
            }
        }
    }
    c
}

fn transpose(a: &M3) -> M3 {
    let mut t = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            t[i][j] = a[j][i];
        }
    }
    t
}

/// Rotates v by the unit quaternion (w, x, y, z): v' = v + 2w (q×v) + 2 q×(q×v).
fn quat_rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    let u = [x, y, z];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let c1 = cross(u, v);
    let c2 = cross(u, c1);
    [
        v[0] + 2.0 * (w * c1[0] + c2[0]),
        v[1] + 2.0 * (w * c1[1] + c2[1]),
        v[2] + 2.0 * (w * c1[2] + c2[2]),
    ]
}

#[derive(Debug, Clone, Copy)]
struct RefSplat {
    id: u32,
    x: f32,
    y: f32,
    conic: [f32; 3],
    opacity: f32,
    color: [f32; 3],
    depth: f32,
    // f64 values for comparing with the library's projection
    center: [f64; 2],
    conic64: [f64; 3],
    radius: f64,
    /// Inclusive tile range tx0, tx1, ty0, ty1 (clamped to the grid).
    tiles: [usize; 4],
}

fn ref_sh(degree: usize, g: &Gaussians, i: usize, dir: [f64; 3]) -> [f64; 3] {
    let r = g.sh_rest_coeffs();
    let coef = |k: usize, c: usize| -> f64 {
        if k == 0 {
            f64::from(g.sh_dc[i][c])
        } else {
            f64::from(g.sh_rest.as_ref().unwrap()[(i * r + k - 1) * 3 + c])
        }
    };
    let [x, y, z] = dir;
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let mut v = SH_C0 * coef(0, c);
        if degree > 0 {
            v = v - SH_C1 * y * coef(1, c) + SH_C1 * z * coef(2, c) - SH_C1 * x * coef(3, c);
        }
        if degree > 1 {
            let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
            v += SH_C2[0] * xy * coef(4, c)
                + SH_C2[1] * yz * coef(5, c)
                + SH_C2[2] * (2.0 * zz - xx - yy) * coef(6, c)
                + SH_C2[3] * xz * coef(7, c)
                + SH_C2[4] * (xx - yy) * coef(8, c);
            if degree > 2 {
                v += SH_C3[0] * y * (3.0 * xx - yy) * coef(9, c)
                    + SH_C3[1] * xy * z * coef(10, c)
                    + SH_C3[2] * y * (4.0 * zz - xx - yy) * coef(11, c)
                    + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coef(12, c)
                    + SH_C3[4] * x * (4.0 * zz - xx - yy) * coef(13, c)
                    + SH_C3[5] * z * (xx - yy) * coef(14, c)
                    + SH_C3[6] * x * (xx - 3.0 * yy) * coef(15, c);
            }
        }
        *o = (v + 0.5).max(0.0);
    }
    out
}

/// Projects every Gaussian independently of the library (f64, explicit matrices).
fn ref_project(g: &Gaussians, cams: &Cameras, view: usize) -> Vec<RefSplat> {
    let (rw, t) = cams.pose(view);
    let [fx, fy, cx, cy] = cams.intrinsics[view];
    let [w, h] = cams.image_size[view];
    let (w, h) = (f64::from(w), f64::from(h));
    let campos = cams.center(view);
    let tiles_x = (w as usize).div_ceil(16);
    let tiles_y = (h as usize).div_ceil(16);
    let mut out = Vec::new();
    for i in 0..g.len() {
        let m = g.means[i].map(f64::from);
        let p: Vec<f64> = (0..3)
            .map(|r| rw[r][0] * m[0] + rw[r][1] * m[1] + rw[r][2] * m[2] + t[r])
            .collect();
        if p[2] <= 0.2 {
            continue;
        }
        // Σ = R S² Rᵀ, R's columns are the rotated basis vectors.
        let q = g.rotations[i].map(f64::from);
        let qn = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
        let q = q.map(|v| v / qn);
        let cols: Vec<[f64; 3]> = (0..3)
            .map(|k| {
                let mut e = [0.0; 3];
                e[k] = 1.0;
                quat_rotate(q, e)
            })
            .collect();
        let rot: M3 = std::array::from_fn(|r| std::array::from_fn(|c| cols[c][r]));
        let s = g.log_scales[i].map(|l| f64::from(l).exp());
        let s2: M3 = [
            [s[0] * s[0], 0.0, 0.0],
            [0.0, s[1] * s[1], 0.0],
            [0.0, 0.0, s[2] * s[2]],
        ];
        let sigma = matmul(&matmul(&rot, &s2), &transpose(&rot));
        // Jacobian with INRIA's 1.3 x half-FOV clamp (generalised to any principal point).
        let clampt = |v: f64, c: f64, f: f64, size: f64| {
            let lo = -c / f;
            let hi = (size - c) / f;
            let mid = (lo + hi) / 2.0;
            let half = (hi - lo) / 2.0;
            v.max(mid - 1.3 * half).min(mid + 1.3 * half)
        };
        let z = p[2];
        let txz = clampt(p[0] / z, cx, fx, w) * z;
        let tyz = clampt(p[1] / z, cy, fy, h) * z;
        let jac: M3 = [
            [fx / z, 0.0, -fx * txz / (z * z)],
            [0.0, fy / z, -fy * tyz / (z * z)],
            [0.0, 0.0, 0.0],
        ];
        let tm = matmul(&jac, &rw);
        let cov = matmul(&matmul(&tm, &sigma), &transpose(&tm));
        let (a, b, c) = (cov[0][0] + 0.3, cov[0][1], cov[1][1] + 0.3);
        let det = a * c - b * b;
        if det.is_nan() || det <= 0.0 || !det.is_finite() {
            continue;
        }
        let mid = 0.5 * (a + c);
        let l1 = mid + (mid * mid - det).max(0.1).sqrt();
        let l2 = mid - (mid * mid - det).max(0.1).sqrt();
        let radius = (3.0 * l1.max(l2).sqrt()).ceil();
        let u = fx * p[0] / z + cx;
        let v = fy * p[1] / z + cy;
        let tr = |c: f64, n: usize| -> Option<[usize; 2]> {
            let lo = ((c - radius) / 16.0).floor();
            let hi = ((c + radius) / 16.0).floor();
            if hi < 0.0 || lo > (n - 1) as f64 {
                return None;
            }
            Some([lo.max(0.0) as usize, hi.min((n - 1) as f64) as usize])
        };
        let (Some([tx0, tx1]), Some([ty0, ty1])) = (tr(u, tiles_x), tr(v, tiles_y)) else {
            continue;
        };
        let d = [m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]];
        let dn = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let color = ref_sh(g.sh_degree, g, i, d.map(|x| x / dn));
        let opacity = 1.0 / (1.0 + (-f64::from(g.opacity_logits[i])).exp());
        let conic64 = [c / det, -b / det, a / det];
        out.push(RefSplat {
            id: i as u32,
            x: u as f32,
            y: v as f32,
            conic: conic64.map(|x| x as f32),
            opacity: opacity as f32,
            color: color.map(|x| x as f32),
            depth: z as f32,
            center: [u, v],
            conic64,
            radius,
            tiles: [tx0, tx1, ty0, ty1],
        });
    }
    out.sort_by(|p, q| p.depth.total_cmp(&q.depth).then(p.id.cmp(&q.id)));
    out
}

struct RefImage {
    width: usize,
    color: Vec<[f32; 3]>,
    depth: Vec<f32>,
    t: Vec<f32>,
    /// Every contributor of every pixel in blend order: (id, weight).
    hits: Vec<Vec<(u32, f32)>>,
}

/// Every Gaussian against every pixel of its 3-sigma tile set, front to back.
fn ref_render(g: &Gaussians, cams: &Cameras, view: usize) -> RefImage {
    let splats = ref_project(g, cams, view);
    let [w, h] = cams.image_size[view].map(|v| v as usize);
    let mut out = RefImage {
        width: w,
        color: vec![[0.0; 3]; w * h],
        depth: vec![0.0; w * h],
        t: vec![1.0; w * h],
        hits: vec![Vec::new(); w * h],
    };
    // Candidate lists per pixel, in depth order: the pixel's tile must lie in the
    // Gaussian's tile range (the same set as testing every Gaussian at every pixel).
    let mut cand: Vec<Vec<u32>> = vec![Vec::new(); w * h];
    for (si, s) in splats.iter().enumerate() {
        let [tx0, tx1, ty0, ty1] = s.tiles;
        for py in ty0 * 16..((ty1 + 1) * 16).min(h) {
            for px in tx0 * 16..((tx1 + 1) * 16).min(w) {
                cand[py * w + px].push(si as u32);
            }
        }
    }
    for py in 0..h {
        for px in 0..w {
            let i = py * w + px;
            let mut t = 1.0f32;
            let mut col = [0.0f32; 3];
            let mut depth = 0.0f32;
            for &si in &cand[i] {
                let s = &splats[si as usize];
                let dx = s.x - (px as f32 + 0.5);
                let dy = s.y - (py as f32 + 0.5);
                let [a, b, c] = s.conic;
                let power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy;
                if power.is_nan() || power > 0.0 {
                    continue;
                }
                // The library's exp (a vectorisable ~2 ulp expf), so results compare exactly.
                let alpha = (s.opacity * splat_raster::math::exp(power)).min(0.99);
                if alpha < 1.0 / 255.0 {
                    continue;
                }
                let test_t = t * (1.0 - alpha);
                if test_t < 1e-4 {
                    break;
                }
                let wgt = alpha * t;
                for (c, sc) in col.iter_mut().zip(s.color) {
                    *c += sc * wgt;
                }
                depth += s.depth * wgt;
                t = test_t;
                out.hits[i].push((s.id, wgt));
            }
            out.color[i] = col;
            out.depth[i] = depth;
            out.t[i] = t;
        }
    }
    out
}

/// The K largest of a contributor list, descending, ties in blend (depth) order.
fn top_k(hits: &[(u32, f32)], k: usize) -> Vec<(u32, f32)> {
    let mut v = hits.to_vec();
    v.sort_by(|a, b| b.1.total_cmp(&a.1)); // stable: ties keep depth order
    v.truncate(k);
    v
}

/// Compares a library render with the reference; returns (max colour error, pixels with
/// hits, top-K slots compared).
fn compare(lib: &ViewRender, r: &RefImage, k: usize, what: &str) -> (f32, usize, usize) {
    let color = lib.color().unwrap();
    let alpha = lib.alpha().unwrap();
    let trans = lib.transmittance().unwrap();
    let depth = lib.depth().unwrap();
    let mut max_err = 0.0f32;
    let mut hit_pixels = 0;
    let mut slots = 0;
    for (i, rc) in r.color.iter().enumerate() {
        let (px, py) = (i % r.width, i / r.width);
        for ch in 0..3 {
            let e = (color[i * 3 + ch] - rc[ch]).abs();
            max_err = max_err.max(e);
            assert!(
                e <= 1e-5,
                "{what}: colour of pixel ({px},{py}) ch {ch}: {} vs reference {}",
                color[i * 3 + ch],
                rc[ch]
            );
        }
        assert!(
            (alpha[i] - (1.0 - r.t[i])).abs() <= 1e-5,
            "{what}: alpha of ({px},{py})"
        );
        assert!(
            (trans[i] - r.t[i]).abs() <= 1e-5,
            "{what}: T of ({px},{py})"
        );
        assert!(
            (depth[i] - r.depth[i]).abs() <= 1e-5 * r.depth[i].abs().max(1.0),
            "{what}: depth of ({px},{py}): {} vs {}",
            depth[i],
            r.depth[i]
        );
        let want = top_k(&r.hits[i], k);
        let (ids, ws) = lib.topk(px, py).unwrap();
        let n = ids.iter().take_while(|&&id| id != NO_GAUSSIAN).count();
        assert_eq!(n, want.len(), "{what}: hit count of ({px},{py})");
        assert!(ids[n..].iter().all(|&id| id == NO_GAUSSIAN) && ws[n..].iter().all(|&w| w == 0.0));
        if n > 0 {
            hit_pixels += 1;
        }
        slots += n;
        // Weights in descending order, matching the reference's sorted weights.
        for j in 0..n {
            assert!(
                (ws[j] - want[j].1).abs() <= 1e-6,
                "{what}: weight {j} of ({px},{py})"
            );
            if j > 0 {
                assert!(ws[j] <= ws[j - 1]);
            }
        }
        // Identical id sets, except where the boundary weight ties within 1e-7.
        let mut got: Vec<u32> = ids[..n].to_vec();
        let mut exp: Vec<u32> = want.iter().map(|h| h.0).collect();
        got.sort_unstable();
        exp.sort_unstable();
        if got != exp {
            let kth = want.last().unwrap().1;
            let weight_of = |id: u32| r.hits[i].iter().find(|h| h.0 == id).map(|h| h.1);
            for id in got
                .iter()
                .filter(|id| !exp.contains(id))
                .chain(exp.iter().filter(|id| !got.contains(id)))
            {
                let w = weight_of(*id).unwrap_or(f32::NAN);
                assert!(
                    (w - kth).abs() <= 1e-7,
                    "{what}: top-K ids of ({px},{py}) differ at id {id} (weight {w}, K-th {kth})"
                );
            }
        } else {
            // Same set: the order must be the reference's (weight desc, depth order ties).
            let order: Vec<u32> = want.iter().map(|h| h.0).collect();
            assert_eq!(&ids[..n], &order[..], "{what}: top-K order of ({px},{py})");
        }
    }
    (max_err, hit_pixels, slots)
}

// ---------------------------------------------------------------------------------------
// Scenes.

/// A random scene in front of a camera at the origin looking down +z (plus stragglers
/// behind it), with SH degree 3, varied scales, rotations and opacities, and some
/// Gaussians centred exactly on tile borders.
fn random_scene(seed: u64, n: usize, cams: &Cameras) -> Gaussians {
    let mut rng = Rng(SplitMix64::new(seed));
    let [fx, fy, cx, cy] = cams.intrinsics[0];
    let [w, h] = cams.image_size[0].map(f64::from);
    let (rw, t) = cams.pose(0);
    let mut means = Vec::new();
    let mut log_scales = Vec::new();
    let mut rotations = Vec::new();
    let mut logits = Vec::new();
    let mut dc = Vec::new();
    let mut rest = Vec::new();
    for i in 0..n {
        let z = if i % 17 == 0 {
            rng.range(-2.0, 0.25) // behind the camera or at the near plane
        } else {
            rng.range(0.5, 6.0)
        };
        let (mut u, mut v) = (rng.range(-0.2 * w, 1.2 * w), rng.range(-0.2 * h, 1.2 * h));
        if i % 7 == 0 {
            u = 16.0 * (rng.range(0.0, w / 16.0)).round(); // on a vertical tile border
        }
        if i % 11 == 0 {
            v = 16.0 * (rng.range(0.0, h / 16.0)).round() + 1e-3; // just past a horizontal one
        }
        let pc = [(u - cx) * z / fx, (v - cy) * z / fy, z];
        // Camera → world: x = Rᵀ (p − t).
        let pw: [f32; 3] = std::array::from_fn(|a| {
            ((0..3).map(|r| rw[r][a] * (pc[r] - t[r])).sum::<f64>()) as f32
        });
        means.push(pw);
        let base = rng.range(-4.0, -0.8);
        log_scales.push(std::array::from_fn(|_| {
            (base + rng.range(-1.5, 1.0)) as f32
        }));
        rotations.push(std::array::from_fn(|_| rng.normal() as f32));
        logits.push(match i % 23 {
            0 => f32::INFINITY,
            1 => -6.0, // opacity < 1/255: never drawn
            _ => rng.range(-3.0, 5.0) as f32,
        });
        dc.push(std::array::from_fn(|_| rng.range(-1.5, 1.5) as f32));
        for _ in 0..15 * 3 {
            rest.push(rng.range(-0.3, 0.3) as f32);
        }
    }
    Gaussians {
        means: means.into(),
        log_scales: log_scales.into(),
        rotations: rotations.into(),
        opacity_logits: logits.into(),
        sh_dc: dc.into(),
        sh_degree: 3,
        sh_rest: Some(rest.into()),
        ..Default::default()
    }
}

fn camera_at(w: u32, h: u32, intrinsics: [f64; 4], eye: [f64; 3], target: [f64; 3]) -> Cameras {
    let pose = camera::look_at(eye, target, [0.0, -1.0, 0.0]).unwrap();
    camera::cameras_from_poses(&[pose], w, h, intrinsics)
}

fn all_outputs(k: usize) -> RenderOptions {
    RenderOptions {
        depth: DepthMode::Accumulated,
        ..RenderOptions::all(k)
    }
}

// ---------------------------------------------------------------------------------------
// Tests against the reference.

/// Rasterizers of `g` for every SIMD width this CPU runs (portable first).
fn rasterizers(g: &Gaussians) -> Vec<Rasterizer<'_>> {
    let mut out = Vec::new();
    for simd in [Simd::Portable, Simd::Avx512] {
        let mut r = Rasterizer::new(g).unwrap();
        match r.set_simd(simd) {
            Ok(()) => {
                assert_eq!(r.simd(), simd);
                out.push(r);
            }
            Err(e) => {
                assert!(matches!(e, RasterError::SimdUnsupported { .. }));
                eprintln!("{} not tested: {e}", simd.name());
            }
        }
    }
    out
}

#[test]
fn tiled_renderer_matches_brute_force_on_random_scenes() {
    let cases: [(u64, usize, u32, u32, [f64; 4]); 4] = [
        (1, 300, 83, 61, [70.0, 70.0, 41.5, 30.5]),
        (2, 500, 50, 37, [40.0, 55.0, 20.0, 21.0]), // off-centre principal point, fx != fy
        (3, 200, 129, 17, [90.0, 90.0, 64.5, 8.5]),
        (4, 400, 64, 48, [48.0, 48.0, 32.0, 24.0]), // multiple of 16
    ];
    let mut total_slots = 0;
    for (seed, n, w, h, intr) in cases {
        // The camera is not at the origin, so world and camera frames differ.
        let cams = camera_at(w, h, intr, [0.3, -0.2, -1.0], [0.5, 0.1, 4.0]);
        let g = camera_projection_scene(seed, n, &cams);
        let r = ref_render(&g, &cams, 0);
        for raster in rasterizers(&g) {
            for k in [1usize, 4, 16] {
                let lib = raster.render_view(&cams, 0, &all_outputs(k)).unwrap();
                let what = format!("seed {seed} {w}x{h} K={k} {}", raster.simd().name());
                let (err, hit_pixels, slots) = compare(&lib, &r, k, &what);
                assert!(
                    hit_pixels > (w * h) as usize / 2,
                    "{what}: only {hit_pixels} pixels hit"
                );
                assert!(err <= 1e-5);
                total_slots += slots;
            }
        }
        let raster = Rasterizer::new(&g).unwrap();
        // The library's f64 projection agrees with the independent one.
        let cam = ViewCamera::from_cameras(&cams, 0).unwrap();
        let refs = ref_project(&g, &cams, 0);
        let visible = (0..g.len())
            .filter(|&i| raster.project(&cam, i).is_some())
            .count();
        assert_eq!(visible, refs.len(), "seed {seed}: culling differs");
        for s in &refs {
            let p = raster.project(&cam, s.id as usize).unwrap();
            for a in 0..2 {
                assert!((p.center[a] - s.center[a]).abs() <= 1e-9 * s.center[a].abs().max(1.0));
            }
            for a in 0..3 {
                assert!((p.conic[a] - s.conic64[a]).abs() <= 1e-9 * s.conic64[a].abs().max(1e-3));
            }
            assert_eq!(p.radius, s.radius);
            assert_eq!(p.tiles.map(|t| t as usize), s.tiles);
        }
    }
    assert!(
        total_slots > 10_000,
        "too few top-K slots compared: {total_slots}"
    );
}

fn camera_projection_scene(seed: u64, n: usize, cams: &Cameras) -> Gaussians {
    random_scene(seed, n, cams)
}

fn guitar() -> Option<&'static Gaussians> {
    static G: OnceLock<Option<Gaussians>> = OnceLock::new();
    G.get_or_init(|| {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/data/splats/guitar.ply"
        );
        if !Path::new(path).exists() {
            eprintln!("SKIPPED: {path} is absent");
            return None;
        }
        Some(scene_io::ply::read_inria_ply(path).unwrap().0)
    })
    .as_ref()
}

/// Orbit cameras around the guitar's centroid at 2.5 x the RMS radius, one per axis
/// direction; returns them with the one covering most pixels first.
fn guitar_orbits(g: &Gaussians, w: u32, h: u32) -> Vec<(Cameras, f64)> {
    let ext = camera::scene_extent(g).unwrap();
    let c = ext.centroid;
    let dist = 2.5 * ext.rms_radius;
    let dirs: [([f64; 3], [f64; 3]); 6] = [
        ([1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),
        ([-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),
        ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),
        ([0.0, -1.0, 0.0], [0.0, 0.0, 1.0]),
        ([0.0, 0.0, 1.0], [0.0, -1.0, 0.0]),
        ([0.0, 0.0, -1.0], [0.0, -1.0, 0.0]),
    ];
    let raster = Rasterizer::new(g).unwrap();
    let opts = RenderOptions {
        color: false,
        alpha: true,
        ..Default::default()
    };
    let mut out: Vec<(Cameras, f64)> = dirs
        .iter()
        .map(|(d, up)| {
            // A slightly oblique direction so no view is exactly axis-aligned.
            let dir = [
                d[0] + 0.3 * up[0] + 0.2,
                d[1] + 0.3 * up[1] + 0.1,
                d[2] + 0.3 * up[2],
            ];
            let nrm = (dir.iter().map(|x| x * x).sum::<f64>()).sqrt();
            let eye: [f64; 3] = std::array::from_fn(|a| c[a] + dist * dir[a] / nrm);
            let pose = camera::look_at(eye, c, *up).unwrap();
            let cams =
                camera::cameras_from_poses(&[pose], w, h, camera::pinhole_intrinsics(w, h, 50.0));
            let r = raster.render_view(&cams, 0, &opts).unwrap();
            let cover =
                r.alpha().unwrap().iter().filter(|a| **a > 0.5).count() as f64 / f64::from(w * h);
            (cams, cover)
        })
        .collect();
    out.sort_by(|a, b| b.1.total_cmp(&a.1));
    out
}

#[test]
fn tiled_renderer_matches_brute_force_on_guitar() {
    let Some(g) = guitar() else { return };
    let rasters = rasterizers(g);
    let orbits = guitar_orbits(g, 96, 64);
    for (v, (cams, cover)) in orbits.iter().take(3).enumerate() {
        let r = ref_render(g, cams, 0);
        for raster in &rasters {
            let lib = raster.render_view(cams, 0, &all_outputs(10)).unwrap();
            let what = format!("guitar orbit {v} {}", raster.simd().name());
            let (err, hit_pixels, slots) = compare(&lib, &r, 10, &what);
            eprintln!("{what}: coverage {cover:.2}, {hit_pixels} pixels hit, {slots} top-K slots, max colour error {err:e}, visible {}", lib.stats().visible);
            assert!(hit_pixels > 500);
        }
    }
}

/// Every output of two renders, bit for bit (the first difference is reported).
fn assert_same_bytes(a: &ViewRender, b: &ViewRender, what: &str) {
    assert_same_outputs(a, b, what, true);
}

/// [`assert_same_bytes`], the colour planes compared only `with_colour`.
fn assert_same_outputs(a: &ViewRender, b: &ViewRender, what: &str, with_colour: bool) {
    fn same<T: PartialEq + std::fmt::Debug>(a: Option<&[T]>, b: Option<&[T]>, what: &str) {
        match (a, b) {
            (Some(a), Some(b)) => {
                assert_eq!(a.len(), b.len(), "{what}: lengths");
                if let Some(i) = (0..a.len()).find(|&i| a[i] != b[i]) {
                    panic!("{what}: first difference at {i}: {:?} vs {:?}", a[i], b[i]);
                }
            }
            (a, b) => assert_eq!(a.is_some(), b.is_some(), "{what}: presence"),
        }
    }
    let bits = |v: Option<&[f32]>| v.map(|v| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>());
    type Plane = fn(&ViewRender) -> Option<&[f32]>;
    let planes: [(&str, Plane); 5] = [
        ("colour", ViewRender::color),
        ("depth", ViewRender::depth),
        ("alpha", ViewRender::alpha),
        ("T", ViewRender::transmittance),
        ("weights", ViewRender::topk_weights),
    ];
    for (name, plane) in planes.into_iter().skip(usize::from(!with_colour)) {
        same(
            bits(plane(a)).as_deref(),
            bits(plane(b)).as_deref(),
            &format!("{what}: {name}"),
        );
    }
    same(a.topk_ids(), b.topk_ids(), &format!("{what}: ids"));
    assert_eq!(a.stats(), b.stats(), "{what}: stats");
}

/// A render without a colour output skips the colour of every splat (spherical harmonics
/// of degree 3 here): every other output is the same bytes as with colour, for the
/// lists-only path (K alone) and the path that also composites depth, alpha and T.
#[test]
fn renders_without_colour_give_the_other_outputs_of_renders_with_it() {
    let cams = camera_at(
        150,
        110,
        [110.0, 110.0, 75.0, 55.0],
        [0.0; 3],
        [0.0, 0.0, 1.0],
    );
    let g = random_scene(21, 3000, &cams);
    assert_eq!(g.sh_degree, 3);
    for raster in rasterizers(&g) {
        for k in [None, Some(8)] {
            for with_rest in [false, true] {
                let colour = RenderOptions {
                    top_k: k,
                    ..if with_rest {
                        all_outputs(k.unwrap_or(1))
                    } else {
                        RenderOptions::default()
                    }
                };
                let plain = RenderOptions {
                    color: false,
                    ..colour
                };
                if plain.validate().is_err() {
                    continue; // nothing left to render
                }
                let with = raster.render_view(&cams, 0, &colour).unwrap();
                let without = raster.render_view(&cams, 0, &plain).unwrap();
                assert!(with.color().is_some() && without.color().is_none());
                let what = format!("{:?}, K {k:?}, all outputs {with_rest}", raster.simd());
                assert_same_outputs(&with, &without, &what, false);
                if k.is_some() {
                    let ids = without.topk_ids().unwrap_or(&[]);
                    assert!(ids.iter().any(|&i| i != NO_GAUSSIAN), "{what}: empty lists");
                }
            }
        }
    }
}

#[test]
fn render_tiles_hands_over_every_tile_once_with_the_lists_of_a_view_render() {
    let cams = camera_at(
        161,
        117,
        [120.0, 120.0, 80.5, 58.5],
        [0.0; 3],
        [0.0, 0.0, 1.0],
    );
    let g = random_scene(12, 3000, &cams);
    let cam = ViewCamera::from_cameras(&cams, 0).unwrap();
    let (tiles_x, tiles_y) = (161usize.div_ceil(TILE), 117usize.div_ceil(TILE));
    for raster in rasterizers(&g) {
        // One scratch and one row vector for every K: both are reused.
        let mut scratch = ListScratch::default();
        let mut rows: Vec<Vec<(usize, usize, usize, usize)>> = vec![vec![(9, 9, 9, 9)]; 20];
        for k in [1usize, 10, 64] {
            let opts = RenderOptions {
                top_k: Some(k),
                color: false,
                ..Default::default()
            };
            let full = raster.render_view(&cams, 0, &opts).unwrap();
            let mismatches = std::sync::atomic::AtomicUsize::new(0);
            for r in &mut rows {
                r.clear();
            }
            let stats = raster
                .render_tiles(&cam, 0, k, &mut scratch, &mut rows, |tile, seen| {
                    assert_eq!(tile.k(), k);
                    seen.push((tile.x0(), tile.y0(), tile.width(), tile.height()));
                    for row in 0..tile.height() {
                        for col in 0..tile.width() {
                            let (ids, ws) = tile.pixel(col, row).unwrap();
                            let (fi, fw) = full.topk(tile.x0() + col, tile.y0() + row).unwrap();
                            let i = (row * TILE + col) * k;
                            assert_eq!(&tile.ids()[i..i + k], ids);
                            // Each entry's position names its id in the tile's splats.
                            for (&at, &id) in tile.positions()[i..i + k].iter().zip(ids) {
                                let named = tile.splat_ids().get(at as usize);
                                assert_eq!(named.copied().unwrap_or(NO_GAUSSIAN), id);
                                assert_eq!(at == NO_GAUSSIAN, id == NO_GAUSSIAN);
                            }
                            if ids != fi || ws != fw {
                                mismatches.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            }
                        }
                    }
                    let mut distinct = tile.splat_ids().to_vec();
                    distinct.sort_unstable();
                    distinct.dedup();
                    assert_eq!(distinct.len(), tile.splat_ids().len(), "a splat twice");
                    assert!(tile.pixel(tile.width(), 0).is_none());
                    assert!(tile.pixel(0, tile.height()).is_none());
                })
                .unwrap();
            let what = format!("{} K={k}", raster.simd().name());
            assert_eq!(mismatches.into_inner(), 0, "{what}: lists differ");
            assert_eq!(stats, full.stats(), "{what}");
            assert!(stats.tile_pairs > 5000, "{what}: scene too thin");
            assert_eq!(rows.len(), tiles_y, "{what}: one state per tile row");
            for (ty, seen) in rows.iter().enumerate() {
                let expected: Vec<_> = (0..tiles_x)
                    .map(|tx| {
                        let (x0, y0) = (tx * TILE, ty * TILE);
                        (x0, y0, (161 - x0).min(TILE), (117 - y0).min(TILE))
                    })
                    .collect();
                assert_eq!(seen, &expected, "{what}: tiles of row {ty}, in order");
            }
        }
        assert!(matches!(
            raster.render_tiles(
                &cam,
                0,
                0,
                &mut ListScratch::default(),
                &mut rows,
                |_, _| {}
            ),
            Err(RasterError::TopKZero)
        ));
    }
}

#[test]
fn every_simd_width_renders_the_same_bytes() {
    // Width and height not multiples of 16: partial tiles and groups.
    let cams = camera_at(
        161,
        117,
        [120.0, 120.0, 80.5, 58.5],
        [0.0; 3],
        [0.0, 0.0, 1.0],
    );
    let g = random_scene(11, 3000, &cams);
    let rasters = rasterizers(&g);
    let lists_only = |k| RenderOptions {
        top_k: Some(k),
        color: false,
        ..Default::default()
    };
    let mut configs = vec![
        ("colour".to_string(), RenderOptions::default()),
        (
            "normalised depth".to_string(),
            RenderOptions {
                depth: DepthMode::Normalized,
                background: [0.2, 0.5, 1.0],
                ..RenderOptions::all(1)
            },
        ),
    ];
    for k in [1, 3, 10, 64, MAX_TOP_K] {
        configs.push((format!("all K={k}"), all_outputs(k)));
        configs.push((format!("lists only K={k}"), lists_only(k)));
    }
    let portable = &rasters[0];
    for other in &rasters[1..] {
        for (name, opts) in &configs {
            let a = portable.render_view(&cams, 0, opts).unwrap();
            let b = other.render_view(&cams, 0, opts).unwrap();
            assert!(a.stats().tile_pairs > 5000, "{name}: scene too thin");
            assert_same_bytes(&a, &b, &format!("{name}, {}", other.simd().name()));
        }
    }
    if let Some(g) = guitar() {
        let rasters = rasterizers(g);
        for (cams, _) in guitar_orbits(g, 200, 150).iter().take(2) {
            for opts in [all_outputs(10), lists_only(40)] {
                let a = rasters[0].render_view(cams, 0, &opts).unwrap();
                for other in &rasters[1..] {
                    let b = other.render_view(cams, 0, &opts).unwrap();
                    assert_same_bytes(&a, &b, &format!("guitar, {}", other.simd().name()));
                }
            }
        }
    }
}

#[test]
fn guitar_orbit_view_covers_the_image_and_has_structure() {
    let Some(g) = guitar() else { return };
    let (cams, cover) = &guitar_orbits(g, 160, 120)[0];
    let raster = Rasterizer::new(g).unwrap();
    let out = raster
        .render_view(cams, 0, &RenderOptions::all(10))
        .unwrap();
    let alpha = out.alpha().unwrap();
    let covered = alpha.iter().filter(|a| **a > 0.5).count() as f64 / alpha.len() as f64;
    assert_eq!(covered, *cover);
    assert!(
        covered > 0.10,
        "only {:.1}% of pixels have alpha > 0.5",
        covered * 100.0
    );
    let color = out.color().unwrap();
    let lum: Vec<f32> = color.chunks_exact(3).map(|c| c[0] + c[1] + c[2]).collect();
    let mean = lum.iter().sum::<f32>() / lum.len() as f32;
    let var = lum.iter().map(|l| (l - mean) * (l - mean)).sum::<f32>() / lum.len() as f32;
    assert!(
        var.sqrt() > 0.05,
        "colour image is nearly constant (std {})",
        var.sqrt()
    );
    // Inside the covered region too, not just foreground vs background.
    let inside: Vec<f32> = lum
        .iter()
        .zip(alpha)
        .filter(|(_, a)| **a > 0.9)
        .map(|(l, _)| *l)
        .collect();
    let (lo, hi) = inside
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), l| (lo.min(*l), hi.max(*l)));
    assert!(hi - lo > 0.2, "covered pixels are flat: {lo}..{hi}");
}

// ---------------------------------------------------------------------------------------
// Invariants.

fn small_scene() -> (Gaussians, Cameras) {
    let cams = camera_at(45, 38, [40.0, 40.0, 22.5, 19.0], [0.0; 3], [0.0, 0.0, 1.0]);
    (random_scene(7, 150, &cams), cams)
}

#[test]
fn weights_and_transmittance_sum_to_one_and_top_k_is_a_prefix_of_the_full_list() {
    let (g, cams) = small_scene();
    let raster = Rasterizer::new(&g).unwrap();
    let full = raster
        .render_view(&cams, 0, &all_outputs(MAX_TOP_K))
        .unwrap();
    let t = full.transmittance().unwrap();
    let mut max_hits = 0;
    for y in 0..full.height() {
        for x in 0..full.width() {
            let (ids, ws) = full.topk(x, y).unwrap();
            let n = ids.iter().take_while(|&&id| id != NO_GAUSSIAN).count();
            assert!(
                n < MAX_TOP_K,
                "pixel ({x},{y}) may have more contributors than K"
            );
            max_hits = max_hits.max(n);
            let s: f64 = ws.iter().map(|w| f64::from(*w)).sum();
            let i = y * full.width() + x;
            assert!(
                (s + f64::from(t[i]) - 1.0).abs() <= 1e-5,
                "pixel ({x},{y}): Σω {s} + T {} != 1",
                t[i]
            );
        }
    }
    assert!(
        max_hits >= 10,
        "scene too thin: at most {max_hits} hits per pixel"
    );
    for k in [1usize, 3, 10] {
        let part = raster.render_view(&cams, 0, &all_outputs(k)).unwrap();
        for y in 0..full.height() {
            for x in 0..full.width() {
                let (fi, fw) = full.topk(x, y).unwrap();
                let (pi, pw) = part.topk(x, y).unwrap();
                assert_eq!(pi, &fi[..k], "K={k} ids at ({x},{y})");
                assert_eq!(pw, &fw[..k], "K={k} weights at ({x},{y})");
            }
        }
        // Colour and the rest do not depend on K.
        assert_eq!(part.color(), full.color());
        assert_eq!(part.transmittance(), full.transmittance());
        // Nor on the other outputs: a lists-only render (as registration renders) stops
        // each pixel once its list is final, and must give the same lists.
        let bare = RenderOptions {
            top_k: Some(k),
            color: false,
            ..Default::default()
        };
        let lists = raster.render_view(&cams, 0, &bare).unwrap();
        assert!(lists.color().is_none() && lists.transmittance().is_none());
        assert_eq!(lists.topk_ids(), part.topk_ids(), "K={k} ids, lists only");
        assert_eq!(
            lists.topk_weights(),
            part.topk_weights(),
            "K={k} weights, lists only"
        );
    }
    // Normalised depth = Σωz / Σω, between the nearest and farthest Gaussian.
    let nd = raster
        .render_view(
            &cams,
            0,
            &RenderOptions {
                depth: DepthMode::Normalized,
                ..Default::default()
            },
        )
        .unwrap();
    let acc = full.depth().unwrap();
    for (i, d) in nd.depth().unwrap().iter().enumerate() {
        let wsum = 1.0 - t[i];
        if wsum > 1e-3 {
            assert!(
                (d - acc[i] / wsum).abs() <= 1e-3 * d.abs().max(1.0),
                "normalised depth at {i}"
            );
            assert!(*d > 0.2 && *d < 7.0);
        } else if wsum == 0.0 {
            assert_eq!(*d, 0.0);
        }
    }
}

#[test]
fn output_is_identical_for_one_and_four_threads() {
    let (g, cams) = small_scene();
    let raster = Rasterizer::new(&g).unwrap();
    let render = |n: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap();
        pool.install(|| raster.render_view(&cams, 0, &all_outputs(8)).unwrap())
    };
    let (a, b) = (render(1), render(4));
    let bits = |v: Option<&[f32]>| v.unwrap().iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(a.color()), bits(b.color()));
    assert_eq!(bits(a.depth()), bits(b.depth()));
    assert_eq!(bits(a.transmittance()), bits(b.transmittance()));
    assert_eq!(bits(a.topk_weights()), bits(b.topk_weights()));
    assert_eq!(a.topk_ids(), b.topk_ids());
    assert_eq!(a.stats(), b.stats());
}

#[test]
fn for_each_view_streams_the_same_renders_with_reused_buffers() {
    let (g, cams1) = small_scene();
    let poses: Vec<[f64; 12]> = (0..3)
        .map(|v| {
            camera::look_at(
                [0.2 * v as f64, 0.0, 0.0],
                [0.0, 0.0, 3.0],
                [0.0, -1.0, 0.0],
            )
            .unwrap()
        })
        .collect();
    let cams = camera::cameras_from_poses(&poses, 45, 38, cams1.intrinsics[0]);
    let raster = Rasterizer::new(&g).unwrap();
    let opts = all_outputs(5);
    let mut seen = Vec::new();
    raster
        .for_each_view(&cams, [2, 0, 1], &opts, |view, r| {
            let single = raster.render_view(&cams, view, &opts)?;
            assert_eq!(r.view(), view);
            assert_eq!(r.color(), single.color());
            assert_eq!(r.topk_ids(), single.topk_ids());
            assert_eq!(r.topk_weights(), single.topk_weights());
            seen.push(view);
            Ok::<(), RasterError>(())
        })
        .unwrap();
    assert_eq!(seen, [2, 0, 1]);
    // Errors stop the stream: a bad view index, and an error from the callback.
    let err = raster
        .for_each_view(&cams, [0, 9], &opts, |_, _| Ok::<(), RasterError>(()))
        .unwrap_err();
    assert!(matches!(
        err,
        RasterError::ViewOutOfRange { view: 9, views: 3 }
    ));
    let mut calls = 0;
    let r: Result<(), Stop> = raster.for_each_view(&cams, 0..3, &opts, |_, _| {
        calls += 1;
        Err(Stop("stop".to_string()))
    });
    assert_eq!((r, calls), (Err(Stop("stop".to_string())), 1));
}

#[derive(Debug, PartialEq)]
struct Stop(String);

impl From<RasterError> for Stop {
    fn from(e: RasterError) -> Stop {
        Stop(e.to_string())
    }
}

fn assert_background(r: &ViewRender, bg: [f32; 3]) {
    assert!(r.transmittance().unwrap().iter().all(|t| *t == 1.0));
    assert!(r.alpha().unwrap().iter().all(|a| *a == 0.0));
    assert!(r.depth().unwrap().iter().all(|d| *d == 0.0));
    assert!(r.topk_ids().unwrap().iter().all(|id| *id == NO_GAUSSIAN));
    assert!(r.topk_weights().unwrap().iter().all(|w| *w == 0.0));
    assert!(r.color().unwrap().chunks_exact(3).all(|c| c == bg));
    assert_eq!(r.stats().visible, 0);
}

#[test]
fn empty_scene_and_everything_behind_the_camera_give_background() {
    let cams = camera_at(37, 21, [30.0, 30.0, 18.5, 10.5], [0.0; 3], [0.0, 0.0, 1.0]);
    let opts = RenderOptions {
        background: [0.25, 0.5, 1.0],
        ..all_outputs(4)
    };
    let empty = Gaussians::default();
    let r = Rasterizer::new(&empty)
        .unwrap()
        .render_view(&cams, 0, &opts)
        .unwrap();
    assert_eq!((r.width(), r.height()), (37, 21));
    assert_background(&r, [0.25, 0.5, 1.0]);

    let mut g = random_scene(3, 100, &cams);
    // Mirror every Gaussian behind the camera (camera at the origin looking down +z), or
    // onto the near plane itself.
    let means: Vec<[f32; 3]> = g
        .means
        .iter()
        .enumerate()
        .map(|(i, m)| [m[0], m[1], if i % 2 == 0 { -m[2].abs() } else { 0.1999 }])
        .collect();
    g.means = means.into();
    let r = Rasterizer::new(&g)
        .unwrap()
        .render_view(&cams, 0, &opts)
        .unwrap();
    assert_background(&r, [0.25, 0.5, 1.0]);
}

fn one_gaussian(mean: [f32; 3], log_scale: f32, logit: f32) -> Gaussians {
    Gaussians {
        means: vec![mean].into(),
        log_scales: vec![[log_scale; 3]].into(),
        rotations: vec![[0.9, 0.1, -0.3, 0.2]].into(),
        opacity_logits: vec![logit].into(),
        sh_dc: vec![[0.5, 0.0, -0.5]].into(),
        ..Default::default()
    }
}

#[test]
fn a_gaussian_on_a_pixel_centre_peaks_at_that_pixel() {
    // fx = 50, cx = 20.3: the ray through pixel (13, 7)'s centre (13.5, 7.5).
    let intr = [50.0, 45.0, 20.3, 11.9];
    let cams = camera_at(40, 24, intr, [0.0; 3], [0.0, 0.0, 1.0]);
    let z = 4.0;
    let mean = [
        ((13.5 - intr[2]) * z / intr[0]) as f32,
        ((7.5 - intr[3]) * z / intr[1]) as f32,
        z as f32,
    ];
    let g = one_gaussian(mean, -3.5, 0.0);
    let r = Rasterizer::new(&g)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(1))
        .unwrap();
    let w = r.topk_weights().unwrap();
    let best = (0..w.len()).max_by(|a, b| w[*a].total_cmp(&w[*b])).unwrap();
    assert_eq!((best % 40, best / 40), (13, 7));
    assert!(
        (w[best] - 0.5).abs() < 1e-5,
        "peak weight {} != opacity",
        w[best]
    );
    // Symmetric about the peak (up to f32 rounding of the mean).
    assert!((w[7 * 40 + 12] - w[7 * 40 + 14]).abs() < 1e-4);
    assert!((w[6 * 40 + 13] - w[8 * 40 + 13]).abs() < 1e-4);
    assert!(w[7 * 40 + 12] > 0.0 && w[7 * 40 + 12] < w[best]);
}

#[test]
fn degenerate_scales_give_defined_results() {
    let cams = camera_at(33, 20, [30.0, 30.0, 16.5, 10.0], [0.0; 3], [0.0, 0.0, 1.0]);
    // exp(-30): a point; the low-pass 0.3 px² keeps it invertible, so it still draws a
    // small blob of alpha = opacity at its centre pixel.
    let tiny = one_gaussian([0.0, 0.0, 3.0], -30.0, 2.0);
    let r = Rasterizer::new(&tiny)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    let a = r.alpha().unwrap();
    let o = 1.0 / (1.0 + (-2.0f32).exp());
    let peak = a.iter().cloned().fold(0.0, f32::max);
    assert!(peak > 0.5 * o && peak <= o + 1e-6, "peak alpha {peak}");
    let covered = a.iter().filter(|x| **x > 0.0).count();
    assert!((1..=16).contains(&covered), "{covered} pixels covered");

    // exp(+30): covers every pixel with alpha = opacity (power ~ 0 everywhere).
    let huge = one_gaussian([0.0, 0.0, 3.0], 30.0, 0.5);
    let r = Rasterizer::new(&huge)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    let o = 1.0 / (1.0 + (-0.5f32).exp());
    assert!(r.alpha().unwrap().iter().all(|x| (x - o).abs() < 1e-5));
    assert!(r
        .topk_ids()
        .unwrap()
        .chunks_exact(2)
        .all(|ids| ids == [0, NO_GAUSSIAN]));

    // So large that the 2D covariance overflows even f64: culled, not a panic.
    let absurd = one_gaussian([0.0, 0.0, 3.0], 400.0, 0.5);
    let r = Rasterizer::new(&absurd)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    assert_background(&r, [0.0; 3]);

    // Infinite opacity logits are opacity 1 (clamped to 0.99) and 0.
    let mut inf = one_gaussian([0.0, 0.0, 3.0], -1.0, f32::INFINITY);
    let r = Rasterizer::new(&inf)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    assert!((r.alpha().unwrap()[10 * 33 + 16] - 0.99).abs() < 1e-6);
    inf.opacity_logits = vec![f32::NEG_INFINITY].into();
    let r = Rasterizer::new(&inf)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    assert_background(&r, [0.0; 3]);
}

#[test]
fn invalid_inputs_are_typed_errors() {
    let cams = camera_at(32, 32, [30.0, 30.0, 16.0, 16.0], [0.0; 3], [0.0, 0.0, 1.0]);
    let mut g = random_scene(5, 10, &cams);
    let mut means = g.means.to_vec();
    means[3] = [0.0, f32::NAN, 1.0];
    g.means = means.into();
    match Rasterizer::new(&g) {
        Err(RasterError::NonFiniteGaussian {
            index: 3,
            field: "means",
            ..
        }) => {}
        other => panic!("expected a non-finite means error, got {other:?}"),
    }
    let mut g = random_scene(5, 10, &cams);
    let mut scales = g.log_scales.to_vec();
    scales[6][1] = f32::INFINITY;
    g.log_scales = scales.into();
    let err = Rasterizer::new(&g).unwrap_err();
    assert!(matches!(
        err,
        RasterError::NonFiniteGaussian {
            index: 6,
            field: "log_scales",
            ..
        }
    ));
    assert!(err.to_string().contains("Gaussian 6"), "{err}");

    let mut g = random_scene(5, 10, &cams);
    let mut rot = g.rotations.to_vec();
    rot[2] = [0.0; 4];
    g.rotations = rot.into();
    assert!(matches!(
        Rasterizer::new(&g),
        Err(RasterError::ZeroRotation { index: 2 })
    ));
    // The checks alone (what gs-refine validates with) give the same errors.
    assert!(matches!(
        splat_raster::check_gaussians(&g),
        Err(RasterError::ZeroRotation { index: 2 })
    ));

    let mut g = random_scene(5, 10, &cams);
    g.opacity_logits = vec![0.0; 9].into();
    assert!(matches!(
        Rasterizer::new(&g),
        Err(RasterError::InconsistentGaussians {
            field: "opacity_logits",
            got: 9,
            expected: 10
        })
    ));

    let g = random_scene(5, 10, &cams);
    splat_raster::check_gaussians(&g).unwrap();
    let raster = Rasterizer::new(&g).unwrap();
    let k = |k| RenderOptions {
        top_k: Some(k),
        ..Default::default()
    };
    assert!(matches!(
        raster.render_view(&cams, 0, &k(0)),
        Err(RasterError::TopKZero)
    ));
    assert!(matches!(
        raster.render_view(&cams, 0, &k(MAX_TOP_K + 1)),
        Err(RasterError::TopKTooLarge { k: 257, max: 256 })
    ));
    assert!(raster.render_view(&cams, 0, &k(MAX_TOP_K)).is_ok());
    assert!(matches!(
        raster.render_view(&cams, 1, &k(4)),
        Err(RasterError::ViewOutOfRange { view: 1, views: 1 })
    ));
    let big =
        camera::cameras_from_poses(&[cams.world_to_camera[0]], 40_000, 10, cams.intrinsics[0]);
    assert!(matches!(
        raster.render_view(&big, 0, &k(4)),
        Err(RasterError::ImageTooLarge { .. })
    ));
    let big = camera::cameras_from_poses(
        &[cams.world_to_camera[0]],
        30_000,
        30_000,
        cams.intrinsics[0],
    );
    assert!(matches!(
        raster.render_view(&big, 0, &k(4)),
        Err(RasterError::ImageTooLarge { .. })
    ));
    let mut bad = cams.clone();
    bad.intrinsics = vec![[0.0, 30.0, 16.0, 16.0]].into();
    assert!(matches!(
        raster.render_view(&bad, 0, &k(4)),
        Err(RasterError::BadCamera { view: 0, .. })
    ));
}

#[test]
fn equal_weights_keep_depth_order_and_equal_depths_keep_id_order() {
    // The optical axis hits the centre of pixel (16, 16) exactly (cx = cy = 16.5), so
    // power = 0 there and alpha = opacity.
    let cams = camera_at(33, 33, [20.0, 20.0, 16.5, 16.5], [0.0; 3], [0.0, 0.0, 1.0]);
    let logit = |o: f64| (o / (1.0 - o)).ln() as f32;
    let scene = |means: Vec<[f32; 3]>, logits: Vec<f32>| Gaussians {
        log_scales: vec![[-3.0; 3]; means.len()].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; means.len()].into(),
        sh_dc: vec![[0.0; 3]; means.len()].into(),
        opacity_logits: logits.into(),
        means: means.into(),
        ..Default::default()
    };
    // Gaussian 1 in front with alpha 0.2, Gaussian 0 behind with alpha 0.25:
    // ω1 = 0.2 and ω0 = (1 − 0.2) · 0.25 = 0.2, the same f32.
    let g = scene(
        vec![[0.0, 0.0, 4.0], [0.0, 0.0, 2.0]],
        vec![logit(0.25), logit(0.2)],
    );
    let raster = Rasterizer::new(&g).unwrap();
    let two = raster.render_view(&cams, 0, &all_outputs(2)).unwrap();
    let (ids, ws) = two.topk(16, 16).unwrap();
    assert_eq!(ws[0], ws[1], "the scene must produce an exact tie");
    assert_eq!(ids, &[1, 0], "the nearer Gaussian comes first on a tie");
    let one = raster.render_view(&cams, 0, &all_outputs(1)).unwrap();
    assert_eq!(one.topk(16, 16).unwrap().0, &[1]);
    let r = ref_render(&g, &cams, 0);
    assert_eq!(
        top_k(&r.hits[16 * 33 + 16], 2),
        vec![(1, ws[0]), (0, ws[1])]
    );

    // Two Gaussians at the same depth: blended in id order, so the lower id gets the
    // larger weight (α vs (1 − α)α) wherever both contribute.
    let g = scene(vec![[0.0, 0.0, 3.0]; 2], vec![logit(0.6); 2]);
    let out = Rasterizer::new(&g)
        .unwrap()
        .render_view(&cams, 0, &all_outputs(2))
        .unwrap();
    let (ids, ws) = out.topk(16, 16).unwrap();
    assert_eq!(ids, &[0, 1]);
    assert!((ws[0] - 0.6).abs() < 1e-6 && (ws[1] - 0.24).abs() < 1e-6);

    // The same at three places on one plane facing the camera, whose spatial (Morton)
    // order is the reverse of their ids, after two Gaussians behind the camera that come
    // first in that order (so positions among the projected splats are not the slots):
    // still blended in id order.
    let means = vec![
        [0.02, 0.0, 3.0],
        [0.0, 0.0, 3.0],
        [-0.02, 0.0, 3.0],
        [-1.0, -1.0, -3.0],
        [-1.0, -0.5, -3.0],
    ];
    let g = scene(means, vec![logit(0.6); 5]);
    let raster = Rasterizer::new(&g).unwrap();
    let cam = ViewCamera::from_cameras(&cams, 0).unwrap();
    let depths: Vec<f64> = (0..3)
        .map(|i| raster.project(&cam, i).unwrap().depth)
        .collect();
    assert!(depths.iter().all(|&d| d == depths[0]), "{depths:?}");
    let out = raster.render_view(&cams, 0, &all_outputs(3)).unwrap();
    let (ids, ws) = out.topk(16, 16).unwrap();
    assert_eq!(ids, &[0, 1, 2]);
    assert!(ws[0] > ws[1] && ws[1] > ws[2], "{ws:?}");
    let r = ref_render(&g, &cams, 0);
    assert_eq!(
        top_k(&r.hits[16 * 33 + 16], 3),
        vec![(0, ws[0]), (1, ws[1]), (2, ws[2])]
    );
}

#[test]
fn render_stats_time_every_phase() {
    let (g, cams) = small_scene();
    let raster = Rasterizer::new(&g).unwrap();
    let r = raster.render_view(&cams, 0, &all_outputs(4)).unwrap();
    let p = r.phases();
    assert!(p.project > std::time::Duration::ZERO, "{p:?}");
    assert!(p.blend > std::time::Duration::ZERO, "{p:?}");
    assert!(r.stats().tile_pairs > 0);
}

/// With the `counters` feature, the blend count of a colour render is the brute-force
/// renderer's number of contributions (ω > 0) over every pixel, exactly, for every SIMD
/// width; a K = 256 render inserts every contribution of pixels with at most 256.
#[cfg(feature = "counters")]
#[test]
fn blend_counts_equal_the_brute_force_contributions() {
    let cams = camera_at(
        83,
        61,
        [70.0, 70.0, 41.5, 30.5],
        [0.3, -0.2, -1.0],
        [0.5, 0.1, 4.0],
    );
    let g = camera_projection_scene(1, 300, &cams);
    let r = ref_render(&g, &cams, 0);
    let want: u64 = r.hits.iter().map(|h| h.len() as u64).sum();
    assert!(want > 10_000, "{want}");
    assert!(r.hits.iter().all(|h| h.len() <= 256));
    for raster in rasterizers(&g) {
        let lanes = if raster.simd() == splat_raster::Simd::Portable {
            4
        } else {
            16
        };
        let color = RenderOptions {
            top_k: None,
            ..RenderOptions::default()
        };
        let c = raster.render_view(&cams, 0, &color).unwrap().stats().counts;
        assert_eq!(c.blends, want, "{}", raster.simd().name());
        assert_eq!(c.inserted, 0);
        assert!(
            c.live_lanes >= c.blends && c.groups * lanes >= c.live_lanes,
            "{c:?}"
        );
        let all = raster
            .render_view(&cams, 0, &all_outputs(256))
            .unwrap()
            .stats()
            .counts;
        assert_eq!(
            (all.blends, all.inserted),
            (want, want),
            "{}",
            raster.simd().name()
        );
    }
}

/// A reused [`ViewRender`] skips re-padding the lists of tiles that were empty in its
/// previous render and still are: views that empty some tiles and fill others, in turn,
/// with K and the image size changing in between, give the bytes of fresh renders.
#[test]
fn reused_renders_equal_fresh_ones_as_tiles_empty_and_fill() {
    let intr = [120.0, 120.0, 80.5, 58.5];
    // Few Gaussians, so that some tiles of each view are empty.
    let g = random_scene(
        21,
        120,
        &camera_at(161, 117, intr, [0.0; 3], [0.0, 0.0, 1.0]),
    );
    let look = |target: [f64; 3]| camera::look_at([0.0; 3], target, [0.0, -1.0, 0.0]).unwrap();
    // Ahead (the scene), half turned (part of it), behind (only the stragglers).
    let poses = [
        look([0.0, 0.0, 1.0]),
        look([1.0, 0.0, 0.6]),
        look([0.0, 0.2, -1.0]),
    ];
    let cams = camera::cameras_from_poses(&poses, 161, 117, intr);
    let small = camera::cameras_from_poses(&poses, 97, 50, intr);
    // Which tiles have only padding, per view.
    let empty_tiles = |r: &ViewRender| -> Vec<bool> {
        let (k, w) = (r.k(), r.width());
        let ids = r.topk_ids().unwrap();
        let mut empty = vec![true; w.div_ceil(TILE) * r.height().div_ceil(TILE)];
        for (p, list) in ids.chunks_exact(k).enumerate() {
            if list[0] != NO_GAUSSIAN {
                empty[(p / w / TILE) * w.div_ceil(TILE) + (p % w) / TILE] = false;
            }
        }
        empty
    };
    for raster in rasterizers(&g) {
        let mut reused = ViewRender::default();
        let mut emptied = [false; 2]; // a tile went empty -> filled, and filled -> empty
        let mut last: Option<Vec<bool>> = None;
        let steps: [(&Cameras, usize, usize); 9] = [
            (&cams, 0, 10),
            (&cams, 2, 10),
            (&cams, 0, 10),
            (&cams, 1, 10),
            (&cams, 2, 10),
            (&cams, 2, 4),
            (&cams, 0, 4),
            (&small, 2, 4),
            (&cams, 2, 10),
        ];
        for (i, &(cs, view, k)) in steps.iter().enumerate() {
            let opts = all_outputs(k);
            raster
                .render_view_into(cs, view, &opts, &mut reused)
                .unwrap();
            let fresh = raster.render_view(cs, view, &opts).unwrap();
            let what = format!("{} step {i}", raster.simd().name());
            assert_eq!(reused.topk_ids(), fresh.topk_ids(), "{what}");
            assert_eq!(
                reused
                    .topk_weights()
                    .map(|w| w.iter().map(|v| v.to_bits()).collect::<Vec<_>>()),
                fresh
                    .topk_weights()
                    .map(|w| w.iter().map(|v| v.to_bits()).collect()),
                "{what}"
            );
            assert_eq!(reused.color(), fresh.color(), "{what}");
            let empty = empty_tiles(&fresh);
            if let Some(prev) = last.filter(|p| p.len() == empty.len()) {
                for (a, b) in prev.iter().zip(&empty) {
                    emptied[0] |= *a && !*b;
                    emptied[1] |= !*a && *b;
                }
            }
            last = Some(empty);
        }
        assert_eq!(emptied, [true, true], "the views must empty and fill tiles");
    }
}
