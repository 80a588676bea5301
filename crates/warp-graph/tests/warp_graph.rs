//! Algorithm 1 on hand-built two- and three-view cases (every gate with a link that must
//! pass and one that must fail), the contingency table against a brute-force per-mask-pair
//! loop, determinism across thread counts, typed errors, exact recovery on synthetic Voronoi
//! scenes, and the clustering scores on the synthetic demo scene.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use profuse_formats::{
    Cameras, FileKind, Floats, Gaussians, Labels, Masks, Matches, Proposals, WarpCoords,
    NO_PROPOSAL,
};
use warp_graph::{
    build_proposals, synthetic, Association, Grouping, Inputs, Outcome, Params, Sampling,
    Visibility, WarpGraphError,
};

// ---------------------------------------------------------------------------------------
// Hand-built inputs: every view W x H, the warp grid equal to the mask grid.

/// A view's label at (x, y), `None` = no mask.
type LabelFn<'a> = &'a dyn Fn(usize, usize) -> Option<u16>;

/// Masks from per-view label closures (`None` = no mask) and per-view mask counts.
fn masks(w: usize, h: usize, views: &[(usize, LabelFn<'_>)]) -> Masks {
    let mut labels = Vec::new();
    let mut offsets = vec![0u32];
    for (count, f) in views {
        for y in 0..h {
            for x in 0..w {
                labels.push(f(x, y).unwrap_or(u16::MAX));
            }
        }
        offsets.push(offsets.last().unwrap() + *count as u32);
    }
    let m = *offsets.last().unwrap() as usize;
    Masks {
        view_names: (0..views.len()).map(|v| format!("v{v}.png")).collect(),
        width: w,
        height: h,
        labels: Labels::U16(labels.into()),
        mask_offsets: offsets.into(),
        features: Floats::F32(vec![1.0; m].into()),
        dim: 1,
        extra: Default::default(),
    }
}

/// One directed warp: for each cell (x, y) the target in view j's pixels (or `None` =
/// certainty 0) and the certainty of the others.
struct Warp<'a> {
    pair: [u32; 2],
    target: &'a dyn Fn(usize, usize) -> Option<(f64, f64)>,
    certainty: f32,
}

/// Matches in normalised coordinates (x before y, as SPEC.md §4.4 stores them).
fn matches(views: usize, w: usize, h: usize, warps: &[Warp<'_>]) -> Matches {
    matches_with(views, w, h, warps, false)
}

fn matches_with(views: usize, w: usize, h: usize, warps: &[Warp<'_>], swap_xy: bool) -> Matches {
    let mut warp = Vec::new();
    let mut cert = Vec::new();
    for wp in warps {
        for y in 0..h {
            for x in 0..w {
                let (t, c) = match (wp.target)(x, y) {
                    Some(t) => (t, wp.certainty),
                    None => ((0.0, 0.0), 0.0),
                };
                let nx = (2.0 * t.0 / w as f64 - 1.0) as f32;
                let ny = (2.0 * t.1 / h as f64 - 1.0) as f32;
                if swap_xy {
                    warp.extend([ny, nx]);
                } else {
                    warp.extend([nx, ny]);
                }
                cert.push(c);
            }
        }
    }
    Matches {
        num_views: views,
        pairs: warps.iter().map(|w| w.pair).collect::<Vec<_>>().into(),
        height: h,
        width: w,
        warp: Floats::F32(warp.into()),
        certainty: Floats::F32(cert.into()),
        coords: WarpCoords::Normalized,
        extra: Default::default(),
    }
}

fn identity(x: usize, y: usize) -> Option<(f64, f64)> {
    Some((x as f64 + 0.5, y as f64 + 0.5))
}

fn plain() -> Params {
    Params {
        visibility: Visibility::None,
        grouping: Grouping::Links,
        ..Params::default()
    }
}

/// The link grouping (Algorithm 1 with the guard and extent rules), whatever the inputs.
fn links() -> Params {
    Params {
        grouping: Grouping::Links,
        ..Params::default()
    }
}

fn run(m: &Masks, t: &Matches, p: &Params) -> Outcome {
    build_proposals(Inputs::new(m, t), p).unwrap()
}

/// Sorted member lists of the proposals.
fn groups(p: &Proposals) -> Vec<Vec<u32>> {
    let mut g = vec![Vec::new(); p.len()];
    for (m, id) in p.mask_proposal.iter().enumerate() {
        if *id != NO_PROPOSAL {
            g[*id as usize].push(m as u32);
        }
    }
    g
}

fn edges(o: &Outcome) -> Vec<[u32; 2]> {
    o.edges.iter().map(|l| l.masks).collect()
}

// ---------------------------------------------------------------------------------------
// Warp channel order and the mutual requirement.

/// View 0: P = top half (0), Q = bottom half (1). View 1: quadrants TL 0, TR 1, BL 2, BR 3.
fn quadrant_masks() -> Masks {
    masks(
        8,
        8,
        &[
            (2, &|_, y| Some(u16::from(y >= 4))),
            (4, &|x, y| Some(u16::from(x >= 4) + 2 * u16::from(y >= 4))),
        ],
    )
}

/// P -> (2, 6) (inside BL), Q -> (6, 2) (inside TR): read with swapped channels, P would
/// land in TR and Q in BL.
fn forward_pq(x: usize, y: usize) -> Option<(f64, f64)> {
    let _ = x;
    Some(if y < 4 { (2.0, 6.0) } else { (6.0, 2.0) })
}

#[test]
fn warp_channels_are_read_x_before_y() {
    let m = quadrant_masks();
    // BL -> (6, 2) in view 0 (inside P), TR -> (2, 6) (inside Q); TL, BR unmatched.
    let backward = |x: usize, y: usize| match (x >= 4, y >= 4) {
        (false, true) => Some((6.0, 2.0)),
        (true, false) => Some((2.0, 6.0)),
        _ => None,
    };
    let warps = [
        Warp {
            pair: [0, 1],
            target: &forward_pq,
            certainty: 1.0,
        },
        Warp {
            pair: [1, 0],
            target: &backward,
            certainty: 1.0,
        },
    ];
    let t = matches(2, 8, 8, &warps);
    let o = run(&m, &t, &plain());
    // Global ids: P 0, Q 1, TL 2, TR 3, BL 4, BR 5.
    assert_eq!(groups(&o.proposals), vec![vec![0, 4], vec![1, 3]]);
    let asso = Association::new(Inputs::new(&m, &t), &plain()).unwrap();
    let d = asso.directed_overlaps(0).unwrap();
    assert_eq!((d.iou(0, 2), d.box_iou(0, 2)), (1.0, 1.0));
    assert_eq!(d.intersection(0, 1), 0.0);
    // The same numbers written y before x give the transposed (wrong) association.
    let swapped = matches_with(2, 8, 8, &warps, true);
    let o = run(&m, &swapped, &plain());
    assert_eq!(groups(&o.proposals), vec![vec![0, 3], vec![1, 4]]);
}

#[test]
fn a_link_that_passes_in_one_direction_only_is_rejected() {
    let m = quadrant_masks();
    // The backward warp contradicts the forward one: BL -> Q, TR -> P.
    let contradicting = |x: usize, y: usize| match (x >= 4, y >= 4) {
        (false, true) => Some((2.0, 6.0)),
        (true, false) => Some((6.0, 2.0)),
        _ => None,
    };
    let warps = [
        Warp {
            pair: [0, 1],
            target: &forward_pq,
            certainty: 1.0,
        },
        Warp {
            pair: [1, 0],
            target: &contradicting,
            certainty: 1.0,
        },
    ];
    let o = run(&m, &matches(2, 8, 8, &warps), &plain());
    assert!(o.edges.is_empty());
    assert!(o.proposals.is_empty());
    let r = &o.report;
    assert_eq!((r.edges_tested, r.edges_accepted), (4, 0));
    assert_eq!(r.rejections.one_direction_only, 4);
    assert_eq!(r.rejections.no_reverse_overlap, 4);

    // Only the forward warp: judged on it by default, skipped with require_both_warps.
    let only_forward = matches(2, 8, 8, &warps[..1]);
    let o = run(&m, &only_forward, &plain());
    assert_eq!(edges(&o), vec![[0, 4], [1, 3]]);
    assert_eq!(o.report.one_direction_pairs, 1);
    let strict = Params {
        require_both_warps: true,
        ..plain()
    };
    let o = run(&m, &only_forward, &strict);
    assert!(o.edges.is_empty());
    assert_eq!((o.report.skipped_pairs, o.report.edges_tested), (1, 0));
}

// ---------------------------------------------------------------------------------------
// Every threshold: a link that must pass and one that must fail.

/// View 0: mask A = cells with x < 6 and even y (30 cells, box 6 x 9 = 54 cells).
/// View 1: mask B everywhere. Identity warps: IoU 0.3 and box IoU 54/100 both ways.
fn striped_case(certainty: f32) -> (Masks, Matches) {
    let m = masks(
        10,
        10,
        &[
            (1, &|x, y| (x < 6 && y % 2 == 0).then_some(0)),
            (1, &|_, _| Some(0)),
        ],
    );
    let t = matches(
        2,
        10,
        10,
        &[
            Warp {
                pair: [0, 1],
                target: &identity,
                certainty,
            },
            Warp {
                pair: [1, 0],
                target: &identity,
                certainty,
            },
        ],
    );
    (m, t)
}

#[test]
fn gated_iou_and_box_iou_are_the_documented_areas() {
    let (m, t) = striped_case(1.0);
    let asso = Association::new(Inputs::new(&m, &t), &plain()).unwrap();
    let f = asso.directed_overlaps(0).unwrap();
    assert_eq!(
        (f.src_area[0], f.dst_area[0], f.intersection(0, 0)),
        (30.0, 100.0, 30.0)
    );
    assert!((f.iou(0, 0) - 0.3).abs() < 1e-12);
    assert!((f.box_iou(0, 0) - 0.54).abs() < 1e-12);
    let b = asso.directed_overlaps(1).unwrap();
    assert_eq!((b.src_area[0], b.dst_area[0]), (100.0, 30.0));
    assert!((b.iou(0, 0) - 0.3).abs() < 1e-12);
    assert!((b.box_iou(0, 0) - 0.54).abs() < 1e-12);
    assert_eq!(f.cells.gated, 100);
}

#[test]
fn tau_iou_and_tau_box_gate_the_mask_and_box_ious() {
    let (m, t) = striped_case(1.0);
    type Set = fn(f64) -> Params;
    type Rejected = fn(&Outcome) -> u64;
    let iou: (Set, Rejected) = (
        |tau| Params {
            tau_iou: tau,
            ..plain()
        },
        |o| o.report.rejections.iou,
    );
    let box_iou: (Set, Rejected) = (
        |tau| Params {
            tau_box: tau,
            ..plain()
        },
        |o| o.report.rejections.box_iou,
    );
    // The case's mask IoU is 0.3 and its box IoU 0.54.
    for (name, (set, rejected), below, above) in [
        ("tau_iou", iou, 0.29, 0.31),
        ("tau_box", box_iou, 0.53, 0.55),
    ] {
        for (tau, linked) in [(below, true), (above, false)] {
            let o = run(&m, &t, &set(tau));
            assert_eq!(!o.edges.is_empty(), linked, "{name} {tau}");
            assert_eq!(rejected(&o), u64::from(!linked), "{name} {tau}");
        }
    }
}

#[test]
fn tau_alpha_gates_the_certainty() {
    let (m, t) = striped_case(0.7);
    for (tau, linked) in [(0.69, true), (0.71, false)] {
        let o = run(
            &m,
            &t,
            &Params {
                tau_alpha: tau,
                ..plain()
            },
        );
        assert_eq!(!o.edges.is_empty(), linked, "tau_alpha {tau}");
        let c = o.report.cells;
        assert_eq!(c.total, 200);
        assert_eq!(c.low_certainty, if linked { 0 } else { 200 });
    }
}

#[test]
fn forward_backward_visibility_rejects_inconsistent_round_trips() {
    // One mask per view; forward identity, backward shifted 3 cells to the right.
    let m = masks(10, 10, &[(1, &|_, _| Some(0)), (1, &|_, _| Some(0))]);
    let shifted = |x: usize, y: usize| Some((x as f64 + 3.5, y as f64 + 0.5));
    let t = matches(
        2,
        10,
        10,
        &[
            Warp {
                pair: [0, 1],
                target: &identity,
                certainty: 1.0,
            },
            Warp {
                pair: [1, 0],
                target: &shifted,
                certainty: 1.0,
            },
        ],
    );
    let none = run(&m, &t, &plain());
    assert_eq!(edges(&none), vec![[0, 1]]);
    let fb = |tol: f32| Params {
        visibility: Visibility::FwdBwd,
        fwd_bwd_tolerance: tol,
        ..plain()
    };
    // Round trip error 3 cells: rejected at 2, accepted at 3.5.
    let strict = run(&m, &t, &fb(2.0));
    assert!(strict.edges.is_empty());
    // Forward: all 100 cells occluded. Backward: the 70 whose target lies in view 0 fail;
    // the 30 whose target is outside view 0 have no evidence and stay in the gate.
    assert_eq!(strict.report.cells.occluded, 170);
    assert_eq!(strict.report.cells.gated, 30);
    let loose = run(&m, &t, &fb(3.5));
    assert_eq!(edges(&loose), vec![[0, 1]]);
    assert_eq!(loose.report.visibility, "fwd-bwd");
}

/// Two cameras with the same pose looking down +z at a step: the left half of the image
/// sees a plane at z = 5, the right half a plane at z = 10 (dense small Gaussians).
fn step_scene() -> (Cameras, Gaussians) {
    let cams = Cameras {
        image_names: vec!["a.png".into(), "b.png".into()],
        image_size: vec![[16u32, 16]; 2].into(),
        intrinsics: vec![[16.0, 16.0, 8.0, 8.0]; 2].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 2]
            .into(),
        distortion: None,
        extra: Default::default(),
    };
    let mut means = Vec::new();
    for (z, x0, x1, half) in [(5.0f32, -3.0f32, -0.05f32, 3.0f32), (10.0, 0.05, 6.0, 6.0)] {
        let n = ((x1 - x0) / 0.1).round() as i32;
        let k = (2.0 * half / 0.1).round() as i32;
        for i in 0..=n {
            for j in 0..=k {
                means.push([x0 + i as f32 * 0.1, -half + j as f32 * 0.1, z]);
            }
        }
    }
    let n = means.len();
    let s = 0.06f32.ln();
    let g = Gaussians {
        means: means.into(),
        log_scales: vec![[s, s, 0.01f32.ln()]; n].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; n].into(),
        opacity_logits: vec![5.0; n].into(),
        sh_dc: vec![[0.0; 3]; n].into(),
        sh_degree: 0,
        sh_rest: None,
        class_ids: None,
        extra: Default::default(),
    };
    (cams, g)
}

#[test]
fn depth_visibility_rejects_correspondences_that_contradict_the_geometry() {
    let (cams, g) = step_scene();
    // Both views: mask 0 on columns 0..6 (the z = 5 plane), mask 1 on columns 10..16 (the
    // z = 10 plane); the columns between see a blend of both and carry no mask.
    let halves: LabelFn<'_> = &|x, _| match x {
        0..6 => Some(0),
        10.. => Some(1),
        _ => None,
    };
    let m = masks(16, 16, &[(2, halves), (2, halves)]);
    let mirror = |x: usize, y: usize| Some((15.5 - x as f64, y as f64 + 0.5));
    let warps = |target: &dyn Fn(usize, usize) -> Option<(f64, f64)>| {
        let w: [Warp<'_>; 2] = [
            Warp {
                pair: [0, 1],
                target,
                certainty: 1.0,
            },
            Warp {
                pair: [1, 0],
                target,
                certainty: 1.0,
            },
        ];
        matches(2, 16, 16, &w)
    };
    let depth = Params {
        visibility: Visibility::Depth,
        ..plain()
    };
    let with_geometry = |t: &Matches, p: &Params| {
        build_proposals(Inputs::new(&m, t).with_cameras(&cams).with_gaussians(&g), p).unwrap()
    };
    // Consistent (identity) correspondences pass the depth test.
    let o = with_geometry(&warps(&identity), &depth);
    assert_eq!(edges(&o), vec![[0, 2], [1, 3]]);
    assert_eq!(o.report.cells.occluded, 0);
    assert_eq!(o.report.visibility, "depth");
    // The mirror maps z = 5 onto z = 10 and back: every cell fails, no links.
    let mirrored = warps(&mirror);
    let o = with_geometry(&mirrored, &depth);
    assert!(o.edges.is_empty());
    // At least the 12 masked columns x 16 rows x 2 directions fail.
    assert!(o.report.cells.occluded >= 384, "{:?}", o.report.cells);
    // Without the test the mirror links the crossed halves.
    let o = with_geometry(&mirrored, &plain());
    assert_eq!(edges(&o), vec![[0, 3], [1, 2]]);
    // `auto` with cameras and Gaussians is both tests; the mirrored round trip is
    // consistent, so only depth rejects.
    let o = with_geometry(&mirrored, &Params::default());
    assert_eq!(o.report.visibility, "both");
    assert!(o.edges.is_empty());
}

/// View 0: halves L (x < 5) and R; view 1: W everywhere; view 2: V everywhere but only
/// linked to view 1. Components: {L, R, W, V} over 3 views, or {L, R, W} over 2.
#[test]
fn s_min_and_v_min_filter_components() {
    let m = masks(
        10,
        10,
        &[(2, &|x, _| Some(u16::from(x >= 5))), (1, &|_, _| Some(0))],
    );
    let w = |pair| Warp {
        pair,
        target: &identity,
        certainty: 1.0,
    };
    let t = matches(2, 10, 10, &[w([0, 1]), w([1, 0])]);
    // {L, R, W}: 3 members over 2 views (L and R both link to W: one common support).
    for (s_min, v_min, kept) in [(3, 2, true), (4, 2, false), (2, 2, true), (2, 3, false)] {
        let o = run(
            &m,
            &t,
            &Params {
                s_min,
                v_min,
                ..plain()
            },
        );
        assert_eq!(edges(&o), vec![[0, 2], [1, 2]]);
        let expected: Vec<Vec<u32>> = if kept { vec![vec![0, 1, 2]] } else { vec![] };
        assert_eq!(
            groups(&o.proposals),
            expected,
            "s_min {s_min} v_min {v_min}"
        );
        if kept {
            assert_eq!(&o.proposals.proposal_views[..], &[2]);
        }
        let c = o.report.components;
        assert_eq!((c.components, c.linked_components), (1, 1));
        assert_eq!(c.dropped_by_s_min + c.dropped_by_v_min, u64::from(!kept));
    }
    // Asking for two common supports refuses to join L and R: two 2-member proposals.
    let o = run(
        &m,
        &t,
        &Params {
            same_view_support: Some(2),
            ..plain()
        },
    );
    assert_eq!(groups(&o.proposals), vec![vec![0, 2]]);
    assert_eq!(o.report.components.refused_links, 1);
}

// ---------------------------------------------------------------------------------------
// Sampling.

#[test]
fn bilinear_sampling_shares_weight_between_labels_and_nearest_does_not() {
    // View 0: P everywhere. View 1: A = x < 5, B = x >= 5. Every cell maps to (4.75, 5.0).
    let m = masks(
        10,
        10,
        &[(1, &|_, _| Some(0)), (2, &|x, _| Some(u16::from(x >= 5)))],
    );
    let to_point = |_: usize, _: usize| Some((4.75, 5.0));
    let t = matches(
        2,
        10,
        10,
        &[Warp {
            pair: [0, 1],
            target: &to_point,
            certainty: 1.0,
        }],
    );
    let asso = Association::new(Inputs::new(&m, &t), &plain()).unwrap();
    let d = asso.directed_overlaps(0).unwrap();
    // Pixel centres 4.5 (A) and 5.5 (B) surround 4.75: weights 0.75 and 0.25 per cell
    // (up to the f32 rounding of the normalised warp).
    let near = |p: f64, q: f64| (p - q).abs() < 1e-5;
    assert!(near(d.intersection(0, 0), 75.0) && near(d.intersection(0, 1), 25.0));
    assert!(near(d.dst_area[0], 75.0) && near(d.dst_area[1], 25.0));
    assert!(near(d.iou(0, 0), 0.75));
    let nearest = Params {
        sampling: Sampling::Nearest,
        ..plain()
    };
    let asso = Association::new(Inputs::new(&m, &t), &nearest).unwrap();
    let d = asso.directed_overlaps(0).unwrap();
    assert_eq!((d.intersection(0, 0), d.intersection(0, 1)), (100.0, 0.0));
    assert_eq!(d.iou(0, 0), 1.0);
}

// ---------------------------------------------------------------------------------------
// The contingency table against a brute-force loop over mask pairs x cells.

struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Weight of label `b` when sampling `labels` at continuous mask coordinates: written
/// per mask, independently of the crate's four-neighbour accumulation.
fn brute_weight(
    labels: &[u16],
    mw: usize,
    mh: usize,
    mx: f64,
    my: f64,
    b: u16,
    nearest: bool,
) -> f64 {
    if !(0.0..=mw as f64).contains(&mx) || !(0.0..=mh as f64).contains(&my) {
        return 0.0;
    }
    let at = |px: i64, py: i64| {
        let px = px.clamp(0, mw as i64 - 1) as usize;
        let py = py.clamp(0, mh as i64 - 1) as usize;
        labels[py * mw + px]
    };
    if nearest {
        return f64::from(u8::from(at(mx.floor() as i64, my.floor() as i64) == b));
    }
    let (x0, y0) = ((mx - 0.5).floor(), (my - 0.5).floor());
    // The documented snap of fractions within 1e-4 of 0 or 1.
    let snap = |f: f64| {
        if f < 1e-4 {
            0.0
        } else if f > 1.0 - 1e-4 {
            1.0
        } else {
            f
        }
    };
    let (fx, fy) = (snap(mx - 0.5 - x0), snap(my - 0.5 - y0));
    let mut w = 0.0;
    for (dx, wx) in [(0, 1.0 - fx), (1, fx)] {
        for (dy, wy) in [(0, 1.0 - fy), (1, fy)] {
            if at(x0 as i64 + dx, y0 as i64 + dy) == b {
                w += wx * wy;
            }
        }
    }
    w
}

fn random_case(
    seed: u64,
    mw: usize,
    mh: usize,
    gw: usize,
    gh: usize,
    pixels: bool,
) -> (Masks, Matches, Cameras) {
    let mut r = Lcg(seed);
    let counts = [5usize, 7];
    let mut labels = Vec::new();
    for n in counts {
        for _ in 0..mw * mh {
            let v = (r.next() * (n + 1) as f64) as u16;
            labels.push(if v as usize == n { u16::MAX } else { v });
        }
    }
    let image = [
        [mw as u32 * 2 + 3, mh as u32 * 3 + 1],
        [mw as u32 + 5, mh as u32 * 2],
    ];
    let mut warp = Vec::new();
    let mut cert = Vec::new();
    for p in 0..2 {
        let [iw, ih] = image[1 - p];
        for _ in 0..gw * gh {
            let (u, v) = (r.next() * 1.4 - 0.2, r.next() * 1.4 - 0.2);
            if pixels {
                warp.extend([(u * f64::from(iw)) as f32, (v * f64::from(ih)) as f32]);
            } else {
                warp.extend([(2.0 * u - 1.0) as f32, (2.0 * v - 1.0) as f32]);
            }
            cert.push(r.next() as f32);
        }
    }
    let m = Masks {
        view_names: vec!["a".into(), "b".into()],
        width: mw,
        height: mh,
        labels: Labels::U16(labels.into()),
        mask_offsets: vec![0u32, 5, 12].into(),
        features: Floats::F32(vec![1.0; 12].into()),
        dim: 1,
        extra: Default::default(),
    };
    let t = Matches {
        num_views: 2,
        pairs: vec![[0u32, 1], [1, 0]].into(),
        height: gh,
        width: gw,
        warp: Floats::F32(warp.into()),
        certainty: Floats::F32(cert.into()),
        coords: if pixels {
            WarpCoords::Pixels
        } else {
            WarpCoords::Normalized
        },
        extra: Default::default(),
    };
    let cams = Cameras {
        image_names: vec!["a".into(), "b".into()],
        image_size: image.to_vec().into(),
        intrinsics: vec![[10.0, 10.0, 5.0, 5.0]; 2].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 2]
            .into(),
        distortion: None,
        extra: Default::default(),
    };
    (m, t, cams)
}

#[test]
fn contingency_table_matches_a_brute_force_loop_over_mask_pairs() {
    let cases = [
        (1, 23, 17, 23, 17, false),
        (2, 23, 17, 11, 9, false),
        (3, 23, 17, 31, 29, true),
        (4, 16, 12, 7, 5, true),
    ];
    for (seed, mw, mh, gw, gh, pixels) in cases {
        let (m, t, cams) = random_case(seed, mw, mh, gw, gh, pixels);
        let labels = match &m.labels {
            Labels::U16(b) => b.to_vec(),
            Labels::U32(_) => unreachable!(),
        };
        for nearest in [false, true] {
            let params = Params {
                tau_alpha: 0.3,
                sampling: if nearest {
                    Sampling::Nearest
                } else {
                    Sampling::Bilinear
                },
                ..plain()
            };
            let asso = Association::new(Inputs::new(&m, &t).with_cameras(&cams), &params).unwrap();
            for row in 0..2 {
                let (i, j) = (row, 1 - row);
                let d = asso.directed_overlaps(row).unwrap();
                let plane = |v: usize| &labels[v * mw * mh..(v + 1) * mw * mh];
                let (ni, nj) = (m.masks_in_view(i), m.masks_in_view(j));
                let mut nonzero = 0;
                for a in 0..ni as u16 {
                    for b in 0..nj as u16 {
                        let (mut inter, mut area_a, mut area_b) = (0.0, 0.0, 0.0);
                        let (mut box_a, mut box_b) = (Vec::new(), Vec::new());
                        for y in 0..gh {
                            for x in 0..gw {
                                let c = row * gw * gh + y * gw + x;
                                if t.certainty.get(c) < 0.3 {
                                    continue;
                                }
                                let px = ((x as f64 + 0.5) * mw as f64 / gw as f64) as usize;
                                let py = ((y as f64 + 0.5) * mh as f64 / gh as f64) as usize;
                                let in_a = plane(i)[py * mw + px] == a;
                                let (wx, wy) = (
                                    f64::from(t.warp.get(2 * c)),
                                    f64::from(t.warp.get(2 * c + 1)),
                                );
                                let (mx, my) = if pixels {
                                    let [iw, ih] = cams.image_size[j];
                                    (
                                        wx * mw as f64 / f64::from(iw),
                                        wy * mh as f64 / f64::from(ih),
                                    )
                                } else {
                                    ((wx + 1.0) / 2.0 * mw as f64, (wy + 1.0) / 2.0 * mh as f64)
                                };
                                let wb = brute_weight(plane(j), mw, mh, mx, my, b, nearest);
                                if in_a {
                                    area_a += 1.0;
                                    inter += wb;
                                    box_a.push((x, y));
                                }
                                if wb > 0.0 {
                                    area_b += wb;
                                    box_b.push((x, y));
                                }
                            }
                        }
                        let (a32, b32) = (u32::from(a), u32::from(b));
                        let close = |p: f64, q: f64| (p - q).abs() <= 1e-9 * (1.0 + q.abs());
                        assert!(
                            close(d.intersection(a32, b32), inter),
                            "seed {seed} ({a},{b})"
                        );
                        assert!(close(d.src_area[a as usize], area_a));
                        assert!(close(d.dst_area[b as usize], area_b));
                        let iou = if inter > 0.0 {
                            inter / (area_a + area_b - inter)
                        } else {
                            0.0
                        };
                        assert!(close(d.iou(a32, b32), iou));
                        let bbox = |cells: &[(usize, usize)]| {
                            cells.iter().fold(
                                (usize::MAX, usize::MAX, 0, 0),
                                |(x0, y0, x1, y1), &(x, y)| {
                                    (x0.min(x), y0.min(y), x1.max(x), y1.max(y))
                                },
                            )
                        };
                        let box_iou = if box_a.is_empty() || box_b.is_empty() {
                            0.0
                        } else {
                            let (p, q) = (bbox(&box_a), bbox(&box_b));
                            let area = |b: (usize, usize, usize, usize)| {
                                if b.0 > b.2 || b.1 > b.3 {
                                    0
                                } else {
                                    (b.2 - b.0 + 1) * (b.3 - b.1 + 1)
                                }
                            };
                            let i = area((p.0.max(q.0), p.1.max(q.1), p.2.min(q.2), p.3.min(q.3)));
                            i as f64 / (area(p) + area(q) - i) as f64
                        };
                        assert!(
                            close(d.box_iou(a32, b32), box_iou),
                            "box seed {seed} ({a},{b})"
                        );
                        nonzero += usize::from(inter > 0.0);
                    }
                }
                // The table lists exactly the pairs with a non-zero intersection.
                assert_eq!(d.intersections.len(), nonzero);
                assert!(d.intersections.iter().all(|o| o.weight > 0.0));
                assert!(nonzero > 5, "seed {seed}: a weak case ({nonzero} overlaps)");
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Determinism, errors, synthetic scenes.

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

#[test]
fn output_is_byte_identical_for_1_and_4_threads() {
    let scene = synthetic::scene(&synthetic::Config {
        views: 6,
        width: 80,
        height: 60,
        masks_per_view: 20,
        neighbours: 2,
        warp_noise: 0.7,
        ..synthetic::Config::default()
    });
    let once = |threads| {
        in_pool(threads, || {
            let o = build_proposals(
                Inputs::new(&scene.masks, &scene.matches),
                &Params::default(),
            )
            .unwrap();
            (o.proposals.to_bytes().unwrap(), o.report, o.edges)
        })
    };
    let (a, b) = (once(1), once(4));
    assert!(a.1.components.proposals > 5);
    assert_eq!(a.0, b.0);
    assert_eq!(a.1, b.1);
    assert_eq!(a.2, b.2);
}

#[test]
fn synthetic_voronoi_scenes_are_recovered_exactly() {
    for (noise, sampling) in [
        (0.0, Sampling::Bilinear),
        (0.4, Sampling::Bilinear),
        (0.0, Sampling::Nearest),
    ] {
        let scene = synthetic::scene(&synthetic::Config {
            views: 5,
            width: 96,
            height: 64,
            masks_per_view: 16,
            neighbours: 2,
            warp_noise: noise,
            seed: 7,
            ..synthetic::Config::default()
        });
        let o = build_proposals(
            Inputs::new(&scene.masks, &scene.matches),
            &Params {
                sampling,
                ..Params::default()
            },
        )
        .unwrap();
        let s = profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &scene.truth)
            .unwrap();
        assert_eq!(s.purity, 1.0, "noise {noise} {sampling:?}");
        assert!(s.ari > 0.97, "noise {noise} {sampling:?}: {s:?}");
        assert_eq!(o.report.visibility, "fwd-bwd");
        o.proposals
            .check_against(&scene.masks, "proposals")
            .unwrap();
    }
}

#[test]
fn inconsistent_inputs_are_typed_errors() {
    let (m, t) = striped_case(1.0);
    // Masks of 2 views, matches of 3.
    let mut three = t.clone();
    three.num_views = 3;
    let e = build_proposals(Inputs::new(&m, &three), &plain()).unwrap_err();
    assert!(
        matches!(
            e,
            WarpGraphError::ViewCountMismatch {
                masks: 2,
                matches: 3
            }
        ),
        "{e}"
    );
    // A pair naming view 5 of 2.
    let mut bad = t.clone();
    bad.pairs = vec![[0u32, 1], [5, 0]].into();
    let e = build_proposals(Inputs::new(&m, &bad), &plain()).unwrap_err();
    assert!(
        matches!(
            e,
            WarpGraphError::PairOutOfRange {
                row: 1,
                view: 5,
                views: 2
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("`pairs` row 1"), "{e}");
    // A repeated ordered pair.
    let mut twice = t.clone();
    twice.pairs = vec![[0u32, 1], [0, 1]].into();
    let e = build_proposals(Inputs::new(&m, &twice), &plain()).unwrap_err();
    assert!(matches!(e, WarpGraphError::BadPair { row: 1, .. }), "{e}");
    // Pixel coordinates need the cameras' image sizes.
    let mut px = t.clone();
    px.coords = WarpCoords::Pixels;
    let e = build_proposals(Inputs::new(&m, &px), &plain()).unwrap_err();
    assert!(matches!(e, WarpGraphError::MissingCameras { .. }), "{e}");
    // Depth visibility needs Gaussians.
    let depth = Params {
        visibility: Visibility::Depth,
        ..Params::default()
    };
    let e = build_proposals(Inputs::new(&m, &t), &depth).unwrap_err();
    assert!(matches!(e, WarpGraphError::MissingGaussians { .. }), "{e}");
    // A label beyond the view's mask count (only possible in unvalidated memory).
    let mut wrong = m.clone();
    wrong.labels = Labels::U16(vec![3u16; 200].into());
    let e = build_proposals(Inputs::new(&wrong, &t), &plain()).unwrap_err();
    assert!(
        matches!(
            e,
            WarpGraphError::LabelOutOfRange {
                view: 0,
                pixel: 0,
                label: 3,
                count: 1
            }
        ),
        "{e}"
    );
    // A warp tensor of the wrong length.
    let mut short = t.clone();
    short.warp = Floats::F32(vec![0.0; 10].into());
    let e = build_proposals(Inputs::new(&m, &short), &plain()).unwrap_err();
    assert!(
        matches!(e, WarpGraphError::Shape { tensor: "warp", .. }),
        "{e}"
    );
    // Parameters outside their domain.
    for p in [
        Params {
            tau_iou: 1.5,
            ..plain()
        },
        Params {
            tau_alpha: f32::NAN,
            ..plain()
        },
        Params {
            s_min: 0,
            ..plain()
        },
        Params {
            fwd_bwd_tolerance: 0.0,
            ..plain()
        },
        Params {
            same_view_support: Some(0),
            ..plain()
        },
        Params {
            extent_agreement: Some(1.5),
            ..plain()
        },
        Params {
            extent_merge_iou: Some(f64::NAN),
            ..plain()
        },
        Params {
            extent_trim: 0.5,
            ..plain()
        },
        Params {
            extent_pad: -0.1,
            ..plain()
        },
        Params {
            consensus: warp_graph::ConsensusParams {
                observed_points: 0,
                ..Default::default()
            },
            ..plain()
        },
    ] {
        let e = build_proposals(Inputs::new(&m, &t), &p).unwrap_err();
        assert!(matches!(e, WarpGraphError::InvalidParameter { .. }), "{e}");
    }
}

#[test]
fn proposals_record_the_parameters_and_round_trip_through_a_file() {
    let (m, t) = striped_case(1.0);
    let o = run(&m, &t, &plain());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("proposals.safetensors");
    o.proposals.write(&path).unwrap();
    let back = Proposals::read(&path).unwrap();
    back.check_against(&m, "proposals").unwrap();
    assert_eq!(back, o.proposals);
    let meta = &back.extra;
    for (k, v) in [
        ("tau_alpha", "0.5"),
        ("tau_iou", "0.2"),
        ("tau_box", "0.08"),
        ("s_min", "2"),
        ("v_min", "2"),
        ("visibility", "none"),
        ("sampling", "bilinear"),
        ("same_view_support", "1"),
        ("extent_agreement", "0.3"),
        ("extent_merge_iou", "0.1"),
        ("extent_trim", "0.05"),
        ("extent_pad", "0.01"),
        // No Gaussians: no extents, the extent rules did not run.
        ("extents", "false"),
    ] {
        assert_eq!(meta.get(k).map(String::as_str), Some(v), "{k}");
    }
}

// ---------------------------------------------------------------------------------------
// The synthetic demo scene: clustering scores against the true objects.

/// A generated demo scene's masks, matches, cameras, exact Gaussians and mask truth.
fn demo_files(dir: &std::path::Path) -> (Masks, Matches, Cameras, Gaussians, Vec<u32>) {
    (
        Masks::read(dir.join("masks.safetensors")).unwrap(),
        Matches::read(dir.join("matches.safetensors")).unwrap(),
        Cameras::read(dir.join("cameras.safetensors")).unwrap(),
        Gaussians::read(dir.join("gt/gaussians.safetensors")).unwrap(),
        profuse_metrics::cluster::read_mask_objects(dir.join("gt/mask_objects.json")).unwrap(),
    )
}

#[test]
fn demo_scene_proposals_score_against_the_true_objects() {
    let dir = tempfile::tempdir().unwrap();
    synth::generate(&synth::Config::preset(synth::Preset::Demo, 0), dir.path()).unwrap();
    let (m, t, cams, g, truth) = demo_files(dir.path());
    let inputs = Inputs::new(&m, &t).with_cameras(&cams).with_gaussians(&g);
    let score = |p: &Params| {
        let o = build_proposals(inputs, p).unwrap();
        o.proposals.check_against(&m, "proposals").unwrap();
        let s =
            profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &truth).unwrap();
        eprintln!(
            "demo seed 0, visibility {}, same_view_support {:?}, extents {:?}/{:?}: ARI {:.4} purity {:.4} completeness {:.4} ({} proposals, {} masks assigned)",
            o.report.visibility, p.same_view_support, p.extent_agreement, p.extent_merge_iou, s.ari, s.purity, s.completeness,
            o.report.components.proposals, o.report.components.masks_assigned
        );
        (s, o)
    };
    // The guard alone (extent rules off).
    let guard_only = Params {
        extent_agreement: None,
        extent_merge_iou: None,
        ..links()
    };
    for vis in [
        Visibility::Auto,
        Visibility::Depth,
        Visibility::FwdBwd,
        Visibility::None,
    ] {
        let (s, o) = score(&Params {
            visibility: vis,
            ..guard_only
        });
        assert!(!o.report.extents);
        assert!(s.ari >= 0.8, "{vis:?}: {s:?}");
        assert!(s.purity >= 0.95, "{vis:?}: {s:?}");
        assert!(s.completeness >= 0.75, "{vis:?}: {s:?}");
        // The default adds the extent rules (depth from the Gaussians whatever the
        // visibility test): the bridge between the east and west walls is refused and
        // fragments no warp connects are merged.
        let (e, o) = score(&Params {
            visibility: vis,
            ..links()
        });
        assert!(o.report.extents);
        assert!(o.report.components.extent_merges > 0, "{:?}", o.report);
        assert!(
            e.ari >= 0.9 && e.ari > s.ari + 0.03,
            "{vis:?}: {e:?} vs {s:?}"
        );
        assert!(e.purity >= 0.98, "{vis:?}: {e:?}");
        assert!(e.completeness >= 0.89, "{vis:?}: {e:?}");
    }
    // The paper's plain components: under-segmented masks glue objects together.
    let (s, o) = score(&Params {
        same_view_support: None,
        ..links()
    });
    assert!(s.purity < 0.7 && s.ari < 0.6, "{s:?}");
    assert_eq!(o.report.components.refused_links, 0);
    // Depth rendering and clustering are deterministic across thread counts.
    let bytes = |threads| {
        in_pool(threads, || {
            build_proposals(inputs, &links())
                .unwrap()
                .proposals
                .to_bytes()
                .unwrap()
        })
    };
    assert_eq!(bytes(1), bytes(4));
}

/// Harsh segmentation (35% of masks split, 30% of regions merged with a neighbour): the
/// link grouping chains objects through the merged masks (purity 0.94 on seed 0 with the
/// exact Gaussians), the view-consensus grouping keeps proposals purer (0.97: it drops the
/// merged masks as under-segmented) and is deterministic across thread counts.
#[test]
fn consensus_grouping_stays_pure_under_harsh_segmentation() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = synth::Config::preset(synth::Preset::Demo, 0);
    cfg.faults.p_split = 0.35;
    cfg.faults.p_merge = 0.3;
    synth::generate(&cfg, dir.path()).unwrap();
    let (m, t, cams, g, truth) = demo_files(dir.path());
    let inputs = Inputs::new(&m, &t).with_cameras(&cams).with_gaussians(&g);
    let score = |p: &Params| {
        let o = build_proposals(inputs, p).unwrap();
        o.proposals.check_against(&m, "proposals").unwrap();
        let s =
            profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &truth).unwrap();
        eprintln!(
            "harsh seed 0, {}: {s:?} {:?}",
            o.report.grouping, o.report.consensus
        );
        (s, o)
    };
    let consensus = Params {
        grouping: Grouping::Consensus,
        ..Params::default()
    };
    let (links, _) = score(&links());
    let (c, o) = score(&consensus);
    let stats = o.report.consensus.clone().unwrap();
    assert!(stats.undersegmented > 0, "{stats:?}");
    // Purity is what registration needs (an impure proposal gives one object's class to
    // another); the merged masks it drops count against its ARI and completeness.
    assert!(
        c.purity >= 0.95 && c.purity > links.purity + 0.02,
        "{c:?} vs {links:?}"
    );
    assert!(c.ari >= 0.6, "{c:?}");
    assert_eq!(
        o.proposals.extra.get("grouping").map(String::as_str),
        Some("consensus")
    );
    let bytes = |threads| {
        in_pool(threads, || {
            build_proposals(inputs, &consensus)
                .unwrap()
                .proposals
                .to_bytes()
                .unwrap()
        })
    };
    assert_eq!(bytes(1), bytes(4));
    // The default (auto) is the consensus grouping when Gaussians are given.
    let auto = build_proposals(inputs, &Params::default()).unwrap();
    assert_eq!(auto.report.grouping, "consensus");
    assert_eq!(auto.proposals.to_bytes().unwrap(), bytes(1));
    // Without Gaussians the consensus grouping has no points: a clear error, while auto
    // falls back to the links.
    let err = build_proposals(Inputs::new(&m, &t), &consensus).unwrap_err();
    assert!(err.to_string().contains("consensus"), "{err}");
    let no_geometry = build_proposals(Inputs::new(&m, &t), &Params::default()).unwrap();
    assert_eq!(no_geometry.report.grouping, "links");
}

/// With exact masks (no faults) every proposal is pure; what remains is the fragmentation
/// of objects seen from views that no warp connects.
#[test]
fn demo_scene_with_exact_masks_gives_pure_proposals() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = synth::Config::preset(synth::Preset::Demo, 0);
    cfg.faults = synth::FaultModel::exact();
    synth::generate(&cfg, dir.path()).unwrap();
    let m = Masks::read(dir.path().join("masks.safetensors")).unwrap();
    let t = Matches::read(dir.path().join("matches.safetensors")).unwrap();
    let truth =
        profuse_metrics::cluster::read_mask_objects(dir.path().join("gt/mask_objects.json"))
            .unwrap();
    for support in [Some(1), None] {
        let o = build_proposals(
            Inputs::new(&m, &t),
            &Params {
                same_view_support: support,
                ..Params::default()
            },
        )
        .unwrap();
        let s =
            profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &truth).unwrap();
        eprintln!("demo seed 0, exact masks, same_view_support {support:?}: {s:?}");
        assert_eq!(s.purity, 1.0, "{s:?}");
        assert!(s.ari >= 0.9, "{s:?}");
    }
}

// ---------------------------------------------------------------------------------------
// Dense warps from geometry (`depth_warps`) against the synthetic scene's exact geometry.

/// Every kept correspondence lands where the ground-truth surface point of its cell
/// projects (ground-truth depth maps, exact cameras), and cells whose point is hidden in
/// view j behind a nearer surface are rejected.
#[test]
fn depth_warps_agree_with_the_ground_truth_geometry() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = synth::Config::preset(synth::Preset::Demo, 3);
    cfg.write_matches = false;
    synth::generate(&cfg, dir.path()).unwrap();
    let cams = Cameras::read(dir.path().join("cameras.safetensors")).unwrap();
    let g = Gaussians::read(dir.path().join("gt/gaussians.safetensors")).unwrap();
    let truth = profuse_formats::ViewMaps::read(dir.path().join("gt/views.safetensors")).unwrap();
    // Stride 1: every cell centre is a pixel centre, where the truth is defined.
    // Default (no edge test), then with the depth-edge test at 0.05.
    let stats = |edge_tol: f64| {
        let params = warp_graph::DepthWarpParams {
            stride: 1,
            pairs: warp_graph::Pairs::Nearest(2),
            edge_tol,
            ..Default::default()
        };
        let (m, report) = warp_graph::depth_warps(&g, &cams, &params, &|_, _| {}).unwrap();
        // Through the formats writer and reader (the file must validate).
        let path = dir.path().join("depth_warps.safetensors");
        m.write(&path).unwrap();
        let m = Matches::read(&path).unwrap();
        assert_eq!((m.width, m.height), (320, 240));
        assert_eq!(m.coords, WarpCoords::Pixels);
        warp_errors(&m, &report, &cams, &truth)
    };
    // Measured (demo seed 3, 24 views, 48 pairs, stride 1). Default: 1,114,833 kept cells,
    // median error 0.29 px, 60% within 0.5 px, 70% within 1 px, occluded cells kept 2.8%,
    // visible cells kept 45%. Edge test 0.05: 736,866 kept, median 0.22 px, 78% within
    // 1 px, occluded kept 0.8%, visible kept 30%. The tail is the ground-truth Gaussians'
    // rendered depth (0.7% median relative error), which blends surfaces where they are
    // sparse.
    let d = stats(f64::INFINITY);
    assert!(
        d.kept > 900_000 && d.median < 0.4 && d.within_1px >= 0.67,
        "{d:?}"
    );
    assert!(
        d.occluded > 100_000 && d.occluded_kept <= 0.04 && d.visible_kept >= 0.4,
        "{d:?}"
    );
    let e = stats(0.05);
    assert!(
        e.kept > 500_000 && e.median < 0.3 && e.within_1px >= 0.75,
        "{e:?}"
    );
    assert!(e.occluded_kept <= 0.015 && e.visible_kept >= 0.25, "{e:?}");
}

#[derive(Debug)]
#[allow(dead_code)] // read through Debug
struct WarpErrors {
    kept: u64,
    median: f64,
    within_1px: f64,
    occluded: u64,
    occluded_kept: f64,
    visible_kept: f64,
}

/// Reprojection errors of the kept cells against the ground truth, and which occluded and
/// visible cells were kept.
fn warp_errors(
    m: &Matches,
    report: &warp_graph::DepthWarpReport,
    cams: &Cameras,
    truth: &profuse_formats::ViewMaps,
) -> WarpErrors {
    let (w, h) = (truth.width, truth.height);
    let gt_depth = |v: usize, px: f64, py: f64| {
        let (x, y) = (px as usize, py as usize);
        (x < w && y < h).then(|| f64::from(truth.depth[truth.index(v, x, y)]))
    };
    let (mut kept, mut within_1px, mut within_half) = (0u64, 0u64, 0u64);
    let (mut occluded, mut occluded_kept, mut visible, mut visible_kept) = (0u64, 0u64, 0u64, 0u64);
    let mut errors = Vec::new();
    for (p, &[i, j]) in m.pairs.iter().enumerate() {
        let (i, j) = (i as usize, j as usize);
        for y in 0..m.height {
            for x in 0..m.width {
                let c = (p * m.height + y) * m.width + x;
                let cert = m.certainty.get(c);
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let Some(z) = gt_depth(i, px, py).filter(|z| *z > 0.0) else {
                    continue;
                };
                let [fx, fy, cx, cy] = cams.intrinsics[i];
                let pc = [(px - cx) / fx * z, (py - cy) / fy * z, z];
                let (r, t) = cams.pose(i);
                let world: [f64; 3] =
                    std::array::from_fn(|k| (0..3).map(|l| r[l][k] * (pc[l] - t[l])).sum());
                let [u, v, zj] = cams.project(j, world);
                if cert > 0.0 {
                    kept += 1;
                    let (wu, wv) = (
                        f64::from(m.warp.get(2 * c)),
                        f64::from(m.warp.get(2 * c + 1)),
                    );
                    let e = ((wu - u).powi(2) + (wv - v).powi(2)).sqrt();
                    within_1px += u64::from(e <= 1.0);
                    within_half += u64::from(e <= 0.5);
                    errors.push(e);
                }
                let Some(dj) =
                    gt_depth(j, u, v).filter(|d| *d > 0.0 && zj > 0.0 && u >= 0.0 && v >= 0.0)
                else {
                    continue;
                };
                if dj < 0.9 * zj {
                    occluded += 1;
                    occluded_kept += u64::from(cert > 0.0);
                } else if (dj - zj).abs() < 0.01 * zj {
                    visible += 1;
                    visible_kept += u64::from(cert > 0.0);
                }
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let share = |a: u64, b: u64| a as f64 / b.max(1) as f64;
    eprintln!(
        "depth warps: {report:?}; kept {kept}: within 0.5 px {:.4}, within 1 px {:.4}, median {:.3} px, p99 {:.3} px; occluded cells kept {occluded_kept}/{occluded} ({:.4}); visible cells kept {visible_kept}/{visible} ({:.4})",
        share(within_half, kept),
        share(within_1px, kept),
        errors[errors.len() / 2],
        errors[errors.len() * 99 / 100],
        share(occluded_kept, occluded),
        share(visible_kept, visible),
    );
    WarpErrors {
        kept,
        median: errors
            .get(errors.len() / 2)
            .copied()
            .unwrap_or(f64::INFINITY),
        within_1px: share(within_1px, kept),
        occluded,
        occluded_kept: share(occluded_kept, occluded),
        visible_kept: share(visible_kept, visible),
    }
}

/// warp-graph on the depth warps instead of synth's exact warps: proposals that score
/// nearly as well against the true objects (demo scene, seed 0). Measured with the link
/// grouping: ARI 0.887 / purity 0.984 / completeness 0.874 from the depth warps against
/// 0.911 / 0.988 / 0.900 from synth's; the default (consensus) grouping: 0.788 for both.
#[test]
fn proposals_from_depth_warps_score_like_proposals_from_exact_warps() {
    let dir = tempfile::tempdir().unwrap();
    synth::generate(&synth::Config::preset(synth::Preset::Demo, 0), dir.path()).unwrap();
    let (m, t, cams, g, truth) = demo_files(dir.path());
    // The demo's warp grid is half the image (stride 2) over its 3 nearest neighbours.
    let params = warp_graph::DepthWarpParams {
        stride: 2,
        pairs: warp_graph::Pairs::Nearest(3),
        ..Default::default()
    };
    let (dense, report) = warp_graph::depth_warps(&g, &cams, &params, &|_, _| {}).unwrap();
    assert_eq!((dense.width, dense.height), (t.width, t.height));
    // The link grouping reads the warps; the default consensus grouping groups over the
    // Gaussians, so it is reported but cannot tell the warps apart.
    let score = |matches: &Matches, p: &Params| {
        let inputs = Inputs::new(&m, matches)
            .with_cameras(&cams)
            .with_gaussians(&g);
        let o = build_proposals(inputs, p).unwrap();
        profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &truth).unwrap()
    };
    for (name, p) in [("links", links()), ("default", Params::default())] {
        let exact = score(&t, &p);
        let ours = score(&dense, &p);
        eprintln!(
            "demo seed 0, {name}: synth warps ({} pairs) ARI {:.4} purity {:.4} completeness {:.4}; depth warps ({} pairs, {} of {} cells kept) ARI {:.4} purity {:.4} completeness {:.4}",
            t.pairs.len(), exact.ari, exact.purity, exact.completeness,
            report.pairs, report.kept, report.cells, ours.ari, ours.purity, ours.completeness
        );
        assert!(
            ours.ari >= exact.ari - 0.05,
            "{name}: {ours:?} vs {exact:?}"
        );
        assert!(
            ours.purity >= exact.purity - 0.02,
            "{name}: {ours:?} vs {exact:?}"
        );
    }
}

#[test]
fn depth_warp_parameters_and_pairs_are_checked() {
    let g = Gaussians::default();
    let cams = synthetic_cameras(3);
    let run = |p: warp_graph::DepthWarpParams| warp_graph::depth_warps(&g, &cams, &p, &|_, _| {});
    let bad = |p: warp_graph::DepthWarpParams, name: &str| {
        let err = run(p).unwrap_err();
        assert!(
            matches!(err, WarpGraphError::InvalidParameter { name: n, .. } if n == name),
            "{err}"
        );
    };
    let d = warp_graph::DepthWarpParams::default;
    bad(warp_graph::DepthWarpParams { stride: 0, ..d() }, "stride");
    bad(
        warp_graph::DepthWarpParams {
            depth_tol: 0.0,
            ..d()
        },
        "depth_tol",
    );
    bad(
        warp_graph::DepthWarpParams {
            min_alpha: 0.0,
            ..d()
        },
        "min_alpha",
    );
    bad(
        warp_graph::DepthWarpParams {
            edge_tol: f64::NAN,
            ..d()
        },
        "edge_tol",
    );
    bad(
        warp_graph::DepthWarpParams {
            pairs: warp_graph::Pairs::Nearest(0),
            ..d()
        },
        "pairs",
    );
    let explicit =
        |p: Vec<[u32; 2]>| warp_graph::resolve_pairs(&cams, &warp_graph::Pairs::Explicit(p));
    assert!(matches!(
        explicit(vec![[0, 3]]),
        Err(WarpGraphError::PairOutOfRange {
            row: 0,
            view: 3,
            ..
        })
    ));
    assert!(matches!(
        explicit(vec![[0, 1], [1, 1]]),
        Err(WarpGraphError::BadPair { row: 1, .. })
    ));
    assert!(matches!(
        explicit(vec![[0, 1], [0, 1]]),
        Err(WarpGraphError::BadPair { row: 1, .. })
    ));
    assert_eq!(
        explicit(vec![[2, 0], [0, 1]]).unwrap(),
        vec![[0, 1], [2, 0]]
    );
    // Views on a line at x = 0, 1, 3: nearest of 0 is 1, of 1 is 0, of 2 is 1.
    let nearest = warp_graph::resolve_pairs(&cams, &warp_graph::Pairs::Nearest(1)).unwrap();
    assert_eq!(nearest, vec![[0, 1], [1, 0], [1, 2], [2, 1]]);
    // Among views 0 and 2 only, view 1 (nearest to both) takes part in no pair.
    let among = |views: Vec<u32>| {
        warp_graph::resolve_pairs(&cams, &warp_graph::Pairs::NearestAmong(1, views))
    };
    assert_eq!(among(vec![2, 0]).unwrap(), vec![[0, 2], [2, 0]]);
    assert!(matches!(
        among(vec![0, 3]),
        Err(WarpGraphError::PairOutOfRange {
            row: 1,
            view: 3,
            ..
        })
    ));
    assert!(matches!(
        among(vec![0, 2, 0]),
        Err(WarpGraphError::InvalidParameter { name: "pairs", .. })
    ));
}

/// Three cameras looking down +z from x = 0, 1, 3.
fn synthetic_cameras(n: usize) -> Cameras {
    let xs = [0.0, 1.0, 3.0];
    Cameras {
        image_names: (0..n).map(|v| format!("v{v}.png")).collect(),
        image_size: vec![[32u32, 24u32]; n].into(),
        intrinsics: vec![[30.0, 30.0, 16.0, 12.0]; n].into(),
        world_to_camera: (0..n)
            .map(|v| {
                [
                    1.0, 0.0, 0.0, -xs[v], 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0,
                ]
            })
            .collect::<Vec<[f64; 12]>>()
            .into(),
        distortion: None,
        extra: Default::default(),
    }
}

// ---------------------------------------------------------------------------------------
// View-pair shards (issue 21).

/// A tiny synth scene with ground-truth Gaussians: the job of a run over it.
fn shard_scene(dir: &std::path::Path) -> warp_graph::job::Job {
    let mut config = synth::Config::preset(synth::Preset::Tiny, 3);
    config.views = 5;
    config.gaussians = 3000;
    synth::generate(&config, dir).unwrap();
    let file = |name: &str| dir.join(name);
    warp_graph::job::Job {
        masks: file("masks.safetensors"),
        matches: file("matches.safetensors"),
        cameras: Some(file("cameras.safetensors")),
        gaussians: Some(file("gt/gaussians.safetensors")),
        out: file("proposals.safetensors"),
    }
}

/// Evidence of consecutive view-pair ranges, merged in any order, equals the evidence of
/// all pairs (links with bit-identical scores, counters), and groups into the proposals
/// of one run, with both groupings (grouped by a fresh association, as a merge is).
#[test]
fn evidence_of_pair_ranges_merges_into_the_evidence_of_one_run() {
    let dir = tempfile::tempdir().unwrap();
    let job = shard_scene(dir.path());
    let masks = Masks::read(&job.masks).unwrap();
    let matches = Matches::read(&job.matches).unwrap();
    let cameras = Cameras::read(job.cameras.as_ref().unwrap()).unwrap();
    let gaussians = Gaussians::read(job.gaussians.as_ref().unwrap()).unwrap();
    for grouping in [Grouping::Consensus, Grouping::Links] {
        let params = Params {
            grouping,
            ..Params::default()
        };
        let inputs = Inputs::new(&masks, &matches)
            .with_cameras(&cameras)
            .with_gaussians(&gaussians);
        let a = Association::new(inputs, &params).unwrap();
        let t = a.num_view_pairs();
        assert!(t >= 4, "{t} view pairs");
        let whole = a.pair_evidence(0..t, &|_, _| {}).unwrap();
        assert!(!whole.edges.is_empty());
        let cuts = [0, 1, 1, t / 2, t];
        let mut shards: Vec<(String, warp_graph::Evidence)> = cuts
            .windows(2)
            .map(|w| {
                let e = a.pair_evidence(w[0]..w[1], &|_, _| {}).unwrap();
                (format!("{}..{}", w[0], w[1]), e)
            })
            .collect();
        shards.reverse();
        let merged = warp_graph::Evidence::merge(shards, t).unwrap();
        assert_eq!(merged, whole);
        let bits = |e: &warp_graph::Evidence| -> Vec<u64> {
            e.edges.iter().map(|l| l.iou.to_bits()).collect()
        };
        assert_eq!(bits(&merged), bits(&whole));
        let one = a.run(&|_, _| {}).unwrap();
        // A fresh association, as in the merging process: no per-view cache from pairs.
        let fresh = Association::new(inputs, &params).unwrap();
        let grouped = fresh.group(&merged).unwrap();
        assert_eq!(grouped.proposals, one.proposals);
        assert_eq!(grouped.report, one.report);
        assert_eq!(grouped.edges, one.edges);
        assert!(a.pair_evidence(0..t + 1, &|_, _| {}).is_err());
        assert!(a
            .group(&a.pair_evidence(0..1, &|_, _| {}).unwrap())
            .is_err());
    }
}

/// `run_shard` files merged by `run_merged` write the bytes of `run`; a missing range, a
/// range in two shards and a shard of other parameters or other Gaussians are refused
/// with the cause named, and nothing is written.
#[test]
fn shard_files_merge_into_the_proposals_file_of_one_run() {
    use warp_graph::job::{self, JobError};
    let dir = tempfile::tempdir().unwrap();
    let job = shard_scene(dir.path());
    let params = Params::default();
    job::run(&job, &params, &|_, _| {}).unwrap();
    let reference = std::fs::read(&job.out).unwrap();
    std::fs::remove_file(&job.out).unwrap();
    let shard = |range: std::ops::Range<usize>, params: &Params, job: &job::Job| {
        let path = dir.path().join(format!(
            "s{}_{}_{}.safetensors",
            range.start, range.end, params.tau_iou
        ));
        let report = job::run_shard(job, params, range, &path, &|_, _| {}).unwrap();
        (path, report.view_pairs)
    };
    let (probe, t) = shard(0..0, &params, &job);
    let (a, _) = shard(0..2, &params, &job);
    let (b, _) = shard(2..t, &params, &job);
    let merged = job::run_merged(&job, &params, &[b.clone(), probe, a.clone()]).unwrap();
    assert_eq!(std::fs::read(&job.out).unwrap(), reference);
    assert_eq!(merged.out, job.out);
    std::fs::remove_file(&job.out).unwrap();

    let refused = |partials: &[std::path::PathBuf], want: &str| {
        let err = job::run_merged(&job, &params, partials).unwrap_err();
        assert!(matches!(err, JobError::Shards(_)), "{err}");
        assert!(err.to_string().contains(want), "{err}");
        assert!(!job.out.exists());
    };
    refused(std::slice::from_ref(&b), "view pairs 0..2");
    let (overlap, _) = shard(1..3, &params, &job);
    refused(&[a.clone(), overlap, b.clone()], "in two shards");
    let other = Params {
        tau_iou: 0.3,
        ..params
    };
    let (foreign, _) = shard(0..2, &other, &job);
    refused(&[foreign, b.clone()], "input_params");
    let mut moved = job.clone();
    moved.gaussians = Some(dir.path().join("gt/other_gaussians.safetensors"));
    let mut g = Gaussians::read(job.gaussians.as_ref().unwrap()).unwrap();
    let mut means = g.means.to_vec();
    means[0][0] += 0.001;
    g.means = means.into();
    g.write(moved.gaussians.as_ref().unwrap()).unwrap();
    let (shifted, _) = shard(0..2, &params, &moved);
    refused(&[shifted, b], "input_gaussians");
}
