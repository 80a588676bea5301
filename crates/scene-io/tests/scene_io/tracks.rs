//! COLMAP tracks as sparse matches (`colmap::track_matches`), against a brute-force
//! reference computed from the synthetic model's ground truth: which views see which
//! point (sets intersected per pair), exact projections, and the widest-angle pair.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use profuse_formats::{Cameras, FileKind, SparseMatches};
use scene_io::colmap::{
    colmap_cameras, read_colmap_model, track_matches, ColmapModel, ColmapOptions, TrackOptions,
    TrackReport,
};
use scene_io::undistort::{cropped, valid_rects};
use scene_io::SceneError;

use super::write;

const WIDTH: f64 = 640.0;
const HEIGHT: f64 = 480.0;
const VIEWS: usize = 8;
/// COLMAP image ids of views 0..8 (views are sorted by name; ids deliberately not).
const IMAGE_IDS: [u32; VIEWS] = [17, 4, 9, 1, 23, 11, 6, 30];

/// SplitMix64, so that the model does not depend on a third-party generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    fn shuffle<T>(&mut self, v: &mut [T]) {
        for i in (1..v.len()).rev() {
            v.swap(i, (self.next() % (i as u64 + 1)) as usize);
        }
    }
}

struct TruthView {
    camera_id: u32,
    q: UnitQuaternion<f64>,
    t: Vector3<f64>,
    centre: [f64; 3],
}

struct TruthPoint {
    id: u64,
    xyz: [f64; 3],
    /// (view, COLMAP pixel) for every view that sees the point, ascending views.
    seen: Vec<(usize, [f64; 2])>,
    /// Views holding a second, wrong keypoint of the point (listed first in the track,
    /// at a larger point2D index than the right one).
    duplicated: Vec<usize>,
}

struct Truth {
    views: Vec<TruthView>,
    points: Vec<TruthPoint>,
    /// COLMAP camera id → (fx, fy, cx, cy, k1, k2, p1, p2).
    cameras: BTreeMap<u32, [f64; 8]>,
}

/// OpenCV radial-tangential distortion and intrinsics, written out independently of the
/// crate.
fn to_pixel(c: &[f64; 8], x: f64, y: f64) -> [f64; 2] {
    let [fx, fy, cx, cy, k1, k2, p1, p2] = *c;
    let r2 = x * x + y * y;
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    [fx * xd + cx, fy * yd + cy]
}

fn look_at(centre: Vector3<f64>) -> UnitQuaternion<f64> {
    let forward = (-centre).normalize();
    let right = forward.cross(&Vector3::z()).normalize();
    let down = forward.cross(&right);
    let r = Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r))
}

/// Eight views on part of a circle around a box of points; each view sees a point when
/// it lands in the photo and a view-dependent coin says so, so pairs share different
/// numbers of points. `lens` is (k1, k2, p1, p2) of both COLMAP cameras; `extent` the
/// box's half size across (past about 2.5 many points project near the photo's borders).
fn make_truth(seed: u64, lens: [f64; 4], extent: f64) -> Truth {
    let mut rng = Rng(seed);
    let [k1, k2, p1, p2] = lens;
    let cameras = BTreeMap::from([
        (1, [500.0, 505.0, 320.5, 240.25, k1, k2, p1, p2]),
        (2, [480.0, 470.0, 318.0, 243.5, k1, k2, p1, p2]),
    ]);
    let views: Vec<TruthView> = (0..VIEWS)
        .map(|k| {
            let a = 1.2 * k as f64;
            let c = Vector3::new(6.0 * a.cos(), 6.0 * a.sin(), 0.6 * (k as f64).sin());
            let q = look_at(c);
            let t = -(q * c);
            let centre = [c.x, c.y, c.z];
            TruthView {
                camera_id: 1 + (k % 2) as u32,
                q,
                t,
                centre,
            }
        })
        .collect();
    let mut points = Vec::new();
    for p in 0..400u64 {
        let xyz = [
            rng.range(-extent, extent),
            rng.range(-extent, extent),
            rng.range(-0.6 * extent, 0.6 * extent),
        ];
        let mut seen = Vec::new();
        for (v, view) in views.iter().enumerate() {
            let x = view.q * Vector3::from(xyz) + view.t;
            let coin = rng.unit() < 0.35 + 0.07 * v as f64;
            if x.z < 0.5 || !coin {
                continue;
            }
            let px = to_pixel(&cameras[&view.camera_id], x.x / x.z, x.y / x.z);
            if px[0] > 0.0 && px[1] > 0.0 && px[0] < WIDTH && px[1] < HEIGHT {
                seen.push((v, px));
            }
        }
        if seen.len() < 2 {
            continue;
        }
        let duplicated = if p % 37 == 0 { vec![seen[0].0] } else { vec![] };
        points.push(TruthPoint {
            id: 5000 - 7 * p,
            xyz,
            seen,
            duplicated,
        });
    }
    Truth {
        views,
        points,
        cameras,
    }
}

/// Writes the model as COLMAP text files: images in id order (not view order), points in
/// shuffled order, keypoints shuffled among keypoints without a point, duplicates last.
fn write_model(dir: &Path, truth: &Truth, camera_model: &str) {
    let mut rng = Rng(99);
    let mut c = String::from("# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n");
    for (id, p) in &truth.cameras {
        let params: Vec<String> = match camera_model {
            "PINHOLE" => p[..4].iter().map(|x| format!("{x:?}")).collect(),
            _ => p.iter().map(|x| format!("{x:?}")).collect(),
        };
        c.push_str(&format!(
            "{id} {camera_model} 640 480 {}\n",
            params.join(" ")
        ));
    }
    write(&dir.join("cameras.txt"), c.as_bytes());

    // Per view: keypoints (pixel, point id); per point: track (image id, index).
    let mut keypoints: Vec<Vec<([f64; 2], i64)>> = vec![Vec::new(); VIEWS];
    for kp in keypoints.iter_mut() {
        for _ in 0..5 {
            kp.push(([rng.range(0.0, WIDTH), rng.range(0.0, HEIGHT)], -1));
        }
    }
    for p in &truth.points {
        for &(v, px) in &p.seen {
            keypoints[v].push((px, p.id as i64));
        }
    }
    for kp in keypoints.iter_mut() {
        rng.shuffle(kp);
    }
    let mut tracks: BTreeMap<u64, Vec<(u32, usize)>> = BTreeMap::new();
    for (v, kp) in keypoints.iter().enumerate() {
        for (idx, &(_, id)) in kp.iter().enumerate() {
            if id >= 0 {
                tracks
                    .entry(id as u64)
                    .or_default()
                    .push((IMAGE_IDS[v], idx));
            }
        }
    }
    for p in &truth.points {
        let track = tracks.get_mut(&p.id).unwrap();
        rng.shuffle(track);
        for &v in &p.duplicated {
            let (_, px) = p.seen.iter().find(|s| s.0 == v).unwrap();
            keypoints[v].push(([px[0] + 3.0, px[1] - 2.0], p.id as i64));
            track.insert(0, (IMAGE_IDS[v], keypoints[v].len() - 1));
        }
    }
    let mut s = String::from("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n");
    let mut by_id: Vec<usize> = (0..VIEWS).collect();
    by_id.sort_by_key(|&v| IMAGE_IDS[v]);
    for v in by_id {
        let view = &truth.views[v];
        let q = view.q.quaternion();
        s.push_str(&format!(
            "{} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {} v{v:02}.jpg\n",
            IMAGE_IDS[v], q.w, q.i, q.j, q.k, view.t.x, view.t.y, view.t.z, view.camera_id
        ));
        let obs: Vec<String> = keypoints[v]
            .iter()
            .map(|(px, id)| format!("{:?} {:?} {id}", px[0], px[1]))
            .collect();
        s.push_str(&obs.join(" "));
        s.push('\n');
    }
    write(&dir.join("images.txt"), s.as_bytes());

    let mut order: Vec<&TruthPoint> = truth.points.iter().collect();
    rng.shuffle(&mut order);
    let mut p = String::from("# POINT3D_ID X Y Z R G B ERROR TRACK[]\n");
    for point in order {
        let track: Vec<String> = tracks[&point.id]
            .iter()
            .map(|(image, idx)| format!("{image} {idx}"))
            .collect();
        let [x, y, z] = point.xyz;
        p.push_str(&format!(
            "{} {x:?} {y:?} {z:?} 10 20 30 0.5 {}\n",
            point.id,
            track.join(" ")
        ));
    }
    write(&dir.join("points3D.txt"), p.as_bytes());
}

/// A model written and read back, with its cameras (`images/` prefix).
fn model(dir: &Path, truth: &Truth, camera_model: &str) -> (ColmapModel, Cameras) {
    write_model(dir, truth, camera_model);
    let model = read_colmap_model(dir).unwrap();
    let cams = colmap_cameras(&model, &ColmapOptions::default()).unwrap();
    (model, cams)
}

/// Expected matches per pair: (point id, pixel in i, pixel in j), points ascending.
type Expected = BTreeMap<(usize, usize), Vec<(u64, [f64; 2], [f64; 2])>>;

fn angle(x: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let u = Vector3::from(a) - Vector3::from(x);
    let w = Vector3::from(b) - Vector3::from(x);
    (u.dot(&w) / (u.norm() * w.norm())).clamp(-1.0, 1.0).acos()
}

/// The brute-force reference: per view the set of points it keeps (`usable`), shared
/// counts by set intersection, each view's `k` most-shared partners (ties: smaller
/// view), and the matches of every kept pair (or only each point's widest pair).
fn expected(
    truth: &Truth,
    usable: &dyn Fn(usize, &TruthPoint) -> Option<[f64; 2]>,
    excluded: &[usize],
    k: usize,
    min_shared: usize,
    one_per_point: bool,
) -> (Expected, BTreeSet<(usize, usize)>) {
    let sets: Vec<BTreeSet<u64>> = (0..VIEWS)
        .map(|v| {
            truth
                .points
                .iter()
                .filter(|p| !excluded.contains(&v) && p.seen.iter().any(|s| s.0 == v))
                .filter(|p| usable(v, p).is_some())
                .map(|p| p.id)
                .collect()
        })
        .collect();
    let mut kept = BTreeSet::new();
    for a in 0..VIEWS {
        let mut partners: Vec<(usize, usize)> = (0..VIEWS)
            .filter(|&b| b != a)
            .map(|b| (sets[a].intersection(&sets[b]).count(), b))
            .filter(|&(n, _)| n >= min_shared.max(1))
            .collect();
        partners.sort_by(|x, y| y.0.cmp(&x.0).then(x.1.cmp(&y.1)));
        for &(_, b) in partners.iter().take(k) {
            kept.insert((a.min(b), a.max(b)));
        }
    }
    let mut points: Vec<&TruthPoint> = truth.points.iter().collect();
    points.sort_by_key(|p| p.id);
    let mut out = Expected::new();
    for p in points {
        let pairs: Vec<(usize, usize)> = kept
            .iter()
            .copied()
            .filter(|(i, j)| sets[*i].contains(&p.id) && sets[*j].contains(&p.id))
            .collect();
        let chosen: Vec<(usize, usize)> = if one_per_point {
            let widest = pairs
                .iter()
                .copied()
                .fold(None, |best: Option<(f64, _)>, (i, j)| {
                    let a = angle(p.xyz, truth.views[i].centre, truth.views[j].centre);
                    match best {
                        Some((b, _)) if b >= a => best,
                        _ => Some((a, (i, j))),
                    }
                });
            widest.map(|(_, pair)| pair).into_iter().collect()
        } else {
            pairs
        };
        for (i, j) in chosen {
            let (a, b) = (usable(i, p).unwrap(), usable(j, p).unwrap());
            out.entry((i, j)).or_default().push((p.id, a, b));
        }
    }
    (out, kept)
}

/// The output equals the reference: same pairs in the same order, same matches in the
/// same order, each coordinate within `tol` pixels (0: exactly the f32 of the value).
fn assert_same(m: &SparseMatches, want: &Expected, tol: f64) {
    let pairs: Vec<(usize, usize)> = m
        .pairs
        .iter()
        .map(|p| (p[0] as usize, p[1] as usize))
        .collect();
    assert_eq!(pairs, want.keys().copied().collect::<Vec<_>>());
    let mut worst = 0.0f64;
    for (p, rows) in want.values().enumerate() {
        let range = m.range(p);
        assert_eq!(range.len(), rows.len(), "pair {:?}", pairs[p]);
        for (n, (_, a, b)) in range.zip(rows) {
            for (got, want) in [(m.points_i[n], a), (m.points_j[n], b)] {
                for c in 0..2 {
                    if tol == 0.0 {
                        assert_eq!(got[c], want[c] as f32, "pair {:?}", pairs[p]);
                    }
                    worst = worst.max((f64::from(got[c]) - want[c]).abs());
                }
            }
        }
    }
    assert!(worst <= tol.max(1e-4), "worst coordinate error {worst} px");
    assert!(m.certainty.iter().all(|c| *c == 1.0));
    assert_eq!(m.num_views, VIEWS);
}

/// The COLMAP pixel of a point in a view (pinhole models: what the matches must carry).
fn colmap_pixel(v: usize, p: &TruthPoint) -> Option<[f64; 2]> {
    p.seen.iter().find(|s| s.0 == v).map(|s| s.1)
}

fn options(k: usize, min_shared: usize, one_per_point: bool) -> TrackOptions {
    TrackOptions {
        neighbours: k,
        min_shared,
        one_per_point,
        ..Default::default()
    }
}

/// (a) + (b): without one-per-point, the matches are every pair of observations among the
/// kept pairs, and the kept pairs are each view's K most-shared partners, for several K
/// and thresholds (some of which leave pairs out by rank and some by threshold).
#[test]
fn tracks_all_pairs_equal_the_brute_force_reference() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(1, [0.0; 4], 2.5);
    let (model, cams) = model(dir.path(), &truth, "PINHOLE");
    let (all, _) = expected(&truth, &colmap_pixel, &[], VIEWS, 1, false);
    let every_pair = all.len();
    assert!(every_pair >= 20, "the views overlap: {every_pair} pairs");
    let mut ranked_out = false;
    let mut thresholded_out = false;
    for (k, min_shared) in [(1, 1), (2, 16), (3, 40), (8, 1), (8, 90), (2, 70)] {
        let (m, report) = track_matches(&model, &cams, &options(k, min_shared, false)).unwrap();
        let (want, kept) = expected(&truth, &colmap_pixel, &[], k, min_shared, false);
        assert_same(&m, &want, 0.0);
        // Every kept pair has at least min_shared matches, so every kept pair is written.
        assert_eq!(report.pairs, kept.len());
        assert_eq!(report.pairs_without_matches, 0);
        assert_eq!(report.matches, want.values().map(Vec::len).sum::<usize>());
        let with_pair = want
            .values()
            .flatten()
            .map(|(id, ..)| *id)
            .collect::<BTreeSet<_>>()
            .len();
        assert_eq!(report.points, with_pair);
        assert_eq!(
            report.points + report.points_without_pair,
            truth.points.len()
        );
        let dups = truth
            .points
            .iter()
            .map(|p| p.duplicated.len())
            .sum::<usize>();
        assert!(dups >= 2);
        assert_eq!(report.duplicate_observations, dups);
        assert_eq!((report.dropped_outside, report.dropped_undistort), (0, 0));
        assert!(!report.undistorted && !report.one_per_point);
        let touching: Vec<usize> = (0..VIEWS)
            .map(|v| kept.iter().filter(|(i, j)| *i == v || *j == v).count())
            .collect();
        assert_eq!(report.view_pairs, touching);
        ranked_out |= min_shared == 1 && kept.len() < every_pair;
        thresholded_out |= k >= VIEWS - 1 && kept.len() < every_pair;
        // Either side chose each kept pair: at most VIEWS * k pairs.
        assert!(kept.len() <= VIEWS * k);
    }
    assert!(ranked_out && thresholded_out);
}

/// (c): with one-per-point, every point with a kept pair appears exactly once, on its
/// widest-angle pair; matches are traced back to points through their exact pixels.
#[test]
fn tracks_one_per_point_uses_each_point_once_on_its_widest_pair() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(2, [0.0; 4], 2.5);
    let (model, cams) = model(dir.path(), &truth, "PINHOLE");
    let (k, min_shared) = (3, 16);
    let (m, report) = track_matches(&model, &cams, &options(k, min_shared, true)).unwrap();
    let (want, kept) = expected(&truth, &colmap_pixel, &[], k, min_shared, true);
    assert_same(&m, &want, 0.0);
    assert_eq!(report.pairs + report.pairs_without_matches, kept.len());

    let mut owner: HashMap<(usize, u32, u32), u64> = HashMap::new();
    for p in &truth.points {
        for &(v, px) in &p.seen {
            owner.insert(
                (v, (px[0] as f32).to_bits(), (px[1] as f32).to_bits()),
                p.id,
            );
        }
    }
    let mut used: BTreeMap<u64, (usize, usize)> = BTreeMap::new();
    for (p, pair) in m.pairs.iter().enumerate() {
        let (i, j) = (pair[0] as usize, pair[1] as usize);
        assert!(i < j && kept.contains(&(i, j)));
        for n in m.range(p) {
            let key = |v: usize, q: [f32; 2]| (v, q[0].to_bits(), q[1].to_bits());
            let a = owner[&key(i, m.points_i[n])];
            assert_eq!(owner[&key(j, m.points_j[n])], a, "both ends are one point");
            assert!(used.insert(a, (i, j)).is_none(), "point {a} used twice");
        }
    }
    let mut checked = 0;
    for p in &truth.points {
        let angles: Vec<((usize, usize), f64)> = kept
            .iter()
            .filter(|(i, j)| colmap_pixel(*i, p).is_some() && colmap_pixel(*j, p).is_some())
            .map(|&(i, j)| {
                (
                    (i, j),
                    angle(p.xyz, truth.views[i].centre, truth.views[j].centre),
                )
            })
            .collect();
        let Some(widest) = angles.iter().map(|a| a.1).reduce(f64::max) else {
            assert!(!used.contains_key(&p.id));
            continue;
        };
        let pair = used[&p.id];
        let chosen = angles.iter().find(|a| a.0 == pair).unwrap().1;
        assert_eq!(chosen, widest, "point {} on {pair:?}", p.id);
        if angles.len() > 1 {
            checked += 1;
        }
    }
    assert_eq!(used.len(), report.points);
    assert_eq!(report.matches, report.points);
    assert!(checked > 50, "{checked} points had a choice of pairs");
    assert!(report.one_per_point);
    // The file validates and round-trips.
    let path = dir.path().join("sparse_matches.safetensors");
    m.write(&path).unwrap();
    let back = SparseMatches::read(&path).unwrap();
    assert_eq!(back.points_i.to_vec(), m.points_i.to_vec());
    assert_eq!(
        back.extra.get("source").map(String::as_str),
        Some("colmap_text_tracks")
    );
}

/// (d): a lens (OPENCV, k1 k2 p1 p2 non-zero) and the cropped pinhole cameras as target:
/// each output point is the 3D point projected by the target camera, within 1e-3 px;
/// observations that land in the cut-away border are dropped and counted. Without a
/// target, the pinhole camera with the input intrinsics.
#[test]
fn tracks_with_a_lens_land_on_pinhole_projections_in_the_cropped_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(3, [0.09, 0.04, 0.002, -0.0015], 4.0);
    let (model, cams) = model(dir.path(), &truth, "OPENCV");
    assert!(cams.distortion.is_some());
    let rects = valid_rects(&cams, "cams").unwrap();
    assert!(rects.iter().all(|r| r[0] > 0 && r[1] > 0), "{rects:?}");
    let cut = cropped(&cams, &rects);
    let in_cut = |v: usize, p: &TruthPoint| {
        colmap_pixel(v, p)?;
        let [u, w, _] = cut.project(v, p.xyz);
        let [width, height] = cut.image_size[v].map(f64::from);
        (u >= 0.0 && w >= 0.0 && u <= width && w <= height).then_some([u, w])
    };
    let opts = TrackOptions {
        target: Some(cut.clone()),
        ..options(3, 16, false)
    };
    let (m, report) = track_matches(&model, &cams, &opts).unwrap();
    let (want, _) = expected(&truth, &in_cut, &[], 3, 16, false);
    assert_same(&m, &want, 1e-3);
    let outside = truth
        .points
        .iter()
        .flat_map(|p| p.seen.iter().map(move |s| (s.0, p)))
        .filter(|(v, p)| in_cut(*v, p).is_none())
        .count();
    assert!(
        outside > 10,
        "{outside} observations in the cut-away border"
    );
    assert_eq!(report.dropped_outside, outside);
    assert_eq!(report.dropped_undistort, 0);
    assert!(report.undistorted);

    let pinhole = |v: usize, p: &TruthPoint| {
        colmap_pixel(v, p)?;
        let [u, w, _] = cams.project(v, p.xyz);
        Some([u, w])
    };
    let (m, report) = track_matches(&model, &cams, &options(3, 16, false)).unwrap();
    let (want, _) = expected(&truth, &pinhole, &[], 3, 16, false);
    assert_same(&m, &want, 1e-3);
    assert_eq!(report.dropped_outside, 0);
}

/// (e): excluded views take part in no pair; the rest equals the reference without them.
#[test]
fn tracks_excluded_views_appear_in_no_pair() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(4, [0.0; 4], 2.5);
    let (model, cams) = model(dir.path(), &truth, "PINHOLE");
    let excluded = [1usize, 4];
    for one_per_point in [false, true] {
        let opts = TrackOptions {
            exclude_views: excluded.to_vec(),
            ..options(2, 16, one_per_point)
        };
        let (m, report) = track_matches(&model, &cams, &opts).unwrap();
        let (want, _) = expected(&truth, &colmap_pixel, &excluded, 2, 16, one_per_point);
        assert_same(&m, &want, 0.0);
        assert!(m
            .pairs
            .iter()
            .all(|p| !excluded.contains(&(p[0] as usize)) && !excluded.contains(&(p[1] as usize))));
        let in_excluded: usize = truth
            .points
            .iter()
            .map(|p| {
                let seen = p.seen.iter().filter(|s| excluded.contains(&s.0)).count();
                seen + p.duplicated.iter().filter(|v| excluded.contains(v)).count()
            })
            .sum();
        assert!(in_excluded > 100);
        assert_eq!(report.excluded_observations, in_excluded);
        assert_eq!((report.view_pairs[1], report.view_pairs[4]), (0, 0));
        let lonely: Vec<usize> = (0..VIEWS)
            .filter(|v| !excluded.contains(v) && !want.keys().any(|(i, j)| i == v || j == v))
            .collect();
        assert_eq!(report.views_without_pair, lonely);
    }
    // Without exclusion the same views do take part.
    let (m, _) = track_matches(&model, &cams, &options(2, 16, false)).unwrap();
    assert!(m.pairs.iter().any(|p| p[0] == 1 || p[1] == 1));
}

fn invalid_parts(e: &SceneError) -> (String, String, String) {
    match e {
        SceneError::Invalid {
            path,
            field,
            detail,
        } => (path.clone(), field.clone(), detail.clone()),
        other => panic!("expected SceneError::Invalid, got {other:?}"),
    }
}

/// (f): references the model does not hold are typed errors naming file and field.
#[test]
fn tracks_bad_references_are_errors_naming_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(5, [0.0; 4], 2.5);
    let (model, cams) = model(dir.path(), &truth, "PINHOLE");
    let opts = TrackOptions::default();
    let run = |m: &ColmapModel| invalid_parts(&track_matches(m, &cams, &opts).unwrap_err());
    let first = model.points[0].id;

    let mut bad = model.clone();
    bad.points[0].track[1].0 = 999;
    let (path, field, detail) = run(&bad);
    assert!(path.ends_with("points3D.txt"), "{path}");
    assert_eq!(field, format!("point3D {first} TRACK[1].IMAGE_ID"));
    assert!(
        detail.contains("image 999 is not in") && detail.contains("images.txt"),
        "{detail}"
    );

    let mut bad = model.clone();
    bad.points[0].track[0].1 = 100_000;
    let (path, field, detail) = run(&bad);
    assert!(path.ends_with("points3D.txt"), "{path}");
    assert_eq!(field, format!("point3D {first} TRACK[0].POINT2D_IDX"));
    assert!(
        detail.contains("index 100000") && detail.contains("points2D"),
        "{detail}"
    );

    // A track element pointing at another point's keypoint.
    let mut bad = model.clone();
    let (image_id, _) = bad.points[0].track[0];
    let image = bad.images.iter().find(|im| im.id == image_id).unwrap();
    let other = image
        .points2d
        .iter()
        .position(|(_, id)| *id >= 0 && *id as u64 != first)
        .unwrap();
    bad.points[0].track[0].1 = other as u32;
    let (_, field, detail) = run(&bad);
    assert_eq!(field, format!("point3D {first} TRACK[0].POINT2D_IDX"));
    assert!(detail.contains(&format!("POINTS2D[{other}]")), "{detail}");

    // A keypoint naming a point3D id the model does not have.
    let mut bad = model.clone();
    let k = bad.images[2]
        .points2d
        .iter()
        .position(|(_, id)| *id < 0)
        .unwrap();
    bad.images[2].points2d[k].1 = 777_777;
    let (path, field, detail) = run(&bad);
    assert!(path.ends_with("images.txt"), "{path}");
    let image = &bad.images[2];
    assert_eq!(
        field,
        format!(
            "image {} ({}) POINTS2D[{k}].POINT3D_ID",
            image.id, image.name
        )
    );
    assert!(detail.contains("point3D 777777 is not in"), "{detail}");

    // The same errors through the text files.
    let text = std::fs::read_to_string(dir.path().join("points3D.txt")).unwrap();
    let line = text.lines().nth(1).unwrap();
    let mut fields: Vec<&str> = line.split(' ').collect();
    fields[8] = "424242";
    let broken = text.replacen(line, &fields.join(" "), 1);
    write(&dir.path().join("points3D.txt"), broken.as_bytes());
    let reread = read_colmap_model(dir.path()).unwrap();
    let (_, field, detail) = run(&reread);
    assert_eq!(field, format!("point3D {} TRACK[0].IMAGE_ID", fields[0]));
    assert!(detail.contains("image 424242"), "{detail}");
}

/// The cameras must be the model's: another images prefix is fine, a missing view, other
/// intrinsics, bad options and a distorted target are errors naming what differs.
#[test]
fn tracks_refuse_cameras_of_another_model_and_bad_options() {
    let dir = tempfile::tempdir().unwrap();
    let truth = make_truth(6, [0.0; 4], 2.5);
    let (model, cams) = model(dir.path(), &truth, "PINHOLE");
    let opts = options(2, 16, true);
    let (reference, _) = track_matches(&model, &cams, &opts).unwrap();
    for prefix in ["", "photos/left"] {
        let other = colmap_cameras(
            &model,
            &ColmapOptions {
                images_prefix: prefix.to_string(),
                ..Default::default()
            },
        )
        .unwrap();
        let (m, _) = track_matches(&model, &other, &opts).unwrap();
        assert_eq!(m.points_i.to_vec(), reference.points_i.to_vec());
        assert_eq!(m.pairs.to_vec(), reference.pairs.to_vec());
    }

    // Cameras made without view 3's image.
    let mut fewer = model.clone();
    fewer.images.retain(|im| im.id != IMAGE_IDS[3]);
    let short = colmap_cameras(&fewer, &ColmapOptions::default()).unwrap();
    let (path, field, detail) = invalid_parts(&track_matches(&model, &short, &opts).unwrap_err());
    assert!(path.ends_with("images.txt"));
    assert_eq!(field, format!("image {} (v03.jpg)", IMAGE_IDS[3]));
    assert!(detail.contains("not among the 7 views"), "{detail}");

    // Other intrinsics for view 5.
    let mut k: Vec<[f64; 4]> = cams.intrinsics.to_vec();
    k[5][2] += 1.0;
    let moved = Cameras {
        intrinsics: k.into(),
        ..cams.clone()
    };
    let (_, field, _) = invalid_parts(&track_matches(&model, &moved, &opts).unwrap_err());
    assert_eq!(field, "cameras view 5 (images/v05.jpg) intrinsics");

    // Views in another order.
    let mut swapped = cams.clone();
    swapped.image_names.swap(0, 1);
    let (_, field, _) = invalid_parts(&track_matches(&model, &swapped, &opts).unwrap_err());
    assert_eq!(field, "cameras image_names");

    let check = |opts: TrackOptions, want: &str| {
        let (_, field, _) = invalid_parts(&track_matches(&model, &cams, &opts).unwrap_err());
        assert_eq!(field, want);
    };
    check(options(0, 16, true), "neighbours");
    check(
        TrackOptions {
            exclude_views: vec![2, VIEWS],
            ..Default::default()
        },
        "exclude_views",
    );
    check(options(2, 100_000, true), "tracks");
    let mut lens = cams.clone();
    lens.distortion = Some([[0.0; 4], [0.1, 0.0, 0.0, 0.0]].repeat(VIEWS / 2).into());
    check(
        TrackOptions {
            target: Some(lens),
            ..Default::default()
        },
        "target cameras distortion[1]",
    );
    let mut one = cams.clone();
    one.image_names.truncate(1);
    check(
        TrackOptions {
            target: Some(one),
            ..Default::default()
        },
        "target cameras",
    );
}

/// The report serialises (the tool prints it).
#[test]
fn tracks_report_serialises_with_its_counts() {
    let report = TrackReport {
        pairs: 3,
        ..Default::default()
    };
    let json = serde_json::to_value(&report).unwrap();
    assert_eq!(json["pairs"], 3);
    assert!(json.get("dropped_outside").is_some() && json.get("view_pairs").is_some());
}
