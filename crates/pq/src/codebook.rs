//! The codebook: M sub-quantisers of 256 centroids each, nearest-centroid encoding and
//! concatenating decode.

use std::collections::BTreeMap;

use profuse_formats::{Features, Pq, KSUB};
use rayon::prelude::*;

use crate::PqError;

/// Vectors encoded per rayon task: large enough to amortise scheduling, small enough to
/// balance two cores on small inputs.
const ENCODE_CHUNK: usize = 1024;

/// A product quantiser's centroids, `[M, 256, dsub]` in faiss's
/// `ProductQuantizer.centroids` layout, plus a transposed copy `[M, dsub, 256]` that
/// lets the nearest-centroid search run over 256 centroids in SIMD lanes.
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    m: usize,
    dsub: usize,
    centroids: Vec<f32>,
    transposed: Vec<f32>,
    metadata: BTreeMap<String, String>,
}

impl Codebook {
    /// A codebook from raw centroids `[m, 256, dsub]` (faiss layout).
    pub fn new(m: usize, dsub: usize, centroids: Vec<f32>) -> Result<Self, PqError> {
        if m == 0 || dsub == 0 {
            return Err(PqError::Inconsistent(format!(
                "m = {m} and dsub = {dsub} must both be >= 1"
            )));
        }
        if centroids.len() != m * KSUB * dsub {
            return Err(PqError::Inconsistent(format!(
                "{} centroid values, expected m x 256 x dsub = {}",
                centroids.len(),
                m * KSUB * dsub
            )));
        }
        if let Some(i) = centroids.iter().position(|v| !v.is_finite()) {
            return Err(PqError::Inconsistent(format!(
                "centroid value {i} is not finite"
            )));
        }
        let transposed = transpose(&centroids, m, dsub);
        Ok(Codebook {
            m,
            dsub,
            centroids,
            transposed,
            metadata: BTreeMap::new(),
        })
    }

    /// The codebook of a pq file (its training metadata comes along).
    pub fn from_pq(pq: &Pq) -> Result<Self, PqError> {
        let mut cb = Codebook::new(pq.m, pq.dsub, pq.centroids.to_vec())?;
        cb.metadata = pq.extra.clone();
        Ok(cb)
    }

    /// Number of sub-quantisers M.
    pub fn m(&self) -> usize {
        self.m
    }

    /// Sub-vector dimension dsub = D / M.
    pub fn dsub(&self) -> usize {
        self.dsub
    }

    /// Full dimension D = M x dsub.
    pub fn dim(&self) -> usize {
        self.m * self.dsub
    }

    /// All centroids, `[M, 256, dsub]`.
    pub fn centroids(&self) -> &[f32] {
        &self.centroids
    }

    /// Centroid `k` of sub-quantiser `m`.
    pub fn centroid(&self, m: usize, k: usize) -> &[f32] {
        let start = (m * KSUB + k) * self.dsub;
        &self.centroids[start..start + self.dsub]
    }

    /// Metadata written into pq files made with this codebook (training parameters).
    pub fn metadata(&self) -> &BTreeMap<String, String> {
        &self.metadata
    }

    /// Mutable access to that metadata.
    pub fn metadata_mut(&mut self) -> &mut BTreeMap<String, String> {
        &mut self.metadata
    }

    /// Encodes one vector of D values into M codes: per sub-vector the centroid with the
    /// smallest squared L2 distance, the lower index on ties.
    ///
    /// # Panics
    /// If `x.len() != D` or `code.len() != M`.
    pub fn encode(&self, x: &[f32], code: &mut [u8]) {
        assert_eq!(x.len(), self.dim(), "vector length");
        assert_eq!(code.len(), self.m, "code length");
        match EncodeLevel::detect() {
            #[cfg(target_arch = "x86_64")]
            EncodeLevel::Avx512 => wide::encode_avx512(self, x, code),
            #[cfg(target_arch = "x86_64")]
            EncodeLevel::Avx2 => wide::encode_avx2(self, x, code),
            EncodeLevel::Baseline => self.encode_inline(x, code),
        }
    }

    /// [`Codebook::encode`]'s loop, inlined into each of its instruction-set variants:
    /// the same IEEE operations in the same order (Rust never fuses a multiply and an
    /// add on its own), so every variant gives the same codes; wider registers only
    /// compute more of the 256 distances at once.
    #[inline(always)]
    fn encode_inline(&self, x: &[f32], code: &mut [u8]) {
        let mut dist = [0f32; KSUB];
        for (m, c) in code.iter_mut().enumerate() {
            *c = nearest(
                &x[m * self.dsub..(m + 1) * self.dsub],
                self.sub_transposed(m),
                &mut dist,
            );
        }
    }

    /// Encodes row-major vectors `[n, D]` into codes `[n, M]`, in parallel.
    ///
    /// # Panics
    /// If the lengths are not multiples of D and M for the same n.
    pub fn encode_batch(&self, xs: &[f32], codes: &mut [u8]) {
        let d = self.dim();
        assert_eq!(xs.len() / d * self.m, codes.len(), "codes length");
        assert_eq!(xs.len() % d, 0, "vectors length");
        codes
            .par_chunks_mut(self.m * ENCODE_CHUNK)
            .zip(xs.par_chunks(d * ENCODE_CHUNK))
            .for_each(|(cc, xc)| {
                for (c, x) in cc.chunks_exact_mut(self.m).zip(xc.chunks_exact(d)) {
                    self.encode(x, c);
                }
            });
    }

    /// Decodes M codes into the D-dimensional concatenation of the selected centroids.
    ///
    /// # Panics
    /// If `code.len() != M` or `out.len() != D`.
    pub fn decode(&self, code: &[u8], out: &mut [f32]) {
        assert_eq!(code.len(), self.m, "code length");
        assert_eq!(out.len(), self.dim(), "output length");
        for (m, (&c, o)) in code.iter().zip(out.chunks_exact_mut(self.dsub)).enumerate() {
            o.copy_from_slice(self.centroid(m, c as usize));
        }
    }

    /// L2 norm of the decoded vector of `code`, accumulated in f64.
    pub fn decoded_norm(&self, code: &[u8]) -> f32 {
        let sq: f64 = code
            .iter()
            .enumerate()
            .map(|(m, &c)| {
                self.centroid(m, c as usize)
                    .iter()
                    .map(|&v| f64::from(v) * f64::from(v))
                    .sum::<f64>()
            })
            .sum();
        sq.sqrt() as f32
    }

    /// Encodes every valid descriptor of a features file into a pq file: codes, decoded
    /// norms and the validity flags; invalid rows get codes 0 and norm 0.
    pub fn encode_features(&self, features: &Features) -> Result<Pq, PqError> {
        if features.dim != self.dim() {
            return Err(PqError::FeatureDim {
                got: features.dim,
                expected: self.dim(),
            });
        }
        let (n, d, m) = (features.len(), self.dim(), self.m);
        let mut codes = vec![0u8; n * m];
        let mut norms = vec![0f32; n];
        codes
            .par_chunks_mut(m * ENCODE_CHUNK)
            .zip(norms.par_chunks_mut(ENCODE_CHUNK))
            .enumerate()
            .for_each(|(chunk, (cc, nc))| {
                let mut x = vec![0f32; d];
                for (i, (c, norm)) in cc.chunks_exact_mut(m).zip(nc.iter_mut()).enumerate() {
                    let row = chunk * ENCODE_CHUNK + i;
                    if features.valid[row] == 1 {
                        features.features.read_into(row * d, &mut x);
                        self.encode(&x, c);
                        *norm = self.decoded_norm(c);
                    }
                }
            });
        let valid: Vec<u8> = features.valid.iter().map(|&v| u8::from(v == 1)).collect();
        Ok(self.to_pq(codes, norms, valid))
    }

    /// A pq file of this codebook with the given codes `[N, M]`, norms and validity.
    pub fn to_pq(&self, codes: Vec<u8>, norms: Vec<f32>, valid: Vec<u8>) -> Pq {
        Pq {
            m: self.m,
            dsub: self.dsub,
            centroids: self.centroids.clone().into(),
            codes: codes.into(),
            norms: norms.into(),
            valid: valid.into(),
            extra: self.metadata.clone(),
        }
    }

    fn sub_transposed(&self, m: usize) -> &[f32] {
        let len = self.dsub * KSUB;
        &self.transposed[m * len..(m + 1) * len]
    }
}

/// The widest registers [`Codebook::encode`] may use, chosen at run time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EncodeLevel {
    Baseline,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl EncodeLevel {
    pub(crate) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
            {
                return EncodeLevel::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return EncodeLevel::Avx2;
            }
        }
        EncodeLevel::Baseline
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod wide {
    //! [`Codebook::encode`] with AVX2 and AVX-512 registers. For the default dsub = 4
    //! the 256 distances and their first minimum are explicit vector code: each distance
    //! is `((a·a + b·b) + c·c) + e·e` with `a = x0 − c0` etc., separate IEEE multiplies
    //! and adds in [`super::distances4`]'s order (no FMA), so the codes are the baseline
    //! build's; other dsub compile [`Codebook::encode_inline`] for the wider registers.

    use std::arch::x86_64::*;

    use super::{Codebook, KSUB};

    pub(super) fn encode_avx2(cb: &Codebook, x: &[f32], code: &mut [u8]) {
        assert!(std::arch::is_x86_feature_detected!("avx2"));
        // SAFETY: AVX2 is present (checked above).
        unsafe { avx2(cb, x, code) }
    }

    pub(super) fn encode_avx512(cb: &Codebook, x: &[f32], code: &mut [u8]) {
        assert!(std::arch::is_x86_feature_detected!("avx512f"));
        assert!(std::arch::is_x86_feature_detected!("avx512vl"));
        // SAFETY: AVX-512 F and VL are present (checked above).
        unsafe { avx512(cb, x, code) }
    }

    #[target_feature(enable = "avx2")]
    fn avx2(cb: &Codebook, x: &[f32], code: &mut [u8]) {
        if cb.dsub != 4 {
            return cb.encode_inline(x, code);
        }
        let mut dist = [0f32; KSUB];
        for (m, c) in code.iter_mut().enumerate() {
            let ct = cb.sub_transposed(m);
            assert!(ct.len() == 4 * KSUB && x.len() >= 4 * m + 4);
            let xs = [0, 1, 2, 3].map(|j| _mm256_set1_ps(x[4 * m + j]));
            let mut best = _mm256_set1_ps(f32::INFINITY);
            for i in (0..KSUB).step_by(8) {
                // SAFETY: i + 8 <= 256, and row j of `ct` spans j·256..(j + 1)·256.
                let d = unsafe { distance8(&xs, ct.as_ptr().add(i)) };
                // `min(d, best)` keeps `best` where d is NaN: a NaN never wins.
                best = _mm256_min_ps(d, best);
                // SAFETY: i + 8 <= 256.
                unsafe { _mm256_storeu_ps(dist.as_mut_ptr().add(i), d) };
            }
            let min = _mm256_set1_ps(horizontal_min8(best));
            *c = 0;
            for i in (0..KSUB).step_by(8) {
                // SAFETY: i + 8 <= 256.
                let d = unsafe { _mm256_loadu_ps(dist.as_ptr().add(i)) };
                let hits = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(d, min));
                if hits != 0 {
                    *c = (i + hits.trailing_zeros() as usize) as u8;
                    break;
                }
            }
        }
    }

    /// # Safety
    /// `ct` points at the transposed dsub = 4 table of one sub-quantiser, offset by the
    /// first of 8 centroids (rows 256 floats apart).
    #[target_feature(enable = "avx2")]
    unsafe fn distance8(xs: &[__m256; 4], ct: *const f32) -> __m256 {
        // SAFETY: the caller guarantees 4 rows of at least 8 floats from `ct`.
        let c = [0, 1, 2, 3].map(|j| unsafe { _mm256_loadu_ps(ct.add(j * KSUB)) });
        let t = [0, 1, 2, 3].map(|j| _mm256_sub_ps(xs[j], c[j]));
        let sq = t.map(|v| _mm256_mul_ps(v, v));
        _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(sq[0], sq[1]), sq[2]), sq[3])
    }

    #[target_feature(enable = "avx2")]
    fn horizontal_min8(v: __m256) -> f32 {
        let mut lanes = [0f32; 8];
        // SAFETY: `lanes` holds 8 floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), v) };
        lanes
            .iter()
            .fold(f32::INFINITY, |a, &b| if b < a { b } else { a })
    }

    #[target_feature(enable = "avx512f,avx512vl,avx2")]
    fn avx512(cb: &Codebook, x: &[f32], code: &mut [u8]) {
        if cb.dsub != 4 {
            return cb.encode_inline(x, code);
        }
        for (m, c) in code.iter_mut().enumerate() {
            let ct = cb.sub_transposed(m);
            assert!(ct.len() == 4 * KSUB && x.len() >= 4 * m + 4);
            let xs = [0, 1, 2, 3].map(|j| _mm512_set1_ps(x[4 * m + j]));
            // All 256 distances stay in 16 registers.
            let d: [__m512; 16] = std::array::from_fn(|g| {
                // SAFETY: 16·g + 16 <= 256, and row j of `ct` spans j·256..(j + 1)·256.
                let c = [0, 1, 2, 3]
                    .map(|j| unsafe { _mm512_loadu_ps(ct.as_ptr().add(j * KSUB + 16 * g)) });
                let t = [0, 1, 2, 3].map(|j| _mm512_sub_ps(xs[j], c[j]));
                let sq = t.map(|v| _mm512_mul_ps(v, v));
                _mm512_add_ps(_mm512_add_ps(_mm512_add_ps(sq[0], sq[1]), sq[2]), sq[3])
            });
            // `min(d, best)` keeps `best` where d is NaN: a NaN never wins.
            let best = d
                .iter()
                .fold(_mm512_set1_ps(f32::INFINITY), |b, &v| _mm512_min_ps(v, b));
            let min = _mm512_set1_ps(_mm512_reduce_min_ps(best));
            *c = 0;
            for (g, &v) in d.iter().enumerate() {
                let hits = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(v, min);
                if hits != 0 {
                    *c = (16 * g + hits.trailing_zeros() as usize) as u8;
                    break;
                }
            }
        }
    }
}

/// `[M, 256, dsub]` -> `[M, dsub, 256]`.
pub(crate) fn transpose(centroids: &[f32], m: usize, dsub: usize) -> Vec<f32> {
    let mut t = vec![0f32; centroids.len()];
    for s in 0..m {
        for k in 0..KSUB {
            for j in 0..dsub {
                t[(s * dsub + j) * KSUB + k] = centroids[(s * KSUB + k) * dsub + j];
            }
        }
    }
    t
}

/// Index of the centroid nearest to the sub-vector `x` among the 256 of one
/// sub-quantiser given transposed (`ct` = `[dsub, 256]`), ties to the lower index.
/// Distances are `sum_j (x_j - c_j)^2` accumulated over `j` in order in f32, the
/// formula of faiss's `fvec_L2sqr` (its AVX2 kernels may fuse the multiply-add, so a
/// near-tie can round the other way there; the faiss test counts such cases).
#[inline(always)]
pub(crate) fn nearest(x: &[f32], ct: &[f32], dist: &mut [f32; KSUB]) -> u8 {
    sub_distances(x, ct, dist);
    argmin_first(dist)
}

/// The squared distances [`nearest`] compares, into `dist`.
#[inline(always)]
pub(crate) fn sub_distances(x: &[f32], ct: &[f32], dist: &mut [f32; KSUB]) {
    if let (&[x0, x1, x2, x3], true) = (x, ct.len() == 4 * KSUB) {
        distances4([x0, x1, x2, x3], ct, dist);
    } else {
        distances(x, ct, dist);
    }
}

/// Squared distances to all 256 centroids, any `dsub`: one pass over the 256 lanes
/// per dimension (vectorises over centroids).
#[inline(always)]
fn distances(x: &[f32], ct: &[f32], dist: &mut [f32; KSUB]) {
    let (first, rest) = ct.split_at(KSUB);
    let x0 = x[0];
    for (d, &c) in dist.iter_mut().zip(first) {
        let t = x0 - c;
        *d = t * t;
    }
    for (&xj, row) in x[1..].iter().zip(rest.chunks_exact(KSUB)) {
        for (d, &c) in dist.iter_mut().zip(row) {
            let t = xj - c;
            *d += t * t;
        }
    }
}

/// [`distances`] for the default `dsub = 4`, summed in registers (same operations in the
/// same order, so the same bits).
#[inline(always)]
fn distances4(x: [f32; 4], ct: &[f32], dist: &mut [f32; KSUB]) {
    let (r0, rest) = ct.split_at(KSUB);
    let (r1, rest) = rest.split_at(KSUB);
    let (r2, r3) = rest.split_at(KSUB);
    for (j, d) in dist.iter_mut().enumerate() {
        let (a, b, c, e) = (x[0] - r0[j], x[1] - r1[j], x[2] - r2[j], x[3] - r3[j]);
        *d = ((a * a + b * b) + c * c) + e * e;
    }
}

/// First index of the minimum (a NaN never wins; all-NaN gives 0). Lane-wise minima
/// and block-wise equality tests vectorise; only the block holding the minimum is
/// scanned element by element.
#[inline(always)]
pub(crate) fn argmin_first(dist: &[f32; KSUB]) -> u8 {
    const LANES: usize = 16;
    let mut lanes = [f32::INFINITY; LANES];
    for chunk in dist.chunks_exact(LANES) {
        for (l, &v) in lanes.iter_mut().zip(chunk) {
            *l = if v < *l { v } else { *l };
        }
    }
    let min = lanes
        .iter()
        .fold(f32::INFINITY, |a, &b| if b < a { b } else { a });
    for (b, chunk) in dist.chunks_exact(LANES).enumerate() {
        if chunk.iter().fold(false, |hit, &v| hit | (v == min)) {
            let i = chunk.iter().position(|&v| v == min).unwrap_or(0);
            return (b * LANES + i) as u8;
        }
    }
    0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn argmin_takes_the_first_of_equal_minima() {
        let mut d = [5f32; KSUB];
        d[200] = 1.0;
        d[37] = 1.0;
        d[255] = 0.5;
        assert_eq!(argmin_first(&d), 255);
        d[255] = 1.0;
        assert_eq!(argmin_first(&d), 37);
        let d = [f32::NAN; KSUB];
        assert_eq!(argmin_first(&d), 0);
    }

    #[test]
    fn every_instruction_set_encodes_alike() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for dsub in [4usize, 3, 8] {
            let m = 6;
            let c: Vec<f32> = (0..m * KSUB * dsub)
                .map(|_| rng.random_range(-1.0f32..1.0))
                .collect();
            let cb = Codebook::new(m, dsub, c).unwrap_or_else(|e| panic!("{e}"));
            for _ in 0..200 {
                let x: Vec<f32> = (0..m * dsub)
                    .map(|_| rng.random_range(-1.2f32..1.2))
                    .collect();
                let mut want = vec![0u8; m];
                cb.encode_inline(&x, &mut want);
                #[cfg(target_arch = "x86_64")]
                {
                    let mut got = vec![0u8; m];
                    if std::arch::is_x86_feature_detected!("avx2") {
                        wide::encode_avx2(&cb, &x, &mut got);
                        assert_eq!(got, want, "avx2, dsub {dsub}");
                    }
                    if EncodeLevel::detect() == EncodeLevel::Avx512 {
                        wide::encode_avx512(&cb, &x, &mut got);
                        assert_eq!(got, want, "avx512, dsub {dsub}");
                    }
                }
            }
        }
    }

    #[test]
    fn the_dsub_4_kernel_gives_the_generic_bits() {
        let ct: Vec<f32> = (0..4 * KSUB)
            .map(|i| ((i * 37 % 101) as f32 * 0.013).sin())
            .collect();
        let x = [0.3f32, -0.7, 0.11, 0.5];
        let (mut a, mut b) = ([0f32; KSUB], [0f32; KSUB]);
        distances(&x, &ct, &mut a);
        distances4(x, &ct, &mut b);
        assert!(a.iter().zip(&b).all(|(p, q)| p.to_bits() == q.to_bits()));
    }
}
