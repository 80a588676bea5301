//! The one error type of the query crate.

use std::io;

/// Why a query could not be scored, selected, rendered or written. Every variant about
/// input names the file (or the argument) and what was expected.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum QueryError {
    /// A file could not be read, validated or written by `profuse_formats`.
    #[error(transparent)]
    Format(#[from] profuse_formats::FormatError),
    /// The rasterizer rejected the Gaussians or a camera.
    #[error("rendering failed: {0}")]
    Raster(#[from] splat_raster::RasterError),
    /// The PQ codes could not be scored.
    #[error("{path}: cannot score the PQ codes: {reason}")]
    Pq {
        /// The pq file.
        path: String,
        /// What went wrong.
        reason: String,
    },
    /// A requested prompt is not in the prompts file.
    #[error("{path}: no prompt named {name:?} (the file has: {available})")]
    UnknownPrompt {
        /// The prompts file.
        path: String,
        /// The requested name.
        name: String,
        /// The names in the file, comma-separated.
        available: String,
    },
    /// No prompt was requested (or the file has none of the requested kind).
    #[error("{path}: {reason}")]
    NoPrompts {
        /// The prompts file.
        path: String,
        /// Why there is nothing to query.
        reason: String,
    },
    /// Prompt embeddings and Gaussian descriptors live in spaces of different dimension.
    #[error(
        "{prompts}: prompt embeddings have dimension {prompt_dim}, but {descriptors} holds \
         descriptors of dimension {descriptor_dim}; both must come from the same embedding space"
    )]
    DimMismatch {
        /// The prompts file (or "prompts").
        prompts: String,
        /// D of the prompts.
        prompt_dim: usize,
        /// The features or pq file (or "descriptors").
        descriptors: String,
        /// D of the descriptors.
        descriptor_dim: usize,
    },
    /// The descriptors do not describe the Gaussians they are used with.
    #[error(
        "{descriptors} holds {descriptor_count} descriptors but {gaussians} holds \
         {gaussian_count} Gaussians; the descriptors must be those of this Gaussian set"
    )]
    CountMismatch {
        /// The features or pq file.
        descriptors: String,
        /// N of the descriptors.
        descriptor_count: usize,
        /// The gaussians file.
        gaussians: String,
        /// N of the Gaussians.
        gaussian_count: usize,
    },
    /// A prompt's embedding cannot be normalised (all zero or not finite).
    #[error("{path}: the embedding of prompt {name:?} is zero or not finite")]
    BadEmbedding {
        /// The prompts file (or "prompts").
        path: String,
        /// The prompt.
        name: String,
    },
    /// The LERF relevancy score needs at least one canonical negative in the prompts.
    #[error(
        "{path}: the relevancy score of {name:?} needs at least one canonical negative \
         prompt (object, things, stuff, texture) other than the prompt itself; none is in the file"
    )]
    NoNegatives {
        /// The prompts file.
        path: String,
        /// The prompt being scored.
        name: String,
    },
    /// A parameter is outside its allowed range.
    #[error("{name} is {value}, expected {expected}")]
    BadParameter {
        /// The parameter (`threshold`, `top_frac`, `gamma`, `k`, `scale`).
        name: &'static str,
        /// Its value, printed.
        value: String,
        /// The allowed range.
        expected: &'static str,
    },
    /// Neither a threshold nor a fraction was given for a score without a natural threshold.
    #[error(
        "the cosine score has no natural threshold: give a threshold (the paper tunes tau by a \
         small grid search) or a top fraction"
    )]
    MissingThreshold,
    /// A requested view does not exist.
    #[error("{path}: view {view} is out of range (the file has {views} views)")]
    ViewOutOfRange {
        /// The cameras file.
        path: String,
        /// The requested view.
        view: usize,
        /// Views in the file.
        views: usize,
    },
    /// The view selection is empty.
    #[error("{reason}")]
    NoViews {
        /// Why no view was selected.
        reason: String,
    },
    /// Two selected views would write the same output file.
    #[error(
        "{path}: views {first} and {second} have the same image stem {stem:?}, so their masks \
         would overwrite each other"
    )]
    DuplicateStem {
        /// The cameras file.
        path: String,
        /// The shared stem.
        stem: String,
        /// The first view.
        first: usize,
        /// The second view.
        second: usize,
    },
    /// An output name is reserved by the output layout.
    #[error(
        "{what} {name:?} collides with the reserved output folder {name:?} of the {layout} layout"
    )]
    ReservedName {
        /// "image stem" or "prompt".
        what: &'static str,
        /// The name.
        name: String,
        /// The layout.
        layout: &'static str,
    },
    /// An output rule refused a path (a name from data that is not a plain file name, an
    /// output directory that is something else; see `profuse_formats::output`).
    #[error(transparent)]
    Output(#[from] profuse_formats::output::OutputError),
    /// A file or directory could not be read, created or written.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The path.
        path: String,
        /// What was attempted.
        action: &'static str,
        /// The cause.
        #[source]
        source: io::Error,
    },
    /// The registration code could not pool the clicked proposal's masks (masks that do
    /// not belong to the cameras, an unusable camera).
    #[error(transparent)]
    Fuse(#[from] profuse_fuse::FuseError),
    /// A click lies outside its view's image.
    #[error(
        "{cameras}: the click ({x}, {y}) is outside view {view}'s image of {width}x{height}          pixels (x is the column in [0, {width}), y the row in [0, {height}))"
    )]
    PixelOutsideImage {
        /// The cameras file.
        cameras: String,
        /// The view.
        view: usize,
        /// The column coordinate.
        x: f64,
        /// The row coordinate.
        y: f64,
        /// The image width.
        width: u32,
        /// The image height.
        height: u32,
    },
    /// No mask covers the clicked pixel (background, label "no mask").
    #[error(
        "{masks}: no mask under the click ({x}, {y}) in view {view} (mask-grid cell \
         [column, row] = {cell:?} is background); click on a segmented region"
    )]
    NoMaskUnderPixel {
        /// The masks file.
        masks: String,
        /// The view.
        view: usize,
        /// The column coordinate.
        x: f64,
        /// The row coordinate.
        y: f64,
        /// The mask-grid cell (column, row).
        cell: [usize; 2],
    },
    /// A click by proposal needs the proposals file.
    #[error("a click selects by the mask's proposal: give the proposals file (or click by mask)")]
    MissingProposals,
    /// The clicked mask has no usable query vector.
    #[error("no query vector for the click: {reason}")]
    NoClickDescriptor {
        /// Why.
        reason: String,
    },
    /// Some selected Gaussian ids are not in the Gaussian set.
    #[error("selection id {id} is out of range for {count} Gaussians")]
    SelectionOutOfRange {
        /// The id.
        id: u32,
        /// N.
        count: usize,
    },
    /// A PNG could not be encoded.
    #[error("{path}: cannot encode PNG: {source}")]
    Image {
        /// The PNG being written.
        path: String,
        /// The cause.
        #[source]
        source: image::ImageError,
    },
}

/// Result alias of this crate.
pub type Result<T, E = QueryError> = std::result::Result<T, E>;

/// Maps an I/O error on `path` to [`QueryError::Io`].
pub(crate) fn io_err<'a>(
    path: &'a std::path::Path,
    action: &'static str,
) -> impl FnOnce(io::Error) -> QueryError + 'a {
    move |source| QueryError::Io {
        path: path.display().to_string(),
        action,
        source,
    }
}
