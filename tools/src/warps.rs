//! Dense warps from the Gaussians' rendered depth (`warp_graph::depth_warps`): the one
//! command line behind `warp-graph warps` and `prep warps`.

use std::path::PathBuf;

use clap::Args;
use serde_json::Value;
use warp_graph::job::{self, WarpsJob};
use warp_graph::{DepthWarpParams, Pairs};

use crate::{progress_bar, BoxError};

/// The arguments of a warps run.
#[derive(Debug, Args)]
pub struct WarpsArgs {
    /// Gaussians file (profuse.gaussians, e.g. from gs-init).
    #[arg(long)]
    pub gaussians: PathBuf,
    /// Cameras file (profuse.cameras).
    #[arg(long)]
    pub cameras: PathBuf,
    /// The matches file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Ordered pairs I-J, comma-separated (default: each view with its --nearest views
    /// by camera centre, both directions).
    #[arg(long, value_delimiter = ',', value_parser = parse_pair, conflicts_with = "nearest")]
    pub pairs: Vec<[u32; 2]>,
    /// Views paired with each view, nearest camera centres first.
    #[arg(long, value_name = "K", default_value_t = 4)]
    pub nearest: usize,
    /// Pair only these views (comma-separated indices), each with its --nearest among
    /// them; the others get no pair and no depth render (e.g. views without masks, or
    /// held-out views). Default: every view.
    #[arg(long, value_delimiter = ',', conflicts_with = "pairs")]
    pub views: Vec<u32>,
    /// Image pixels per grid cell along each axis.
    #[arg(long, value_name = "S", default_value_t = 4)]
    pub stride: usize,
    /// Relative depth tolerance: certainty falls to 0 at this disagreement.
    #[arg(long, value_name = "T", default_value_t = 0.05)]
    pub depth_tol: f64,
    /// Accumulated alpha below which a rendered pixel has no depth.
    #[arg(long, value_name = "A", default_value_t = 0.5)]
    pub min_alpha: f32,
    /// Reject cells on a depth edge: a 4-neighbour's depth differs by more than E
    /// relative (default off: more precise warps, but fewer links in warp-graph).
    #[arg(long, value_name = "E")]
    pub edge_tol: Option<f64>,
}

/// Renders the depth of every view, warps cells between view pairs and writes the matches
/// file; returns the JSON report.
pub fn run(a: WarpsArgs, show: bool) -> Result<Value, BoxError> {
    crate::check_outputs([a.out.as_path()])?;
    let params = DepthWarpParams {
        stride: a.stride,
        depth_tol: a.depth_tol,
        min_alpha: a.min_alpha,
        edge_tol: a.edge_tol.unwrap_or(warp_graph::DEFAULT_EDGE_TOL),
        pairs: if !a.pairs.is_empty() {
            Pairs::Explicit(a.pairs)
        } else if !a.views.is_empty() {
            Pairs::NearestAmong(a.nearest, a.views)
        } else {
            Pairs::Nearest(a.nearest)
        },
    };
    let job = WarpsJob {
        gaussians: a.gaussians,
        cameras: a.cameras,
        out: a.out,
    };
    let bar = progress_bar(show, 0, "warps", "depth maps + view pairs");
    let report = job::run_warps(&job, &params, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    Ok(serde_json::to_value(report?)?)
}

fn parse_pair(s: &str) -> Result<[u32; 2], String> {
    let (i, j) = s
        .split_once('-')
        .ok_or_else(|| format!("{s:?}: expected a pair I-J of view indices"))?;
    let view = |t: &str| {
        t.trim()
            .parse::<u32>()
            .map_err(|e| format!("{s:?}: {t:?} is not a view index ({e})"))
    };
    Ok([view(i)?, view(j)?])
}
