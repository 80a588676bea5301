//! Render-versus-photo comparison: PSNR over the covered pixels, and a side-by-side image.

/// A [0, 1] colour channel as 8 bits (clamped, rounded).
pub fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// PSNR in dB (8-bit peak 255) of an RGB8 render against an RGB8 photo of the same size,
/// over the pixels whose accumulated alpha exceeds 0.5; `None` when no pixel is covered,
/// infinity when they agree exactly.
///
/// # Panics
/// When the three buffers do not describe the same number of pixels.
pub fn psnr_covered(render: &[u8], photo: &[u8], alpha: &[f32]) -> Option<f64> {
    assert!(render.len() == photo.len() && render.len() == 3 * alpha.len());
    let (mut se, mut n) = (0.0f64, 0usize);
    for ((r, p), a) in render.chunks_exact(3).zip(photo.chunks_exact(3)).zip(alpha) {
        if *a > 0.5 {
            se += r
                .iter()
                .zip(p)
                .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
                .sum::<f64>();
            n += 1;
        }
    }
    (n > 0).then(|| {
        let mse = se / (3 * n) as f64;
        if mse > 0.0 {
            10.0 * (255.0f64 * 255.0 / mse).log10()
        } else {
            f64::INFINITY
        }
    })
}

/// Two RGB8 images of `width` x `height` side by side (`left` on the left): an RGB8 image
/// of `2 width` x `height`.
pub fn side_by_side(left: &[u8], right: &[u8], width: usize, height: usize) -> Vec<u8> {
    let row = 3 * width;
    let mut out = Vec::with_capacity(2 * row * height);
    for y in 0..height {
        out.extend_from_slice(&left[y * row..(y + 1) * row]);
        out.extend_from_slice(&right[y * row..(y + 1) * row]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_a_uniform_error_is_the_closed_form() {
        // Every covered channel off by 5: MSE 25, PSNR = 10 log10(255² / 25).
        let render = [10u8, 20, 30, 0, 0, 0];
        let photo = [15u8, 25, 35, 200, 200, 200];
        let alpha = [0.9f32, 0.1];
        let psnr = psnr_covered(&render, &photo, &alpha).unwrap_or(0.0);
        assert!((psnr - 10.0 * (255.0f64 * 255.0 / 25.0).log10()).abs() < 1e-12);
        assert_eq!(psnr_covered(&render, &photo, &[0.0, 0.5]), None);
        assert_eq!(psnr_covered(&render, &render, &alpha), Some(f64::INFINITY));
    }

    #[test]
    fn side_by_side_interleaves_rows_and_to_u8_clamps() {
        let l = [1u8, 1, 1, 2, 2, 2];
        let r = [9u8, 9, 9, 8, 8, 8];
        assert_eq!(
            side_by_side(&l, &r, 1, 2),
            vec![1, 1, 1, 9, 9, 9, 2, 2, 2, 8, 8, 8]
        );
        assert_eq!((to_u8(-1.0), to_u8(0.5), to_u8(2.0)), (0, 128, 255));
    }
}
