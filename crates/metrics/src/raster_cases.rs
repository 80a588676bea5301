//! Polygon cases rasterised by the reference rule, as pixel runs: what `metrics rasterize`
//! prints for the OpenCV agreement test (crates/metrics/python), which fills the same
//! polygons with `cv2.fillPoly` and compares pixel for pixel.

use serde::{Deserialize, Serialize};

use crate::lerf::MAX_SIDE;
use crate::mask::{fill_poly_as, fits_int32, reference_vertices, Mask, OpenCvFill};
use crate::{MetricsError, Result};

/// The input: `{"cases": [{"width", "height", "polygon": [[x, y], ...]}]}`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Cases {
    /// The cases.
    pub cases: Vec<Case>,
}

/// One polygon on a frame.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Case {
    /// Frame width (1..=[`MAX_SIDE`]).
    pub width: u32,
    /// Frame height (1..=[`MAX_SIDE`]).
    pub height: u32,
    /// The vertices as the label files give them.
    pub polygon: Vec<[f64; 2]>,
}

/// One case's mask: its pixel count and its runs `[y, x_begin, x_end)` in row order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Runs {
    /// Selected pixels.
    pub pixels: u64,
    /// `[y, x_begin, x_end]` with `x_end` exclusive.
    pub runs: Vec<[usize; 3]>,
}

/// The rasterised cases.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Report {
    /// Number of cases.
    pub cases: usize,
    /// One mask per case, in order.
    pub masks: Vec<Runs>,
}

/// The runs of selected pixels of each row of a mask.
pub fn runs(m: &Mask) -> Vec<[usize; 3]> {
    let w = (m.width as usize).max(1);
    let mut runs = Vec::new();
    for (y, row) in m.pixels.chunks(w).enumerate() {
        let mut x = 0;
        while x < row.len() {
            if row[x] {
                let begin = x;
                while x < row.len() && row[x] {
                    x += 1;
                }
                runs.push([y, begin, x]);
            } else {
                x += 1;
            }
        }
    }
    runs
}

/// Parses the cases JSON (`path` names it in errors), checks each case and rasterises it
/// with `variant`'s fill rule.
pub fn rasterize_cases(text: &str, path: &str, variant: OpenCvFill) -> Result<Report> {
    let input: Cases = serde_json::from_str(text).map_err(|source| MetricsError::Json {
        path: path.to_string(),
        expected:
            "polygon cases {\"cases\": [{\"width\", \"height\", \"polygon\": [[x, y], ...]}]}",
        source,
    })?;
    let invalid = |field: String, detail: String| MetricsError::Invalid {
        path: path.to_string(),
        field,
        detail,
    };
    let mut masks = Vec::with_capacity(input.cases.len());
    for (i, case) in input.cases.iter().enumerate() {
        if !(1..=MAX_SIDE).contains(&case.width) || !(1..=MAX_SIDE).contains(&case.height) {
            let size = format!("{}x{}", case.width, case.height);
            let detail = format!("{size}, expected each side in 1..={MAX_SIDE}");
            return Err(invalid(format!("cases[{i}]"), detail));
        }
        if let Some(k) = case
            .polygon
            .iter()
            .position(|p| !p.iter().all(|&v| fits_int32(v)))
        {
            let detail = format!("{:?} does not fit int32 after truncation", case.polygon[k]);
            return Err(invalid(format!("cases[{i}].polygon[{k}]"), detail));
        }
        let m = fill_poly_as(
            &reference_vertices(&case.polygon),
            case.width,
            case.height,
            variant,
        );
        masks.push(Runs {
            pixels: m.count(),
            runs: runs(&m),
        });
    }
    Ok(Report {
        cases: masks.len(),
        masks,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_square_is_one_run_per_row_and_bad_cases_name_their_field() {
        let text =
            r#"{"cases": [{"width": 8, "height": 6, "polygon": [[1,1],[4,1],[4,3],[1,3]]}]}"#;
        let r = rasterize_cases(text, "c.json", OpenCvFill::Current).unwrap();
        assert_eq!(r.cases, 1);
        // fillPoly includes the boundary: x 1..=4 on rows 1..=3.
        assert_eq!(r.masks[0].runs, vec![[1, 1, 5], [2, 1, 5], [3, 1, 5]]);
        assert_eq!(r.masks[0].pixels, 12);
        let e = rasterize_cases(
            r#"{"cases": [{"width": 0, "height": 6, "polygon": []}]}"#,
            "c.json",
            OpenCvFill::Current,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("c.json") && e.contains("cases[0]"), "{e}");
        let e = rasterize_cases("{}", "c.json", OpenCvFill::Current)
            .unwrap_err()
            .to_string();
        assert!(e.contains("c.json"), "{e}");
    }
}
