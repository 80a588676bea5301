//! COLMAP's own tracks as sparse matches (SPEC.md §4.5), so that gs-init can triangulate
//! a COLMAP scene without a learned matcher.
//!
//! * **Which views.** View `v` is the `v`-th registered image by name ([`view_order`], the
//!   order of [`colmap_cameras`]). The cameras passed in must be what [`colmap_cameras`]
//!   made of this model: the view names must be the model's image names behind one common
//!   prefix (any `images_prefix`), in the same order, and sizes, intrinsics, lens and
//!   poses must equal the model's; anything else is an error naming the view, so a
//!   cameras file of another model (or one missing an image) cannot shift the matches.
//! * **Observations.** A 3D point is observed in view `v` at the `points2D` entry its
//!   track names. Views in [`TrackOptions::exclude_views`] take no part. A point with
//!   several observations in one view (a merged track) keeps the one with the smallest
//!   point2D index. Each kept observation is undistorted with the cameras' lens and
//!   expressed in the pinhole camera of its view, [`TrackOptions::target`]'s pixels when
//!   given (the same rule as keypoint pairs, [`crate::keypoints`]); one that cannot be
//!   undistorted, or that falls outside its target image, is dropped and counted.
//!   COLMAP's pixel coordinates already put pixel centres at +0.5: no shift.
//! * **Which pairs.** Two views share a point when both keep an observation of it. Each
//!   view chooses the [`TrackOptions::neighbours`] views it shares the most points with
//!   (ties: the smaller view index), among those sharing at least
//!   [`TrackOptions::min_shared`]; a pair is kept when either side chose it.
//! * **Which matches.** With [`TrackOptions::one_per_point`] (the default), each point gives
//!   one match, on the kept pair of its observations with the widest triangulation angle
//!   at the point (COLMAP's xyz and the two camera centres; ties: the smallest `(i, j)`):
//!   gs-init makes one Gaussian per match, so a point seen in `n` views would otherwise
//!   become up to `n (n − 1) / 2` coincident Gaussians, and the widest pair is the best
//!   conditioned triangulation (gs-init rejects rays closer than 2°). Without it, every
//!   kept pair of a point's observations gives a match.
//! * **Layout.** Pairs are written once as `(i, j)` with `i < j`, ascending; matches within
//!   a pair by ascending 3D point id; certainty 1. A kept pair left without matches (every
//!   point it shares chose another pair) is not written.
//! * **Errors.** A track naming an image that is not in the model, a point2D index beyond
//!   its image's `points2D`, or a point2D that observes another point, and a point2D
//!   naming a point3D id that is not in the model, are [`crate::SceneError::Invalid`]
//!   naming the file and field. No kept pair is an error, not an empty file.
//! * Deterministic: no threads, no hash-order output.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};

use profuse_formats::{Cameras, SparseMatches};
use serde::Serialize;

use super::{colmap_cameras, view_order, ColmapImage, ColmapModel, ColmapOptions, ColmapPoint};
use crate::error::{invalid, Result};
use crate::fsutil::show;
use crate::undistort::{to_target_pixel, PointDrop};

/// Default [`TrackOptions::neighbours`].
pub const DEFAULT_NEIGHBOURS: usize = 8;
/// Default [`TrackOptions::min_shared`].
pub const DEFAULT_MIN_SHARED: usize = 16;

/// How tracks become matches.
#[derive(Debug, Clone)]
pub struct TrackOptions {
    /// Pairs kept per view: each view is paired with the K views it shares the most 3D
    /// points with (default 8); a pair is kept when either side chose it.
    pub neighbours: usize,
    /// A pair needs at least this many shared points (default 16).
    pub min_shared: usize,
    /// View indices (into the imported cameras, i.e. sorted-by-name order) that take no
    /// part: held-out photos. No pair touches them.
    pub exclude_views: Vec<usize>,
    /// Undistort with the cameras' lens and express points in these pinhole target
    /// cameras (same views, same order), e.g. the cropped cameras of
    /// [`crate::undistort::undistort_scene`] with `crop`; `None`: the pinhole camera with
    /// the input intrinsics.
    pub target: Option<Cameras>,
    /// One match per 3D point (default true), on the kept pair of its track with the
    /// widest triangulation angle at the point (ties: the smallest `(i, j)`), so gs-init
    /// makes one Gaussian per point; false: every kept pair the track spans.
    pub one_per_point: bool,
}

impl Default for TrackOptions {
    fn default() -> Self {
        TrackOptions {
            neighbours: DEFAULT_NEIGHBOURS,
            min_shared: DEFAULT_MIN_SHARED,
            exclude_views: Vec::new(),
            target: None,
            one_per_point: true,
        }
    }
}

/// What [`track_matches`] did.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct TrackReport {
    /// Pairs written.
    pub pairs: usize,
    /// Pairs kept by the neighbour rule but not written: with one match per point, every
    /// point they share chose a wider pair.
    pub pairs_without_matches: usize,
    /// Matches written.
    pub matches: usize,
    /// 3D points that gave at least one match.
    pub points: usize,
    /// 3D points that gave none: fewer than two kept observations, or no kept pair
    /// among their views.
    pub points_without_pair: usize,
    /// Observations dropped because the lens model could not undistort them.
    pub dropped_undistort: usize,
    /// Observations dropped because they fall outside their target camera's image.
    pub dropped_outside: usize,
    /// Observations in excluded views.
    pub excluded_observations: usize,
    /// Further observations of a point in a view that already has one (merged tracks).
    pub duplicate_observations: usize,
    /// Whether the points were undistorted (the cameras carry a lens).
    pub undistorted: bool,
    /// Whether each point gave at most one match.
    pub one_per_point: bool,
    /// Per view: the written pairs it belongs to.
    pub view_pairs: Vec<usize>,
    /// Per view: the matches in which it is view i, gs-init's reference (which samples
    /// at most its budget, 15,000 by default, per reference).
    pub reference_matches: Vec<usize>,
    /// Views (not excluded) that belong to no written pair: gs-init seeds nothing from them.
    pub views_without_pair: Vec<usize>,
}

/// A 3D point's kept observations: (view, pixel in the target camera), ascending views,
/// one per view.
struct Track {
    xyz: [f64; 3],
    obs: Vec<(usize, [f32; 2])>,
}

/// One match: (point in view i, point in view j).
type Match = ([f32; 2], [f32; 2]);

/// The matches of one pair.
type PairMatches = Vec<Match>;

/// The tracks of `model` as sparse matches between the views of `cameras`, which must be
/// [`colmap_cameras`] of the same model (see the module documentation for the rules).
pub fn track_matches(
    model: &ColmapModel,
    cameras: &Cameras,
    opts: &TrackOptions,
) -> Result<(SparseMatches, TrackReport)> {
    let views = image_views(model, cameras)?;
    check_options(model, cameras, opts)?;
    let n = cameras.len();
    let mut excluded = vec![false; n];
    for &v in &opts.exclude_views {
        if let Some(e) = excluded.get_mut(v) {
            *e = true;
        }
    }
    let mut report = TrackReport {
        undistorted: cameras
            .distortion
            .as_ref()
            .is_some_and(|d| d.iter().any(|l| *l != [0.0; 4])),
        one_per_point: opts.one_per_point,
        ..Default::default()
    };
    let target = opts.target.as_ref();
    let tracks = collect_tracks(model, cameras, &views, &excluded, target, &mut report)?;
    let shared = shared_counts(&tracks);
    let kept = select_pairs(&shared, n, opts.neighbours, opts.min_shared);
    if kept.is_empty() {
        let most = shared.values().max().copied().unwrap_or(0);
        return Err(invalid(
            &show(&model.files.points),
            "tracks",
            format!(
                "no two views share at least {} kept observations (the most any pair shares is {most}), so there are no matches to write; lower min_shared",
                opts.min_shared
            ),
        ));
    }
    let centres: Vec<[f64; 3]> = (0..n).map(|v| cameras.center(v)).collect();
    let buckets = assign(&tracks, &kept, &centres, opts.one_per_point, &mut report);

    let mut pairs = Vec::with_capacity(buckets.len());
    let mut offsets = vec![0u64];
    let (mut points_i, mut points_j) = (Vec::new(), Vec::new());
    report.view_pairs = vec![0; n];
    report.reference_matches = vec![0; n];
    for (&(i, j), matches) in &buckets {
        let index = |v: usize| {
            u32::try_from(v)
                .map_err(|_| invalid(&show(&model.files.images), "images", "more than 2^32 views"))
        };
        pairs.push([index(i)?, index(j)?]);
        for &(a, b) in matches {
            points_i.push(a);
            points_j.push(b);
        }
        offsets.push(points_i.len() as u64);
        for v in [i, j] {
            if let Some(c) = report.view_pairs.get_mut(v) {
                *c += 1;
            }
        }
        if let Some(c) = report.reference_matches.get_mut(i) {
            *c += matches.len();
        }
    }
    report.pairs = pairs.len();
    report.pairs_without_matches = kept.len() - buckets.len();
    report.matches = points_i.len();
    report.views_without_pair = (0..n)
        .filter(|&v| report.view_pairs.get(v) == Some(&0) && excluded.get(v) == Some(&false))
        .collect();
    let matches = SparseMatches {
        num_views: n,
        pairs: pairs.into(),
        pair_offsets: offsets.into(),
        certainty: vec![1.0f32; points_i.len()].into(),
        points_i: points_i.into(),
        points_j: points_j.into(),
        extra: BTreeMap::from([(
            "source".to_string(),
            format!("colmap_{}_tracks", model.files.format.name()),
        )]),
    };
    Ok((matches, report))
}

/// The view of each image id, after checking that `cameras` are [`colmap_cameras`] of
/// `model` with some images prefix.
fn image_views(model: &ColmapModel, cameras: &Cameras) -> Result<BTreeMap<u32, usize>> {
    let label = show(&model.files.images);
    let order = view_order(model)?;
    let mut views = BTreeMap::new();
    for (v, image) in order.iter().enumerate() {
        if views.insert(image.id, v).is_some() {
            return Err(invalid(
                &label,
                format!("image {} ({}) IMAGE_ID", image.id, image.name),
                format!("image id {} is listed twice", image.id),
            ));
        }
    }
    let images_prefix = common_prefix(&order, cameras, &label)?;
    let expected = colmap_cameras(
        model,
        &ColmapOptions {
            images_prefix,
            ..Default::default()
        },
    )?;
    same_cameras(&expected, cameras, &label)?;
    Ok(views)
}

const CAMERAS_HINT: &str =
    "the cameras must be the ones `scene-io colmap` (colmap_cameras) made of this model";

/// `prefix` when `view_name` is `prefix/name` (empty when it is `name`).
fn prefix_of(view_name: &str, name: &str) -> Option<String> {
    if view_name == name {
        return Some(String::new());
    }
    let prefix = view_name.strip_suffix(name)?.strip_suffix('/')?;
    Some(prefix.to_string())
}

/// The one prefix that makes view `v`'s name out of the `v`-th image name, for every `v`.
fn common_prefix(order: &[&ColmapImage], cameras: &Cameras, label: &str) -> Result<String> {
    let names = &cameras.image_names;
    let positional = names.len() == order.len()
        && names
            .iter()
            .zip(order)
            .all(|(view, image)| prefix_of(view, &image.name).is_some());
    if !positional {
        // Say what is wrong: an image no view names, a view no image names, or the order.
        let named = |view: &str| order.iter().any(|im| prefix_of(view, &im.name).is_some());
        if let Some(image) = order
            .iter()
            .find(|im| !names.iter().any(|view| prefix_of(view, &im.name).is_some()))
        {
            return Err(invalid(
                label,
                format!("image {} ({})", image.id, image.name),
                format!(
                    "not among the {} views of the cameras; {CAMERAS_HINT}",
                    names.len()
                ),
            ));
        }
        if let Some((v, view)) = names.iter().enumerate().find(|(_, view)| !named(view)) {
            return Err(invalid(
                label,
                format!("cameras view {v} ({view})"),
                format!("names no image of the model; {CAMERAS_HINT}"),
            ));
        }
        return Err(invalid(
            label,
            "cameras image_names",
            format!(
                "{} views for {} images, or not in the model's order (sorted by name); {CAMERAS_HINT}",
                names.len(),
                order.len()
            ),
        ));
    }
    let mut prefix: Option<String> = None;
    for (v, (view, image)) in names.iter().zip(order).enumerate() {
        let p = prefix_of(view, &image.name).unwrap_or_default();
        match &prefix {
            None => prefix = Some(p),
            Some(first) if *first == p => {}
            Some(first) => {
                return Err(invalid(
                    label,
                    format!("cameras view {v} ({view})"),
                    format!(
                    "prefix {p:?} before the image name, but view 0 has {first:?}; {CAMERAS_HINT}"
                ),
                ))
            }
        }
    }
    Ok(prefix.unwrap_or_default())
}

/// Whether two numbers agree to 1e-9 (relative beyond 1).
fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(1.0)
}

/// An error unless `cameras` equal `expected` (names, sizes, intrinsics, lens, poses).
fn same_cameras(expected: &Cameras, cameras: &Cameras, label: &str) -> Result<()> {
    let lens = |c: &Cameras, v: usize| {
        c.distortion
            .as_ref()
            .map_or(Some([0.0; 4]), |d| d.get(v).copied())
    };
    for (v, name) in expected.image_names.iter().enumerate() {
        let mismatch = |what: &str, got: String, want: String| {
            invalid(
                label,
                format!("cameras view {v} ({name}) {what}"),
                format!("{got} in the cameras, {want} in the model; {CAMERAS_HINT}"),
            )
        };
        let got_name = cameras.image_names.get(v);
        if got_name != Some(name) {
            return Err(mismatch(
                "name",
                format!("{got_name:?}"),
                format!("{name:?}"),
            ));
        }
        let (got, want) = (cameras.image_size.get(v), expected.image_size.get(v));
        if got != want {
            return Err(mismatch(
                "image_size",
                format!("{got:?}"),
                format!("{want:?}"),
            ));
        }
        let rows = [
            (
                "intrinsics",
                cameras.intrinsics.get(v).map(|k| k.to_vec()),
                expected.intrinsics.get(v).map(|k| k.to_vec()),
            ),
            (
                "distortion",
                lens(cameras, v).map(|k| k.to_vec()),
                lens(expected, v).map(|k| k.to_vec()),
            ),
            (
                "world_to_camera",
                cameras.world_to_camera.get(v).map(|k| k.to_vec()),
                expected.world_to_camera.get(v).map(|k| k.to_vec()),
            ),
        ];
        for (what, got, want) in rows {
            let same = match (&got, &want) {
                (Some(g), Some(w)) => {
                    g.len() == w.len() && g.iter().zip(w).all(|(a, b)| close(*a, *b))
                }
                _ => false,
            };
            if !same {
                return Err(mismatch(what, format!("{got:?}"), format!("{want:?}")));
            }
        }
    }
    Ok(())
}

/// Errors for options that do not fit the cameras.
fn check_options(model: &ColmapModel, cameras: &Cameras, opts: &TrackOptions) -> Result<()> {
    let label = show(&model.files.images);
    let n = cameras.len();
    if opts.neighbours == 0 {
        return Err(invalid(
            &label,
            "neighbours",
            "0: each view must be allowed at least one partner view",
        ));
    }
    if let Some(&v) = opts.exclude_views.iter().find(|&&v| v >= n) {
        return Err(invalid(
            &label,
            "exclude_views",
            format!("view {v}, but the cameras have {n} views (0..{n})"),
        ));
    }
    if let Some(t) = &opts.target {
        if t.len() != n || t.intrinsics.len() != n || t.image_size.len() != n {
            return Err(invalid(
                &label,
                "target cameras",
                format!("{n} views, but the target cameras have {}", t.len()),
            ));
        }
        let lens = t
            .distortion
            .as_ref()
            .and_then(|d| d.iter().position(|l| *l != [0.0; 4]));
        if let Some(v) = lens {
            return Err(invalid(
                &label,
                format!("target cameras distortion[{v}]"),
                "a lens model: the target cameras must be pinhole (e.g. from `undistort`)",
            ));
        }
    }
    Ok(())
}

/// Every point's kept observations (points by ascending id), after checking every
/// reference of the model's tracks and points2D.
fn collect_tracks(
    model: &ColmapModel,
    cameras: &Cameras,
    views: &BTreeMap<u32, usize>,
    excluded: &[bool],
    target: Option<&Cameras>,
    report: &mut TrackReport,
) -> Result<Vec<Track>> {
    let points_label = show(&model.files.points);
    let images_label = show(&model.files.images);
    let points = points_by_id(model)?;
    let images: HashMap<u32, &ColmapImage> = model.images.iter().map(|im| (im.id, im)).collect();
    let mut tracks = Vec::with_capacity(points.len());
    for point in points {
        let mut obs: Vec<(usize, u32, [f64; 2])> = Vec::with_capacity(point.track.len());
        for (k, &(image_id, idx)) in point.track.iter().enumerate() {
            let field = |what: &str| format!("point3D {} TRACK[{k}].{what}", point.id);
            let (Some(image), Some(&v)) = (images.get(&image_id), views.get(&image_id)) else {
                return Err(invalid(
                    &points_label,
                    field("IMAGE_ID"),
                    format!("image {image_id} is not in {images_label}"),
                ));
            };
            let Some(&(xy, observed)) = usize::try_from(idx)
                .ok()
                .and_then(|i| image.points2d.get(i))
            else {
                return Err(invalid(
                    &points_label,
                    field("POINT2D_IDX"),
                    format!(
                        "index {idx}, but image {image_id} ({}) has {} points2D",
                        image.name,
                        image.points2d.len()
                    ),
                ));
            };
            if i64::try_from(point.id).ok() != Some(observed) {
                return Err(invalid(
                    &points_label,
                    field("POINT2D_IDX"),
                    format!(
                        "POINTS2D[{idx}] of image {image_id} ({}) observes point3D {observed}, not {}",
                        image.name, point.id
                    ),
                ));
            }
            if excluded.get(v).copied().unwrap_or(true) {
                report.excluded_observations += 1;
            } else {
                obs.push((v, idx, xy));
            }
        }
        obs.sort_by_key(|&(v, idx, _)| (v, idx));
        let before = obs.len();
        obs.dedup_by_key(|o| o.0);
        report.duplicate_observations += before - obs.len();
        let mut kept = Vec::with_capacity(obs.len());
        for (v, _, xy) in obs {
            match to_target_pixel(cameras, target, v, xy, true) {
                Ok(p) => kept.push((v, p)),
                Err(PointDrop::Undistort) => report.dropped_undistort += 1,
                Err(PointDrop::Outside) => report.dropped_outside += 1,
            }
        }
        tracks.push(Track {
            xyz: point.xyz,
            obs: kept,
        });
    }
    Ok(tracks)
}

/// The model's points by ascending id, after checking that ids are unique and that every
/// point2D's point3D id names one of them.
fn points_by_id(model: &ColmapModel) -> Result<Vec<&ColmapPoint>> {
    let points_label = show(&model.files.points);
    let mut points: Vec<&ColmapPoint> = model.points.iter().collect();
    points.sort_by_key(|p| p.id);
    if let Some([a, _]) = points
        .windows(2)
        .find(|w| matches!(w, [a, b] if a.id == b.id))
    {
        return Err(invalid(
            &points_label,
            format!("point3D {} POINT3D_ID", a.id),
            format!("point3D {} is listed twice", a.id),
        ));
    }
    let ids: HashSet<u64> = points.iter().map(|p| p.id).collect();
    for image in &model.images {
        for (k, &(_, id)) in image.points2d.iter().enumerate() {
            // COLMAP writes −1 for a keypoint without a point.
            let Ok(id) = u64::try_from(id) else { continue };
            if !ids.contains(&id) {
                return Err(invalid(
                    &show(&model.files.images),
                    format!(
                        "image {} ({}) POINTS2D[{k}].POINT3D_ID",
                        image.id, image.name
                    ),
                    format!("point3D {id} is not in {points_label}"),
                ));
            }
        }
    }
    Ok(points)
}

/// Points shared by each pair of views `(i, j)`, `i < j`.
fn shared_counts(tracks: &[Track]) -> BTreeMap<(usize, usize), usize> {
    let mut shared: HashMap<(usize, usize), usize> = HashMap::new();
    for t in tracks {
        for (k, &(a, _)) in t.obs.iter().enumerate() {
            for &(b, _) in t.obs.iter().skip(k + 1) {
                *shared.entry((a, b)).or_default() += 1;
            }
        }
    }
    shared.into_iter().collect()
}

/// The pairs some view chose among its `neighbours` most-shared partners (at least
/// `min_shared` points; ties: the smaller view).
fn select_pairs(
    shared: &BTreeMap<(usize, usize), usize>,
    views: usize,
    neighbours: usize,
    min_shared: usize,
) -> BTreeSet<(usize, usize)> {
    let mut partners: Vec<Vec<(usize, usize)>> = vec![Vec::new(); views];
    for (&(a, b), &count) in shared {
        if count >= min_shared.max(1) {
            if let Some(list) = partners.get_mut(a) {
                list.push((count, b));
            }
            if let Some(list) = partners.get_mut(b) {
                list.push((count, a));
            }
        }
    }
    let mut kept = BTreeSet::new();
    for (v, list) in partners.iter_mut().enumerate() {
        list.sort_by(|x, y| y.0.cmp(&x.0).then(x.1.cmp(&y.1)));
        for &(_, other) in list.iter().take(neighbours) {
            kept.insert((v.min(other), v.max(other)));
        }
    }
    kept
}

/// Angle at `x` between the rays to `a` and `b` (radians).
fn angle_at(x: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let u: [f64; 3] = std::array::from_fn(|k| a[k] - x[k]);
    let w: [f64; 3] = std::array::from_fn(|k| b[k] - x[k]);
    let cross = [
        u[1] * w[2] - u[2] * w[1],
        u[2] * w[0] - u[0] * w[2],
        u[0] * w[1] - u[1] * w[0],
    ];
    let norm = cross.iter().map(|c| c * c).sum::<f64>().sqrt();
    norm.atan2(u[0] * w[0] + u[1] * w[1] + u[2] * w[2])
}

/// Each point's matches on the kept pairs, grouped by pair (points in ascending id).
fn assign(
    tracks: &[Track],
    kept: &BTreeSet<(usize, usize)>,
    centres: &[[f64; 3]],
    one_per_point: bool,
    report: &mut TrackReport,
) -> BTreeMap<(usize, usize), PairMatches> {
    let mut buckets: BTreeMap<(usize, usize), PairMatches> = BTreeMap::new();
    for t in tracks {
        let mut emitted = false;
        let mut widest: Option<(f64, (usize, usize), Match)> = None;
        for (k, &(i, pi)) in t.obs.iter().enumerate() {
            for &(j, pj) in t.obs.iter().skip(k + 1) {
                if !kept.contains(&(i, j)) {
                    continue;
                }
                if !one_per_point {
                    buckets.entry((i, j)).or_default().push((pi, pj));
                    emitted = true;
                    continue;
                }
                let (Some(&ci), Some(&cj)) = (centres.get(i), centres.get(j)) else {
                    continue;
                };
                let angle = angle_at(t.xyz, ci, cj);
                // Pairs come in ascending (i, j): only a strictly wider one replaces.
                if widest.is_none_or(|(best, ..)| angle > best) {
                    widest = Some((angle, (i, j), (pi, pj)));
                }
            }
        }
        if let Some((_, pair, m)) = widest {
            buckets.entry(pair).or_default().push(m);
            emitted = true;
        }
        if emitted {
            report.points += 1;
        } else {
            report.points_without_pair += 1;
        }
    }
    buckets
}
