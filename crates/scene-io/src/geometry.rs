//! Pose conversions shared by the camera importers (quaternions, projection and lens
//! math live in [`profuse_formats::camera`]).

use nalgebra::Matrix3;

/// A 3x3 matrix, row-major.
pub use profuse_formats::camera::Mat3;

/// Largest entry of |MᵀM − I| for which a rotation read from a text file is snapped to
/// the nearest rotation; beyond it the matrix is not a rotation and import fails. Text
/// formats print 6 to 17 digits, so genuine rotations deviate by ~1e-6 at most.
pub const REORTHONORMALIZE_TOLERANCE: f64 = 1e-3;

/// Deviation below which a matrix is taken as an exact rotation and left untouched.
const EXACT_ROTATION_DEVIATION: f64 = 8.0 * f64::EPSILON;

/// Largest entry of |MᵀM − I|.
pub fn orthonormality_error(m: &Mat3) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((dot - want).abs());
        }
    }
    worst
}

/// Determinant of a 3x3 matrix.
pub fn determinant(m: &Mat3) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Why a matrix could not be accepted as a rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NotARotation {
    /// |MᵀM − I| exceeds [`REORTHONORMALIZE_TOLERANCE`] (the value is the deviation).
    NotOrthonormal(f64),
    /// A reflection (determinant ≤ 0) or non-finite entries.
    Reflection(f64),
}

impl std::fmt::Display for NotARotation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NotARotation::NotOrthonormal(d) => write!(
                f,
                "rotation is not orthonormal (largest |RᵀR − I| entry {d:.3e}, tolerance {REORTHONORMALIZE_TOLERANCE:e})"
            ),
            NotARotation::Reflection(det) => {
                write!(f, "rotation has determinant {det:.6}, expected +1 (a reflection or non-finite)")
            }
        }
    }
}

/// The nearest rotation (polar decomposition via SVD: U Vᵀ) of a matrix that is within
/// [`REORTHONORMALIZE_TOLERANCE`] of orthonormal with positive determinant.
pub fn snap_to_rotation(m: &Mat3) -> Result<Mat3, NotARotation> {
    let det = determinant(m);
    if !det.is_finite() || det <= 0.0 {
        return Err(NotARotation::Reflection(det));
    }
    let deviation = orthonormality_error(m);
    if deviation > REORTHONORMALIZE_TOLERANCE {
        return Err(NotARotation::NotOrthonormal(deviation));
    }
    if deviation <= EXACT_ROTATION_DEVIATION {
        // Already a rotation to rounding: keep the input bits (an SVD would only add noise).
        return Ok(*m);
    }
    let a = Matrix3::from_fn(|i, j| m[i][j]);
    let svd = a.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(NotARotation::NotOrthonormal(deviation));
    };
    let r = u * v_t;
    Ok(std::array::from_fn(|i| std::array::from_fn(|j| r[(i, j)])))
}

/// World-to-camera `[R | t]` row-major (our `world_to_camera` row) from a camera-to-world
/// rotation and camera centre: R = R_c2wᵀ, t = −R C.
pub fn world_to_camera_from_c2w(r_c2w: &Mat3, centre: [f64; 3]) -> [f64; 12] {
    let mut out = [0.0; 12];
    for i in 0..3 {
        let row = [r_c2w[0][i], r_c2w[1][i], r_c2w[2][i]];
        let t = -(row[0] * centre[0] + row[1] * centre[1] + row[2] * centre[2]);
        out[i * 4] = row[0];
        out[i * 4 + 1] = row[1];
        out[i * 4 + 2] = row[2];
        out[i * 4 + 3] = t;
    }
    out
}

/// A 4x4 row-major matrix product.
pub fn mat4_mul(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..4).map(|k| a[i][k] * b[k][j]).sum()))
}

/// The rotation block of a 4x4 matrix.
pub fn rotation_block(m: &[[f64; 4]; 4]) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| m[i][j]))
}

/// The translation column of a 4x4 matrix.
pub fn translation_column(m: &[[f64; 4]; 4]) -> [f64; 3] {
    [m[0][3], m[1][3], m[2][3]]
}

#[cfg(test)]
mod tests {
    use profuse_formats::camera::quaternion_to_rotation;

    use super::*;

    #[test]
    fn snapping_fixes_small_noise_and_rejects_large() {
        let noisy = [[1.0, 2e-5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0 + 1e-5]];
        let r = snap_to_rotation(&noisy).unwrap_or_default();
        assert!(orthonormality_error(&r) < 1e-12);
        let bad = [[1.1, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(matches!(
            snap_to_rotation(&bad),
            Err(NotARotation::NotOrthonormal(_))
        ));
        let mirror = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(matches!(
            snap_to_rotation(&mirror),
            Err(NotARotation::Reflection(_))
        ));
    }

    #[test]
    fn c2w_inversion_maps_centre_to_origin() {
        let r = quaternion_to_rotation([0.9, 0.1, -0.3, 0.2]).unwrap_or_default();
        let c = [1.0, -2.0, 3.0];
        let w2c = world_to_camera_from_c2w(&r, c);
        for i in 0..3 {
            let x =
                w2c[i * 4] * c[0] + w2c[i * 4 + 1] * c[1] + w2c[i * 4 + 2] * c[2] + w2c[i * 4 + 3];
            assert!(x.abs() < 1e-12);
        }
    }
}
