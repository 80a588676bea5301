//! LangSplat / Dr. Splat `language_features/` → one [`Masks`] file.
//!
//! LangSplat's `preprocess.py` writes per image `<stem>_s.npy`, segmentation maps
//! [4, H, W] (float32 in LangSplat, any integer or float type accepted), and
//! `<stem>_f.npy`, the CLIP features of all four levels concatenated [M, 512]. Level `l`
//! of the seg map holds row indices into that table, already offset by the sizes of the
//! levels before it; −1 = no mask. The levels are, in order (LangSplat's
//! `get_language_feature`, `feature_level`): 0 = `default`, 1 = `s`, 2 = `m`, 3 = `l`.
//! `<stem>` is the image file name up to its first `.` (LangSplat's `split('.')[0]`).
//!
//! For the chosen level each view's used rows are compacted into local ids `0..k` in
//! first-appearance raster order, rows are re-normalised (a zero row is an error), and
//! features are stored as F16 when every source table is f16, else F32. Labels are U16
//! unless a view has more than 65535 masks.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use half::f16;
use profuse_formats::{Cameras, Floats, Labels, Masks};
use serde::Serialize;

use crate::error::{invalid, missing, Result};
use crate::fsutil::{list_dir, show};
use crate::npy::{read_npy, NpyArray, NpyDtype};

/// Names of LangSplat's seg-map levels, by index.
pub const LEVEL_NAMES: [&str; 4] = ["default", "s", "m", "l"];

/// Options of [`import_langsplat`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LangSplatOptions {
    /// Seg-map level 0..=3 (`default`, `s`, `m`, `l`).
    pub level: usize,
    /// When given, views follow its order and `view_names` are its `image_names`;
    /// otherwise views are the sorted stems found in the directory.
    pub cameras: Option<Cameras>,
}

/// What [`import_langsplat`] did.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct LangSplatReport {
    pub views: usize,
    pub masks: usize,
    pub level: usize,
    pub level_name: String,
    pub width: usize,
    pub height: usize,
    pub feature_dim: usize,
    /// `F16` or `F32`.
    pub feature_dtype: String,
    /// Source feature rows not used by the chosen level (other levels' masks).
    pub unused_rows: usize,
}

/// The LangSplat stem of an image name: its file name up to the first `.`.
pub fn langsplat_stem(image_name: &str) -> String {
    let file = image_name.rsplit('/').next().unwrap_or(image_name);
    file.split('.').next().unwrap_or(file).to_string()
}

/// Reads a `language_features/` directory into one masks file.
pub fn import_langsplat(
    dir: impl AsRef<Path>,
    options: &LangSplatOptions,
) -> Result<(Masks, LangSplatReport)> {
    let dir = dir.as_ref();
    let label = show(dir);
    let level_name = LEVEL_NAMES.get(options.level).ok_or_else(|| {
        invalid(
            &label,
            "level",
            format!("{}, expected 0..=3 (default, s, m, l)", options.level),
        )
    })?;
    let views = list_views(dir, options.cameras.as_ref())?;

    let mut grid: Option<(usize, usize, String)> = None;
    let mut dim: Option<(usize, String)> = None;
    let mut all_f16 = true;
    let mut labels: Vec<u32> = Vec::new();
    let mut offsets: Vec<u32> = vec![0];
    let mut rows: Vec<Vec<f32>> = Vec::new();
    let mut unused_rows = 0;
    for view in &views {
        let seg = read_npy(&view.seg)?;
        let seg_label = show(&view.seg);
        let (h, w) = seg_plane_size(&seg, options.level, &seg_label)?;
        match &grid {
            Some((gh, gw, first)) if (*gh, *gw) != (h, w) => {
                return Err(invalid(&seg_label, "shape", format!("seg maps are {h}x{w} (HxW) here but {gh}x{gw} in {first}; all views must share H, W")));
            }
            Some(_) => {}
            None => grid = Some((h, w, seg_label.clone())),
        }
        let features = read_npy(&view.features)?;
        let feat_label = show(&view.features);
        let (m, d) = feature_table_size(&features, &feat_label)?;
        match &dim {
            Some((gd, first)) if *gd != d => {
                return Err(invalid(
                    &feat_label,
                    "shape",
                    format!("feature dimension {d} here but {gd} in {first}"),
                ));
            }
            Some(_) => {}
            None => dim = Some((d, feat_label.clone())),
        }
        all_f16 &= features.dtype() == NpyDtype::F16;

        let plane = level_plane(&seg, options.level, h * w, &seg_label)?;
        let (local, used) = compact(&plane, m, &seg_label, options.level)?;
        labels.extend(local);
        unused_rows += m - used.len();
        push_rows(&mut rows, &features.to_f32_vec(), &used, d, &feat_label)?;
        let total = u32::try_from(rows.len())
            .map_err(|_| invalid(&label, "masks", "more than 4294967295 masks"))?;
        offsets.push(total);
    }

    let (height, width, _) = grid.unwrap_or_default();
    let (feature_dim, _) = dim.unwrap_or_default();
    let labels = stored_labels(labels, &offsets);
    let features = stored_features(&rows, all_f16);
    let report = LangSplatReport {
        views: views.len(),
        masks: rows.len(),
        level: options.level,
        level_name: (*level_name).to_string(),
        width,
        height,
        feature_dim,
        feature_dtype: if all_f16 { "F16" } else { "F32" }.to_string(),
        unused_rows,
    };
    let masks = Masks {
        view_names: views.into_iter().map(|v| v.name).collect(),
        width,
        height,
        labels,
        mask_offsets: offsets.into(),
        features,
        dim: feature_dim,
        extra: BTreeMap::from([
            ("source".to_string(), "langsplat".to_string()),
            (
                "langsplat_level".to_string(),
                format!("{} ({level_name})", options.level),
            ),
        ]),
    };
    Ok((masks, report))
}

/// Appends the normalised rows `used` of a view's `d`-wide feature `table` to `rows`; an
/// error names a row of zero or non-finite norm.
fn push_rows(
    rows: &mut Vec<Vec<f32>>,
    table: &[f32],
    used: &[usize],
    d: usize,
    feat_label: &str,
) -> Result<()> {
    for &row in used {
        let start = row * d;
        let values = table.get(start..start + d).unwrap_or_default();
        rows.push(normalised(values).ok_or_else(|| {
            invalid(
                feat_label,
                format!("row {row}"),
                "has zero or non-finite norm; a mask feature must be a direction",
            )
        })?);
    }
    Ok(())
}

/// The view-local labels in the narrowest dtype that holds every view's masks (`offsets`:
/// the views' first global masks, then the total).
fn stored_labels(labels: Vec<u32>, offsets: &[u32]) -> Labels {
    let per_view_max = offsets
        .windows(2)
        .map(|w| w.get(1).copied().unwrap_or(0) - w.first().copied().unwrap_or(0))
        .max()
        .unwrap_or(0);
    if per_view_max <= u32::from(u16::MAX) {
        Labels::U16(
            labels
                .iter()
                .map(|l| if *l == u32::MAX { u16::MAX } else { *l as u16 })
                .collect::<Vec<_>>()
                .into(),
        )
    } else {
        Labels::U32(labels.into())
    }
}

/// The mask features, one row after the other: F16 when every view stored F16.
fn stored_features(rows: &[Vec<f32>], all_f16: bool) -> Floats {
    let flat: Vec<f32> = rows.concat();
    if all_f16 {
        Floats::F16(
            flat.iter()
                .map(|v| f16::from_f32(*v))
                .collect::<Vec<_>>()
                .into(),
        )
    } else {
        Floats::F32(flat.into())
    }
}

struct View {
    name: String,
    seg: PathBuf,
    features: PathBuf,
}

/// Views in cameras order (names = image names) or sorted stems (names = stems).
fn list_views(dir: &Path, cameras: Option<&Cameras>) -> Result<Vec<View>> {
    let label = show(dir);
    let view = |name: String, stem: &str| -> Result<View> {
        let seg = dir.join(format!("{stem}_s.npy"));
        let features = dir.join(format!("{stem}_f.npy"));
        for (p, what) in [
            (&seg, "seg maps [4, H, W]"),
            (&features, "feature table [M, D]"),
        ] {
            if !p.is_file() {
                return Err(missing(&show(p), format!("file for view {name:?}"), what));
            }
        }
        Ok(View {
            name,
            seg,
            features,
        })
    };
    let views = match cameras {
        Some(c) => {
            let mut seen: HashMap<String, &str> = HashMap::new();
            c.image_names
                .iter()
                .map(|name| {
                    let stem = langsplat_stem(name);
                    if let Some(other) = seen.insert(stem.clone(), name) {
                        return Err(invalid(
                            &label,
                            "cameras image_names",
                            format!("{other:?} and {name:?} share the LangSplat stem {stem:?}"),
                        ));
                    }
                    view(name.clone(), &stem)
                })
                .collect::<Result<Vec<_>>>()?
        }
        None => list_dir(dir)?
            .iter()
            .filter_map(|p| {
                p.file_name()?
                    .to_str()?
                    .strip_suffix("_s.npy")
                    .map(str::to_string)
            })
            .map(|stem| view(stem.clone(), &stem))
            .collect::<Result<Vec<_>>>()?,
    };
    if views.is_empty() {
        return Err(missing(
            &label,
            "`*_s.npy` files",
            "LangSplat seg maps, one per view",
        ));
    }
    Ok(views)
}

fn seg_plane_size(seg: &NpyArray, level: usize, label: &str) -> Result<(usize, usize)> {
    match seg.shape.as_slice() {
        [levels, h, w] if *levels > level && *h > 0 && *w > 0 => Ok((*h, *w)),
        _ => Err(invalid(
            label,
            "shape",
            format!(
                "{:?}, expected [4, H, W] seg maps with level {level} present",
                seg.shape
            ),
        )),
    }
}

fn feature_table_size(features: &NpyArray, label: &str) -> Result<(usize, usize)> {
    match (features.shape.as_slice(), features.dtype().is_float()) {
        ([m, d], true) if *d > 0 => Ok((*m, *d)),
        _ => Err(invalid(
            label,
            "shape",
            format!(
                "{:?} dtype {}, expected a float feature table [M, D]",
                features.shape,
                features.dtype().code()
            ),
        )),
    }
}

/// The seg-map values of one level as integers (−1 = none).
fn level_plane(seg: &NpyArray, level: usize, plane: usize, label: &str) -> Result<Vec<i64>> {
    let start = level * plane;
    let values = seg
        .to_i64_vec()
        .map_err(|e| invalid(label, "seg map", e.to_string()))?;
    Ok(values
        .get(start..start + plane)
        .unwrap_or_default()
        .to_vec())
}

/// Local ids in first-appearance raster order (`u32::MAX` = none) and the source rows
/// in local-id order.
fn compact(
    plane: &[i64],
    rows: usize,
    label: &str,
    level: usize,
) -> Result<(Vec<u32>, Vec<usize>)> {
    let mut local_of: HashMap<usize, u32> = HashMap::new();
    let mut used = Vec::new();
    let mut out = Vec::with_capacity(plane.len());
    for (pixel, v) in plane.iter().enumerate() {
        if *v == -1 {
            out.push(u32::MAX);
            continue;
        }
        let row = usize::try_from(*v)
            .ok()
            .filter(|r| *r < rows)
            .ok_or_else(|| {
                invalid(
                    label,
                    format!("level {level} pixel {pixel}"),
                    format!("value {v}, expected -1 or a feature row < {rows}"),
                )
            })?;
        let next = used.len() as u32;
        let id = *local_of.entry(row).or_insert_with(|| {
            used.push(row);
            next
        });
        out.push(id);
    }
    Ok((out, used))
}

/// The row scaled to unit L2 norm; `None` for a zero or non-finite norm.
fn normalised(row: &[f32]) -> Option<Vec<f32>> {
    let norm = row
        .iter()
        .map(|v| f64::from(*v) * f64::from(*v))
        .sum::<f64>()
        .sqrt();
    (norm.is_finite() && norm > 0.0)
        .then(|| row.iter().map(|v| (f64::from(*v) / norm) as f32).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stems_follow_langsplat() {
        assert_eq!(langsplat_stem("images/frame_00001.jpg"), "frame_00001");
        assert_eq!(langsplat_stem("a.b.png"), "a");
    }

    #[test]
    fn compaction_is_first_appearance_order() {
        let (ids, used) = compact(&[-1, 7, 3, 7, -1, 3, 5], 8, "t", 0).unwrap_or_default();
        assert_eq!(ids, vec![u32::MAX, 0, 1, 0, u32::MAX, 1, 2]);
        assert_eq!(used, vec![7, 3, 5]);
        assert!(compact(&[8], 8, "t", 0).is_err());
        assert!(compact(&[-2], 8, "t", 0).is_err());
    }
}
