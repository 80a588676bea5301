//! The crate's typed errors.

/// What can go wrong when training, encoding or querying a product quantiser.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum PqError {
    /// `m` sub-quantisers were asked for but the vectors have a dimension that `m`
    /// does not divide (or `m` is 0).
    #[error("vector dimension {dim} is not divisible into m = {m} sub-quantisers (need m >= 1 and dim % m == 0)")]
    DimNotDivisible {
        /// Vector dimension D.
        dim: usize,
        /// Requested number of sub-quantisers M.
        m: usize,
    },
    /// Training 256 centroids per sub-quantiser needs at least 256 distinct training rows.
    #[error("k-means needs at least {needed} valid vectors (one per centroid), found {valid}")]
    TooFewVectors {
        /// Valid vectors available.
        valid: usize,
        /// Vectors needed (256).
        needed: usize,
    },
    /// The training sample size is below the number of centroids.
    #[error("training sample size {sample} is below the {needed} centroids of a sub-quantiser")]
    SampleTooSmall {
        /// Requested sample size.
        sample: usize,
        /// Minimum (256).
        needed: usize,
    },
    /// A query's dimension differs from the codebook's.
    #[error("query has {got} dimensions, the codebook has {expected}")]
    QueryDim {
        /// Query length.
        got: usize,
        /// Codebook dimension M x dsub.
        expected: usize,
    },
    /// A query is all zero or has a NaN/infinite element, so cosine is undefined.
    #[error("query is all zero or not finite, so its cosine score is undefined")]
    DegenerateQuery,
    /// Vectors to encode have a dimension that differs from the codebook's.
    #[error("vectors have {got} dimensions, the codebook has {expected}")]
    FeatureDim {
        /// Vector dimension.
        got: usize,
        /// Codebook dimension M x dsub.
        expected: usize,
    },
    /// A hand-built [`profuse_formats::Pq`] (or centroid table) whose tensor sizes disagree.
    #[error("inconsistent codebook: {0}")]
    Inconsistent(String),
}
