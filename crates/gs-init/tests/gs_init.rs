//! gs-init against closed-form geometry and synthetic scenes with exact ground truth.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use gs_init::geometry::{ray_angle_deg, triangulate_normalised};
use gs_init::select::{nearest_views, pose_features, select_references};
use gs_init::{
    initialise_dense, initialise_files, initialise_sparse, knn_scales, triangulate, Gates,
    ImageDir, InitError, Inputs, MatchFile, Params, Reason, Scale, View, ViewImage,
};
use profuse_formats::{Cameras, FileKind, Gaussians, Matches, SparseMatches, WarpCoords};
use synth::{Camera, Config, Preset, Scene};

// ---------------------------------------------------------------- helpers

fn view_of(c: &Camera) -> View {
    View {
        rotation: c.rotation,
        translation: c.translation,
        intrinsics: c.intrinsics,
        distortion: [0.0; 4],
    }
}

fn cameras_of(cams: &[Camera]) -> Cameras {
    synth::cameras_table(cams, (0..cams.len()).map(|i| format!("v{i}.png")).collect())
}

fn pixel(v: &View, p: [f64; 3]) -> [f64; 2] {
    let q = v.project(p);
    [q[0], q[1]]
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn lerp(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [
        a[0] + t * (b[0] - a[0]),
        a[1] + t * (b[1] - a[1]),
        a[2] + t * (b[2] - a[2]),
    ]
}

const GATES: Gates = Gates {
    max_reproj_px: 2.0,
    min_angle_deg: 2.0,
    near: 0.2,
};

fn generate(preset: Preset, seed: u64, tweak: impl FnOnce(&mut Config)) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::preset(preset, seed);
    config.write_masks = false;
    config.gaussians = 0;
    tweak(&mut config);
    synth::generate(&config, dir.path()).unwrap();
    dir
}

struct SceneData {
    cameras: Cameras,
    images: ImageDir,
    matches: Matches,
    scene: Scene,
}

fn load(dir: &Path) -> SceneData {
    let cameras = Cameras::read(dir.join("cameras.safetensors")).unwrap();
    SceneData {
        images: ImageDir::new(dir, &cameras.image_names),
        matches: Matches::read(dir.join("matches.safetensors")).unwrap(),
        scene: Scene::from_json(dir.join("gt/scene.json")).unwrap(),
        cameras,
    }
}

/// Diagonal of the room's bounding box.
fn extent(scene: &Scene) -> f64 {
    let s = scene.room_size;
    (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt()
}

/// Sorted distances of the means to the true surface; at most ~50,000 of them (an even
/// stride through the set), since each costs a projection onto every object.
fn surface_distances(scene: &Scene, g: &Gaussians) -> Vec<f64> {
    let stride = g.len().div_ceil(50_000).max(1);
    let mut d: Vec<f64> = g
        .means
        .iter()
        .step_by(stride)
        .map(|m| scene.distance_to_surface(m.map(f64::from)))
        .collect();
    d.sort_by(f64::total_cmp);
    d
}

fn assert_counts_add_up(r: &gs_init::Report) {
    let rej = &r.rejected;
    assert_eq!(
        rej.total,
        rej.non_finite + rej.behind_camera + rej.reprojection + rej.low_angle
    );
    assert_eq!(r.sampled, r.kept + rej.total, "{r:?}");
    assert_eq!(r.triangulated, r.sampled - rej.non_finite);
    assert_eq!(
        r.references.iter().map(|x| x.kept).sum::<u64>(),
        r.kept,
        "per-reference kept"
    );
    assert!(r.references.iter().all(|x| x.sampled <= x.confident));
}

/// The exact matches of the given ordered pairs of a dense matches file, as sparse
/// matches in pixels: every cell with certainty > 0 (each `stride`-th).
fn dense_to_sparse(
    m: &Matches,
    cams: &Cameras,
    pairs: &[[u32; 2]],
    stride: usize,
) -> SparseMatches {
    let cells = m.width * m.height;
    let mut out = SparseMatches {
        num_views: m.num_views,
        ..Default::default()
    };
    let (mut pi, mut pj, mut offsets) = (Vec::new(), Vec::new(), vec![0u64]);
    for pair in pairs {
        let p = m.pairs.iter().position(|q| q == pair).unwrap();
        let [i, j] = pair.map(|v| v as usize);
        let [wi, hi] = cams.image_size[i];
        let (sx, sy) = (
            f64::from(wi) / m.width as f64,
            f64::from(hi) / m.height as f64,
        );
        let mut n = 0;
        for c in (0..cells).filter(|c| m.certainty.get(p * cells + c) > 0.0) {
            n += 1;
            if n % stride != 0 {
                continue;
            }
            let at = (p * cells + c) * 2;
            let t = [f64::from(m.warp.get(at)), f64::from(m.warp.get(at + 1))];
            let q = gs_init::warp_to_pixels(t, m.coords, cams.image_size[j]);
            pi.push([
                (((c % m.width) as f64 + 0.5) * sx) as f32,
                (((c / m.width) as f64 + 0.5) * sy) as f32,
            ]);
            pj.push([q[0] as f32, q[1] as f32]);
        }
        offsets.push(pi.len() as u64);
    }
    out.pairs = pairs.to_vec().into();
    out.certainty = vec![1.0; pi.len()].into();
    out.points_i = pi.into();
    out.points_j = pj.into();
    out.pair_offsets = offsets.into();
    out
}

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    gs_init::rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

// ---------------------------------------------------------------- DLT, closed form

/// Known points projected exactly into two cameras come back to 1e-4, in a world frame
/// far from the origin, with rotated cameras and with lens distortion.
#[test]
fn dlt_recovers_exactly_projected_points() {
    let offset = [1000.0, -2000.0, 500.0];
    let at = |p: [f64; 3]| [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]];
    let a = view_of(&Camera::look_at(
        at([0.0, 0.0, 0.0]),
        at([0.0, 5.0, 0.3]),
        640,
        480,
        60.0,
    ));
    let b = view_of(&Camera::look_at(
        at([1.5, 0.5, 0.4]),
        at([0.2, 5.0, 0.0]),
        640,
        480,
        70.0,
    ));
    let mut bd = b;
    bd.distortion = [-0.15, 0.04, 0.002, -0.001];
    let points = [
        [0.0, 5.0, 0.0],
        [1.0, 4.0, -0.5],
        [-1.2, 7.5, 1.0],
        [0.3, 2.0, 0.2],
        [2.0, 12.0, -1.5],
    ];
    for (va, vb) in [(a, b), (a, bd), (bd, a)] {
        for p in points.map(at) {
            let t = triangulate(&va, pixel(&va, p), &vb, pixel(&vb, p));
            let x = t.point.expect("a finite point");
            assert!(dist(x, p) < 1e-4, "{x:?} vs {p:?}");
            assert!(t.max_reproj_px() < 1e-6, "{:?}", t.reproj_px);
            let want = ray_angle_deg(sub(p, va.center()), sub(p, vb.center()));
            assert!((t.angle_deg - want).abs() < 1e-6);
            assert!((t.depths[0] - va.to_camera(p)[2]).abs() < 1e-4);
            assert_eq!(t.check(&GATES), Ok(()));
        }
    }
}

// ---------------------------------------------------------------- gates

fn stereo() -> (View, View) {
    // Two cameras 1 m apart on x, both looking down +y.
    let a = view_of(&Camera::look_at(
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        640,
        480,
        60.0,
    ));
    let b = view_of(&Camera::look_at(
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        640,
        480,
        60.0,
    ));
    (a, b)
}

#[test]
fn reprojection_gate_passes_small_and_rejects_large_errors() {
    let (a, b) = stereo();
    let p = [0.5, 6.0, 0.3];
    let (pa, pb) = (pixel(&a, p), pixel(&b, p));
    // Rectified pair: epipolar lines are image rows, so a vertical shift leaves them.
    for (shift, want) in [
        (0.0, Ok(())),
        (1.5, Ok(())),
        (8.0, Err(Reason::Reprojection)),
        (-30.0, Err(Reason::Reprojection)),
    ] {
        let t = triangulate(&a, pa, &b, [pb[0], pb[1] + shift]);
        assert_eq!(t.check(&GATES), want, "shift {shift}: {t:?}");
        // The DLT splits the disagreement between the two views.
        assert!(t.max_reproj_px() <= shift.abs() * 0.75 + 1e-6, "{t:?}");
    }
    // A shift along the epipolar line is invisible to two views: only depth changes.
    let t = triangulate(&a, pa, &b, [pb[0] + 5.0, pb[1]]);
    assert_eq!(t.check(&GATES), Ok(()));
}

#[test]
fn angle_gate_passes_wide_and_rejects_narrow_rays() {
    let (a, b) = stereo();
    // The angle at a point straight ahead of the baseline midpoint at distance d is
    // 2 atan(0.5 / d).
    for (angle, want) in [
        (3.0f64, Ok(())),
        (2.05, Ok(())),
        (1.9, Err(Reason::LowAngle)),
        (0.5, Err(Reason::LowAngle)),
    ] {
        let d = 0.5 / (angle.to_radians() / 2.0).tan();
        let p = [0.5, d, 0.0];
        let t = triangulate(&a, pixel(&a, p), &b, pixel(&b, p));
        assert!((t.angle_deg - angle).abs() < 1e-6, "{t:?}");
        assert_eq!(t.check(&GATES), want, "angle {angle}");
    }
}

#[test]
fn behind_camera_gate_rejects_points_behind_or_too_near() {
    let (a, b) = stereo();
    let in_front = [0.5, 4.0, 0.1];
    let t = triangulate(&a, pixel(&a, in_front), &b, pixel(&b, in_front));
    assert_eq!(t.check(&GATES), Ok(()));
    // Behind both cameras: the matches are consistent (projection mirrors through the
    // centre), but the point is at negative depth.
    let behind = [0.5, -4.0, 0.1];
    let t = triangulate(&a, pixel(&a, behind), &b, pixel(&b, behind));
    assert!(dist(t.point.unwrap(), behind) < 1e-6);
    assert!(t.depths[0] < 0.0 && t.max_reproj_px() < 1e-6);
    assert_eq!(t.check(&GATES), Err(Reason::BehindCamera));
    // In front but nearer than `near` to camera a (0.15 < 0.2); a wide angle, so only
    // the near gate can fail.
    let near = [0.3, 0.15, 0.0];
    let t = triangulate(&a, pixel(&a, near), &b, pixel(&b, near));
    assert!((t.depths[0] - 0.15).abs() < 1e-6);
    assert_eq!(t.check(&GATES), Err(Reason::BehindCamera));
    let lenient = Gates { near: 0.1, ..GATES };
    assert_eq!(t.check(&lenient), Ok(()));
}

#[test]
fn parallel_rays_are_non_finite() {
    let (a, b) = stereo();
    // The same direction from both centres: the rays meet at infinity.
    let dir = [0.2, 1.0, -0.1];
    let na = [dir[0] / dir[1], -dir[2] / dir[1]];
    let t = triangulate_normalised(&a, na, &b, na);
    assert_eq!(t.point, None);
    assert_eq!(t.check(&GATES), Err(Reason::NonFinite));
    // A slightly converging pair is finite but far and narrow.
    let t = triangulate_normalised(&a, na, &b, [na[0] - 1e-3, na[1]]);
    assert!(t.point.is_some());
    assert_eq!(t.check(&GATES), Err(Reason::LowAngle));
}

/// A wrong warp lying exactly on its epipolar line has a smaller two-view error than the
/// right, slightly noisy ones; the other neighbours do not confirm it, so the right point
/// is kept. With one neighbour only, the wrong one cannot be told apart.
#[test]
fn neighbour_agreement_beats_a_wrong_match_on_the_epipolar_line() {
    let look = |c: [f64; 3]| Camera::look_at(c, [c[0], c[1] + 1.0, c[2]], 64, 48, 60.0);
    let cams = [
        look([0.0, 0.0, 0.0]),
        look([1.0, 0.0, 0.0]),
        look([-1.0, 0.0, 0.0]),
        look([0.5, 0.0, 0.3]),
    ];
    let views: Vec<View> = cams.iter().map(view_of).collect();
    let cameras = cameras_of(&cams);
    // The cell centre of a 1x1 grid is the reference pixel (32, 24): the optical axis.
    let truth = [0.0, 4.0, 0.0];
    let wrong = [0.0, 8.0, 0.0];
    let noisy = |v: &View| {
        let q = pixel(v, truth);
        [q[0] as f32, q[1] as f32 + 0.5]
    };
    let exact_wrong = {
        let q = pixel(&views[3], wrong);
        [q[0] as f32, q[1] as f32]
    };
    let matches = |pairs: Vec<[u32; 2]>, warp: Vec<f32>| Matches {
        num_views: 4,
        certainty: profuse_formats::Floats::F32(vec![1.0; pairs.len()].into()),
        pairs: pairs.into(),
        height: 1,
        width: 1,
        warp: profuse_formats::Floats::F32(warp.into()),
        coords: WarpCoords::Pixels,
        extra: Default::default(),
    };
    let images = vec![ViewImage::filled(64, 48, [0, 0, 0]); 4];
    let all = matches(
        vec![[0, 1], [0, 2], [0, 3]],
        [noisy(&views[1]), noisy(&views[2]), exact_wrong].concat(),
    );
    let (g, r) = initialise_dense(&cameras, &images, &all, &Params::default()).unwrap();
    assert_eq!((r.sampled, r.kept, r.dlt_solves), (1, 1, 3));
    let kept = g.means[0].map(f64::from);
    assert!(dist(kept, truth) < 0.2, "{kept:?}");
    // The wrong match alone is consistent in two views: it is kept, at the wrong depth.
    let alone = matches(vec![[0, 3]], exact_wrong.to_vec());
    let (g, _) = initialise_dense(&cameras, &images, &alone, &Params::default()).unwrap();
    assert!(dist(g.means[0].map(f64::from), wrong) < 1e-3);
    // Its two-view error is smaller than the right ones'.
    let t_right = triangulate(
        &views[0],
        [32.0, 24.0],
        &views[1],
        noisy(&views[1]).map(f64::from),
    );
    let t_wrong = triangulate(
        &views[0],
        [32.0, 24.0],
        &views[3],
        exact_wrong.map(f64::from),
    );
    assert!(t_wrong.max_reproj_px() < t_right.max_reproj_px());
}

// ---------------------------------------------------------------- reference selection

fn orbit(n: usize) -> Vec<View> {
    (0..n)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / n as f64;
            view_of(&Camera::look_at(
                [4.0 * a.cos(), 4.0 * a.sin(), 1.5],
                [0.0, 0.0, 0.5],
                64,
                48,
                60.0,
            ))
        })
        .collect()
}

#[test]
fn reference_kmeans_spreads_references_around_an_orbit() {
    let views = orbit(36);
    let f = pose_features(&views);
    let all: Vec<usize> = (0..36).collect();
    for seed in 0..5 {
        let refs = select_references(&f, &all, 6, seed);
        assert_eq!(refs, select_references(&f, &all, 6, seed), "deterministic");
        assert_eq!(refs.len(), 6);
        // Six references on 36 evenly spaced views: every gap between consecutive
        // references (in view steps of 10°) is close to 6 steps.
        let gaps: Vec<usize> = (0..6)
            .map(|k| (refs[(k + 1) % 6] + 36 - refs[k]) % 36)
            .collect();
        assert!(
            gaps.iter().all(|g| (4..=8).contains(g)),
            "seed {seed}: {refs:?} gaps {gaps:?}"
        );
    }
    // Not more candidates than references: all of them.
    assert_eq!(select_references(&f, &[3, 1, 7], 6, 0), vec![1, 3, 7]);
    // Only candidates are chosen.
    let odd: Vec<usize> = (1..36).step_by(2).collect();
    assert!(select_references(&f, &odd, 5, 0).iter().all(|r| r % 2 == 1));
}

#[test]
fn neighbours_are_the_nearest_poses_among_the_options() {
    let views = orbit(12);
    let f = pose_features(&views);
    let all: Vec<usize> = (0..12).collect();
    let n = nearest_views(&f, 0, &all, 3);
    assert_eq!(n.len(), 3);
    assert!(n[..2].contains(&1) && n[..2].contains(&11), "{n:?}");
    assert!(n[2] == 2 || n[2] == 10);
    // Restricted to the views with a pair.
    assert_eq!(nearest_views(&f, 0, &[5, 6, 2], 2), vec![2, 5]);
}

// ---------------------------------------------------------------- scale rules

#[test]
fn knn_scale_is_the_lattice_spacing() {
    let pts: Vec<[f64; 3]> = (0..5)
        .flat_map(|x| {
            (0..5).flat_map(move |y| {
                (0..5).map(move |z| [x as f64 * 0.1, y as f64 * 0.1, z as f64 * 0.1])
            })
        })
        .collect();
    let s = knn_scales(&pts, 3);
    // An interior point has six neighbours at 0.1.
    let interior = pts.iter().position(|p| p == &[0.2, 0.2, 0.2]).unwrap();
    assert!((s[interior] - 0.1).abs() < 1e-12);
    assert!(s.iter().all(|v| (*v - 0.1).abs() < 1e-12));
    // Duplicates are clamped, a single point gets the floor.
    assert_eq!(
        knn_scales(&[[1.0; 3]; 4], 3),
        vec![gs_init::MIN_KNN_DIST2.sqrt(); 4]
    );
    assert_eq!(knn_scales(&[[1.0; 3]], 3).len(), 1);
}

/// One match, three scale rules, checked against their formulas.
#[test]
fn scale_rules_follow_their_formulas() {
    let cams = [
        Camera::look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 64, 48, 60.0),
        Camera::look_at([1.0, 0.0, 0.0], [1.0, 1.0, 0.0], 64, 48, 60.0),
    ];
    let cameras = cameras_of(&cams);
    let (a, b) = (view_of(&cams[0]), view_of(&cams[1]));
    let p = [0.3, 5.0, 0.2];
    let f32p = |q: [f64; 2]| [q[0] as f32, q[1] as f32];
    let matches = SparseMatches {
        num_views: 2,
        pairs: vec![[0, 1]].into(),
        pair_offsets: vec![0, 1].into(),
        points_i: vec![f32p(pixel(&a, p))].into(),
        points_j: vec![f32p(pixel(&b, p))].into(),
        certainty: vec![1.0].into(),
        ..Default::default()
    };
    let images = vec![ViewImage::filled(64, 48, [10, 200, 90]); 2];
    let run = |scale| {
        let params = Params {
            scale,
            ..Params::default()
        };
        initialise_sparse(&cameras, &images, &matches, &params)
            .unwrap()
            .0
    };
    let f = cams[0].intrinsics[0];
    let depth = 5.0;
    let g = run(Scale::Pixels { pixels: 2.0 });
    assert!((f64::from(g.log_scales[0][0]) - (2.0 * depth / f).ln()).abs() < 1e-4);
    assert_eq!(g.log_scales[0][0], g.log_scales[0][2]);
    let g = run(Scale::Distance { factor: 0.0005 });
    let d = dist(p, [0.0; 3]);
    assert!((f64::from(g.log_scales[0][1]) - (0.0005 * d).ln()).abs() < 1e-4);
    let g = run(Scale::Knn { k: 3 });
    assert!((f64::from(g.log_scales[0][0]) - gs_init::MIN_KNN_DIST2.sqrt().ln()).abs() < 1e-4);
    // A match that fails a gate leaves an empty, still valid, set.
    let behind = SparseMatches {
        points_j: vec![[0.0, 0.0]].into(),
        ..matches.clone()
    };
    let (empty, r) = initialise_sparse(&cameras, &images, &behind, &Params::default()).unwrap();
    assert_eq!((empty.len(), r.kept, r.rejected.total), (0, 0, 1));
    assert!(r.median_reproj_px.is_none());
    empty.to_bytes().unwrap();
    // A malformed in-memory image is an error, not a silent grey.
    let mut short = images.clone();
    short[0].rgb.pop();
    let err = initialise_sparse(&cameras, &short, &matches, &Params::default()).unwrap_err();
    assert!(matches!(err, InitError::ImageData { view: 0, .. }), "{err}");
    // The other attributes: identity rotation, opacity 0.5, colour from the image.
    assert_eq!(g.rotations[0], [1.0, 0.0, 0.0, 0.0]);
    assert_eq!(g.opacity_logits[0], 0.0);
    for (c, want) in g.sh_dc[0].iter().zip([10.0f32, 200.0, 90.0]) {
        assert!((c * gs_init::SH_C0 as f32 + 0.5 - want / 255.0).abs() < 1e-5);
    }
}

// ---------------------------------------------------------------- synthetic scenes

/// The headline target: on the synth `demo` scene (exact matches), the median distance
/// of the initial Gaussians to the true surface is far below 0.5% of the scene extent.
#[test]
fn demo_scene_dense_points_lie_on_the_surface() {
    let dir = generate(Preset::Demo, 0, |_| {});
    let s = load(dir.path());
    let (g, report) =
        initialise_dense(&s.cameras, &s.images, &s.matches, &Params::default()).unwrap();
    assert_counts_add_up(&report);
    assert_eq!(
        report.references.len(),
        24,
        "24 views <= 180 references: all"
    );
    assert!(report.references.iter().all(|r| r.neighbours.len() == 3));
    let want: u64 = report
        .references
        .iter()
        .map(|r| r.confident.min(15_000))
        .sum();
    assert_eq!(report.sampled, want);
    assert!(
        report.sampled > 23 * 15_000,
        "nearly every view has more confident cells than the budget"
    );
    assert!(
        report.kept as f64 > 0.95 * report.sampled as f64,
        "{:?}",
        report.rejected
    );
    assert!(report.median_reproj_px.unwrap() < 1e-3);
    g.to_bytes().unwrap();

    let d = surface_distances(&s.scene, &g);
    let ext = extent(&s.scene);
    let med = d[d.len() / 2];
    let p99 = d[d.len() * 99 / 100];
    eprintln!(
        "demo dense: {} Gaussians, median distance to surface {med:.3e} m = {:.2e} of the extent {ext:.2} m, p99 {p99:.3e} m, rejected {:?}",
        g.len(),
        med / ext,
        report.rejected
    );
    assert!(med < 0.005 * ext);
    assert!(
        med < 1e-4,
        "exact matches triangulate to the surface: {med}"
    );
    assert!(p99 < 1e-3, "{p99}");
}

/// Dense warps with matcher-like faults (0.5 px noise, 16% outliers with high certainty)
/// still give points on the surface; few wrong points survive the gates.
#[test]
fn dense_matches_with_noise_and_outliers_are_gated() {
    let dir = generate(Preset::Demo, 2, |c| {
        c.views = 12;
        c.warp_noise_px = 0.5;
        c.outlier_frac = 0.16;
    });
    let s = load(dir.path());
    let params = Params {
        budget: 3000,
        ..Params::default()
    };
    let (g, report) = initialise_dense(&s.cameras, &s.images, &s.matches, &params).unwrap();
    assert_counts_add_up(&report);
    let d = surface_distances(&s.scene, &g);
    let ext = extent(&s.scene);
    let med = d[d.len() / 2];
    let far = d.iter().filter(|x| **x > 0.01 * ext).count() as f64 / d.len() as f64;
    eprintln!("noisy dense: median {med:.4} m, {far:.4} beyond 1% of the extent, {report:?}");
    assert!(med < 0.005 * ext, "{med}");
    assert!(far < 0.025, "{far}");
    assert!(report.kept as f64 > 0.75 * report.sampled as f64);
}

/// Sparse matches: correct ones mixed with deliberately wrong ones of known kind; each
/// wrong kind is rejected with its reason, every correct match is kept on the surface.
#[test]
fn wrong_sparse_matches_are_rejected_with_the_right_reasons() {
    let dir = generate(Preset::Demo, 1, |c| {
        c.views = 12;
        c.width = 160;
        c.height = 120;
    });
    let s = load(dir.path());
    let cams: Vec<Camera> = (0..s.cameras.len())
        .map(|v| Camera::from_cameras(&s.cameras, v))
        .collect();
    let pairs: Vec<[u32; 2]> = s
        .matches
        .pairs
        .iter()
        .copied()
        .filter(|p| p[0] < p[1])
        .collect();
    let exact = dense_to_sparse(&s.matches, &s.cameras, &pairs, 5);
    let (mut pi, mut pj, mut offsets) = (Vec::new(), Vec::new(), vec![0u64]);
    let mut truth = Vec::new();
    let (mut n_ok, mut n_shift, mut n_behind, mut n_far) = (0, 0, 0, 0);
    for (p, [i, j]) in pairs.iter().enumerate() {
        let (ci, cj) = (&cams[*i as usize], &cams[*j as usize]);
        for (k, m) in exact.range(p).enumerate() {
            let a = exact.points_i[m].map(f64::from);
            let b = exact.points_j[m].map(f64::from);
            // Ground truth independent of gs-init: the ray cast through the pixel.
            let x = s
                .scene
                .raycast(ci.center(), ci.ray(a[0], a[1]))
                .unwrap()
                .point;
            let (zi, zj) = (ci.to_camera(x)[2], cj.to_camera(x)[2]);
            let angle = ray_angle_deg(sub(x, ci.center()), sub(x, cj.center()));
            if angle < 4.0 || zi < 0.3 || zj < 0.3 {
                continue;
            }
            let (target, keep) = match k % 5 {
                0 => {
                    // 20 px across the epipolar line.
                    let e = cj.project(lerp(x, ci.center(), 0.2));
                    let q = cj.project(x);
                    let (dx, dy) = (e[0] - q[0], e[1] - q[1]);
                    let l = dx.hypot(dy);
                    n_shift += 1;
                    ([b[0] - 20.0 * dy / l, b[1] + 20.0 * dx / l], false)
                }
                1 => {
                    // A point behind camera i on the same ray (mirror through the centre).
                    let xb = lerp(ci.center(), x, -0.5);
                    let q = cj.project(xb);
                    if q[2].abs() < 0.5 {
                        continue;
                    }
                    n_behind += 1;
                    ([q[0], q[1]], false)
                }
                2 => {
                    // A point 100 times farther along the ray: in front, but seen at a
                    // narrow angle.
                    let xf = lerp(ci.center(), x, 100.0);
                    let q = cj.project(xf);
                    let narrow = ray_angle_deg(sub(xf, ci.center()), sub(xf, cj.center()));
                    if q[2] < 1.0 || narrow > 1.0 {
                        continue;
                    }
                    n_far += 1;
                    ([q[0], q[1]], false)
                }
                _ => {
                    n_ok += 1;
                    (b, true)
                }
            };
            pi.push(exact.points_i[m]);
            pj.push([target[0] as f32, target[1] as f32]);
            if keep {
                truth.push(x);
            }
        }
        offsets.push(pi.len() as u64);
    }
    assert!(
        n_ok > 500 && n_shift > 100 && n_behind > 100 && n_far > 50,
        "{n_ok} {n_shift} {n_behind} {n_far}"
    );
    let n = pi.len();
    let matches = SparseMatches {
        num_views: s.cameras.len(),
        pairs: pairs.clone().into(),
        pair_offsets: offsets.into(),
        points_i: pi.into(),
        points_j: pj.into(),
        certainty: vec![1.0; n].into(),
        ..Default::default()
    };
    let params = Params {
        budget: 1_000_000,
        ..Params::default()
    };
    let (g, r) = initialise_sparse(&s.cameras, &s.images, &matches, &params).unwrap();
    assert_counts_add_up(&r);
    assert_eq!(r.sampled as usize, n);
    assert_eq!(
        (
            r.kept,
            r.rejected.reprojection,
            r.rejected.behind_camera,
            r.rejected.low_angle,
            r.rejected.non_finite
        ),
        (n_ok, n_shift, n_behind, n_far, 0),
        "{r:?}"
    );
    // The kept points are the correct matches, in input order, on their true points.
    for (m, x) in g.means.iter().zip(&truth) {
        assert!(dist(m.map(f64::from), *x) < 1e-3, "{m:?} vs {x:?}");
    }
}

/// Real keypoint matchers give ~16% wrong matches; random targets mixed in at that rate
/// are nearly all rejected and the kept cloud stays on the surface.
#[test]
fn random_sparse_outliers_at_16_percent_are_rejected() {
    let dir = generate(Preset::Demo, 3, |c| {
        c.views = 12;
        c.width = 160;
        c.height = 120;
    });
    let s = load(dir.path());
    let pairs: Vec<[u32; 2]> = s.matches.pairs.to_vec();
    let exact = dense_to_sparse(&s.matches, &s.cameras, &pairs, 3);
    let (mut pi, mut pj, mut offsets) = (Vec::new(), Vec::new(), vec![0u64]);
    let mut state = 12345u64;
    let mut unit = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut n_random = 0u64;
    for (p, [_, j]) in pairs.iter().enumerate() {
        let [w, h] = s.cameras.image_size[*j as usize];
        for m in exact.range(p) {
            pi.push(exact.points_i[m]);
            if unit() < 0.16 {
                n_random += 1;
                pj.push([
                    (unit() * f64::from(w)) as f32,
                    (unit() * f64::from(h)) as f32,
                ]);
            } else {
                pj.push(exact.points_j[m]);
            }
        }
        offsets.push(pi.len() as u64);
    }
    let n = pi.len() as u64;
    let matches = SparseMatches {
        num_views: s.cameras.len(),
        pairs: pairs.into(),
        pair_offsets: offsets.into(),
        points_i: pi.into(),
        points_j: pj.into(),
        certainty: vec![1.0; n as usize].into(),
        ..Default::default()
    };
    let params = Params {
        budget: 1_000_000,
        ..Params::default()
    };
    let (g, r) = initialise_sparse(&s.cameras, &s.images, &matches, &params).unwrap();
    assert_counts_add_up(&r);
    let n_correct = n - n_random;
    // Correct matches fail only where the geometry is genuinely weak (narrow angle,
    // very near); random ones pass only near their epipolar line.
    let survivors = r.kept as f64 - n_correct as f64;
    eprintln!(
        "random outliers: {n_random} of {n}, report {:?}, kept {}",
        r.rejected, r.kept
    );
    assert!(r.rejected.total as f64 >= 0.9 * n_random as f64);
    assert!(survivors < 0.1 * n_random as f64, "{survivors}");
    assert!(r.rejected.reprojection + r.rejected.behind_camera >= (0.8 * n_random as f64) as u64);
    let d = surface_distances(&s.scene, &g);
    let ext = extent(&s.scene);
    let off = d.iter().filter(|x| **x > 0.005 * ext).count() as f64 / d.len() as f64;
    eprintln!(
        "random outliers: kept cloud median distance {:.2e} m, {off:.4} beyond 0.5% of the extent",
        d[d.len() / 2]
    );
    assert!(d[d.len() / 2] < 1e-3, "{}", d[d.len() / 2]);
    assert!(off < 0.03, "{off}");
}

/// With one neighbour per reference and an unlimited budget, the dense path and the sparse
/// path over the same pairs' exact matches make the same points.
#[test]
fn dense_and_sparse_paths_agree_on_the_same_matches() {
    let dir = generate(Preset::Tiny, 0, |_| {});
    let s = load(dir.path());
    let params = Params {
        neighbours: 1,
        budget: 1_000_000,
        certainty_threshold: 0.0,
        ..Params::default()
    };
    let (gd, rd) = initialise_dense(&s.cameras, &s.images, &s.matches, &params).unwrap();
    assert_counts_add_up(&rd);
    let pairs: Vec<[u32; 2]> = rd
        .references
        .iter()
        .map(|r| [r.view as u32, r.neighbours[0] as u32])
        .collect();
    let sparse = dense_to_sparse(&s.matches, &s.cameras, &pairs, 1);
    let (gs, rs) = initialise_sparse(&s.cameras, &s.images, &sparse, &params).unwrap();
    assert_counts_add_up(&rs);
    assert_eq!(rs.mode, "sparse");
    assert_eq!(
        (rd.sampled, rd.kept, rd.rejected),
        (rs.sampled, rs.kept, rs.rejected)
    );
    assert!(rd.kept > 1000, "{rd:?}");
    for (a, b) in gd.means.iter().zip(gs.means.iter()) {
        assert!(
            dist(a.map(f64::from), b.map(f64::from)) < 1e-4,
            "{a:?} {b:?}"
        );
    }
    for (a, b) in gd.sh_dc.iter().zip(gs.sh_dc.iter()) {
        assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5));
    }
    let d = surface_distances(&s.scene, &gs);
    assert!(d[d.len() / 2] < 1e-4);
}

/// Byte-identical files for 1 and 4 threads, dense and sparse, every scale rule.
#[test]
fn output_is_identical_for_1_and_4_threads() {
    let dir = generate(Preset::Demo, 4, |c| {
        c.views = 10;
        c.width = 96;
        c.height = 72;
        c.outlier_frac = 0.1;
    });
    let s = load(dir.path());
    let sparse = dense_to_sparse(&s.matches, &s.cameras, &s.matches.pairs.to_vec(), 2);
    for scale in [Scale::Pixels { pixels: 1.0 }, Scale::Knn { k: 3 }] {
        let params = Params {
            references: 6,
            budget: 1500,
            scale,
            ..Params::default()
        };
        let run = |threads| {
            in_pool(threads, || {
                let (d, rd) = initialise_dense(&s.cameras, &s.images, &s.matches, &params).unwrap();
                let (sp, rs) = initialise_sparse(&s.cameras, &s.images, &sparse, &params).unwrap();
                (d.to_bytes().unwrap(), sp.to_bytes().unwrap(), rd, rs)
            })
        };
        let one = run(1);
        let four = run(4);
        assert_eq!(one.2.references.len(), 6);
        assert!(one.2.kept > 1000 && one.3.kept > 1000);
        assert!(one.0 == four.0, "dense bytes differ ({scale:?})");
        assert!(one.1 == four.1, "sparse bytes differ ({scale:?})");
        assert_eq!(one.2, four.2);
        assert_eq!(one.3, four.3);
        // Another seed samples differently.
        let other = Params { seed: 1, ..params };
        let (d, _) = initialise_dense(&s.cameras, &s.images, &s.matches, &other).unwrap();
        assert!(d.to_bytes().unwrap() != one.0);
    }
}

// ---------------------------------------------------------------- bad input

#[test]
fn bad_inputs_are_typed_errors_naming_the_file() {
    let dir = generate(Preset::Tiny, 5, |_| {});
    let root = dir.path();
    let inputs = Inputs::scene(root).unwrap();
    assert!(matches!(inputs.matches, MatchFile::Dense(_)));
    let params = Params::default();
    let (g, r) = initialise_files(&inputs, &params, &|_, _| {}).unwrap();
    assert_eq!(g.len() as u64, r.kept);
    let cameras = Cameras::read(&inputs.cameras).unwrap();
    let m = Matches::read(root.join("matches.safetensors")).unwrap();

    // A pair naming a view the cameras do not have.
    let bad_pairs = root.join("bad_pairs.safetensors");
    let mut pairs = m.pairs.to_vec();
    pairs[3] = [pairs[3][0], 4];
    Matches {
        num_views: 5,
        pairs: pairs.into(),
        ..m.clone()
    }
    .write(&bad_pairs)
    .unwrap();
    let with = |matches| Inputs {
        matches,
        ..inputs.clone()
    };
    let err = initialise_files(
        &with(MatchFile::Dense(bad_pairs.clone())),
        &params,
        &|_, _| {},
    )
    .unwrap_err();
    assert!(
        matches!(
            err,
            InitError::PairOutOfRange {
                pair: 3,
                view: 4,
                views: 4,
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("bad_pairs.safetensors"), "{err}");

    // A matches file made for another number of views.
    let other = root.join("other_views.safetensors");
    Matches {
        num_views: 7,
        ..m.clone()
    }
    .write(&other)
    .unwrap();
    let err = initialise_files(&with(MatchFile::Dense(other)), &params, &|_, _| {}).unwrap_err();
    assert!(
        matches!(
            err,
            InitError::ViewCount {
                num_views: 7,
                views: 4,
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("other_views.safetensors"));

    // An image of the wrong size.
    let img1 = root.join(&cameras.image_names[1]);
    image::RgbImage::new(10, 10).save(&img1).unwrap();
    let err = initialise_files(&inputs, &params, &|_, _| {}).unwrap_err();
    assert!(
        matches!(
            err,
            InitError::ImageSize {
                view: 1,
                found_w: 10,
                expected_w: 64,
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("frame_00001.png"), "{err}");

    // A missing image.
    std::fs::remove_file(&img1).unwrap();
    let err = initialise_files(&inputs, &params, &|_, _| {}).unwrap_err();
    assert!(
        matches!(err, InitError::ImageMissing { view: 1, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("frame_00001.png"), "{err}");

    // A file of another kind, a bad parameter, a scene without matches.
    let err = initialise_files(
        &with(MatchFile::Sparse(root.join("matches.safetensors"))),
        &params,
        &|_, _| {},
    )
    .unwrap_err();
    assert!(
        err.to_string().contains("matches.safetensors")
            && err.to_string().contains("sparse_matches"),
        "{err}"
    );
    let err = initialise_files(
        &inputs,
        &Params {
            budget: 0,
            ..params
        },
        &|_, _| {},
    )
    .unwrap_err();
    assert!(matches!(err, InitError::Param { name: "budget", .. }));
    let empty = tempfile::tempdir().unwrap();
    assert!(matches!(
        Inputs::scene(empty.path()),
        Err(InitError::NoMatches { .. })
    ));
}

/// `--images` may also point at the folder that holds the image files themselves.
#[test]
fn image_dir_accepts_the_scene_or_the_images_folder() {
    let dir = generate(Preset::Tiny, 6, |_| {});
    let cameras = Cameras::read(dir.path().join("cameras.safetensors")).unwrap();
    for root in [dir.path().to_path_buf(), dir.path().join("images")] {
        let images = ImageDir::new(&root, &cameras.image_names);
        use gs_init::ImageSource;
        assert_eq!(images.dimensions(2).unwrap(), [64, 48]);
        assert_eq!(images.load(2).unwrap().rgb.len(), 64 * 48 * 3);
    }
}

#[test]
fn normalized_and_pixel_warps_give_the_same_points() {
    let dir = generate(Preset::Tiny, 7, |_| {});
    let s = load(dir.path());
    assert_eq!(s.matches.coords, WarpCoords::Normalized);
    let cells = s.matches.width * s.matches.height;
    let mut warp = s.matches.warp.to_f32_vec();
    for (p, [_, j]) in s.matches.pairs.iter().enumerate() {
        let size = s.cameras.image_size[*j as usize];
        for c in 0..cells {
            let at = (p * cells + c) * 2;
            let q = gs_init::warp_to_pixels(
                [f64::from(warp[at]), f64::from(warp[at + 1])],
                WarpCoords::Normalized,
                size,
            );
            warp[at] = q[0] as f32;
            warp[at + 1] = q[1] as f32;
        }
    }
    let pixels = Matches {
        coords: WarpCoords::Pixels,
        warp: profuse_formats::Floats::F32(warp.into()),
        ..s.matches.clone()
    };
    let params = Params::default();
    let (a, ra) = initialise_dense(&s.cameras, &s.images, &s.matches, &params).unwrap();
    let (b, rb) = initialise_dense(&s.cameras, &s.images, &pixels, &params).unwrap();
    assert_eq!((ra.kept, ra.rejected), (rb.kept, rb.rejected));
    for (x, y) in a.means.iter().zip(b.means.iter()) {
        assert!(dist(x.map(f64::from), y.map(f64::from)) < 1e-4);
    }
}
