//! Deterministic "CLIP-like" clustered unit vectors for tests and benchmarks: a set of
//! random unit class prototypes, each vector `normalize(prototype + noise)`.
//!
//! Vector `i` is a pure function of (seed, i), so benchmarks can stream a million
//! vectors in any order or chunking without materialising them.

use std::collections::BTreeMap;

use profuse_formats::{Features, Floats, Pq};
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::{train, PqError, TrainParams};

/// Generator of clustered unit vectors.
#[derive(Debug, Clone)]
pub struct Clustered {
    dim: usize,
    prototypes: Vec<f32>,
    noise: f32,
    seed: u64,
}

impl Clustered {
    /// `classes` prototypes in `dim` dimensions; each vector adds noise of total norm
    /// about `noise` to its prototype before normalising (so its cosine with the
    /// prototype is about `1 / sqrt(1 + noise^2)`: 0.85 for noise 0.62, the spread of
    /// CLIP features of one object).
    ///
    /// # Panics
    /// If `dim` or `classes` is 0.
    pub fn new(dim: usize, classes: usize, noise: f32, seed: u64) -> Self {
        assert!(dim > 0 && classes > 0, "dim and classes must be >= 1");
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(u64::MAX);
        let mut prototypes = vec![0f32; classes * dim];
        for p in prototypes.chunks_exact_mut(dim) {
            for v in p.iter_mut() {
                *v = gaussian(&mut rng);
            }
            normalize(p);
        }
        Clustered {
            dim,
            prototypes,
            noise,
            seed,
        }
    }

    /// Vector dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of classes.
    pub fn classes(&self) -> usize {
        self.prototypes.len() / self.dim
    }

    /// Prototype of class `c`.
    pub fn prototype(&self, c: usize) -> &[f32] {
        &self.prototypes[c * self.dim..(c + 1) * self.dim]
    }

    /// Class of vector `i`.
    pub fn class_of(&self, i: u64) -> usize {
        let mut rng = self.rng(i);
        ((u128::from(rng.next_u64()) * self.classes() as u128) >> 64) as usize
    }

    /// Writes unit vector `i` into `out` (`dim` values).
    pub fn vector(&self, i: u64, out: &mut [f32]) {
        let mut rng = self.rng(i);
        let c = ((u128::from(rng.next_u64()) * self.classes() as u128) >> 64) as usize;
        // Uniform noise in [-a, a) with a = sqrt(3) * noise / sqrt(dim): per-coordinate
        // variance noise^2 / dim, so the noise vector's norm is about `noise`.
        let a = 3f32.sqrt() * self.noise / (self.dim as f32).sqrt();
        for (o, &p) in out.iter_mut().zip(self.prototype(c)) {
            *o = p + a * (2.0 * unit(&mut rng) - 1.0);
        }
        normalize(out);
    }

    /// A text-like query near class `c`: `normalize(prototype + noise)`, its own stream.
    pub fn query(&self, c: usize, noise: f32, salt: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ 0x5157_4552_5900_0000);
        rng.set_stream(salt);
        let a = 3f32.sqrt() * noise / (self.dim as f32).sqrt();
        let mut q: Vec<f32> = self
            .prototype(c)
            .iter()
            .map(|&p| p + a * (2.0 * unit(&mut rng) - 1.0))
            .collect();
        normalize(&mut q);
        q
    }

    /// Vectors `start..start + n`, row-major `[n, dim]`.
    pub fn vectors(&self, start: u64, n: usize) -> Vec<f32> {
        let mut out = vec![0f32; n * self.dim];
        for (i, row) in out.chunks_exact_mut(self.dim).enumerate() {
            self.vector(start + i as u64, row);
        }
        out
    }

    /// A features file of `n` vectors where every `invalid_every`-th row (0 = none) is
    /// invalid (all zero).
    pub fn features(&self, n: usize, invalid_every: usize) -> Features {
        let mut data = self.vectors(0, n);
        let valid: Vec<u8> = (0..n)
            .map(|i| u8::from(invalid_every == 0 || i % invalid_every != invalid_every - 1))
            .collect();
        for (row, &v) in data.chunks_exact_mut(self.dim).zip(&valid) {
            if v == 0 {
                row.fill(0.0);
            }
        }
        Features {
            features: Floats::F32(data.into()),
            dim: self.dim,
            valid: valid.into(),
            weight_sum: None,
            extra: BTreeMap::new(),
        }
    }

    /// A pq of `n` of these vectors (every 11th invalid) with `m` sub-quantisers, trained
    /// quickly (4 Lloyd iterations on 4096 samples): the data of the crate's fast-scan
    /// tests, small enough for a debug build.
    pub fn quick_pq(&self, n: usize, m: usize) -> Result<Pq, PqError> {
        let features = self.features(n, 11);
        let params = TrainParams {
            m,
            iters: 4,
            sample: 4096,
            seed: 3,
        };
        train(&features, &params)?.encode_features(&features)
    }

    fn rng(&self, i: u64) -> ChaCha8Rng {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        rng.set_stream(i);
        rng
    }
}

/// Uniform in [0, 1).
fn unit(rng: &mut ChaCha8Rng) -> f32 {
    (rng.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// Standard normal by Box-Muller (one of the pair).
fn gaussian(rng: &mut ChaCha8Rng) -> f32 {
    let u1 = (f64::from(rng.next_u32()) + 1.0) / 4_294_967_297.0;
    let u2 = f64::from(rng.next_u32()) / 4_294_967_296.0;
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

/// Scales `v` to unit L2 norm (f64 accumulation); a zero vector stays zero.
pub fn normalize(v: &mut [f32]) {
    let n = v
        .iter()
        .map(|&x| f64::from(x) * f64::from(x))
        .sum::<f64>()
        .sqrt();
    if n > 0.0 {
        for x in v.iter_mut() {
            *x = (f64::from(*x) / n) as f32;
        }
    }
}
