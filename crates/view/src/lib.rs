//! `profuse view`: a local web viewer of a pipeline output. A small HTTP server
//! ([`listen`], [`Listener::serve`]) sends the page, the vendored gsplat.js viewer, the scene's
//! Gaussians as `.splat` rows ([`splat`]) and the camera presets ([`presets`]), and answers
//! selection requests: the LERF relevancy of every Gaussian for every prompt is computed
//! once from the PQ codes with the query crate ([`ViewScene::open`]), and a request applies
//! the slider's threshold with the query crate's selection rule; a click goes through the
//! query crate's `resolve_click`. An output without a prompts file (a `profuse prepare`
//! scene without a CLIP text encoder) is viewed click only: no text prompts, and a click
//! is scored by cosine against the PQ codes ([`ScoringPaths::ClickCosine`],
//! [`DEFAULT_CLICK_COSINE_THRESHOLD`]). The browser never sees a descriptor.
//!
//! See the crate README for the library choice, the page and the measured frame rates.

pub mod error;
pub mod http;
pub mod presets;
pub mod scene;
pub mod server;
pub mod splat;

pub use error::{Result, ViewError};
pub use presets::{presets, rotation_to_quaternion, Preset};
pub use scene::{OutputPaths, SceneInfo, ScoringPaths, ViewScene, DEFAULT_CLICK_COSINE_THRESHOLD};
pub use server::{answer, host_allowed, listen, percent_decode, respond, Answer, Listener};
pub use splat::{splat_bytes, SPLAT_ROW_BYTES};
