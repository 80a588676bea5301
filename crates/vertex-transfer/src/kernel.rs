//! The per-Gaussian pieces of the transfer kernel: the Mahalanobis metric of the
//! Gaussian's own covariance, its opacity, and its class probabilities.

use profuse_formats::camera::quaternion_to_rotation;

use crate::classes::ClassSet;

/// The descriptor dot product (f32, fixed summation order), shared with query.
pub use profuse_pq::dot;

/// One Gaussian prepared for gating: d² = |W (x − μ)|² with W = S⁻¹ Rᵀ, which is
/// (x − μ)ᵀ Σ⁻¹ (x − μ) for Σ = R S Sᵀ Rᵀ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kernel {
    /// Centre μ.
    pub mean: [f32; 3],
    /// Whitening matrix W = S⁻¹ Rᵀ, row-major: row i is the i-th local axis / scale i.
    pub whiten: [[f32; 3]; 3],
    /// Opacity in [0, 1].
    pub opacity: f32,
}

impl Kernel {
    /// Builds the kernel of a Gaussian in the INRIA parameterisation: log-scales,
    /// quaternion (w, x, y, z) normalised here (the zero quaternion becomes the identity),
    /// opacity logit. Each standard deviation is clamped to at least `min_scale`, so flat
    /// or underflowing axes stay invertible.
    pub fn new(
        mean: [f32; 3],
        log_scales: [f32; 3],
        rotation: [f32; 4],
        opacity_logit: f32,
        min_scale: f32,
    ) -> Kernel {
        let r = rotation_matrix(rotation);
        let floor = f64::from(min_scale);
        let mut whiten = [[0.0f32; 3]; 3];
        for (axis, row) in whiten.iter_mut().enumerate() {
            let s = f64::from(log_scales[axis]).exp().max(floor);
            for (k, w) in row.iter_mut().enumerate() {
                // Row `axis` of Rᵀ is column `axis` of R.
                *w = (r[k][axis] / s) as f32;
            }
        }
        Kernel {
            mean,
            whiten,
            opacity: sigmoid(opacity_logit),
        }
    }

    /// Squared Mahalanobis distance of `x` under this Gaussian's covariance.
    #[inline]
    pub fn mahalanobis_sq(&self, x: [f32; 3]) -> f32 {
        let d = [
            x[0] - self.mean[0],
            x[1] - self.mean[1],
            x[2] - self.mean[2],
        ];
        self.whiten
            .iter()
            .map(|row| {
                let u = row[0] * d[0] + row[1] * d[1] + row[2] * d[2];
                u * u
            })
            .sum()
    }

    /// The kernel weight exp(−d²/2) · opacity for a squared distance `d2`.
    #[inline]
    pub fn weight(&self, d2: f32) -> f32 {
        (-0.5 * d2).exp() * self.opacity
    }
}

/// Rotation matrix of a quaternion (w, x, y, z), normalised in f64; the zero (or
/// non-finite) quaternion gives the identity.
pub fn rotation_matrix(q: [f32; 4]) -> [[f64; 3]; 3] {
    quaternion_to_rotation(q.map(f64::from)).unwrap_or([
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ])
}

/// Opacity 1 / (1 + exp(−logit)), evaluated in f64 (±inf logits give 1 and 0).
pub fn sigmoid(logit: f32) -> f32 {
    (1.0 / (1.0 + (-f64::from(logit)).exp())) as f32
}

/// Writes the class probabilities of one descriptor into `out` (one per class): the
/// softmax over class prompts of cos(descriptor, prompt) / temperature, summed per class.
/// The descriptor need not be unit length (decoded PQ codes are not); a zero descriptor
/// has cosine 0 to every prompt.
///
/// # Panics
/// If `out` is shorter than the number of classes (`descriptor` must hold D values).
pub fn class_probabilities(
    descriptor: &[f32],
    classes: &ClassSet,
    temperature: f32,
    logits: &mut Vec<f64>,
    out: &mut [f32],
) {
    let norm = f64::from(dot(descriptor, descriptor)).sqrt();
    let inv = if norm > 0.0 { 1.0 / norm } else { 0.0 };
    let t = f64::from(temperature);
    logits.clear();
    logits.extend(
        (0..classes.prompts())
            .map(|q| f64::from(dot(descriptor, classes.prompt_embedding(q))) * inv / t),
    );
    let max = logits.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut total = 0.0;
    for l in logits.iter_mut() {
        *l = (*l - max).exp();
        total += *l;
    }
    out.iter_mut().for_each(|o| *o = 0.0);
    for (q, e) in logits.iter().enumerate() {
        out[classes.prompt_class(q)] += (e / total) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_matrix_is_orthonormal_and_rotates_about_z() {
        let h = std::f32::consts::FRAC_1_SQRT_2;
        // 90° about z, given unnormalised (scaled by 3).
        let r = rotation_matrix([3.0 * h, 0.0, 0.0, 3.0 * h]);
        let expected = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        for i in 0..3 {
            for j in 0..3 {
                assert!((r[i][j] - expected[i][j]).abs() < 1e-6, "{r:?}");
            }
        }
        assert_eq!(rotation_matrix([0.0; 4])[1], [0.0, 1.0, 0.0]);
    }

    #[test]
    fn sigmoid_handles_extreme_logits() {
        assert_eq!(sigmoid(f32::INFINITY), 1.0);
        assert_eq!(sigmoid(f32::NEG_INFINITY), 0.0);
        assert!((sigmoid(0.0) - 0.5).abs() < 1e-7);
    }

    #[test]
    fn degenerate_scales_are_clamped_to_the_minimum() {
        // log-scale −200 underflows to 0 in f64; the clamp keeps W finite.
        let k = Kernel::new(
            [0.0; 3],
            [-200.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            1e-3,
        );
        assert!((k.whiten[0][0] - 1000.0).abs() < 1e-3);
        assert!((k.mahalanobis_sq([1e-3, 0.0, 0.0]) - 1.0).abs() < 1e-6);
        assert!((k.mahalanobis_sq([0.0, 2.0, 0.0]) - 4.0).abs() < 1e-6);
        // A huge scale makes the axis free: d² does not grow along it.
        let k = Kernel::new([0.0; 3], [1e30, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], 0.0, 1e-3);
        assert_eq!(k.mahalanobis_sq([1e6, 0.0, 0.0]), 0.0);
    }
}
