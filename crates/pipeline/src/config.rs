//! Every parameter of every stage, with the paper's values as defaults, readable from a
//! TOML file and overridable by `stage.key=value` assignments (the `--set` flag).
//!
//! Unknown sections or keys are errors (a typo must not silently fall back to a default),
//! and the effective configuration is written next to the outputs as `config.toml`, so a
//! run can be repeated exactly with `--config out/config.toml`.

use serde::{Deserialize, Serialize};

use crate::error::{PipelineError, Result};

/// The whole configuration, one section per stage.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// gs-init: triangulated initial Gaussians (paper 3.1).
    pub gs_init: GsInit,
    /// warp-graph: 3D Context Proposals (paper 3.2, Algorithm 1).
    pub warp_graph: WarpGraph,
    /// fuse: registration of proposal descriptors (paper 3.3).
    pub fuse: Fuse,
    /// pq: product quantisation (paper 3.4).
    pub pq: PqConfig,
    /// query: open-vocabulary selection (paper 3.4, 4.2).
    pub query: Query,
    /// vertex-transfer: mesh-vertex labels (paper 4.3).
    pub vertex_transfer: VertexTransfer,
}

/// gs-init parameters (EDGS / paper values).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GsInit {
    /// Reference views chosen by k-means over camera poses.
    pub references: usize,
    /// Neighbours per reference by pose distance.
    pub neighbours: usize,
    /// A match is confident when its certainty is above this.
    pub certainty_threshold: f64,
    /// Confident matches sampled per reference view.
    pub budget: usize,
    /// Seed of the reference k-means and of the sampling.
    pub seed: u64,
    /// Largest reprojection error (pixels) accepted in each view.
    pub max_reproj_px: f64,
    /// Smallest triangulation angle (degrees).
    pub min_angle_deg: f64,
    /// A point needs camera z > near in both views.
    pub near: f64,
    /// Initial scale rule: `pixels:P`, `distance:F` or `knn:K`.
    pub scale: String,
}

impl Default for GsInit {
    fn default() -> Self {
        let p = gs_init::Params::default();
        GsInit {
            references: p.references,
            neighbours: p.neighbours,
            certainty_threshold: p.certainty_threshold,
            budget: p.budget,
            seed: p.seed,
            max_reproj_px: p.max_reproj_px,
            min_angle_deg: p.min_angle_deg,
            near: p.near,
            scale: "pixels:1".into(),
        }
    }
}

impl GsInit {
    /// The crate's parameters.
    pub fn params(&self) -> Result<gs_init::Params> {
        let scale = parse_scale(&self.scale)?;
        Ok(gs_init::Params {
            references: self.references,
            neighbours: self.neighbours,
            certainty_threshold: self.certainty_threshold,
            budget: self.budget,
            seed: self.seed,
            max_reproj_px: self.max_reproj_px,
            min_angle_deg: self.min_angle_deg,
            near: self.near,
            scale,
        })
    }
}

fn parse_scale(s: &str) -> Result<gs_init::Scale> {
    let bad = || PipelineError::Config {
        key: "gs_init.scale".into(),
        detail: format!("{s:?}; expected pixels[:P], distance[:F] or knn[:K]"),
    };
    let (mode, value) = s.split_once(':').unwrap_or((s, ""));
    let num = |default: f64| -> Result<f64> {
        if value.is_empty() {
            Ok(default)
        } else {
            value.parse().map_err(|_| bad())
        }
    };
    Ok(match mode {
        "pixels" => gs_init::Scale::Pixels { pixels: num(1.0)? },
        "distance" => gs_init::Scale::Distance {
            factor: num(0.0005)?,
        },
        "knn" => gs_init::Scale::Knn {
            k: if value.is_empty() {
                3
            } else {
                value.parse().map_err(|_| bad())?
            },
        },
        _ => return Err(bad()),
    })
}

/// warp-graph parameters (the authors' run script: tau_iou 0.2, tau_box 0.08).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarpGraph {
    /// Certainty threshold of the gate.
    pub tau_alpha: f32,
    /// Mask IoU threshold, both directions.
    pub tau_iou: f64,
    /// Bounding-box IoU threshold, both directions.
    pub tau_box: f64,
    /// Smallest proposal (masks).
    pub s_min: usize,
    /// Fewest distinct views of a proposal.
    pub v_min: usize,
    /// `bilinear` or `nearest` label warping.
    pub sampling: String,
    /// Occlusion test: `auto`, `none`, `depth`, `fwd-bwd` or `both`.
    pub visibility: String,
    /// Relative depth tolerance of the depth test.
    pub depth_tolerance: f32,
    /// Accumulated alpha below which rendered depth counts as unknown.
    pub depth_min_alpha: f32,
    /// Forward-backward tolerance in grid cells.
    pub fwd_bwd_tolerance: f32,
    /// Skip view pairs that lack one of their two warps.
    pub require_both_warps: bool,
    /// Same-view guard: masks of one view joined only with this many common linked masks
    /// (0 = off, the paper's plain connected components).
    pub same_view_support: usize,
    /// Extent rule 1: refuse a union whose two components disagree in 3D below this
    /// agreement (0 = off).
    pub extent_agreement: f64,
    /// Extent rule 2: merge components whose padded 3D boxes have at least this IoU
    /// (0 = off).
    pub extent_merge_iou: f64,
    /// Share of an extent's points trimmed on each side of each axis for its box.
    pub extent_trim: f64,
    /// Box padding on each side, as a share of the scene diagonal.
    pub extent_pad: f64,
    /// How masks become proposals: `auto` (consensus, since the pipeline always has
    /// cameras and Gaussians), `links` (paper Algorithm 1 with the guard and extent rules
    /// above) or `consensus` (view consensus over the Gaussians).
    pub grouping: String,
    /// Consensus: share of a mask's points that must carry a label in a view for the view
    /// to observe it.
    pub consensus_visible_ratio: f64,
    /// Consensus: share of the labelled points one mask must hold to contain the mask.
    pub consensus_contained_ratio: f64,
    /// Consensus: a mask split in more than this share of its observing views is
    /// under-segmented.
    pub consensus_undersegment_ratio: f64,
    /// Consensus: two clusters join when supporters >= this share of observers.
    pub consensus_threshold: f64,
    /// Consensus: most Gaussians tracked as points.
    pub consensus_max_points: usize,
    /// Consensus: unite clusters along the warp links where no view contradicts.
    pub consensus_link_merge: bool,
}

impl Default for WarpGraph {
    fn default() -> Self {
        let p = warp_graph::Params::default();
        WarpGraph {
            tau_alpha: p.tau_alpha,
            tau_iou: p.tau_iou,
            tau_box: p.tau_box,
            s_min: p.s_min,
            v_min: p.v_min,
            sampling: p.sampling.name().into(),
            visibility: p.visibility.name().into(),
            depth_tolerance: p.depth_tolerance,
            depth_min_alpha: p.depth_min_alpha,
            fwd_bwd_tolerance: p.fwd_bwd_tolerance,
            require_both_warps: p.require_both_warps,
            same_view_support: p.same_view_support.unwrap_or(0),
            extent_agreement: p.extent_agreement.unwrap_or(0.0),
            extent_merge_iou: p.extent_merge_iou.unwrap_or(0.0),
            extent_trim: p.extent_trim,
            extent_pad: p.extent_pad,
            grouping: p.grouping.name().into(),
            consensus_visible_ratio: p.consensus.visible_ratio,
            consensus_contained_ratio: p.consensus.contained_ratio,
            consensus_undersegment_ratio: p.consensus.undersegment_ratio,
            consensus_threshold: p.consensus.consensus,
            consensus_max_points: p.consensus.max_points,
            consensus_link_merge: p.consensus.link_merge,
        }
    }
}

impl WarpGraph {
    /// The crate's parameters.
    pub fn params(&self) -> Result<warp_graph::Params> {
        use warp_graph::{Sampling, Visibility};
        let sampling = match self.sampling.as_str() {
            "bilinear" => Sampling::Bilinear,
            "nearest" => Sampling::Nearest,
            other => {
                return Err(config_err(
                    "warp_graph.sampling",
                    other,
                    "bilinear or nearest",
                ))
            }
        };
        let visibility = match self.visibility.as_str() {
            "auto" => Visibility::Auto,
            "none" => Visibility::None,
            "depth" => Visibility::Depth,
            "fwd-bwd" => Visibility::FwdBwd,
            "both" => Visibility::Both,
            other => {
                return Err(config_err(
                    "warp_graph.visibility",
                    other,
                    "auto, none, depth, fwd-bwd or both",
                ))
            }
        };
        let grouping = warp_graph::Grouping::parse(&self.grouping).ok_or_else(|| {
            config_err(
                "warp_graph.grouping",
                &self.grouping,
                "auto, links or consensus",
            )
        })?;
        Ok(warp_graph::Params {
            grouping,
            consensus: warp_graph::ConsensusParams {
                visible_ratio: self.consensus_visible_ratio,
                contained_ratio: self.consensus_contained_ratio,
                undersegment_ratio: self.consensus_undersegment_ratio,
                consensus: self.consensus_threshold,
                max_points: self.consensus_max_points,
                link_merge: self.consensus_link_merge,
            },
            tau_alpha: self.tau_alpha,
            tau_iou: self.tau_iou,
            tau_box: self.tau_box,
            s_min: self.s_min,
            v_min: self.v_min,
            sampling,
            visibility,
            depth_tolerance: self.depth_tolerance,
            depth_min_alpha: self.depth_min_alpha,
            fwd_bwd_tolerance: self.fwd_bwd_tolerance,
            require_both_warps: self.require_both_warps,
            same_view_support: (self.same_view_support > 0).then_some(self.same_view_support),
            extent_agreement: (self.extent_agreement > 0.0).then_some(self.extent_agreement),
            extent_merge_iou: (self.extent_merge_iou > 0.0).then_some(self.extent_merge_iou),
            extent_trim: self.extent_trim,
            extent_pad: self.extent_pad,
            ..warp_graph::Params::default()
        })
    }
}

/// fuse parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Fuse {
    /// Top-K contributors per pixel (paper: 10).
    pub k: usize,
    /// Masks without a proposal: `ignore` (paper) or `singleton`.
    pub orphans: String,
    /// The Dr. Splat-style baseline: every mask registers its own feature.
    pub no_proposals: bool,
    /// What a mask's pixels register: `proposals` (paper: its proposal's descriptor) or
    /// `blend` (its proposal's descriptor blended with its own feature by how well it
    /// agrees with the proposal, `profuse_fuse::Grouping::Blend`). Ignored with
    /// `no_proposals`.
    pub registration: String,
}

impl Default for Fuse {
    fn default() -> Self {
        Fuse {
            k: profuse_fuse::DEFAULT_K,
            orphans: profuse_fuse::Orphans::default().name().into(),
            no_proposals: false,
            registration: "proposals".into(),
        }
    }
}

impl Fuse {
    /// The groups of the configured registration over `proposals`.
    pub fn groups(
        &self,
        masks: &profuse_formats::Masks,
        proposals: &profuse_formats::Proposals,
        proposals_name: &str,
    ) -> Result<profuse_fuse::Groups> {
        let orphans = profuse_fuse::Orphans::parse(&self.orphans)
            .ok_or_else(|| config_err("fuse.orphans", &self.orphans, "ignore or singleton"))?;
        let groups = match self.registration.as_str() {
            "proposals" => {
                profuse_fuse::Groups::from_proposals(masks, proposals, orphans, proposals_name)
            }
            "blend" => profuse_fuse::Groups::blend(masks, proposals, orphans, proposals_name),
            other => return Err(config_err("fuse.registration", other, "proposals or blend")),
        };
        groups.map_err(|e| PipelineError::Stage {
            stage: "fuse",
            source: Box::new(e),
        })
    }
}

/// pq parameters (faiss defaults; Dr. Splat's PQ128x8).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PqConfig {
    /// Sub-quantisers M (the descriptor dimension must be a multiple).
    pub m: usize,
    /// Lloyd iterations.
    pub iters: usize,
    /// Most training vectors.
    pub sample: usize,
    /// Seed.
    pub seed: u64,
}

impl Default for PqConfig {
    fn default() -> Self {
        let p = profuse_pq::TrainParams::default();
        PqConfig {
            m: p.m,
            iters: p.iters,
            sample: p.sample,
            seed: p.seed,
        }
    }
}

impl PqConfig {
    /// The crate's parameters.
    pub fn params(&self) -> profuse_pq::TrainParams {
        profuse_pq::TrainParams {
            m: self.m,
            iters: self.iters,
            sample: self.sample,
            seed: self.seed,
        }
    }
}

/// query parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Query {
    /// `relevancy` (LERF, with the canonical negatives) or `cosine`.
    pub score: String,
    /// Selection threshold τ on the score.
    pub threshold: f32,
    /// Silhouette threshold γ of the per-view masks.
    pub gamma: f32,
    /// Top-K contributors per pixel for the masks.
    pub k: usize,
    /// Prompts to query; empty = the categories of the LERF label files when the scene has
    /// them, else every class prompt.
    pub prompts: Vec<String>,
    /// Also write overlays of the selections on the rendered views.
    pub overlay: bool,
}

impl Default for Query {
    fn default() -> Self {
        Query {
            score: "relevancy".into(),
            threshold: profuse_query::DEFAULT_RELEVANCY_THRESHOLD,
            gamma: profuse_query::DEFAULT_GAMMA,
            k: profuse_query::DEFAULT_TOP_K,
            prompts: Vec::new(),
            overlay: true,
        }
    }
}

/// vertex-transfer parameters (paper 4.3: K 64, σ 3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VertexTransfer {
    /// Nearest Gaussian centres per vertex.
    pub k: usize,
    /// Mahalanobis gate.
    pub sigma: f32,
    /// Softmax temperature over class cosines.
    pub temperature: f32,
    /// Smallest Gaussian scale used in the covariance (guards degenerate Gaussians).
    pub min_scale: f32,
}

impl Default for VertexTransfer {
    fn default() -> Self {
        let p = vertex_transfer::Params::default();
        VertexTransfer {
            k: p.k,
            sigma: p.sigma,
            temperature: p.temperature,
            min_scale: p.min_scale,
        }
    }
}

impl VertexTransfer {
    /// The crate's parameters.
    pub fn params(&self) -> vertex_transfer::Params {
        vertex_transfer::Params {
            k: self.k,
            sigma: self.sigma,
            temperature: self.temperature,
            min_scale: self.min_scale,
        }
    }
}

fn config_err(key: &str, value: &str, expected: &str) -> PipelineError {
    PipelineError::Config {
        key: key.into(),
        detail: format!("{value:?}; expected {expected}"),
    }
}

impl Config {
    /// Parses a TOML configuration (missing keys take their defaults); `label` names the
    /// file in errors.
    pub fn from_toml(text: &str, label: &str) -> Result<Config> {
        toml::from_str(text).map_err(|e| PipelineError::Config {
            key: label.into(),
            detail: e.to_string(),
        })
    }

    /// Applies the keys of a TOML configuration on top of this one: a key the text sets
    /// wins, every other key keeps its value here (unlike [`Config::from_toml`], whose
    /// missing keys take the paper's defaults). Unknown sections or keys are errors;
    /// `label` names the file in errors.
    pub fn with_toml(&self, text: &str, label: &str) -> Result<Config> {
        let err = |detail: String| PipelineError::Config {
            key: label.into(),
            detail,
        };
        let overlay: toml::Table = toml::from_str(text).map_err(|e| err(e.to_string()))?;
        // Checks the sections and keys (and their types) first.
        Config::from_toml(text, label)?;
        let mut table = toml::Table::try_from(self).map_err(|e| err(e.to_string()))?;
        for (section, value) in overlay {
            let (Some(toml::Value::Table(base)), toml::Value::Table(keys)) =
                (table.get_mut(&section), value)
            else {
                return Err(err(format!("[{section}] is not a section")));
            };
            base.extend(keys);
        }
        toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| err(e.to_string()))
    }

    /// Applies `section.key=value` assignments (values in TOML syntax; a bare word is taken
    /// as a string), in order.
    pub fn with_overrides(&self, assignments: &[String]) -> Result<Config> {
        let mut table = toml::Table::try_from(self).map_err(|e| PipelineError::Config {
            key: "config".into(),
            detail: e.to_string(),
        })?;
        for a in assignments {
            let (path, value) = a.split_once('=').ok_or_else(|| PipelineError::Config {
                key: a.clone(),
                detail: "expected section.key=value".into(),
            })?;
            let (section, key) =
                path.trim()
                    .split_once('.')
                    .ok_or_else(|| PipelineError::Config {
                        key: path.into(),
                        detail: "expected section.key (e.g. fuse.k)".into(),
                    })?;
            let value = parse_value(value.trim());
            let Some(toml::Value::Table(sec)) = table.get_mut(section) else {
                return Err(PipelineError::Config {
                    key: path.into(),
                    detail: format!(
                        "unknown section {section:?}; sections: gs_init, warp_graph, fuse, pq, query, vertex_transfer"
                    ),
                });
            };
            if !sec.contains_key(key) {
                let keys: Vec<&String> = sec.keys().collect();
                return Err(PipelineError::Config {
                    key: path.into(),
                    detail: format!("unknown key {key:?}; keys of [{section}]: {keys:?}"),
                });
            }
            sec.insert(key.to_string(), value);
        }
        toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| PipelineError::Config {
                key: "--set".into(),
                detail: e.to_string(),
            })
    }

    /// The configuration as TOML text (every key, defaults included).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every section by converting it to the crates' parameter types.
    pub fn validate(&self) -> Result<()> {
        self.gs_init.params()?;
        self.warp_graph.params()?;
        profuse_fuse::Orphans::parse(&self.fuse.orphans)
            .ok_or_else(|| config_err("fuse.orphans", &self.fuse.orphans, "ignore or singleton"))?;
        if !matches!(self.fuse.registration.as_str(), "proposals" | "blend") {
            return Err(config_err(
                "fuse.registration",
                &self.fuse.registration,
                "proposals or blend",
            ));
        }
        if !matches!(self.query.score.as_str(), "relevancy" | "cosine") {
            return Err(config_err(
                "query.score",
                &self.query.score,
                "relevancy or cosine",
            ));
        }
        Ok(())
    }
}

fn parse_value(text: &str) -> toml::Value {
    // A value is TOML (numbers, booleans, quoted strings, arrays); anything else is a
    // bare string, so `--set gs_init.scale=knn:3` works without shell-quoted quotes.
    toml::from_str::<toml::Table>(&format!("v = {text}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(text.to_string()))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_through_toml() {
        let c = Config::default();
        let back = Config::from_toml(&c.to_toml(), "x").unwrap();
        assert_eq!(back, c);
        assert_eq!(c.fuse.k, 10);
        assert_eq!(c.warp_graph.tau_iou, 0.2);
        assert_eq!(c.warp_graph.tau_box, 0.08);
        assert_eq!(c.vertex_transfer.k, 64);
        assert_eq!(c.pq.m, 128);
    }

    #[test]
    fn overrides_parse_toml_values_and_reject_unknown_keys() {
        let c = Config::default()
            .with_overrides(&[
                "fuse.k=40".into(),
                "gs_init.scale=knn:3".into(),
                "query.prompts=[\"chair\", \"bed\"]".into(),
                "fuse.no_proposals=true".into(),
            ])
            .unwrap();
        assert_eq!(c.fuse.k, 40);
        assert!(c.fuse.no_proposals);
        assert_eq!(c.gs_init.scale, "knn:3");
        assert_eq!(c.query.prompts, vec!["chair", "bed"]);
        let e = Config::default()
            .with_overrides(&["fuse.kk=4".into()])
            .unwrap_err();
        assert!(e.to_string().contains("kk"), "{e}");
        let e = Config::default()
            .with_overrides(&["fusion.k=4".into()])
            .unwrap_err();
        assert!(e.to_string().contains("fusion"), "{e}");
        let e = Config::default()
            .with_overrides(&["fuse.k=abc".into()])
            .unwrap_err();
        assert!(e.to_string().contains("--set"), "{e}");
        let e = Config::from_toml("[fuse]\nkay = 3\n", "cfg.toml").unwrap_err();
        assert!(
            e.to_string().contains("cfg.toml") && e.to_string().contains("kay"),
            "{e}"
        );
    }

    #[test]
    fn warp_graph_defaults_are_the_crates_and_zero_switches_a_rule_off() {
        let c = Config::default();
        assert_eq!(
            c.warp_graph.params().unwrap(),
            warp_graph::Params::default()
        );
        let off = c
            .with_overrides(&[
                "warp_graph.extent_agreement=0".into(),
                "warp_graph.extent_merge_iou=0.0".into(),
                "warp_graph.same_view_support=0".into(),
            ])
            .unwrap()
            .warp_graph
            .params()
            .unwrap();
        assert_eq!(off.extent_agreement, None);
        assert_eq!(off.extent_merge_iou, None);
        assert_eq!(off.same_view_support, None);
        assert_eq!(off.extent_trim, warp_graph::Params::default().extent_trim);
    }

    #[test]
    fn invalid_choices_are_config_errors() {
        let mut c = Config::default();
        c.warp_graph.visibility = "sometimes".into();
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("warp_graph.visibility"));
        let mut c = Config::default();
        c.gs_init.scale = "huge".into();
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("gs_init.scale"));
        let c = Config::default()
            .with_overrides(&["fuse.registration=\"mix\"".into()])
            .unwrap();
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("fuse.registration"));
        let c = Config::default()
            .with_overrides(&["fuse.registration=blend".into()])
            .unwrap();
        assert_eq!(c.fuse.registration, "blend");
        c.validate().unwrap();
    }

    #[test]
    fn with_toml_keeps_the_keys_the_text_does_not_set() {
        let base = Config::default()
            .with_overrides(&["pq.iters=10".into(), "fuse.k=12".into()])
            .unwrap();
        let c = base.with_toml("[fuse]\nk = 40\n", "c.toml").unwrap();
        assert_eq!((c.fuse.k, c.pq.iters), (40, 10));
        // A complete configuration replaces everything.
        let full = Config::default();
        assert_eq!(base.with_toml(&full.to_toml(), "c.toml").unwrap(), full);
        let e = base.with_toml("[fuse]\nkay = 3\n", "c.toml").unwrap_err();
        assert!(
            e.to_string().contains("c.toml") && e.to_string().contains("kay"),
            "{e}"
        );
        assert!(base.with_toml("k = 3\n", "c.toml").is_err());
    }
}
