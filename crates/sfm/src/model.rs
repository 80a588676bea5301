//! A summary scan of the binary models that COLMAP's mapper writes: which images were
//! registered, how many points, their mean reprojection error and track length. The full
//! reader, with poses and intrinsics, is `scene_io::colmap::read_colmap_model`; this crate
//! only needs the counts to pick and report a model, so it does not depend on scene-io.
//!
//! Layouts (COLMAP `src/base/reconstruction.cc`, little-endian, unchanged from 3.x to 4.x):
//! `images.bin`: u64 count, then per image u32 id, 4 f64 qvec, 3 f64 tvec, u32 camera id,
//! a NUL-terminated name, u64 keypoint count and 24 bytes per keypoint (f64 x, f64 y,
//! i64 point id). `points3D.bin`: u64 count, then per point u64 id, 3 f64 xyz, 3 u8 rgb,
//! f64 error, u64 track length and 8 bytes per track element (u32 image id, u32 index).

use std::path::{Path, PathBuf};

use crate::SfmError;

/// What a model holds, in the counts the report needs.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ModelSummary {
    pub dir: PathBuf,
    /// Names of the registered images, in file order.
    pub registered: Vec<String>,
    pub points: usize,
    /// Track elements summed over points (2D observations of 3D points).
    pub observations: u64,
    /// Mean over points of COLMAP's per-point mean reprojection error, in pixels.
    pub mean_reproj_px: f64,
    /// Observations per point.
    pub mean_track_length: f64,
}

/// Reads `images.bin` and `points3D.bin` of `dir`.
pub(crate) fn summarize(dir: &Path) -> Result<ModelSummary, SfmError> {
    let images_path = dir.join("images.bin");
    let bytes = read(&images_path)?;
    let registered = image_names(&bytes).map_err(|why| SfmError::Model {
        path: images_path.clone(),
        why,
    })?;
    let points_path = dir.join("points3D.bin");
    let bytes = read(&points_path)?;
    let (points, observations, error_sum) = point_stats(&bytes).map_err(|why| SfmError::Model {
        path: points_path.clone(),
        why,
    })?;
    let per_point = |x: f64| if points == 0 { 0.0 } else { x / points as f64 };
    Ok(ModelSummary {
        dir: dir.to_path_buf(),
        registered,
        points,
        observations,
        mean_reproj_px: per_point(error_sum),
        mean_track_length: per_point(observations as f64),
    })
}

fn read(path: &Path) -> Result<Vec<u8>, SfmError> {
    std::fs::read(path).map_err(|e| SfmError::io(path, e))
}

/// Bounds-checked little-endian reads; every failure says at which byte.
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(format!(
                "ends at byte {} inside a record that needs {n} more bytes from byte {}",
                self.bytes.len(),
                self.pos
            ));
        };
        let out = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(out)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn u64(&mut self) -> Result<u64, String> {
        self.array().map(u64::from_le_bytes)
    }

    fn f64(&mut self) -> Result<f64, String> {
        self.array().map(f64::from_le_bytes)
    }

    /// Skips `count` records of `size` bytes.
    fn skip(&mut self, count: u64, size: usize) -> Result<(), String> {
        let n = usize::try_from(count)
            .ok()
            .and_then(|c| c.checked_mul(size))
            .ok_or_else(|| format!("record count {count} at byte {} is too large", self.pos))?;
        self.take(n).map(|_| ())
    }

    /// A count that cannot exceed what the remaining bytes hold at `min_record` bytes each.
    fn count(&mut self, min_record: usize) -> Result<u64, String> {
        let at = self.pos;
        let n = self.u64()?;
        let room = (self.bytes.len() - self.pos) / min_record.max(1);
        if n > room as u64 {
            return Err(format!(
                "count {n} at byte {at} exceeds what the remaining {} bytes can hold",
                self.bytes.len() - self.pos
            ));
        }
        Ok(n)
    }

    fn finish(&self) -> Result<(), String> {
        if self.pos == self.bytes.len() {
            Ok(())
        } else {
            Err(format!(
                "{} unexpected bytes after the last record",
                self.bytes.len() - self.pos
            ))
        }
    }
}

/// Image id (4) + qvec (32) + tvec (24) + camera id (4) + NUL (1) + keypoint count (8).
const MIN_IMAGE_RECORD: usize = 73;
/// Point id (8) + xyz (24) + rgb (3) + error (8) + track length (8).
const MIN_POINT_RECORD: usize = 51;

fn image_names(bytes: &[u8]) -> Result<Vec<String>, String> {
    let mut c = Cursor { bytes, pos: 0 };
    let n = c.count(MIN_IMAGE_RECORD)?;
    let mut names = Vec::with_capacity(n as usize);
    for _ in 0..n {
        c.take(4 + 32 + 24 + 4)?;
        let rest = &bytes[c.pos..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| format!("image name at byte {} has no terminating NUL", c.pos))?;
        let name = String::from_utf8_lossy(c.take(len)?).into_owned();
        c.take(1)?;
        let keypoints = c.u64()?;
        c.skip(keypoints, 24)?;
        names.push(name);
    }
    c.finish()?;
    Ok(names)
}

/// (points, observations, sum of per-point errors).
fn point_stats(bytes: &[u8]) -> Result<(usize, u64, f64), String> {
    let mut c = Cursor { bytes, pos: 0 };
    let n = c.count(MIN_POINT_RECORD)?;
    let (mut observations, mut error_sum) = (0u64, 0.0f64);
    for _ in 0..n {
        c.take(8 + 24 + 3)?;
        let error = c.f64()?;
        // COLMAP writes -1 for a point whose error was never computed.
        if error.is_finite() && error >= 0.0 {
            error_sum += error;
        }
        let track = c.u64()?;
        c.skip(track, 8)?;
        observations = observations.saturating_add(track);
    }
    c.finish()?;
    Ok((n as usize, observations, error_sum))
}

/// The numbered model folders under `sparse` (`0`, `1`, …) that hold an `images.bin`,
/// in numeric order.
pub(crate) fn model_dirs(sparse: &Path) -> Result<Vec<(u32, PathBuf)>, SfmError> {
    let entries = match std::fs::read_dir(sparse) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(SfmError::io(sparse, e)),
    };
    let mut dirs = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| SfmError::io(sparse, e))?;
        let index = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<u32>().ok());
        let path = entry.path();
        if let Some(index) = index {
            if path.join("images.bin").is_file() {
                dirs.push((index, path));
            }
        }
    }
    dirs.sort();
    Ok(dirs)
}

/// Summaries of every model under `sparse`, the largest (most registered images, then
/// most points, then lowest number) first, and that one renamed to `sparse/0` (the
/// model that was `0` takes its old number).
pub(crate) fn pick_largest(sparse: &Path) -> Result<Vec<ModelSummary>, SfmError> {
    let mut summaries = Vec::new();
    for (index, dir) in model_dirs(sparse)? {
        summaries.push((index, summarize(&dir)?));
    }
    let best = summaries
        .iter()
        .enumerate()
        .max_by(|(_, (ia, a)), (_, (ib, b))| {
            (a.registered.len(), a.points)
                .cmp(&(b.registered.len(), b.points))
                .then(ib.cmp(ia))
        })
        .map(|(i, _)| i);
    let Some(best) = best else {
        return Ok(Vec::new());
    };
    let (best_index, _) = summaries[best];
    if best_index != 0 {
        swap_dirs(sparse, best_index)?;
        for (index, s) in &mut summaries {
            if *index == 0 {
                *index = best_index;
            } else if *index == best_index {
                *index = 0;
            }
            s.dir = sparse.join(index.to_string());
        }
    }
    summaries.sort_by_key(|(index, _)| *index);
    Ok(summaries.into_iter().map(|(_, s)| s).collect())
}

/// Renames `sparse/k` to `sparse/0` and the old `sparse/0`, if any, to `sparse/k`.
fn swap_dirs(sparse: &Path, k: u32) -> Result<(), SfmError> {
    let zero = sparse.join("0");
    let other = sparse.join(k.to_string());
    let parked = sparse.join(".profuse-sfm-swap");
    let rename =
        |from: &Path, to: &Path| std::fs::rename(from, to).map_err(|e| SfmError::io(from, e));
    let had_zero = zero.exists();
    if had_zero {
        rename(&zero, &parked)?;
    }
    rename(&other, &zero)?;
    if had_zero {
        rename(&parked, &other)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image_record(out: &mut Vec<u8>, id: u32, name: &str, keypoints: u64) {
        out.extend(id.to_le_bytes());
        out.extend([0u8; 56]);
        out.extend(1u32.to_le_bytes());
        out.extend(name.as_bytes());
        out.push(0);
        out.extend(keypoints.to_le_bytes());
        out.extend(vec![0u8; 24 * keypoints as usize]);
    }

    fn point_record(out: &mut Vec<u8>, error: f64, track: u64) {
        out.extend([0u8; 35]);
        out.extend(error.to_le_bytes());
        out.extend(track.to_le_bytes());
        out.extend(vec![0u8; 8 * track as usize]);
    }

    #[test]
    fn scans_names_and_point_statistics() {
        let mut images = 2u64.to_le_bytes().to_vec();
        image_record(&mut images, 1, "a.jpg", 3);
        image_record(&mut images, 2, "sub/b.jpg", 0);
        assert_eq!(
            image_names(&images),
            Ok(vec!["a.jpg".into(), "sub/b.jpg".into()])
        );

        let mut points = 2u64.to_le_bytes().to_vec();
        point_record(&mut points, 0.5, 2);
        point_record(&mut points, 1.5, 4);
        assert_eq!(point_stats(&points), Ok((2, 6, 2.0)));
    }

    fn write_model(dir: &Path, names: &[&str], points: u64) {
        std::fs::create_dir_all(dir).unwrap_or_else(|e| panic!("{e}"));
        let mut images = (names.len() as u64).to_le_bytes().to_vec();
        for (i, n) in names.iter().enumerate() {
            image_record(&mut images, i as u32 + 1, n, 1);
        }
        let mut pts = points.to_le_bytes().to_vec();
        for _ in 0..points {
            point_record(&mut pts, 1.0, 2);
        }
        std::fs::write(dir.join("images.bin"), images).unwrap_or_else(|e| panic!("{e}"));
        std::fs::write(dir.join("points3D.bin"), pts).unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn the_largest_model_becomes_sparse_0() {
        let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let sparse = tmp.path().join("sparse");
        write_model(&sparse.join("0"), &["a.jpg", "b.jpg"], 5);
        write_model(&sparse.join("1"), &["a.jpg", "c.jpg", "d.jpg"], 3);
        write_model(&sparse.join("2"), &["e.jpg", "f.jpg"], 9);
        std::fs::create_dir_all(sparse.join("notes")).unwrap_or_else(|e| panic!("{e}"));
        let models = pick_largest(&sparse).unwrap_or_else(|e| panic!("{e}"));
        let counts: Vec<_> = models
            .iter()
            .map(|m| (m.registered.len(), m.points))
            .collect();
        assert_eq!(counts, [(3, 3), (2, 5), (2, 9)]);
        assert_eq!(models[0].dir, sparse.join("0"));
        assert_eq!(
            summarize(&sparse.join("0"))
                .map(|m| m.registered.len())
                .ok(),
            Some(3)
        );
        assert_eq!(summarize(&sparse.join("1")).map(|m| m.points).ok(), Some(5));
        assert!(!sparse.join(".profuse-sfm-swap").exists());
        let empty = tmp.path().join("none");
        assert_eq!(pick_largest(&empty).map(|m| m.len()).ok(), Some(0));
    }

    #[test]
    fn truncated_and_oversized_files_are_errors() {
        let mut images = 1u64.to_le_bytes().to_vec();
        image_record(&mut images, 1, "a.jpg", 3);
        for cut in 0..images.len() {
            assert!(image_names(&images[..cut]).is_err(), "cut at {cut}");
        }
        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend([0u8; 100]);
        assert!(image_names(&huge).is_err());
        assert!(point_stats(&huge).is_err());
        let mut points = 1u64.to_le_bytes().to_vec();
        point_record(&mut points, 0.5, 2);
        points.push(7);
        assert!(point_stats(&points).is_err());
        // A track length that overflows usize arithmetic.
        let mut points = 1u64.to_le_bytes().to_vec();
        points.extend([0u8; 43]);
        points.extend(u64::MAX.to_le_bytes());
        assert!(point_stats(&points).is_err());
    }
}
