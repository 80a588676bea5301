//! COLMAP text model: `cameras.txt`, `images.txt`, `points3D.txt` (the layout of COLMAP's
//! `scripts/python/read_write_model.py`). Lines starting with `#` are comments.

use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;

use super::model::{insert_camera, CameraModel, ColmapCamera, ColmapImage, ColmapPoint};
use crate::error::{parse_err, unsupported, Result};
use crate::fsutil::{read_text_capped, show};

/// Whitespace-separated fields of one line, parsed with errors naming file, line, field.
struct Fields<'a> {
    tokens: std::str::SplitAsciiWhitespace<'a>,
    label: &'a str,
    line: usize,
}

impl<'a> Fields<'a> {
    fn new(text: &'a str, label: &'a str, line: usize) -> Self {
        Fields {
            tokens: text.split_ascii_whitespace(),
            label,
            line,
        }
    }

    fn next<T: FromStr>(&mut self, field: &str, expected: &str) -> Result<T> {
        let token = self.tokens.next();
        token.and_then(|t| t.parse().ok()).ok_or_else(|| {
            parse_err(
                self.label,
                self.line,
                field,
                expected,
                token.unwrap_or("end of line"),
            )
        })
    }

    fn f64(&mut self, field: &str) -> Result<f64> {
        let v: f64 = self.next(field, "a number")?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(parse_err(
                self.label,
                self.line,
                field,
                "a finite number",
                v.to_string(),
            ))
        }
    }

    fn word(&mut self, field: &str) -> Result<&'a str> {
        self.tokens
            .next()
            .ok_or_else(|| parse_err(self.label, self.line, field, "a value", "end of line"))
    }

    fn done(&mut self, what: &str) -> Result<()> {
        match self.tokens.next() {
            None => Ok(()),
            Some(t) => Err(parse_err(self.label, self.line, what, "end of line", t)),
        }
    }

    fn is_done(&self) -> bool {
        self.tokens.clone().next().is_none()
    }
}

/// Numbered lines that are neither empty nor comments.
fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

pub(crate) fn read_cameras(path: &Path, max_bytes: u64) -> Result<BTreeMap<u32, ColmapCamera>> {
    let label = show(path);
    let text = read_text_capped(path, max_bytes, " (raise it with --max-text-mb)")?;
    let mut cameras = BTreeMap::new();
    for (line, content) in content_lines(&text) {
        let mut f = Fields::new(content, &label, line);
        let id: u32 = f.next("CAMERA_ID", "a camera id (unsigned integer)")?;
        let model_name = f.word("MODEL")?;
        let model = CameraModel::from_name(model_name).ok_or_else(|| {
            unsupported(
                &label,
                "camera model",
                format!("line {line}: {model_name:?} is not a COLMAP camera model"),
            )
        })?;
        let width: u64 = f.next("WIDTH", "a width in pixels")?;
        let height: u64 = f.next("HEIGHT", "a height in pixels")?;
        let params = (0..model.num_params())
            .map(|i| f.f64(&format!("PARAMS[{i}] of {}", model.name())))
            .collect::<Result<Vec<_>>>()?;
        f.done(&format!(
            "{} parameters of {}",
            model.num_params(),
            model.name()
        ))?;
        insert_camera(
            &mut cameras,
            ColmapCamera {
                id,
                model,
                width,
                height,
                params,
            },
            &label,
            format!("line {line}: CAMERA_ID"),
        )?;
    }
    Ok(cameras)
}

pub(crate) fn read_images(path: &Path, max_bytes: u64) -> Result<Vec<ColmapImage>> {
    let label = show(path);
    let text = read_text_capped(path, max_bytes, " (raise it with --max-text-mb)")?;
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l));
    let mut images = Vec::new();
    // As in COLMAP's reader: after an image line, the next line holds its points2D,
    // even when it is empty (an image without keypoints).
    while let Some((line, raw)) = lines.next() {
        let content = raw.trim();
        if content.is_empty() || content.starts_with('#') {
            continue;
        }
        let mut f = Fields::new(content, &label, line);
        let id: u32 = f.next("IMAGE_ID", "an image id (unsigned integer)")?;
        let mut qvec = [0.0; 4];
        for (slot, name) in qvec.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *slot = f.f64(name)?;
        }
        let mut tvec = [0.0; 3];
        for (slot, name) in tvec.iter_mut().zip(["TX", "TY", "TZ"]) {
            *slot = f.f64(name)?;
        }
        let camera_id: u32 = f.next("CAMERA_ID", "a camera id (unsigned integer)")?;
        // The name is the rest of the line: COLMAP names do not contain spaces, but keep
        // any so that the error (a missing image) names the real file.
        let name = f.tokens.clone().collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(parse_err(
                &label,
                line,
                "NAME",
                "an image name",
                "end of line",
            ));
        }
        let (points_line, points_text) = lines.next().unwrap_or((line + 1, ""));
        let points2d = parse_points2d(points_text, &label, points_line)?;
        images.push(ColmapImage {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        });
    }
    Ok(images)
}

fn parse_points2d(text: &str, label: &str, line: usize) -> Result<Vec<([f64; 2], i64)>> {
    let mut f = Fields::new(text, label, line);
    let mut points = Vec::new();
    while !f.is_done() {
        let i = points.len();
        let x = f.f64(&format!("POINTS2D[{i}].X"))?;
        let y = f.f64(&format!("POINTS2D[{i}].Y"))?;
        let id: i64 = f.next(&format!("POINTS2D[{i}].POINT3D_ID"), "a point3D id or -1")?;
        points.push(([x, y], id));
    }
    Ok(points)
}

pub(crate) fn read_points(path: &Path, max_bytes: u64) -> Result<Vec<ColmapPoint>> {
    let label = show(path);
    let text = read_text_capped(path, max_bytes, " (raise it with --max-text-mb)")?;
    let mut points = Vec::new();
    for (line, content) in content_lines(&text) {
        let mut f = Fields::new(content, &label, line);
        let id: u64 = f.next("POINT3D_ID", "a point id (unsigned integer)")?;
        let xyz = [f.f64("X")?, f.f64("Y")?, f.f64("Z")?];
        let mut rgb = [0u8; 3];
        for (slot, name) in rgb.iter_mut().zip(["R", "G", "B"]) {
            *slot = f.next(name, "a colour value 0..255")?;
        }
        let error = f.f64("ERROR")?;
        let mut track = Vec::new();
        while !f.is_done() {
            let i = track.len();
            let image: u32 = f.next(&format!("TRACK[{i}].IMAGE_ID"), "an image id")?;
            let idx: u32 = f.next(&format!("TRACK[{i}].POINT2D_IDX"), "a keypoint index")?;
            track.push((image, idx));
        }
        points.push(ColmapPoint {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(points)
}
