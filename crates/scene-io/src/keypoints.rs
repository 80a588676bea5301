//! Keypoint-pair files (one `.npz` per view pair, two (n, 2) arrays of matched pixel
//! positions: the layout XFeat, LightGlue and LoFTR users save) to a `sparse_matches` file.
//!
//! * **Which views.** A file is named `<stem_i>_<stem_j>.npz`, where a stem is the file
//!   name without extension of an `image_names` entry of the cameras file. Stems may contain
//!   underscores: every split point is tried and exactly one must name two views. Files
//!   whose stems name no view of the cameras (a frame dropped on import because its image
//!   is missing) are skipped and listed in the report; a stem that matches two views is an
//!   error.
//! * **Pixel convention.** Matchers report OpenCV keypoints (integer = pixel centre), so
//!   `+0.5` is added by default to reach SPEC.md's corner origin; `integer_centres = false`
//!   keeps the values.
//! * **Lens distortion.** When the cameras carry `distortion`, both keypoints of a match are
//!   undistorted ([`crate::undistort`]) into the pinhole camera with the same intrinsics,
//!   so everything downstream is pinhole; a match either of whose points cannot be
//!   undistorted (beyond the model's fold) is dropped and counted. With `target` cameras
//!   (the cropped pinhole cameras of `undistort --crop`), the points are expressed in
//!   those cameras' pixels instead, and a match either of whose points falls outside its
//!   target image is dropped and counted.
//! * **Certainty.** Keypoint matchers give none, so every match gets 1.
//! * Pairs appear in file-name order; rows keep their order within a file.
//! * No pair file naming two views (every file skipped, or none given) is an error, not
//!   an empty file.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, SparseMatches};
use serde::Serialize;

use crate::error::{invalid, missing, Result};
use crate::fsutil::show;
use crate::npy::{read_npz, write_npz, NpyArray, NpyData};
use crate::undistort::{to_target_pixel, PointDrop};

/// How to read the keypoint files.
#[derive(Debug, Clone)]
pub struct KeypointOptions {
    /// Array holding the view-i keypoints (XFeat scripts: `kpts_i`; LightGlue: often `keypoints0`).
    pub key_i: String,
    /// Array holding the view-j keypoints.
    pub key_j: String,
    /// Keypoints put pixel centres at integers (OpenCV): add 0.5.
    pub integer_centres: bool,
    /// Undistort with the cameras' lens model when they have one.
    pub undistort: bool,
    /// Pinhole cameras (same views, same order) whose pixels the output is in, e.g. the
    /// cropped cameras of `undistort --crop`; `None`: the pinhole camera with the input's
    /// intrinsics.
    pub target: Option<Cameras>,
}

impl Default for KeypointOptions {
    fn default() -> Self {
        KeypointOptions {
            key_i: "kpts_i".into(),
            key_j: "kpts_j".into(),
            integer_centres: true,
            undistort: true,
            target: None,
        }
    }
}

/// What the import did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct KeypointReport {
    /// Pair files read.
    pub pairs: usize,
    /// Matches written.
    pub matches: usize,
    /// Matches dropped because a point could not be undistorted.
    pub dropped_undistort: usize,
    /// Matches dropped because a point fell outside its target camera's image.
    pub dropped_outside: usize,
    /// Whether the keypoints were undistorted.
    pub undistorted: bool,
    /// Files skipped, with the reason.
    pub skipped: Vec<String>,
}

/// Imports keypoint-pair files into sparse matches between the views of `cameras`.
pub fn import_keypoint_pairs(
    files: &[PathBuf],
    cameras: &Cameras,
    cameras_label: &str,
    opts: &KeypointOptions,
) -> Result<(SparseMatches, KeypointReport)> {
    let stems = view_stems(cameras, cameras_label)?;
    if let Some(t) = &opts.target {
        if t.len() != cameras.len() {
            return Err(invalid(
                cameras_label,
                "target cameras",
                format!(
                    "{} views, but the target cameras have {}",
                    cameras.len(),
                    t.len()
                ),
            ));
        }
    }
    let mut files = files.to_vec();
    files.sort();
    let mut report = KeypointReport {
        undistorted: opts.undistort && cameras.distortion.is_some(),
        ..Default::default()
    };
    let mut pairs = Vec::new();
    let mut offsets = vec![0u64];
    let (mut points_i, mut points_j) = (Vec::new(), Vec::new());
    let mut seen = BTreeMap::new();
    for file in &files {
        let label = show(file);
        let Some((vi, vj)) = pair_views(file, &stems) else {
            report.skipped.push(format!(
                "{label}: the name is not <stem_i>_<stem_j>.npz with two image stems of {cameras_label}"
            ));
            continue;
        };
        if let Some(first) = seen.insert((vi, vj), label.clone()) {
            return Err(invalid(
                &label,
                "file name",
                format!("pair ({vi}, {vj}) was already read from {first}"),
            ));
        }
        let (ki, kj) = read_pair(file, opts)?;
        let shift = if opts.integer_centres { 0.5 } else { 0.0 };
        let target = opts.target.as_ref();
        let pixel = |v: usize, p: [f64; 2]| {
            to_target_pixel(cameras, target, v, p.map(|x| x + shift), opts.undistort)
        };
        for (a, b) in ki.into_iter().zip(kj) {
            // A point that cannot be undistorted counts before one outside its image.
            match (pixel(vi, a), pixel(vj, b)) {
                (Ok(a), Ok(b)) => {
                    points_i.push(a);
                    points_j.push(b);
                }
                (Err(PointDrop::Undistort), _) | (_, Err(PointDrop::Undistort)) => {
                    report.dropped_undistort += 1
                }
                _ => report.dropped_outside += 1,
            }
        }
        pairs.push([vi as u32, vj as u32]);
        offsets.push(points_i.len() as u64);
        report.pairs += 1;
    }
    if report.pairs == 0 {
        let why = match report.skipped.first() {
            Some(first) => format!(
                "all {} files were skipped (first: {first})",
                report.skipped.len()
            ),
            None => "no pair file was given".to_string(),
        };
        return Err(invalid(
            cameras_label,
            "keypoint pair files",
            format!(
                "none names two views of these cameras, so there are no matches to write: {why}"
            ),
        ));
    }
    report.matches = points_i.len();
    let n = points_i.len();
    let matches = SparseMatches {
        num_views: cameras.len(),
        pairs: pairs.into(),
        pair_offsets: offsets.into(),
        points_i: points_i.into(),
        points_j: points_j.into(),
        certainty: vec![1.0f32; n].into(),
        extra: Default::default(),
    };
    Ok((matches, report))
}

/// The pair file name of two images: `<stem_i>_<stem_j>.npz` (the file stems of the
/// image names, which [`import_keypoint_pairs`] maps back to views).
pub fn pair_file_name(name_i: &str, name_j: &str) -> String {
    let stem = |n: &str| {
        Path::new(n)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    format!("{}_{}.npz", stem(name_i), stem(name_j))
}

/// Writes one keypoint-pair file in the layout [`import_keypoint_pairs`] reads (and XFeat
/// scripts save): float32 arrays `kpts_i` and `kpts_j` of shape (n, 2), row r of both one
/// match, pixel centres at integers. Written atomically (temporary file, then rename).
pub fn write_keypoint_pair(path: &Path, kpts_i: &[[f32; 2]], kpts_j: &[[f32; 2]]) -> Result<()> {
    let label = show(path);
    if kpts_i.len() != kpts_j.len() {
        return Err(invalid(
            &label,
            "kpts_j",
            format!("{} rows, but kpts_i has {}", kpts_j.len(), kpts_i.len()),
        ));
    }
    let array = |rows: &[[f32; 2]]| {
        NpyArray::new(
            vec![rows.len(), 2],
            NpyData::F32(rows.iter().flatten().copied().collect()),
        )
        .ok_or_else(|| invalid(&label, "keypoints", "too many rows"))
    };
    let (a, b) = (array(kpts_i)?, array(kpts_j)?);
    write_npz(path, &[("kpts_i", &a), ("kpts_j", &b)])
}

/// View index of each image stem; an error when two views share a stem.
fn view_stems(cameras: &Cameras, label: &str) -> Result<BTreeMap<String, usize>> {
    let mut stems = BTreeMap::new();
    for (v, name) in cameras.image_names.iter().enumerate() {
        let stem = Path::new(name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        if let Some(other) = stems.insert(stem.clone(), v) {
            return Err(invalid(
                label,
                "image_names",
                format!("views {other} and {v} share the file stem {stem:?}, so pair files cannot name them"),
            ));
        }
    }
    Ok(stems)
}

/// The two views a `<stem_i>_<stem_j>.npz` file name refers to.
fn pair_views(file: &Path, stems: &BTreeMap<String, usize>) -> Option<(usize, usize)> {
    let name = file.file_stem()?.to_str()?;
    let mut found = None;
    for (at, _) in name.match_indices('_') {
        if let (Some(&i), Some(&j)) = (stems.get(&name[..at]), stems.get(&name[at + 1..])) {
            if found.is_some() {
                return None;
            }
            found = Some((i, j));
        }
    }
    found.filter(|(i, j)| i != j)
}

/// The two keypoint arrays of a pair file as (x, y) rows, checked for shape and finiteness.
/// Matched keypoints of one pair file: (x, y) rows of view i and of view j.
type KeypointRows = (Vec<[f64; 2]>, Vec<[f64; 2]>);

fn read_pair(file: &Path, opts: &KeypointOptions) -> Result<KeypointRows> {
    let label = show(file);
    let arrays = read_npz(file)?;
    let points = |key: &str| -> Result<Vec<[f64; 2]>> {
        let a = arrays.get(key).ok_or_else(|| {
            missing(
                &label,
                key,
                format!(
                    "an (n, 2) array; the file has {:?} (choose names with --key-i/--key-j)",
                    arrays.keys().collect::<Vec<_>>()
                ),
            )
        })?;
        if a.shape.len() != 2 || a.shape[1] != 2 {
            return Err(invalid(
                &label,
                key,
                format!("shape {:?}, expected (n, 2)", a.shape),
            ));
        }
        let v = a.to_f64_vec();
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(crate::SceneError::NonFinite {
                path: label.clone(),
                field: key.to_string(),
                index: i / 2,
                value: v[i].to_string(),
            });
        }
        Ok(v.chunks_exact(2).map(|c| [c[0], c[1]]).collect())
    };
    let (ki, kj) = (points(&opts.key_i)?, points(&opts.key_j)?);
    if ki.len() != kj.len() {
        return Err(invalid(
            &label,
            opts.key_j.as_str(),
            format!("{} rows, but {} has {}", kj.len(), opts.key_i, ki.len()),
        ));
    }
    Ok((ki, kj))
}
