//! Which views to match: each view with its `k` nearest views by camera position and
//! viewing direction (the rule of the fox's `matches_xfeat/make_matches.py`), made
//! independent of the scene's scale.
//!
//! For views `i != j`, with camera centres `C` and unit viewing directions `f` (the camera's
//! +z axis in the world):
//!
//! `d(i, j) = |C_i - C_j| / m + ANGLE_WEIGHT * (1 - f_i . f_j)`
//!
//! where `m` is the median, over the views taking part, of the distance to their nearest
//! other camera (`1` when that is zero or undefined). make_matches.py used
//! `|C_i - C_j| + 10 (1 - cos)` in the fox's transforms.json units, whose median nearest
//! distance is 0.301: its angle weight is 33 in these units. Any weight from 20 to 50 gives
//! exactly its 92 fox pairs; 30 is used.
//!
//! Each view takes its `k` smallest `d` (ties: lower view index) among the other views
//! taking part; a pair is kept once, as `(min, max)`, and the list is sorted. Excluded
//! views (held out) are neither matched nor candidates.

use std::path::Path;

use profuse_formats::Cameras;

use crate::error::{input, Result};

/// Weight of the viewing-angle term, in median nearest-camera distances.
pub const ANGLE_WEIGHT: f64 = 30.0;

/// The view pairs to match: every view not in `exclude` with its `k` nearest (see the
/// module documentation), deduplicated, as `(i, j)` with `i < j`, sorted.
pub fn neighbour_pairs(cameras: &Cameras, k: usize, exclude: &[usize]) -> Vec<(usize, usize)> {
    let views: Vec<usize> = (0..cameras.len())
        .filter(|v| !exclude.contains(v))
        .collect();
    let centre: Vec<[f64; 3]> = (0..cameras.len()).map(|v| cameras.center(v)).collect();
    let forward: Vec<[f64; 3]> = (0..cameras.len())
        .map(|v| {
            // Row 2 of R is the camera's +z axis in world coordinates (x_cam = R x + t).
            let (r, _) = cameras.pose(v);
            let n = (r[2][0] * r[2][0] + r[2][1] * r[2][1] + r[2][2] * r[2][2]).sqrt();
            if n > 0.0 {
                [r[2][0] / n, r[2][1] / n, r[2][2] / n]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let dist = |i: usize, j: usize| -> f64 {
        let d: f64 = (0..3).map(|a| (centre[i][a] - centre[j][a]).powi(2)).sum();
        d.sqrt()
    };
    let mut nearest: Vec<f64> = views
        .iter()
        .filter_map(|&i| {
            views
                .iter()
                .filter(|&&j| j != i)
                .map(|&j| dist(i, j))
                .min_by(f64::total_cmp)
        })
        .collect();
    let m = median(&mut nearest)
        .filter(|m| m.is_finite() && *m > 0.0)
        .unwrap_or(1.0);
    let mut pairs = std::collections::BTreeSet::new();
    for &i in &views {
        let mut others: Vec<(f64, usize)> = views
            .iter()
            .filter(|&&j| j != i)
            .map(|&j| {
                let cos: f64 = (0..3).map(|a| forward[i][a] * forward[j][a]).sum();
                (
                    dist(i, j) / m + ANGLE_WEIGHT * (1.0 - cos.clamp(-1.0, 1.0)),
                    j,
                )
            })
            .collect();
        others.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for &(_, j) in others.iter().take(k) {
            pairs.insert((i.min(j), i.max(j)));
        }
    }
    pairs.into_iter().collect()
}

/// The views named by `items`: each an image name or file stem of `cameras` (tried
/// first, since stems are often numbers: the fox's `0018` is view 10), else a view index.
pub fn resolve_views(cameras: &Cameras, items: &[String]) -> Result<Vec<usize>> {
    let stem = |n: &str| {
        Path::new(n)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let mut views = Vec::new();
    for item in items.iter().map(|s| s.trim()).filter(|s| !s.is_empty()) {
        let by_name = cameras
            .image_names
            .iter()
            .position(|n| n == item || stem(n) == item || stem(n) == stem(item));
        let v = match (by_name, item.parse::<usize>()) {
            (Some(v), _) => v,
            (None, Ok(v)) if v < cameras.len() => v,
            _ => {
                return Err(input(
                    format!("view {item:?}"),
                    format!(
                        "names no image of the cameras (by name or stem) and is not a view index below {}",
                        cameras.len()
                    ),
                ))
            }
        };
        if !views.contains(&v) {
            views.push(v);
        }
    }
    Ok(views)
}

/// The median (mean of the two middle values for an even count, as numpy), or `None`.
fn median(values: &mut [f64]) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(values[n / 2]),
        _ => Some(0.5 * (values[n / 2 - 1] + values[n / 2])),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Cameras on a line along x, all looking along +z, except view 3 which looks back.
    fn line(xs: &[f64]) -> Cameras {
        let n = xs.len();
        let mut w2c = Vec::new();
        for (v, x) in xs.iter().enumerate() {
            // R = identity (or a half turn about y for view 3), t = -R C.
            let s = if v == 3 { -1.0 } else { 1.0 };
            w2c.push([s, 0.0, 0.0, -s * x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, s, 0.0]);
        }
        Cameras {
            image_names: (0..n).map(|v| format!("{v:04}.jpg")).collect(),
            image_size: vec![[4u32, 4]; n].into(),
            intrinsics: vec![[1.0, 1.0, 2.0, 2.0]; n].into(),
            world_to_camera: w2c.into(),
            distortion: None,
            extra: Default::default(),
        }
    }

    #[test]
    fn nearest_by_distance_and_angle_scale_free() {
        let xs = [0.0, 1.0, 2.0, 3.0, 4.0, 10.0];
        let cams = line(&xs);
        // m = 1. k = 1: 0-1; 1-0 (tie with 2: the lower index); 2-1; 3 looks back, so
        // every candidate costs 60 more and 2 wins its tie with 4; 4 takes 2 (2) over
        // 3 (1 + 60); 5-4.
        let p = neighbour_pairs(&cams, 1, &[]);
        assert_eq!(p, vec![(0, 1), (1, 2), (2, 3), (2, 4), (4, 5)]);
        // Scaling the scene changes nothing.
        let scaled = line(&xs.map(|x| x * 1000.0));
        assert_eq!(
            neighbour_pairs(&scaled, 2, &[]),
            neighbour_pairs(&cams, 2, &[])
        );
        // Excluded views are neither matched nor candidates.
        let p = neighbour_pairs(&cams, 2, &[1, 4]);
        assert!(p
            .iter()
            .all(|&(i, j)| ![1, 4].contains(&i) && ![1, 4].contains(&j)));
        assert_eq!(p, vec![(0, 2), (0, 3), (0, 5), (2, 3), (2, 5)]);
        assert!(neighbour_pairs(&cams, 0, &[]).is_empty());
    }

    #[test]
    fn views_by_name_stem_or_index() {
        let cams = line(&[0.0, 1.0, 2.0]);
        let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        // "0002" is the stem of view 2; "1" is no stem, so view index 1.
        let got = resolve_views(&cams, &names(&["0002", "0000.jpg", "1", "0002"]));
        assert_eq!(got.ok(), Some(vec![2, 0, 1]));
        assert!(resolve_views(&cams, &names(&["7"])).is_err());
        assert!(resolve_views(&cams, &names(&["fox"])).is_err());
    }
}
