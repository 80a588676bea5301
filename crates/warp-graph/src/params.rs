//! Parameters of Algorithm 1 and their defaults (with the reasons for them).

use crate::consensus::ConsensusParams;
use crate::error::{Result, WarpGraphError};

/// How the label map of view j is sampled at a warped (sub-pixel) position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Sampling {
    /// Bilinear weights over the four mask pixels whose centres surround the position
    /// (paper eq. warp: "bilinear sampling at sub-pixel accuracy"); each label receives the
    /// sum of its weights, so a warped mask is a fractional (soft) mask.
    #[default]
    Bilinear,
    /// The label of the mask pixel containing the position (weight 1).
    Nearest,
}

impl Sampling {
    /// Name used in metadata, reports and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Sampling::Bilinear => "bilinear",
            Sampling::Nearest => "nearest",
        }
    }
}

/// Which occlusion test forms `vis_mask` (paper eq. gate).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Visibility {
    /// The best available: `Both` when cameras and Gaussians are given, else `FwdBwd`.
    #[default]
    Auto,
    /// No occlusion test: vis_mask is all true.
    None,
    /// Depth rendered from the Gaussians in both views (needs cameras and Gaussians).
    Depth,
    /// Forward-backward consistency of the two warps of a view pair.
    FwdBwd,
    /// `Depth` and `FwdBwd` together (a cell must pass both).
    Both,
}

impl Visibility {
    /// Name used in metadata, reports and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Visibility::Auto => "auto",
            Visibility::None => "none",
            Visibility::Depth => "depth",
            Visibility::FwdBwd => "fwd-bwd",
            Visibility::Both => "both",
        }
    }

    /// Whether the depth test is part of this mode.
    pub fn uses_depth(self) -> bool {
        matches!(self, Visibility::Depth | Visibility::Both)
    }

    /// Whether the forward-backward test is part of this mode.
    pub fn uses_fwd_bwd(self) -> bool {
        matches!(self, Visibility::FwdBwd | Visibility::Both)
    }
}

/// How the masks become proposals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Grouping {
    /// The default: `Consensus` when cameras and Gaussians are given, else `Links`. On
    /// the accuracy sweep (crate README, "Measured") the consensus grouping keeps
    /// proposals pure where the link grouping chains objects, and is never far behind it.
    #[default]
    Auto,
    /// Union of the linked masks (paper Algorithm 1): plain connected components with
    /// `same_view_support = None`, else the guarded union with the extent rules.
    Links,
    /// View consensus over the Gaussian centres (MaskClustering-style; see the
    /// `consensus` module docs): needs cameras and Gaussians. The warp links are still
    /// computed and reported, but the proposals come from the consensus.
    Consensus,
}

impl Grouping {
    /// Name used in metadata, reports and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Grouping::Auto => "auto",
            Grouping::Links => "links",
            Grouping::Consensus => "consensus",
        }
    }

    /// Parses [`Grouping::name`].
    pub fn parse(s: &str) -> Option<Grouping> {
        match s {
            "auto" => Some(Grouping::Auto),
            "links" => Some(Grouping::Links),
            "consensus" => Some(Grouping::Consensus),
            _ => None,
        }
    }
}

/// Parameters of the cross-view mask association (paper Algorithm 1).
///
/// Defaults: `tau_iou = 0.2` and `tau_box = 0.08` are the values of the authors' run
/// script (the paper gives none). `tau_alpha = 0.5`: the gate only has to keep reliable
/// correspondences, and IoU is a ratio, so dropping uncertain cells costs little while
/// admitting wrong matches dilutes every overlap; 0.5 is the matcher saying "more likely
/// right than wrong". EDGS's 0.05 is a *sampling* threshold for triangulation, where recall
/// matters more than precision. `s_min = v_min = 2`: a proposal needs at least one
/// cross-view link, the minimum of multi-view evidence (edges only join different views,
/// so every linked component has at least two views). `depth_tolerance = 0.1`: depth
/// rendered from initial Gaussians blends surfaces at silhouettes and where coverage is thin
/// (on the synthetic demo scene's ground-truth Gaussians: median relative error 0.6%, 90th
/// percentile 19%); 5% rejected about 15% of the correct correspondences there, 10% about
/// 8%, while a real occlusion changes depth by far more. `same_view_support = Some(1)`: a
/// deviation from the paper's plain connected components, see [`Params::same_view_support`].
/// The extent rules (`extent_agreement = Some(0.3)`, `extent_merge_iou = Some(0.1)`) are a
/// second one, active only with the guard and with depth (cameras and Gaussians); their
/// values sit in the middle of a plateau (agreement 0.2-0.4 and merge IoU 0.05-0.2 change
/// the mean ARI over eight synthetic demo scenes by less than 0.005).
///
/// As serde (the pipeline's `[warp_graph]` section), every parameter is one flat key:
/// see [`crate::FlatParams`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(from = "crate::FlatParams", into = "crate::FlatParams")]
pub struct Params {
    /// Certainty threshold τ_α of the gate Γ = [α >= τ_α] ∧ vis_mask, in [0, 1].
    pub tau_alpha: f32,
    /// Mask IoU threshold τ_iou, in [0, 1], required in both directions.
    pub tau_iou: f64,
    /// Bounding-box IoU threshold τ_box, in [0, 1], required in both directions.
    pub tau_box: f64,
    /// Minimal members of a proposal (s_min >= 1).
    pub s_min: usize,
    /// Minimal distinct views of a proposal (v_min >= 1).
    pub v_min: usize,
    /// How view j's labels are sampled at the warped positions.
    pub sampling: Sampling,
    /// The occlusion test of the gate.
    pub visibility: Visibility,
    /// Depth test: relative tolerance on |z_j − D_j(q)| / D_j(q) (> 0).
    pub depth_tolerance: f32,
    /// Depth test: a rendered depth counts only where the accumulated alpha reaches this
    /// (in (0, 1]); elsewhere there is no depth evidence and the cell is not rejected.
    pub depth_min_alpha: f32,
    /// Forward-backward test: largest round-trip error, in cells of the warp grid (> 0).
    pub fwd_bwd_tolerance: f32,
    /// When only one of the two warps of a view pair exists, `false` judges the pair on
    /// that one direction, `true` skips the pair (no edges from it).
    pub require_both_warps: bool,
    /// Views whose rendered depth is kept in memory at once (an LRU cache, >= 1).
    pub depth_cache_views: usize,
    /// `None`: proposals are the plain connected components of Algorithm 1. `Some(s)`
    /// (default `Some(1)`): links are applied strongest first (smaller of the two
    /// directions' IoUs, ties by mask ids), and a union is refused when it would put two
    /// masks of one view into one proposal while fewer than `s` masks of other views link to
    /// both of them. Two masks of one view are disjoint image regions; they belong to one
    /// object when the object was split (then the whole object's masks in the neighbouring
    /// views link to both halves), but an under-segmented mask covering objects A and B
    /// links to A's and B's masks alike, and plain components then glue the two objects
    /// (and, by chains of such masks, most of a scene) into one proposal. On the synthetic
    /// demo scenes (default fault model) this raises the adjusted Rand index against the
    /// true objects from 0.11-0.46 to 0.81-0.88.
    pub same_view_support: Option<usize>,
    /// Extent rule 1 (needs depth: cameras and Gaussians; only with the same-view guard).
    /// `Some(t)` (default `Some(0.3)`): a link that would unite two components of two masks
    /// or more is refused when their 3D extents disagree: the larger of "share of A's
    /// points inside B's padded box" and the converse is below `t`. Every mask's cells are
    /// lifted to world points with the rendered depth; see the crate documentation. An
    /// under-segmented mask links two objects' components by one edge, and the warps hold
    /// no evidence against it (the two objects never share a view pair), but the two
    /// components lie apart in 3D. `None`: off.
    pub extent_agreement: Option<f64>,
    /// Extent rule 2 (needs depth; only with the same-view guard). `Some(t)` (default
    /// `Some(0.1)`): after the links, components of two masks or more whose padded 3D
    /// boxes have IoU >= `t` are merged, largest IoU first, unless the same-view guard
    /// objects. It joins fragments of one object that no warp pair connects (seen from
    /// opposite sides of an orbit, or with gated cells too sparse for the box test).
    /// `None`: off.
    pub extent_merge_iou: Option<f64>,
    /// Share of an extent's points left out on each side of each axis when its box is
    /// taken, in [0, 0.5) (default 0.05: a few wrong depths do not stretch it).
    pub extent_trim: f64,
    /// Padding of every box on each side, as a share of the scene diagonal (default 0.01:
    /// planar surfaces have boxes of almost no thickness, and a box IoU needs volume).
    pub extent_pad: f64,
    /// How masks become proposals (default [`Grouping::Auto`]).
    pub grouping: Grouping,
    /// Parameters of [`Grouping::Consensus`].
    pub consensus: ConsensusParams,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            tau_alpha: 0.5,
            tau_iou: 0.2,
            tau_box: 0.08,
            s_min: 2,
            v_min: 2,
            sampling: Sampling::Bilinear,
            visibility: Visibility::Auto,
            depth_tolerance: 0.1,
            depth_min_alpha: 0.5,
            fwd_bwd_tolerance: 2.0,
            require_both_warps: false,
            depth_cache_views: 8,
            same_view_support: Some(1),
            extent_agreement: Some(0.3),
            extent_merge_iou: Some(0.1),
            extent_trim: 0.05,
            extent_pad: 0.01,
            grouping: Grouping::Auto,
            consensus: ConsensusParams::default(),
        }
    }
}

impl Params {
    /// Checks every parameter's domain.
    pub fn validate(&self) -> Result<()> {
        let bad = |name: &'static str, value: String, expected: &'static str| {
            Err(WarpGraphError::InvalidParameter {
                name,
                value,
                expected,
            })
        };
        let unit = |v: f64| v.is_finite() && (0.0..=1.0).contains(&v);
        if !unit(f64::from(self.tau_alpha)) {
            return bad(
                "tau_alpha",
                self.tau_alpha.to_string(),
                "a number in [0, 1]",
            );
        }
        if !unit(self.tau_iou) {
            return bad("tau_iou", self.tau_iou.to_string(), "a number in [0, 1]");
        }
        if !unit(self.tau_box) {
            return bad("tau_box", self.tau_box.to_string(), "a number in [0, 1]");
        }
        if self.s_min == 0 {
            return bad("s_min", "0".into(), "an integer >= 1");
        }
        if self.v_min == 0 {
            return bad("v_min", "0".into(), "an integer >= 1");
        }
        if !(self.depth_tolerance.is_finite() && self.depth_tolerance > 0.0) {
            return bad(
                "depth_tolerance",
                self.depth_tolerance.to_string(),
                "a finite number > 0",
            );
        }
        if !(self.depth_min_alpha > 0.0 && self.depth_min_alpha <= 1.0) {
            return bad(
                "depth_min_alpha",
                self.depth_min_alpha.to_string(),
                "a number in (0, 1]",
            );
        }
        if !(self.fwd_bwd_tolerance.is_finite() && self.fwd_bwd_tolerance > 0.0) {
            return bad(
                "fwd_bwd_tolerance",
                self.fwd_bwd_tolerance.to_string(),
                "a finite number > 0 (grid cells)",
            );
        }
        if self.same_view_support == Some(0) {
            return bad("same_view_support", "0".into(), "an integer >= 1 (or none)");
        }
        for (name, v) in [
            ("extent_agreement", self.extent_agreement),
            ("extent_merge_iou", self.extent_merge_iou),
        ] {
            if let Some(v) = v {
                if !unit(v) {
                    return bad(name, v.to_string(), "a number in [0, 1] (or none)");
                }
            }
        }
        if !(self.extent_trim.is_finite() && (0.0..0.5).contains(&self.extent_trim)) {
            return bad(
                "extent_trim",
                self.extent_trim.to_string(),
                "a number in [0, 0.5)",
            );
        }
        if !(self.extent_pad.is_finite() && self.extent_pad >= 0.0) {
            return bad(
                "extent_pad",
                self.extent_pad.to_string(),
                "a finite number >= 0",
            );
        }
        let c = &self.consensus;
        for (name, v) in [
            ("consensus_visible_ratio", c.visible_ratio),
            ("consensus_contained_ratio", c.contained_ratio),
            ("consensus_undersegment_ratio", c.undersegment_ratio),
            ("consensus_threshold", c.consensus),
            ("consensus_union_ratio", c.union_ratio),
        ] {
            if !unit(v) {
                return bad(name, v.to_string(), "a number in [0, 1]");
            }
        }
        for (name, v) in [
            ("consensus_observed_points", c.observed_points),
            ("consensus_max_points", c.max_points),
            ("depth_cache_views", self.depth_cache_views),
        ] {
            if v == 0 {
                return bad(name, "0".into(), "an integer >= 1");
            }
        }
        Ok(())
    }
}
