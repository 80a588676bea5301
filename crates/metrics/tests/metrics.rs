//! Integration tests of profuse-metrics against hand-computed cases and brute force.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use profuse_metrics::cluster::{adjusted_rand_index, cluster_scores, NONE};
use profuse_metrics::surface::{scene_extent, summarize, surface_distances};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * (1.0 + a.abs().max(b.abs()))
}

/// ARI from the four pair counts over all item pairs (Hubert & Arabie's pair-counting
/// form), with unassigned items as singletons and unlabelled items dropped.
fn brute_force_ari(predicted: &[u32], truth: &[u32]) -> f64 {
    let items: Vec<usize> = (0..truth.len()).filter(|&i| truth[i] != NONE).collect();
    let same_p = |i: usize, j: usize| predicted[i] != NONE && predicted[i] == predicted[j];
    let (mut n11, mut n10, mut n01, mut n00) = (0f64, 0f64, 0f64, 0f64);
    for (a, &i) in items.iter().enumerate() {
        for &j in &items[a + 1..] {
            match (same_p(i, j), truth[i] == truth[j]) {
                (true, true) => n11 += 1.0,
                (true, false) => n10 += 1.0,
                (false, true) => n01 += 1.0,
                (false, false) => n00 += 1.0,
            }
        }
    }
    let den = (n00 + n01) * (n01 + n11) + (n00 + n10) * (n10 + n11);
    if den == 0.0 {
        1.0
    } else {
        2.0 * (n00 * n11 - n01 * n10) / den
    }
}

mod cluster {
    /// The oracle proposals group masks by ground-truth object (ids by ascending object),
    /// leave masks on no object out, count members and distinct views, and score a
    /// perfect clustering.
    #[test]
    fn oracle_proposals_are_the_ground_truth_partition() {
        use profuse_metrics::cluster::{oracle_proposals, proposal_scores};
        let truth = [5, 2, NONE, 5, 2, 7, 5];
        let views = [0, 0, 0, 1, 1, 1, 1];
        let p = oracle_proposals(&truth, &views).unwrap();
        assert_eq!(&p.mask_proposal[..], &[1, 0, NONE, 1, 0, 2, 1]);
        assert_eq!(&p.proposal_size[..], &[2, 3, 1]);
        assert_eq!(&p.proposal_views[..], &[2, 2, 1]);
        assert_eq!(
            p.extra.get("grouping").map(String::as_str),
            Some("ground-truth")
        );
        let s = proposal_scores(&p, &truth).unwrap();
        assert!(close(s.ari, 1.0) && close(s.purity, 1.0) && close(s.completeness, 1.0));
        assert!(oracle_proposals(&truth, &views[..3]).is_err());
    }

    /// A mask attached to a proposal (`mask_instance`) counts in that proposal for the
    /// proposal scores and as a singleton for the member scores; without `mask_instance`
    /// both score `mask_proposal`.
    #[test]
    fn proposal_scores_count_attached_masks_and_member_scores_do_not() {
        use profuse_metrics::cluster::{member_scores, proposal_scores};
        let truth = [0, 0, 0, 1, 1];
        let mut p = profuse_formats::Proposals {
            mask_proposal: vec![0, 0, NONE, 1, 1].into(),
            proposal_size: vec![2, 2].into(),
            proposal_views: vec![1, 1].into(),
            ..Default::default()
        };
        let members = member_scores(&p, &truth).unwrap();
        // {0, 1}, {2}, {3, 4} against {0, 1, 2}, {3, 4}: index 2, rows 2, columns 4,
        // expected 2 · 4 / 10 = 0.8: (2 − 0.8) / (3 − 0.8) = 6/11.
        assert!(close(members.ari, 6.0 / 11.0), "{}", members.ari);
        assert!(close(proposal_scores(&p, &truth).unwrap().ari, 6.0 / 11.0));
        p.mask_instance = Some(vec![0, 0, 0, 1, 1].into());
        let instances = proposal_scores(&p, &truth).unwrap();
        assert!(close(instances.ari, 1.0) && close(instances.completeness, 1.0));
        assert_eq!((instances.assigned, members.assigned), (5, 4));
        assert!(close(member_scores(&p, &truth).unwrap().ari, 6.0 / 11.0));
    }

    use super::*;

    #[test]
    fn ari_hand_cases() {
        // Identical up to renaming.
        assert_eq!(
            adjusted_rand_index(&[5, 5, 9, 9, 1], &[0, 0, 1, 1, 2]).unwrap(),
            1.0
        );
        // Splitting one object in two: (1 − 1/3) / (3/2 − 1/3) = 4/7.
        assert!(close(
            adjusted_rand_index(&[0, 0, 1, 2], &[0, 0, 1, 1]).unwrap(),
            4.0 / 7.0
        ));
        // Crossed partitions: index 0, expected 2/3, max 2 → −1/2.
        assert!(close(
            adjusted_rand_index(&[0, 0, 1, 1], &[0, 1, 0, 1]).unwrap(),
            -0.5
        ));
        // One cluster against all singletons: index 0, expected 0 → 0.
        assert_eq!(
            adjusted_rand_index(&[0, 0, 0, 0], &[0, 1, 2, 3]).unwrap(),
            0.0
        );
        // Degenerate but identical: everything together / everything apart / < 2 items.
        assert_eq!(adjusted_rand_index(&[3, 3, 3], &[1, 1, 1]).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[NONE, NONE], &[1, 2]).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[], &[]).unwrap(), 1.0);
        assert_eq!(adjusted_rand_index(&[4], &[2]).unwrap(), 1.0);
    }

    #[test]
    fn unassigned_items_are_singletons_and_unlabelled_items_are_dropped() {
        // Unassigned items never join a cluster: two unassigned items of the same object
        // do not recover that object.
        assert_eq!(
            adjusted_rand_index(&[NONE, NONE, 1, 1], &[0, 0, 1, 1]).unwrap(),
            adjusted_rand_index(&[7, 8, 1, 1], &[0, 0, 1, 1]).unwrap()
        );
        // Items without truth change nothing, whatever their prediction.
        let with = cluster_scores(&[0, 0, 1, 2, 0, 1], &[0, 0, 1, 1, NONE, NONE]).unwrap();
        let without = cluster_scores(&[0, 0, 1, 2], &[0, 0, 1, 1]).unwrap();
        assert_eq!(format!("{with:?}"), format!("{without:?}"));
        assert_eq!(with.items, 4);
    }

    #[test]
    fn purity_and_completeness_hand_case() {
        // truth:     a a a a | b b | c c | -
        // predicted: 0 0 0 1 | 1 1 | _ _ | 0     (_ = unassigned, - = no truth)
        let (a, b, c) = (10, 20, 30);
        let pred = [0, 0, 0, 1, 1, 1, NONE, NONE, 0];
        let truth = [a, a, a, a, b, b, c, c, NONE];
        let s = cluster_scores(&pred, &truth).unwrap();
        assert_eq!((s.items, s.assigned, s.clusters), (8, 6, 2));
        // Cluster 0 = {a,a,a}: majority 3; cluster 1 = {a,b,b}: majority 2 → 5/6.
        assert!(close(s.purity, 5.0 / 6.0), "{s:?}");
        // a: best cluster holds 3; b: 2; c: two singletons → 1. (3+2+1)/8.
        assert!(close(s.completeness, 6.0 / 8.0), "{s:?}");
        assert!(close(s.ari, brute_force_ari(&pred, &truth)));
    }

    #[test]
    fn empty_and_unassigned_only_inputs() {
        let s = cluster_scores(&[NONE, NONE, NONE], &[1, 1, 2]).unwrap();
        assert_eq!((s.items, s.assigned, s.clusters), (3, 0, 0));
        assert_eq!(s.purity, 0.0);
        assert!(close(s.completeness, 2.0 / 3.0));
        let s = cluster_scores(&[1, 2], &[NONE, NONE]).unwrap();
        assert_eq!(
            (s.items, s.purity, s.completeness, s.ari),
            (0, 0.0, 0.0, 1.0)
        );
    }

    #[test]
    fn length_mismatch_is_a_typed_error() {
        let e = cluster_scores(&[0, 1], &[0]).unwrap_err();
        assert!(e.to_string().contains("predicted has 2"), "{e}");
    }

    #[test]
    fn ari_matches_brute_force_pair_counting_on_random_cases() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for case in 0..400 {
            let n = rng.random_range(0..40);
            let kp = rng.random_range(1..6u32);
            let kt = rng.random_range(1..6u32);
            let draw = |rng: &mut ChaCha8Rng, k: u32| {
                if rng.random_bool(0.15) {
                    NONE
                } else {
                    rng.random_range(0..k) * 1000 + 3
                }
            };
            let pred: Vec<u32> = (0..n).map(|_| draw(&mut rng, kp)).collect();
            let truth: Vec<u32> = (0..n).map(|_| draw(&mut rng, kt)).collect();
            let fast = adjusted_rand_index(&pred, &truth).unwrap();
            let slow = brute_force_ari(&pred, &truth);
            assert!(
                (fast - slow).abs() < 1e-9,
                "case {case}: {fast} vs {slow}\n{pred:?}\n{truth:?}"
            );
            // Renaming the predicted labels changes nothing.
            let renamed: Vec<u32> = pred
                .iter()
                .map(|&p| if p == NONE { p } else { p ^ 0x5a5a })
                .collect();
            assert_eq!(adjusted_rand_index(&renamed, &truth).unwrap(), fast);
            // A partition against itself (unassigned included, as singletons) scores 1.
            let t2: Vec<u32> = pred
                .iter()
                .enumerate()
                .map(|(i, &p)| if p == NONE { 1_000_000 + i as u32 } else { p })
                .collect();
            assert_eq!(adjusted_rand_index(&pred, &t2).unwrap(), 1.0);
        }
    }
}

mod surface {
    use super::*;
    use synth::{ObjectSpec, Scene, ShapeSpec, Texture};

    fn ball_scene(radius: f64, centre: [f64; 3]) -> Scene {
        let ball = ObjectSpec {
            index: 0,
            name: "ball".into(),
            class_id: 40,
            class_name: "otherprop".into(),
            room: false,
            shape: ShapeSpec::Ball { radius },
            translation: centre,
            yaw: 0.3,
            color: [100, 100, 100],
            texture: Texture::Plain,
        };
        Scene::new([4.0, 3.0, 12.0], vec![ball]).unwrap()
    }

    #[test]
    fn distances_to_a_ball_are_exact_and_thread_count_independent() {
        let (r, c) = (0.5, [0.2, -0.1, 1.0]);
        let scene = ball_scene(r, c);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let points: Vec<[f32; 3]> = (0..3000)
            .map(|_| [0; 3].map(|_: i32| rng.random_range(-1.5f32..1.5)))
            .collect();
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| surface_distances(&points, |p| scene.distance_to_surface(p)))
        };
        let d1 = run(1);
        assert_eq!(d1, run(4));
        for (p, d) in points.iter().zip(&d1) {
            let to_centre = (0..3)
                .map(|k| (f64::from(p[k]) - c[k]).powi(2))
                .sum::<f64>()
                .sqrt();
            let exact = (to_centre - r).abs();
            assert!(
                (f64::from(*d) - exact).abs() < 1e-5,
                "{p:?}: {d} vs {exact}"
            );
        }
    }

    #[test]
    fn extent_is_the_room_diagonal() {
        assert_eq!(scene_extent(ball_scene(0.1, [0.0; 3]).room_size), 13.0);
    }

    #[test]
    fn summary_hand_case() {
        // sorted: 1..=10; median 5.5, p90 at rank 8.1 → 9.1, mean 5.5.
        let d: Vec<f32> = [7, 3, 10, 1, 5, 9, 2, 8, 6, 4].map(|v| v as f32).to_vec();
        let s = summarize(&d, 11.0);
        assert_eq!(s.count, 10);
        assert!(
            close(s.median, 5.5) && close(s.mean, 5.5) && close(s.p90, 9.1),
            "{s:?}"
        );
        assert!(close(s.median_rel, 0.5));
        let odd = summarize(&[3.0, 1.0, 2.0], 1.0);
        assert!(odd.median == 2.0 && close(odd.p90, 2.8), "{odd:?}");
        let empty = summarize(&[f32::NAN], 1.0);
        assert_eq!(empty.count, 0);
        assert!(empty.median.is_nan() && empty.mean.is_nan());
        assert_eq!(
            serde_json::to_value(&empty).unwrap()["median"],
            serde_json::Value::Null
        );
    }
}

mod mask {
    use profuse_metrics::mask::{
        fill_poly, fill_poly_as, rasterize_polygon, rasterize_polygon_centres, Mask, OpenCvFill,
    };
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn selected(m: &Mask) -> Vec<(u32, u32)> {
        (0..m.height)
            .flat_map(|y| (0..m.width).map(move |x| (x, y)))
            .filter(|&(x, y)| m.pixels[(y * m.width + x) as usize])
            .collect()
    }

    /// A mask from rows of `#` (selected) and `.`.
    fn picture(rows: &[&str]) -> Vec<bool> {
        rows.iter()
            .flat_map(|r| r.chars().map(|c| c == '#'))
            .collect()
    }

    /// The reference rule, by hand: a right triangle with legs of 4 pixels. The outline
    /// (8-connected lines, the hypotenuse a perfect diagonal) and the inside are filled.
    #[test]
    fn fill_poly_triangle_by_hand() {
        let m = fill_poly(&[[1, 1], [5, 1], [1, 5]], 7, 7);
        let expected = picture(&[
            ".......", ".#####.", ".####..", ".###...", ".##....", ".#.....", ".......",
        ]);
        assert_eq!(m.pixels, expected);
    }

    /// A rectangle traced through pixel coordinates includes its boundary pixels: corners
    /// (1, 1) and (4, 3) give 4 x 3 pixels, not the 3 x 2 of its area.
    #[test]
    fn fill_poly_rectangle_includes_its_boundary() {
        let m = fill_poly(&[[1, 1], [4, 1], [4, 3], [1, 3]], 6, 5);
        let expected = picture(&["......", ".####.", ".####.", ".####.", "......"]);
        assert_eq!(m.pixels, expected);
        assert_eq!(m.count(), 12);
        // Fractional vertices truncate toward zero first (3.9 -> 3, -0.5 -> 0).
        let t = rasterize_polygon(&[[-0.5, -0.5], [3.9, 0.2], [3.9, 2.7], [0.9, 2.99]], 6, 5);
        let expected = picture(&["####..", "####..", "####..", "......", "......"]);
        assert_eq!(t.pixels, expected);
    }

    /// Clipping: a polygon entirely outside draws nothing; one covering the image fills it;
    /// a degenerate one (a point, a segment) draws its outline only.
    #[test]
    fn fill_poly_outside_covering_and_degenerate() {
        assert_eq!(fill_poly(&[[-5, -5], [-1, -5], [-1, -1]], 4, 4).count(), 0);
        assert_eq!(fill_poly(&[[5, 0], [9, 0], [9, 3]], 4, 4).count(), 0);
        assert_eq!(
            fill_poly(&[[-9, -9], [9, -9], [9, 9], [-9, 9]], 4, 3).count(),
            12
        );
        assert_eq!(fill_poly(&[], 4, 4).count(), 0);
        let point = fill_poly(&[[2, 1]], 4, 4);
        assert_eq!(point.pixels, picture(&["....", "..#.", "....", "...."]));
        let segment = fill_poly(&[[0, 0], [3, 3]], 4, 4);
        assert_eq!(segment.pixels, picture(&["#...", ".#..", "..#.", "...#"]));
        // Triangles with vertices outside: the visible part. The hypotenuse x + y = 6
        // passes through pixel (3, 3), x + y = 7 through (3, 4) and (4, 3); boundary
        // pixels are in, so only (4, 4) of the 5 x 5 image is out.
        let m = fill_poly(&[[0, 0], [6, 0], [0, 6]], 4, 4);
        assert_eq!(m.count(), 16);
        let m = fill_poly(&[[0, 0], [7, 0], [0, 7]], 5, 5);
        assert_eq!(
            m.pixels,
            picture(&["#####", "#####", "#####", "#####", "####."])
        );
    }

    /// Self-intersecting polygons fill by the even-odd rule of the scan line: this bow tie
    /// is the left triangle (0,0)-(2,2)-(0,4) and the right one (4,0)-(2,2)-(4,4). On row
    /// 2 the two diagonals meet at x = 2, so the spans 0..=2 and 2..=4 join; rows 0 and 4
    /// (no active edge: rows are half-open) hold only the outline's end pixels.
    #[test]
    fn fill_poly_bow_tie() {
        let m = fill_poly(&[[0, 0], [4, 4], [4, 0], [0, 4]], 5, 5);
        let expected = picture(&["#...#", "##.##", "#####", "##.##", "#...#"]);
        assert_eq!(m.pixels, expected, "{:?}", m.pixels);
    }

    /// The legacy variant differs only when vertices lie outside the image.
    #[test]
    fn fill_poly_variants_agree_inside_the_image() {
        let poly = [[1, 2], [9, 0], [7, 8], [3, 5], [0, 9]];
        assert_eq!(
            fill_poly_as(&poly, 10, 10, OpenCvFill::Legacy),
            fill_poly(&poly, 10, 10)
        );
    }

    /// Per-pixel even-odd test with the crossing x by division: a reference for polygons
    /// whose boundary passes through no pixel centre.
    fn brute_force(poly: &[[f64; 2]], w: u32, h: u32) -> Vec<bool> {
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (px, py) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
                let mut inside = false;
                for i in 0..poly.len() {
                    let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                    if (a[1] > py) != (b[1] > py)
                        && a[0] + (py - a[1]) * (b[0] - a[0]) / (b[1] - a[1]) > px
                    {
                        inside = !inside;
                    }
                }
                out.push(inside);
            }
        }
        out
    }

    #[test]
    fn pixel_aligned_square_covers_its_pixels() {
        let m = rasterize_polygon_centres(&[[1.0, 2.0], [4.0, 2.0], [4.0, 3.0], [1.0, 3.0]], 6, 5);
        assert_eq!(selected(&m), vec![(1, 2), (2, 2), (3, 2)]);
    }

    #[test]
    fn square_through_pixel_centres_keeps_top_left_edges() {
        // Edges at x = 0.5, 2.5 and y = 0.5, 2.5 pass through centres: top and left
        // centres are in, right and bottom out, so 4 pixels = the square's area.
        let m = rasterize_polygon_centres(&[[0.5, 0.5], [2.5, 0.5], [2.5, 2.5], [0.5, 2.5]], 4, 4);
        assert_eq!(selected(&m), vec![(0, 0), (1, 0), (0, 1), (1, 1)]);
        // Orientation does not matter.
        let ccw =
            rasterize_polygon_centres(&[[0.5, 0.5], [0.5, 2.5], [2.5, 2.5], [2.5, 0.5]], 4, 4);
        assert_eq!(ccw, m);
    }

    #[test]
    fn triangle_hand_count() {
        // x + y < 8 below the hypotenuse; centres on it (x + y + 1 = 8) lie on a
        // right/bottom edge: out. Inside: x + y <= 6, 1 + 2 + ... + 7 = 28 pixels.
        let m = rasterize_polygon_centres(&[[0.0, 0.0], [8.0, 0.0], [0.0, 8.0]], 8, 8);
        assert_eq!(m.count(), 28);
        assert!(selected(&m).iter().all(|&(x, y)| x + y <= 6));
    }

    #[test]
    fn diamond_with_centres_on_every_edge_follows_the_tie_rule() {
        // |x − 2.5| + |y − 2.5| < 2 strictly: 5 centres. On the boundary: the left vertex
        // (0,2) and the two centres on the left edges (1,1), (1,3) are in; the top, right
        // and bottom vertices and the centres on the right edges are out. 8 = the area.
        let m = rasterize_polygon_centres(&[[2.5, 0.5], [4.5, 2.5], [2.5, 4.5], [0.5, 2.5]], 5, 5);
        let mut expected = vec![
            (2, 1),
            (1, 2),
            (2, 2),
            (3, 2),
            (2, 3),
            (0, 2),
            (1, 1),
            (1, 3),
        ];
        expected.sort_by_key(|&(x, y)| (y, x));
        assert_eq!(selected(&m), expected);
    }

    #[test]
    fn polygons_sharing_an_edge_through_centres_partition_the_pixels() {
        let a = rasterize_polygon_centres(&[[0.5, 0.5], [4.5, 0.5], [4.5, 4.5]], 5, 5);
        let b = rasterize_polygon_centres(&[[0.5, 0.5], [4.5, 4.5], [0.5, 4.5]], 5, 5);
        let square =
            rasterize_polygon_centres(&[[0.5, 0.5], [4.5, 0.5], [4.5, 4.5], [0.5, 4.5]], 5, 5);
        assert_eq!(a.intersection(&b), 0);
        let mut u = a.clone();
        u.union_with(&b);
        assert_eq!(u, square);
        assert_eq!(square.count(), 16);
    }

    #[test]
    fn bridged_hole_and_degenerate_polygons() {
        // synth's layout: outer loop, then the hole joined by a doubled bridge.
        let poly = [
            [0.0, 0.0],
            [4.0, 0.0],
            [4.0, 4.0],
            [0.0, 4.0], // outer
            [0.0, 0.0],
            [1.0, 0.0],
            [1.0, 1.0],
            [1.0, 3.0],
            [3.0, 3.0],
            [3.0, 1.0],
            [1.0, 1.0],
            [1.0, 0.0],
        ];
        let m = rasterize_polygon_centres(&poly, 4, 4);
        assert_eq!(m.count(), 12);
        assert!(!m.pixels[4 + 1] && !m.pixels[2 * 4 + 2]);
        assert_eq!(
            rasterize_polygon_centres(&[[0.0, 0.0], [3.0, 3.0]], 4, 4).count(),
            0
        );
        assert_eq!(rasterize_polygon_centres(&[], 4, 4).count(), 0);
        // Outside the image, or partly outside: clipped.
        assert_eq!(
            rasterize_polygon_centres(&[[-5.0, -5.0], [-1.0, -5.0], [-1.0, -1.0]], 4, 4).count(),
            0
        );
        assert_eq!(
            rasterize_polygon_centres(&[[-9.0, -9.0], [9.0, -9.0], [9.0, 9.0], [-9.0, 9.0]], 4, 3)
                .count(),
            12
        );
    }

    #[test]
    fn random_polygons_match_the_per_pixel_even_odd_test() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for case in 0..300 {
            let (w, h) = (rng.random_range(1..40), rng.random_range(1..30));
            let n = rng.random_range(3..12);
            // Coordinates off the half-pixel grid: no centre lies on an edge.
            let poly: Vec<[f64; 2]> = (0..n)
                .map(|_| {
                    [
                        rng.random_range(-5.0..f64::from(w) + 5.0),
                        rng.random_range(-5.0..f64::from(h) + 5.0),
                    ]
                })
                .collect();
            let m = rasterize_polygon_centres(&poly, w, h);
            assert_eq!(m.pixels, brute_force(&poly, w, h), "case {case}: {poly:?}");
        }
    }
}

mod lerf {
    use std::path::Path;

    use profuse_metrics::lerf::{
        evaluate_scene, grid_search, mean_over_scenes, prediction_path, query_file_name,
        read_label_dir, LabelFrame, LabelScene, PredDir,
    };
    use profuse_metrics::mask::{rasterize_polygon, rasterize_polygon_centres, Mask};
    use profuse_metrics::{MetricsError, Result};

    fn rect(x0: f64, y0: f64, x1: f64, y1: f64) -> serde_json::Value {
        serde_json::json!({"category": "", "segmentation": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]],
            "bbox": [x0, y0, x1, y1]})
    }

    /// A label object covering the pixels `r[0]..r[2]` x `r[1]..r[3]` (end exclusive):
    /// the reference rule includes the traced outline, so the polygon's corners are the
    /// first and last pixel, `[r[0], r[1]]` and `[r[2] - 1, r[3] - 1]`.
    fn object(category: &str, r: [f64; 4]) -> serde_json::Value {
        let mut o = rect(r[0], r[1], r[2] - 1.0, r[3] - 1.0);
        o["category"] = category.into();
        o
    }

    fn write_label(dir: &Path, stem: &str, w: u32, h: u32, objects: Vec<serde_json::Value>) {
        let j = serde_json::json!({"info": {"name": format!("{stem}.jpg"), "width": w, "height": h},
            "objects": objects});
        std::fs::write(dir.join(format!("{stem}.json")), j.to_string()).unwrap();
    }

    fn write_png(path: &Path, m: &Mask) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let bytes: Vec<u8> = m.pixels.iter().map(|&p| if p { 255 } else { 0 }).collect();
        image::GrayImage::from_raw(m.width, m.height, bytes)
            .unwrap()
            .save(path)
            .unwrap();
    }

    /// Pixels `r[0]..r[2]` x `r[1]..r[3]` (end exclusive), for predictions.
    fn area_mask(w: u32, h: u32, r: [f64; 4]) -> Mask {
        rasterize_polygon_centres(
            &[[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]],
            w,
            h,
        )
    }

    /// The box with corners `r` under the reference rule (outline included).
    fn rect_mask(w: u32, h: u32, r: [f64; 4]) -> Mask {
        rasterize_polygon(
            &[[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]],
            w,
            h,
        )
    }

    /// frame_a (10x10): "mug" = two 2x2 squares (8 px), "plate" = 4x1 (4 px).
    /// frame_b (10x10): "mug" = 4x4 at the origin (16 px), "spoon" = a polygon outside
    /// the image (covers no pixel: skipped as empty ground truth).
    fn toy_labels(dir: &Path) {
        write_label(
            dir,
            "frame_a",
            10,
            10,
            vec![
                object("mug", [0.0, 0.0, 2.0, 2.0]),
                object("plate", [0.0, 5.0, 4.0, 6.0]),
                object("mug", [6.0, 6.0, 8.0, 8.0]),
            ],
        );
        write_label(
            dir,
            "frame_b",
            10,
            10,
            vec![
                object("mug", [0.0, 0.0, 4.0, 4.0]),
                object("spoon", [11.0, 11.0, 12.4, 14.0]),
            ],
        );
    }

    #[test]
    fn hand_case_union_strict_threshold_missing_and_empty() {
        let tmp = tempfile::tempdir().unwrap();
        let (labels, pred) = (tmp.path().join("labels"), tmp.path().join("pred"));
        std::fs::create_dir_all(&labels).unwrap();
        toy_labels(&labels);
        // frame_a mug: the first square plus 2 px of background → IoU 4/10, and the
        // second square must count as ground truth too (union), so not 4/6.
        let mut m = area_mask(10, 10, [0.0, 0.0, 2.0, 2.0]);
        m.union_with(&area_mask(10, 10, [2.0, 0.0, 3.0, 2.0]));
        write_png(&prediction_path(&pred, "frame_a", "mug"), &m);
        // frame_a plate: an all-zero prediction → IoU 0, not missing.
        write_png(
            &prediction_path(&pred, "frame_a", "plate"),
            &Mask::empty(10, 10),
        );
        // frame_b mug: 4 of 16 px → IoU exactly 0.25, which does NOT count for Acc@0.25.
        write_png(
            &prediction_path(&pred, "frame_b", "mug"),
            &area_mask(10, 10, [0.0, 0.0, 2.0, 2.0]),
        );
        // frame_b spoon: no file (and empty ground truth anyway).
        let scene = read_label_dir(&labels).unwrap();
        assert_eq!(scene.name, "labels");
        let s = evaluate_scene(&scene, &PredDir { dir: pred.clone() }, None).unwrap();
        assert_eq!((s.frames, s.pairs, s.missing, s.empty_gt), (2, 3, 0, 1));
        let ious: Vec<(&str, &str, f64)> = s
            .rows
            .iter()
            .map(|r| (r.frame.as_str(), r.query.as_str(), r.iou))
            .collect();
        assert_eq!(
            ious,
            vec![
                ("frame_a", "mug", 0.4),
                ("frame_a", "plate", 0.0),
                ("frame_b", "mug", 0.25)
            ]
        );
        assert_eq!(
            (
                s.rows[0].gt_pixels,
                s.rows[0].pred_pixels,
                s.rows[0].intersection
            ),
            (8, 6, 4)
        );
        assert!((s.miou - 100.0 * 0.65 / 3.0).abs() < 1e-9, "{}", s.miou);
        assert!((s.acc25 - 100.0 / 3.0).abs() < 1e-9, "{}", s.acc25);
        let mug = &s.per_query[0];
        assert_eq!((mug.query.as_str(), mug.pairs), ("mug", 2));
        assert!((mug.miou - 32.5).abs() < 1e-9 && (mug.acc25 - 50.0).abs() < 1e-9);

        // Removing the plate file makes that pair missing: still IoU 0, now counted.
        std::fs::remove_file(prediction_path(&pred, "frame_a", "plate")).unwrap();
        let s2 = evaluate_scene(&scene, &PredDir { dir: pred.clone() }, None).unwrap();
        assert_eq!((s2.missing, s2.miou), (1, s.miou));
        assert!(s2.rows[1].missing);

        // Restricting the queries.
        let only = ["plate".to_string()];
        let s3 = evaluate_scene(&scene, &PredDir { dir: pred }, Some(&only)).unwrap();
        assert_eq!((s3.pairs, s3.miou), (1, 0.0));
    }

    #[test]
    fn size_mismatch_and_bad_label_files_are_typed_errors() {
        let tmp = tempfile::tempdir().unwrap();
        let (labels, pred) = (tmp.path().join("labels"), tmp.path().join("pred"));
        std::fs::create_dir_all(&labels).unwrap();
        toy_labels(&labels);
        write_png(
            &prediction_path(&pred, "frame_b", "mug"),
            &Mask::empty(10, 9),
        );
        let scene = read_label_dir(&labels).unwrap();
        let e = evaluate_scene(&scene, &PredDir { dir: pred }, None).unwrap_err();
        assert!(
            matches!(
                e,
                MetricsError::MaskSize {
                    found_height: 9,
                    ..
                }
            ),
            "{e}"
        );
        assert!(
            e.to_string().contains("mug.png") && e.to_string().contains("10x9"),
            "{e}"
        );

        let bad = tmp.path().join("bad");
        std::fs::create_dir_all(&bad).unwrap();
        std::fs::write(bad.join("f.json"), r#"{"info": {"name": "f", "width": 4, "height": 4}, "objects": [{"category": "x", "segmentation": [[0, 0], [1]]}]}"#).unwrap();
        let e = read_label_dir(&bad).unwrap_err();
        assert!(e.to_string().contains("f.json"), "{e}");
        std::fs::write(
            bad.join("f.json"),
            r#"{"info": {"name": "f", "width": 0, "height": 4}, "objects": []}"#,
        )
        .unwrap();
        let e = read_label_dir(&bad).unwrap_err();
        assert!(e.to_string().contains("info.width"), "{e}");
        let e = read_label_dir(tmp.path().join("pred-none")).unwrap_err();
        assert!(matches!(e, MetricsError::Io { .. }), "{e}");
    }

    /// synth's label polygons (pixel-edge tracings, holes bridged) rasterise back to
    /// exactly the object components of the ground-truth id maps.
    #[test]
    fn synth_label_polygons_rasterise_to_their_components() {
        use profuse_formats::{FileKind, ViewMaps};
        let tmp = tempfile::tempdir().unwrap();
        synth::generate(&synth::Config::preset(synth::Preset::Demo, 4), tmp.path()).unwrap();
        let scene = read_label_dir(tmp.path().join("gt/label")).unwrap();
        let views = ViewMaps::read(tmp.path().join("gt/views.safetensors")).unwrap();
        let ids = views.object_ids.as_ref().unwrap();
        let mut checked = 0;
        for frame in &scene.frames {
            let v = views
                .view_names
                .iter()
                .position(|n| n.ends_with(&format!("{}.png", frame.stem)))
                .unwrap();
            let raw: serde_json::Value = serde_json::from_str(
                &std::fs::read_to_string(tmp.path().join(format!("gt/label/{}.json", frame.stem)))
                    .unwrap(),
            )
            .unwrap();
            for (o, j) in frame.objects.iter().zip(raw["objects"].as_array().unwrap()) {
                let m = rasterize_polygon_centres(&o.polygon, frame.width, frame.height);
                assert_eq!(
                    m.count(),
                    j["area"].as_u64().unwrap(),
                    "{} {}",
                    frame.stem,
                    o.category
                );
                let object = j["object"].as_u64().unwrap() as u32;
                for (i, _) in m.pixels.iter().enumerate().filter(|(_, p)| **p) {
                    let (x, y) = (i % views.width, i / views.width);
                    assert_eq!(ids[views.index(v, x, y)], object);
                }
                checked += 1;
            }
        }
        assert!(checked >= 10, "{checked}");
    }

    #[test]
    fn query_file_names_are_path_safe() {
        assert_eq!(query_file_name("glass of water"), "glass of water");
        assert_eq!(query_file_name("a/b\\c"), "a_b_c");
        assert_eq!(query_file_name(".."), "_..");
        assert_eq!(query_file_name(""), "_");
        assert_eq!(
            prediction_path(Path::new("P"), "frame_00041", "red apple"),
            Path::new("P/frame_00041/red apple.png")
        );
    }

    #[test]
    fn grid_search_finds_the_best_threshold_and_averages_scenes() {
        let tmp = tempfile::tempdir().unwrap();
        let labels = tmp.path().join("labels");
        std::fs::create_dir_all(&labels).unwrap();
        toy_labels(&labels);
        let scene = read_label_dir(&labels).unwrap();
        let other = LabelScene {
            name: "copy".into(),
            ..scene.clone()
        };
        // The prediction is the ground-truth box grown by |t − 0.4| · 10 px (clipped): exact
        // at t = 0.4. Scene 1 ("copy") gets no predictions at all.
        let masks = |t: f64, s: usize, f: &LabelFrame, q: &str| -> Result<Option<Mask>> {
            if s == 1 {
                return Ok(None);
            }
            let grow = ((t - 0.4).abs() * 10.0).round();
            let mut m = Mask::empty(f.width, f.height);
            for o in f.objects.iter().filter(|o| o.category == q) {
                let xs = o.polygon.iter().map(|p| p[0]);
                let ys = o.polygon.iter().map(|p| p[1]);
                let r = [
                    xs.clone().fold(f64::INFINITY, f64::min) - grow,
                    ys.clone().fold(f64::INFINITY, f64::min) - grow,
                    xs.fold(f64::NEG_INFINITY, f64::max) + grow,
                    ys.fold(f64::NEG_INFINITY, f64::max) + grow,
                ];
                m.union_with(&rect_mask(f.width, f.height, r));
            }
            Ok(Some(m))
        };
        let grid = [0.2, 0.3, 0.4, 0.5];
        let g = grid_search(&[scene.clone(), other], &grid, None, masks).unwrap();
        assert_eq!(g.rows.len(), 4);
        assert_eq!(g.best.threshold, 0.4);
        // Perfect on scene 0, nothing on scene 1: the mean over scenes is 50 %.
        assert!(
            (g.best.miou - 50.0).abs() < 1e-9 && (g.best.acc25 - 50.0).abs() < 1e-9,
            "{:?}",
            g.best
        );
        assert_eq!(g.best.missing, 3);
        assert_eq!(g.best.scenes[0].1, 100.0);
        assert!(g.rows.iter().all(|r| r.miou <= g.best.miou));
        // 0.3 and 0.5 grow by the same 1 px: equal scores, both worse.
        assert_eq!(g.rows[1].miou, g.rows[3].miou);
        assert!(g.rows[1].miou < g.best.miou);
        // Empty grid: error.
        assert!(grid_search(&[scene], &[], None, masks).is_err());
    }

    #[test]
    fn scene_means_skip_scenes_without_pairs_and_threads_do_not_matter() {
        let tmp = tempfile::tempdir().unwrap();
        let labels = tmp.path().join("labels");
        std::fs::create_dir_all(&labels).unwrap();
        toy_labels(&labels);
        let scene = read_label_dir(&labels).unwrap();
        let half = |f: &LabelFrame, _: &str| -> Result<Option<Mask>> {
            Ok(Some(rect_mask(f.width, f.height, [0.0, 0.0, 2.0, 4.0])))
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| evaluate_scene(&scene, &half, None).unwrap())
        };
        let (a, b) = (run(1), run(4));
        assert_eq!(
            serde_json::to_string(&a).unwrap(),
            serde_json::to_string(&b).unwrap()
        );
        let none = evaluate_scene(&scene, &half, Some(&["nothing".to_string()])).unwrap();
        assert_eq!(none.pairs, 0);
        assert!(none.miou.is_nan());
        let mean = mean_over_scenes(&[a.clone(), none]);
        assert_eq!((mean.scenes, mean.miou, mean.acc25), (1, a.miou, a.acc25));
    }
}

mod scannet {
    use profuse_metrics::scannet::{
        evaluate, ground_truth_labels, mean_over_scenes, ClassSet, CLASSES_19,
    };
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn hand_case_present_class_averaging_and_ignored_ids() {
        // truth: wall x3, floor x2, bed x1, unannotated 0, ceiling 22 (not in 19), 41 (bogus)
        let truth = [1, 1, 1, 2, 2, 4, 0, 22, 41];
        // pred:  wall, floor, -1 | floor, chair(5: absent class) | 4 | anything on ignored
        let pred = [1, 2, -1, 2, 5, 4, 1, 1, 1];
        let s = evaluate(&pred, &truth, ClassSet::Nyu19).unwrap();
        assert_eq!(
            (s.evaluated, s.ignored, s.correct, s.unlabelled_or_outside),
            (6, 3, 3, 1)
        );
        assert_eq!(s.classes_present, 3);
        let row = |id| s.per_class.iter().find(|r| r.id == id).unwrap();
        // wall: TP 1, FN 2, FP 0 → IoU 1/3, acc 1/3.
        assert!((row(1).iou - 100.0 / 3.0).abs() < 1e-9 && (row(1).acc - 100.0 / 3.0).abs() < 1e-9);
        // floor: TP 1, FN 1, FP 1 → IoU 1/3, acc 1/2.
        assert!((row(2).iou - 100.0 / 3.0).abs() < 1e-9 && row(2).acc == 50.0);
        // bed: perfect.
        assert_eq!((row(4).iou, row(4).acc), (100.0, 100.0));
        // chair is predicted once but absent: IoU 0 in the table, not in the means.
        assert_eq!(
            (row(5).gt_count, row(5).pred_count, row(5).iou),
            (0, 1, 0.0)
        );
        assert!(row(5).acc.is_nan());
        assert_eq!(row(3).name, "cabinet");
        assert!(row(3).iou.is_nan());
        assert!((s.miou - (100.0 / 3.0 + 100.0 / 3.0 + 100.0) / 3.0).abs() < 1e-9);
        assert!((s.macc - (100.0 / 3.0 + 50.0 + 100.0) / 3.0).abs() < 1e-9);
        assert_eq!(s.per_class.len(), 19);

        // The 10-class set has no cabinet... and the same present classes here.
        let s10 = evaluate(&pred, &truth, ClassSet::Nyu10).unwrap();
        assert_eq!(s10.per_class.len(), 10);
        assert_eq!(s10.miou, s.miou);
    }

    #[test]
    fn empty_predictions_and_empty_ground_truth() {
        let truth = [1, 2, 2, 0];
        let s = evaluate(&[-1; 4], &truth, ClassSet::Nyu15).unwrap();
        assert_eq!(
            (s.miou, s.macc, s.correct, s.unlabelled_or_outside),
            (0.0, 0.0, 0, 3)
        );
        let s = evaluate(&[1, 2], &[0, 22], ClassSet::Nyu15).unwrap();
        assert_eq!(s.classes_present, 0);
        assert!(s.miou.is_nan() && s.macc.is_nan());
        assert!(evaluate(&[1], &[1, 2], ClassSet::Nyu15).is_err());
        let m =
            mean_over_scenes(&[s, evaluate(&[1, 2], &[1, 2], ClassSet::Nyu15).unwrap()]).unwrap();
        assert_eq!((m.scenes, m.miou, m.macc), (1, 100.0, 100.0));
        let mixed = [
            evaluate(&[1], &[1], ClassSet::Nyu15).unwrap(),
            evaluate(&[1], &[1], ClassSet::Nyu10).unwrap(),
        ];
        assert!(mean_over_scenes(&mixed).is_err());
    }

    #[test]
    fn matches_a_per_class_reference_on_random_labels() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..50 {
            let n = rng.random_range(0..300);
            let truth: Vec<u32> = (0..n).map(|_| rng.random_range(0..42)).collect();
            let pred: Vec<i32> = (0..n).map(|_| rng.random_range(-1..42)).collect();
            for set in [
                ClassSet::Nyu19,
                ClassSet::Nyu15,
                ClassSet::Nyu10,
                ClassSet::Nyu40,
            ] {
                let s = evaluate(&pred, &truth, set).unwrap();
                let ids = set.ids();
                let mut ious = Vec::new();
                let mut accs = Vec::new();
                for &c in ids {
                    let evald = |i: usize| ids.contains(&truth[i]);
                    let tp = (0..n)
                        .filter(|&i| truth[i] == c && pred[i] == c as i32)
                        .count();
                    let fn_ = (0..n)
                        .filter(|&i| truth[i] == c && pred[i] != c as i32)
                        .count();
                    let fp = (0..n)
                        .filter(|&i| evald(i) && truth[i] != c && pred[i] == c as i32)
                        .count();
                    if tp + fn_ > 0 {
                        ious.push(tp as f64 / (tp + fp + fn_) as f64);
                        accs.push(tp as f64 / (tp + fn_) as f64);
                    }
                }
                // The confusion lists against a brute-force count of every cell.
                let evald = |i: usize| ids.contains(&truth[i]);
                let as_slot = |p: i32| {
                    u32::try_from(p)
                        .ok()
                        .filter(|p| ids.contains(p))
                        .map_or(-1, |p| p as i32)
                };
                for row in &s.per_class {
                    let c = row.id;
                    let mut fp = std::collections::BTreeMap::<i32, u64>::new();
                    let mut missed = std::collections::BTreeMap::<i32, u64>::new();
                    for i in (0..n).filter(|&i| evald(i)) {
                        let p = as_slot(pred[i]);
                        if p == c as i32 && truth[i] != c {
                            *fp.entry(truth[i] as i32).or_default() += 1;
                        }
                        if truth[i] == c && p != c as i32 {
                            *missed.entry(p).or_default() += 1;
                        }
                    }
                    let got = |l: &[profuse_metrics::scannet::Confusion]| {
                        let mut v: Vec<(i32, u64)> = l.iter().map(|x| (x.id, x.count)).collect();
                        // Listed most first, ties by id.
                        assert!(l.windows(2).all(|w| w[0].count > w[1].count
                            || (w[0].count == w[1].count && w[0].id < w[1].id)));
                        v.sort_unstable();
                        v
                    };
                    assert_eq!(
                        got(&row.false_positives),
                        fp.into_iter().collect::<Vec<_>>()
                    );
                    assert_eq!(got(&row.missed_as), missed.into_iter().collect::<Vec<_>>());
                    let sum = |l: &[profuse_metrics::scannet::Confusion]| {
                        l.iter().map(|x| x.count).sum::<u64>()
                    };
                    assert_eq!(sum(&row.false_positives), row.pred_count - row.correct);
                    assert_eq!(sum(&row.missed_as), row.gt_count - row.correct);
                    assert!(row
                        .missed_as
                        .iter()
                        .all(|x| (x.id == -1) == (x.name == "none")));
                }
                assert_eq!(s.classes_present, ious.len());
                if !ious.is_empty() {
                    let miou = 100.0 * ious.iter().sum::<f64>() / ious.len() as f64;
                    let macc = 100.0 * accs.iter().sum::<f64>() / accs.len() as f64;
                    assert!((s.miou - miou).abs() < 1e-9 && (s.macc - macc).abs() < 1e-9);
                }
            }
        }
    }

    /// The real ScanNet scene0000_00 (shared data): ground truth against itself scores 100
    /// for every set, the table lists exactly the set's classes present in the scene, and
    /// dropping one present class costs exactly its share of the mean.
    #[test]
    fn real_scene_ground_truth_against_itself() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../../shared/data/scannet/scene0000_00");
        if !dir.exists() {
            eprintln!("SKIPPED: {} is absent", dir.display());
            return;
        }
        let mesh = scene_io::scannet::read_labelled_mesh(&dir).unwrap();
        let truth = ground_truth_labels(&mesh, dir.display()).unwrap();
        assert_eq!(truth.len(), 81_369);
        let pred: Vec<i32> = truth.iter().map(|&t| t as i32).collect();
        for set in ClassSet::PAPER {
            let s = evaluate(&pred, &truth, set).unwrap();
            assert_eq!((s.miou, s.macc), (100.0, 100.0), "set {}", set.name());
            let mut present: Vec<u32> = truth
                .iter()
                .copied()
                .filter(|t| set.ids().contains(t))
                .collect();
            present.sort_unstable();
            present.dedup();
            let listed: Vec<u32> = s
                .per_class
                .iter()
                .filter(|r| r.gt_count > 0)
                .map(|r| r.id)
                .collect();
            assert_eq!(listed, present);
            assert!(present.len() >= 5, "{present:?}");
            let expected_eval = truth.iter().filter(|t| set.ids().contains(t)).count() as u64;
            assert_eq!(s.evaluated, expected_eval);
        }
        // Remove the wall (1) predictions: wall IoU and recall 0, every other class 100.
        let no_wall: Vec<i32> = pred.iter().map(|&p| if p == 1 { -1 } else { p }).collect();
        let s = evaluate(&no_wall, &truth, ClassSet::Nyu19).unwrap();
        let k = s.classes_present as f64;
        assert!((s.miou - 100.0 * (k - 1.0) / k).abs() < 1e-9, "{}", s.miou);
        assert!(CLASSES_19.contains(&1));
    }
}
