//! CLIP ONNX exports: mask crops embedded by an image encoder, text prompts embedded by a
//! text encoder after CLIP's BPE tokenisation.
//!
//! The interface is that of the Hugging Face exports of `CLIPVisionModelWithProjection`
//! (input `pixel_values` f32 [N, 3, 224, 224], output `image_embeds` [N, D]) and
//! `CLIPTextModelWithProjection` (input `input_ids` i64 [N, 77], optional
//! `attention_mask` i64 [N, 77], output `text_embeds` [N, D]). A model with a single input
//! is driven through it whatever its name, and without the named output its first output
//! is used, which must be [N, D].

use std::path::{Path, PathBuf};

use instant_clip_tokenizer::{Token, Tokenizer};
use ort::session::Session;
use ort::value::Tensor;
use profuse_formats::label_space::CANONICAL_NEGATIVES;
use profuse_formats::Prompts;

use crate::error::{input, PrepError, Result};
use crate::image::{taps, RgbImage};
use crate::runtime::{io_names, open_session};

/// CLIP's text context length.
pub const CONTEXT: usize = 77;
/// CLIP's image input side.
pub const IMAGE_SIZE: usize = 224;
/// CLIP's per-channel mean on the 0..1 scale.
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
/// CLIP's per-channel standard deviation on the 0..1 scale.
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_6, 0.275_777_1];

/// CLIP token ids of `text`: start-of-text, the BPE tokens (truncated to fit), end-of-text,
/// zero padding to `CONTEXT` (OpenAI's `clip.tokenize`).
pub fn tokenize(tokenizer: &Tokenizer, text: &str) -> Vec<i64> {
    let mut tokens = vec![tokenizer.start_of_text()];
    tokenizer.encode(text, &mut tokens);
    tokens.truncate(CONTEXT - 1);
    tokens.push(tokenizer.end_of_text());
    let mut ids: Vec<i64> = tokens
        .into_iter()
        .map(|t: Token| i64::from(t.to_u16()))
        .collect();
    ids.resize(CONTEXT, 0);
    ids
}

/// The crop of one mask as LangSplat/Dr. Splat's preprocessing makes it: the image with
/// every pixel outside the mask set to black, cropped to the mask's bounding box, padded to
/// a square with black (centred), resized bilinearly to 224 x 224, normalised with CLIP's
/// mean/std on the 0..1 scale. `inside(x, y)` says whether image pixel (x, y) is in the
/// mask; `bbox` is its inclusive box in image pixels. Planar [3, 224, 224].
pub fn image_input(
    img: &RgbImage,
    bbox: [usize; 4],
    inside: &dyn Fn(usize, usize) -> bool,
) -> Vec<f32> {
    let (x0, y0) = (bbox[0], bbox[1]);
    let (w, h) = (bbox[2] + 1 - x0, bbox[3] + 1 - y0);
    let side = w.max(h);
    // Offsets of the crop inside the square canvas (integer division, as LangSplat's pad).
    let (ox, oy) = ((side - w) / 2, (side - h) / 2);
    let value = |cx: usize, cy: usize, c: usize| -> f32 {
        if cx < ox || cy < oy || cx >= ox + w || cy >= oy + h {
            return 0.0;
        }
        let (x, y) = (x0 + cx - ox, y0 + cy - oy);
        if inside(x, y) {
            f32::from(img.at(x, y, c))
        } else {
            0.0
        }
    };
    let t = taps(side, IMAGE_SIZE);
    let plane = IMAGE_SIZE * IMAGE_SIZE;
    let mut out = vec![0f32; 3 * plane];
    for (oy_, &(ya, yb, fy)) in t.iter().enumerate() {
        for (ox_, &(xa, xb, fx)) in t.iter().enumerate() {
            for c in 0..3 {
                let top = value(xa, ya, c) * (1.0 - fx) + value(xb, ya, c) * fx;
                let bottom = value(xa, yb, c) * (1.0 - fx) + value(xb, yb, c) * fx;
                let v = (top * (1.0 - fy) + bottom * fy) / 255.0;
                out[c * plane + oy_ * IMAGE_SIZE + ox_] = (v - CLIP_MEAN[c]) / CLIP_STD[c];
            }
        }
    }
    out
}

/// A CLIP encoder session (image or text side).
#[derive(Debug)]
pub struct ClipModel {
    session: Session,
    path: PathBuf,
    input: String,
    attention_mask: bool,
    output: String,
}

impl ClipModel {
    /// Opens an image (`text = false`) or text encoder and checks its interface.
    pub fn open(
        env: &ort::environment::Environment,
        path: &Path,
        text: bool,
        threads: usize,
    ) -> Result<ClipModel> {
        let session = open_session(env, path, threads)?;
        let (inputs, outputs) = io_names(&session);
        let (want_in, want_out) = if text {
            ("input_ids", "text_embeds")
        } else {
            ("pixel_values", "image_embeds")
        };
        let bad = |message: String| PrepError::ModelInterface {
            model: path.to_path_buf(),
            message,
        };
        let input = if inputs.iter().any(|n| n == want_in) {
            want_in.to_string()
        } else if inputs.len() == 1 {
            inputs[0].clone()
        } else {
            return Err(bad(format!("no input `{want_in}` among {inputs:?}")));
        };
        let attention_mask = text && inputs.iter().any(|n| n == "attention_mask");
        let extra = inputs.len() - 1 - usize::from(attention_mask);
        if extra > 0 {
            return Err(bad(format!(
                "inputs {inputs:?}: expected only `{want_in}`{}",
                if text { " and `attention_mask`" } else { "" }
            )));
        }
        let output = if outputs.iter().any(|n| n == want_out) {
            want_out.to_string()
        } else {
            outputs
                .first()
                .cloned()
                .ok_or_else(|| bad("the model has no output".to_string()))?
        };
        Ok(ClipModel {
            session,
            path: path.to_path_buf(),
            input,
            attention_mask,
            output,
        })
    }

    /// Embeds one image input ([3, 224, 224]) and returns the L2-normalised vector.
    pub fn embed_image(&mut self, pixels: Vec<f32>) -> Result<Vec<f32>> {
        let t = Tensor::from_array(([1usize, 3, IMAGE_SIZE, IMAGE_SIZE], pixels))
            .map_err(|e| self.fail("cannot make the input", e))?;
        let inputs = ort::inputs![self.input.clone() => t];
        self.run_one(inputs)
    }

    /// Embeds one token sequence ([77] ids) and returns the L2-normalised vector.
    pub fn embed_tokens(&mut self, ids: Vec<i64>) -> Result<Vec<f32>> {
        let mask: Vec<i64> = ids
            .iter()
            .enumerate()
            .map(|(i, t)| i64::from(*t != 0 || i == 0))
            .collect();
        let t = Tensor::from_array(([1usize, CONTEXT], ids))
            .map_err(|e| self.fail("cannot make the input", e))?;
        let mut inputs = ort::inputs![self.input.clone() => t];
        if self.attention_mask {
            let m = Tensor::from_array(([1usize, CONTEXT], mask))
                .map_err(|e| self.fail("cannot make the input", e))?;
            inputs.push(("attention_mask".into(), m.into()));
        }
        self.run_one(inputs)
    }

    fn fail(&self, action: &'static str, e: ort::Error) -> PrepError {
        PrepError::Onnx {
            model: self.path.clone(),
            action,
            message: e.to_string(),
        }
    }

    fn run_one(
        &mut self,
        inputs: Vec<(
            std::borrow::Cow<'_, str>,
            ort::session::SessionInputValue<'_>,
        )>,
    ) -> Result<Vec<f32>> {
        let outputs = self.session.run(inputs).map_err(|e| PrepError::Onnx {
            model: self.path.clone(),
            action: "inference failed",
            message: e.to_string(),
        })?;
        let (shape, data) = outputs[self.output.as_str()]
            .try_extract_tensor::<f32>()
            .map_err(|e| PrepError::Onnx {
                model: self.path.clone(),
                action: "the output is not a float tensor",
                message: e.to_string(),
            })?;
        if shape.len() != 2 || shape[0] != 1 || data.is_empty() {
            return Err(PrepError::ModelInterface {
                model: self.path.clone(),
                message: format!(
                    "output `{}` has shape {shape:?}, expected [1, D]",
                    self.output
                ),
            });
        }
        normalized(data.to_vec()).ok_or_else(|| PrepError::ModelInterface {
            model: self.path.clone(),
            message: format!("output `{}` is zero or not finite", self.output),
        })
    }
}

/// `v / |v|`, `None` for a zero or non-finite vector.
pub fn normalized(mut v: Vec<f32>) -> Option<Vec<f32>> {
    let n = v
        .iter()
        .map(|x| f64::from(*x) * f64::from(*x))
        .sum::<f64>()
        .sqrt();
    if !(n.is_finite() && n > 0.0) {
        return None;
    }
    v.iter_mut().for_each(|x| *x = (f64::from(*x) / n) as f32);
    Some(v)
}

/// The prompt names: the user's texts (trimmed, in order, duplicates removed), then the
/// LERF canonical negatives that are not among them.
pub fn prompt_names(texts: &[String]) -> Result<Vec<String>> {
    let mut names: Vec<String> = Vec::new();
    for t in texts {
        let t = t.trim();
        if t.is_empty() {
            return Err(input("prompt text", "is empty"));
        }
        if !names.iter().any(|n| n == t) {
            names.push(t.to_string());
        }
    }
    for neg in CANONICAL_NEGATIVES {
        if !names.iter().any(|n| n == neg) {
            names.push(neg.to_string());
        }
    }
    Ok(names)
}

/// Embeds the prompt texts (plus the canonical negatives) with a text encoder.
pub fn make_prompts(model: &mut ClipModel, texts: &[String]) -> Result<Prompts> {
    let tokenizer = Tokenizer::new();
    let names = prompt_names(texts)?;
    let mut embeddings = Vec::new();
    let mut dim = 0;
    for name in &names {
        let e = model.embed_tokens(tokenize(&tokenizer, name))?;
        dim = e.len();
        embeddings.extend(e);
    }
    let negatives = CANONICAL_NEGATIVES.len();
    let user = names.len()
        - names
            .iter()
            .filter(|n| CANONICAL_NEGATIVES.contains(&n.as_str()))
            .count();
    let _ = negatives;
    let prompts = Prompts {
        class_ids: None,
        dim,
        embeddings: embeddings.into(),
        extra: [
            (
                "generator".to_string(),
                "prep prompts (CLIP text encoder)".to_string(),
            ),
            ("user_prompts".to_string(), user.to_string()),
        ]
        .into(),
        names,
    };
    Ok(prompts)
}
