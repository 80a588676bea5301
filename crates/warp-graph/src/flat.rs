//! [`Params`] flat: every parameter one key, as in the pipeline's `[warp_graph]` TOML
//! section and on the `warp-graph` tool's command line (with the `clap` feature). An
//! optional rule is one number with 0 = off, and the consensus parameters carry a
//! `consensus_` prefix. This is the only place the key names are written; [`Params`]
//! (de)serialises through it.

use serde::{Deserialize, Serialize};

use crate::consensus::{ConsensusParams, PointWeight};
use crate::params::{Grouping, Params, Sampling, Visibility};

/// The defaults, for the command-line help.
#[cfg(feature = "clap")]
fn d() -> Params {
    Params::default()
}

/// Every parameter of [`Params`] as one flat key (see the field docs of [`Params`] and
/// [`ConsensusParams`] for the meanings and the reasons for the defaults).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct FlatParams {
    /// Certainty threshold of the gate Γ = [certainty >= tau_alpha] ∧ vis_mask.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().tau_alpha))]
    pub tau_alpha: f32,
    /// Gated mask IoU needed in both directions (authors' run script: 0.2).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().tau_iou))]
    pub tau_iou: f64,
    /// Gated bounding-box IoU needed in both directions (authors' run script: 0.08).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().tau_box))]
    pub tau_box: f64,
    /// Minimal members of a proposal.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().s_min))]
    pub s_min: usize,
    /// Minimal distinct views of a proposal.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().v_min))]
    pub v_min: usize,
    /// How view j's labels are sampled at warped positions.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = d().sampling))]
    pub sampling: Sampling,
    /// Occlusion test forming vis_mask.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = d().visibility))]
    pub visibility: Visibility,
    /// Depth test: relative tolerance |z_j − D_j(q)| <= tol · D_j(q).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().depth_tolerance))]
    pub depth_tolerance: f32,
    /// Depth test: rendered depth counts only where the accumulated alpha reaches this.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().depth_min_alpha))]
    pub depth_min_alpha: f32,
    /// Forward-backward test: largest round-trip error in warp-grid cells.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().fwd_bwd_tolerance))]
    pub fwd_bwd_tolerance: f32,
    /// Skip view pairs that have only one of their two warps (default: judge them on the
    /// one available).
    #[cfg_attr(feature = "clap", arg(long))]
    pub require_both_warps: bool,
    /// Same-view guard: two masks of one view join a proposal only when at least this many
    /// masks of other views link to both; 0 = the paper's plain connected components.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().same_view_support.unwrap_or(0)))]
    pub same_view_support: usize,
    /// Extent rule 1 (needs --gaussians; only with the same-view guard): refuse a link
    /// that unites two components of two masks or more whose 3D extents agree less than
    /// this (the larger share of one's depth points inside the other's padded box);
    /// 0 = off.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().extent_agreement.unwrap_or(0.0)))]
    pub extent_agreement: f64,
    /// Extent rule 2 (needs --gaussians; only with the same-view guard): after the links,
    /// merge components whose padded 3D boxes have at least this IoU (largest first, the
    /// same-view guard still applies); 0 = off. Both rules 0 = the guard alone.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().extent_merge_iou.unwrap_or(0.0)))]
    pub extent_merge_iou: f64,
    /// Share of a component's depth points left out on each side of each axis when its 3D
    /// box is taken.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().extent_trim))]
    pub extent_trim: f64,
    /// Padding of the 3D boxes on each side, as a share of the scene diagonal.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().extent_pad))]
    pub extent_pad: f64,
    /// How masks become proposals: `links` (the warp links of Algorithm 1, with the guard
    /// and extent rules above), `consensus` (view consensus over the Gaussians; needs
    /// cameras and Gaussians; see the crate README), or `auto` (consensus when cameras and
    /// Gaussians are given, else links).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = d().grouping))]
    pub grouping: Grouping,
    /// Consensus: a view observes a mask when at least this share of the mask's points (by
    /// weight, see --consensus-point-weight) carry a label there.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.visible_ratio))]
    pub consensus_visible_ratio: f64,
    /// Consensus: a view observes a mask only through at least this many of its points
    /// (1: any), so that one large Gaussian does not make an observation.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.observed_points))]
    pub consensus_observed_points: usize,
    /// Consensus: a mask is contained in a mask of another view when more than this share
    /// of its labelled points (by weight) there carry that mask's label.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.contained_ratio))]
    pub consensus_contained_ratio: f64,
    /// Consensus: a mask split in more than this share of the other views observing it is
    /// under-segmented and joins no proposal.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.undersegment_ratio))]
    pub consensus_undersegment_ratio: f64,
    /// Consensus: count a mask's own view (which always contains it) among the views
    /// judging it under-segmented, as MaskClustering does (default: only the other views).
    #[cfg_attr(feature = "clap", arg(long))]
    pub consensus_own_view_votes: bool,
    /// Consensus: two clusters join when the views containing both in one mask are at
    /// least this share of the views containing both.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.consensus))]
    pub consensus_threshold: f64,
    /// Consensus: within an iteration, two clusters are not united when the views
    /// containing both put them in one mask less often than this share (0.6: a tie, such
    /// as two views of four, is refused); 0 unites every consistent pair.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.union_ratio))]
    pub consensus_union_ratio: f64,
    /// Consensus: most Gaussians tracked as points (every k-th beyond; all are rendered).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().consensus.max_points))]
    pub consensus_max_points: usize,
    /// Consensus: unite clusters along the warp links after the iterations (step 7 of the
    /// crate README's consensus rules); the flag `--no-consensus-link-merge` turns it off.
    #[cfg_attr(
        feature = "clap",
        arg(long = "no-consensus-link-merge", action = clap::ArgAction::SetFalse)
    )]
    pub consensus_link_merge: bool,
    /// Consensus: what a mask's point weighs in the votes: `pixels` (the mask pixels it
    /// wins, so votes measure area whatever the density of the Gaussians) or `points` (one
    /// each, MaskClustering's count).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = d().consensus.point_weight))]
    pub consensus_point_weight: PointWeight,
    /// Rendered depth maps kept in memory at once (LRU over views); memory, not method,
    /// so not part of the pipeline's configuration.
    #[serde(skip)]
    #[cfg_attr(feature = "clap", arg(long, default_value_t = d().depth_cache_views))]
    pub depth_cache_views: usize,
}

impl Default for FlatParams {
    fn default() -> Self {
        Params::default().into()
    }
}

fn off_if_zero<T: PartialOrd + Default>(v: T) -> Option<T> {
    (v > T::default()).then_some(v)
}

impl From<FlatParams> for Params {
    fn from(f: FlatParams) -> Params {
        Params {
            tau_alpha: f.tau_alpha,
            tau_iou: f.tau_iou,
            tau_box: f.tau_box,
            s_min: f.s_min,
            v_min: f.v_min,
            sampling: f.sampling,
            visibility: f.visibility,
            depth_tolerance: f.depth_tolerance,
            depth_min_alpha: f.depth_min_alpha,
            fwd_bwd_tolerance: f.fwd_bwd_tolerance,
            require_both_warps: f.require_both_warps,
            depth_cache_views: f.depth_cache_views,
            same_view_support: off_if_zero(f.same_view_support),
            extent_agreement: off_if_zero(f.extent_agreement),
            extent_merge_iou: off_if_zero(f.extent_merge_iou),
            extent_trim: f.extent_trim,
            extent_pad: f.extent_pad,
            grouping: f.grouping,
            consensus: ConsensusParams {
                visible_ratio: f.consensus_visible_ratio,
                observed_points: f.consensus_observed_points,
                contained_ratio: f.consensus_contained_ratio,
                undersegment_ratio: f.consensus_undersegment_ratio,
                own_view_votes: f.consensus_own_view_votes,
                consensus: f.consensus_threshold,
                union_ratio: f.consensus_union_ratio,
                max_points: f.consensus_max_points,
                link_merge: f.consensus_link_merge,
                point_weight: f.consensus_point_weight,
            },
        }
    }
}

impl From<Params> for FlatParams {
    fn from(p: Params) -> FlatParams {
        FlatParams {
            tau_alpha: p.tau_alpha,
            tau_iou: p.tau_iou,
            tau_box: p.tau_box,
            s_min: p.s_min,
            v_min: p.v_min,
            sampling: p.sampling,
            visibility: p.visibility,
            depth_tolerance: p.depth_tolerance,
            depth_min_alpha: p.depth_min_alpha,
            fwd_bwd_tolerance: p.fwd_bwd_tolerance,
            require_both_warps: p.require_both_warps,
            same_view_support: p.same_view_support.unwrap_or(0),
            extent_agreement: p.extent_agreement.unwrap_or(0.0),
            extent_merge_iou: p.extent_merge_iou.unwrap_or(0.0),
            extent_trim: p.extent_trim,
            extent_pad: p.extent_pad,
            grouping: p.grouping,
            consensus_visible_ratio: p.consensus.visible_ratio,
            consensus_observed_points: p.consensus.observed_points,
            consensus_contained_ratio: p.consensus.contained_ratio,
            consensus_undersegment_ratio: p.consensus.undersegment_ratio,
            consensus_own_view_votes: p.consensus.own_view_votes,
            consensus_threshold: p.consensus.consensus,
            consensus_union_ratio: p.consensus.union_ratio,
            consensus_max_points: p.consensus.max_points,
            consensus_link_merge: p.consensus.link_merge,
            consensus_point_weight: p.consensus.point_weight,
            depth_cache_views: p.depth_cache_views,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn flat_round_trips_and_zero_switches_a_rule_off() {
        let p = Params::default();
        assert_eq!(Params::from(FlatParams::from(p)), p);
        let f = FlatParams {
            same_view_support: 0,
            extent_agreement: 0.0,
            ..FlatParams::default()
        };
        let q = Params::from(f);
        assert_eq!((q.same_view_support, q.extent_agreement), (None, None));
        assert_eq!(q.extent_merge_iou, Some(0.1));
    }

    #[test]
    fn enums_have_their_names_as_serde_values() {
        for v in [
            Visibility::Auto,
            Visibility::None,
            Visibility::Depth,
            Visibility::FwdBwd,
            Visibility::Both,
        ] {
            let s = serde_json::to_value(v).unwrap();
            assert_eq!(s, v.name());
        }
        assert_eq!(serde_json::to_value(Sampling::Nearest).unwrap(), "nearest");
        assert_eq!(
            serde_json::to_value(Grouping::Consensus).unwrap(),
            "consensus"
        );
    }
}
