//! The SAM encoder/decoder pair through ONNX Runtime: preprocessing, one embedding per
//! image, one decoder call per point prompt.

use std::path::{Path, PathBuf};
use std::time::Instant;

use ort::session::Session;
use ort::value::{Tensor, TensorRef};

use crate::error::{PrepError, Result};
use crate::image::{resample_planar, RgbImage};
use crate::runtime::{open_session, require_io};

/// Side of SAM's square model input.
pub const INPUT_SIZE: usize = 1024;
/// Channels of the image embedding.
pub const EMBED_DIM: usize = 256;
/// Side of the image embedding grid (one cell per 16 x 16 input pixels).
pub const EMBED_SIDE: usize = 64;
/// SAM's per-channel normalisation on the 0..255 scale.
pub const PIXEL_MEAN: [f32; 3] = [123.675, 116.28, 103.53];
/// SAM's per-channel standard deviation on the 0..255 scale.
pub const PIXEL_STD: [f32; 3] = [58.395, 57.12, 57.375];

/// The size an image is resized to before padding: longest side 1024, the other side
/// `floor(side * 1024 / longest + 0.5)` (SAM's `ResizeLongestSide`).
pub fn resized_size(width: usize, height: usize) -> (usize, usize) {
    let scale = INPUT_SIZE as f64 / width.max(height) as f64;
    let side = |s: usize| ((s as f64 * scale + 0.5).floor() as usize).clamp(1, INPUT_SIZE);
    (side(width), side(height))
}

/// The encoder input [3, 1024, 1024] of an image: bilinear resize (half-pixel centres,
/// no rounding to 8 bits) of the longest side to 1024, zero padding right and bottom (after
/// normalisation, as SAM pads the normalised tensor), per-channel mean/std normalisation.
pub fn preprocess(img: &RgbImage) -> Vec<f32> {
    let (nw, nh) = resized_size(img.width, img.height);
    let plane = INPUT_SIZE * INPUT_SIZE;
    let mut out = vec![0f32; 3 * plane];
    resample_planar(
        img,
        (0, 0, img.width, img.height),
        (nw, nh),
        INPUT_SIZE,
        plane,
        &mut out,
        |c, v| (v - PIXEL_MEAN[c]) / PIXEL_STD[c],
    );
    out
}

/// The image embedding of one view.
#[derive(Debug, Clone)]
pub struct Embedding {
    /// [256, 64, 64] row-major.
    pub data: Vec<f32>,
    /// Width of the image it was computed from.
    pub image_width: usize,
    /// Height of the image it was computed from.
    pub image_height: usize,
}

/// What [`Sam::decode_points`] keeps of a decoded prompt: (point index, mask logits,
/// predicted IoU) to a value or nothing.
pub type KeepFn<'a, T> = dyn Fn(usize, &[f32], f32) -> Option<T> + Sync + 'a;

/// Results of one decoder worker, tagged with their point index.
type Indexed<T> = Vec<(usize, Option<T>)>;

/// A loaded encoder and a pool of decoder sessions (one per worker thread: a session runs
/// one call at a time).
#[derive(Debug)]
pub struct Sam {
    encoder: Session,
    decoders: Vec<Session>,
    encoder_path: PathBuf,
    decoder_path: PathBuf,
}

const DECODER_INPUTS: [&str; 6] = [
    "image_embeddings",
    "point_coords",
    "point_labels",
    "mask_input",
    "has_mask_input",
    "orig_im_size",
];

impl Sam {
    /// Opens both models; the encoder uses `threads` intra-op threads, and `threads`
    /// single-threaded decoder sessions run prompts in parallel.
    pub fn open(
        env: &ort::environment::Environment,
        encoder: &Path,
        decoder: &Path,
        threads: usize,
    ) -> Result<Sam> {
        let threads = threads.max(1);
        let enc = open_session(env, encoder, threads)?;
        require_io(&enc, encoder, &[], &[])?;
        if enc.inputs().len() != 1 || enc.outputs().is_empty() {
            return Err(PrepError::ModelInterface {
                model: encoder.to_path_buf(),
                message: "expected one input [1,3,1024,1024] and an output [1,256,64,64]"
                    .to_string(),
            });
        }
        let mut decoders = Vec::with_capacity(threads);
        for _ in 0..threads {
            let d = open_session(env, decoder, 1)?;
            require_io(&d, decoder, &DECODER_INPUTS, &["masks", "iou_predictions"])?;
            decoders.push(d);
        }
        Ok(Sam {
            encoder: enc,
            decoders,
            encoder_path: encoder.to_path_buf(),
            decoder_path: decoder.to_path_buf(),
        })
    }

    /// Opens the encoder only (for descriptors of existing masks); decoding then fails.
    pub fn open_encoder(
        env: &ort::environment::Environment,
        encoder: &Path,
        threads: usize,
    ) -> Result<Sam> {
        let enc = open_session(env, encoder, threads.max(1))?;
        Ok(Sam {
            encoder: enc,
            decoders: Vec::new(),
            encoder_path: encoder.to_path_buf(),
            decoder_path: PathBuf::new(),
        })
    }

    /// Runs the encoder on one image.
    pub fn encode(&mut self, img: &RgbImage) -> Result<Embedding> {
        let model = self.encoder_path.clone();
        let fail = |action, e: ort::Error| PrepError::Onnx {
            model: model.clone(),
            action,
            message: e.to_string(),
        };
        let input = Tensor::from_array(([1usize, 3, INPUT_SIZE, INPUT_SIZE], preprocess(img)))
            .map_err(|e| fail("cannot make the input tensor", e))?;
        let outputs = self
            .encoder
            .run(ort::inputs![input])
            .map_err(|e| fail("inference failed", e))?;
        let (shape, data) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| fail("output is not a float tensor", e))?;
        let want = [1i64, EMBED_DIM as i64, EMBED_SIDE as i64, EMBED_SIDE as i64];
        if shape.iter().copied().ne(want) {
            return Err(PrepError::ModelInterface {
                model,
                message: format!("encoder output has shape {shape:?}, expected {want:?}"),
            });
        }
        // A broken export (or weights) that yields NaN would otherwise make every mask fail
        // the filters silently: an empty masks file and exit 0.
        if let Some(i) = data.iter().position(|x| !x.is_finite()) {
            return Err(PrepError::ModelInterface {
                model,
                message: format!(
                    "the encoder's output is not finite (value {} at index {i})",
                    data[i]
                ),
            });
        }
        Ok(Embedding {
            data: data.to_vec(),
            image_width: img.width,
            image_height: img.height,
        })
    }

    /// Number of decoder workers.
    pub fn workers(&self) -> usize {
        self.decoders.len()
    }

    /// Decodes one prompt per entry of `points` (image pixels, x right, y down) at mask
    /// size `out` = (height, width) and hands each result (prompt index, mask
    /// logits `out.0 * out.1` row-major, predicted IoU) to `keep`; returns what `keep`
    /// returned, in point order whatever the number of workers.
    pub fn decode_points<T: Send>(
        &mut self,
        emb: &Embedding,
        points: &[Prompt],
        out: (usize, usize),
        keep: &KeepFn<'_, T>,
    ) -> Result<Vec<Option<T>>> {
        let n = self.decoders.len();
        if n == 0 {
            return Err(crate::error::input("SAM", "no decoder was opened"));
        }
        let model = &self.decoder_path;
        let results: Vec<Result<Indexed<T>>> = std::thread::scope(|s| {
            let handles: Vec<_> = self
                .decoders
                .iter_mut()
                .enumerate()
                .map(|(k, session)| {
                    s.spawn(move || {
                        (k..points.len())
                            .step_by(n)
                            .map(|i| {
                                let (logits, iou) =
                                    decode_one(session, model, emb, points[i], out)?;
                                Ok((i, keep(i, &logits, iou)))
                            })
                            .collect::<Result<Vec<_>>>()
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
                .collect()
        });
        let mut all: Vec<Option<T>> = (0..points.len()).map(|_| None).collect();
        for part in results {
            for (i, v) in part? {
                all[i] = v;
            }
        }
        Ok(all)
    }
}

/// A prompt in image pixels: an include point, optionally with a box (x0, y0, x1, y1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prompt {
    /// The include point.
    pub point: (f64, f64),
    /// An optional box around it.
    pub bbox: Option<[f64; 4]>,
}

impl From<(f64, f64)> for Prompt {
    fn from(point: (f64, f64)) -> Prompt {
        Prompt { point, bbox: None }
    }
}

/// One decoder call: the include point plus SAM's padding point (0, 0) with label −1 (or,
/// with a box, the point and the box corners with labels 2 and 3, as SAM's ONNX example
/// does), no mask input, output at `out` = (height, width).
pub fn decode_one(
    session: &mut Session,
    model: &Path,
    emb: &Embedding,
    prompt: Prompt,
    out: (usize, usize),
) -> Result<(Vec<f32>, f32)> {
    let fail = |action, e: ort::Error| PrepError::Onnx {
        model: model.to_path_buf(),
        action,
        message: e.to_string(),
    };
    let (nw, nh) = resized_size(emb.image_width, emb.image_height);
    let sx = nw as f64 / emb.image_width as f64;
    let sy = nh as f64 / emb.image_height as f64;
    let (x, y) = prompt.point;
    let (coords, labels) = match prompt.bbox {
        None => (vec![x * sx, y * sy, 0.0, 0.0], vec![1.0f32, -1.0]),
        Some(b) => (
            vec![x * sx, y * sy, b[0] * sx, b[1] * sy, b[2] * sx, b[3] * sy],
            vec![1.0f32, 2.0, 3.0],
        ),
    };
    let n = labels.len();
    let coords: Vec<f32> = coords.into_iter().map(|c| c as f32).collect();
    let side = EMBED_SIDE;
    let t = |r: ort::Result<Tensor<f32>>| r.map_err(|e| fail("cannot make an input tensor", e));
    let embedding =
        TensorRef::from_array_view(([1usize, EMBED_DIM, side, side], emb.data.as_slice()))
            .map_err(|e| fail("cannot make an input tensor", e))?;
    let inputs = ort::inputs![
        "image_embeddings" => embedding,
        "point_coords" => t(Tensor::from_array(([1usize, n, 2], coords)))?,
        "point_labels" => t(Tensor::from_array(([1usize, n], labels)))?,
        "mask_input" => t(Tensor::from_array(([1usize, 1, 256, 256], vec![0f32; 256 * 256])))?,
        "has_mask_input" => t(Tensor::from_array(([1usize], vec![0f32])))?,
        "orig_im_size" => t(Tensor::from_array(([2usize], vec![out.0 as f32, out.1 as f32])))?,
    ];
    let outputs = session
        .run(inputs)
        .map_err(|e| fail("inference failed", e))?;
    let (shape, masks) = outputs["masks"]
        .try_extract_tensor::<f32>()
        .map_err(|e| fail("`masks` is not a float tensor", e))?;
    if masks.len() != out.0 * out.1 {
        return Err(PrepError::ModelInterface {
            model: model.to_path_buf(),
            message: format!(
                "`masks` has shape {shape:?}, expected [1, 1, {}, {}] (one mask per prompt)",
                out.0, out.1
            ),
        });
    }
    let (_, iou) = outputs["iou_predictions"]
        .try_extract_tensor::<f32>()
        .map_err(|e| fail("`iou_predictions` is not a float tensor", e))?;
    let iou = iou.first().copied().unwrap_or(0.0);
    if !iou.is_finite() || masks.iter().any(|x| !x.is_finite()) {
        return Err(PrepError::ModelInterface {
            model: model.to_path_buf(),
            message: "the decoder's mask logits or predicted IoU are not finite".to_string(),
        });
    }
    Ok((masks.to_vec(), iou))
}

/// Seconds since `t`.
pub(crate) fn secs(t: Instant) -> f64 {
    t.elapsed().as_secs_f64()
}
