//! Typed errors of gs-init. Every variant about input names the file it is about.

use profuse_formats::FormatError;

/// Why an initialisation could not run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InitError {
    /// A file could not be read, failed validation, or could not be written.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The folder of the output file cannot be created.
    #[error("{path}: cannot create the output folder")]
    OutputFolder {
        /// The folder.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A match pair names a view the cameras file does not have.
    #[error("{matches}: tensor `pairs` row {pair} names view {view}, but {cameras} has {views} views (ids 0..{views})")]
    PairOutOfRange {
        /// The matches file.
        matches: String,
        /// The pair's row.
        pair: usize,
        /// The view id.
        view: u32,
        /// The cameras file.
        cameras: String,
        /// Its number of views.
        views: usize,
    },
    /// The matches file was made for another number of views.
    #[error("{matches}: metadata `num_views` is {num_views}, but {cameras} has {views} views")]
    ViewCount {
        /// The matches file.
        matches: String,
        /// Its `num_views`.
        num_views: usize,
        /// The cameras file.
        cameras: String,
        /// Its number of views.
        views: usize,
    },
    /// The image of a view does not exist.
    #[error("{path}: image of view {view} not found")]
    ImageMissing {
        /// The path (or label) looked for.
        path: String,
        /// The view.
        view: usize,
    },
    /// The image of a view cannot be decoded.
    #[error("{path}: cannot read image")]
    Image {
        /// The image file.
        path: String,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// An image's size differs from the size the cameras file gives its view.
    #[error("{path}: image is {found_w}x{found_h} pixels, but {cameras} gives view {view} the size {expected_w}x{expected_h}")]
    ImageSize {
        /// The image file.
        path: String,
        /// The view.
        view: usize,
        /// Actual width.
        found_w: u32,
        /// Actual height.
        found_h: u32,
        /// The cameras file.
        cameras: String,
        /// Width in the cameras file.
        expected_w: u32,
        /// Height in the cameras file.
        expected_h: u32,
    },
    /// An in-memory image whose pixel buffer does not hold width x height RGB pixels.
    #[error("{path}: image of view {view} has {found} bytes, expected {expected} ({width}x{height} RGB)")]
    ImageData {
        /// The image's label.
        path: String,
        /// The view.
        view: usize,
        /// Bytes present.
        found: usize,
        /// Bytes expected.
        expected: usize,
        /// Declared width.
        width: u32,
        /// Declared height.
        height: u32,
    },
    /// A scene directory has neither `matches.safetensors` nor `sparse_matches.safetensors`.
    #[error("{dir}: no matches.safetensors or sparse_matches.safetensors")]
    NoMatches {
        /// The scene directory.
        dir: String,
    },
    /// A parameter is outside its valid range.
    #[error("parameter `{name}` is {value}, expected {expected}")]
    Param {
        /// The parameter.
        name: &'static str,
        /// Its value, printed.
        value: String,
        /// What is accepted.
        expected: &'static str,
    },
}

/// Result alias of this crate.
pub type Result<T, E = InitError> = std::result::Result<T, E>;
