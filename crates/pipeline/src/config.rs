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
    pub gs_init: gs_init::FlatParams,
    /// gs-refine: photometric refinement of gs-init's Gaussians (paper 3.1, after EDGS);
    /// `iterations = 0` (the default) skips the stage.
    pub gs_refine: gs_refine::job::JobParams,
    /// warp-graph: 3D Context Proposals (paper 3.2, Algorithm 1).
    pub warp_graph: warp_graph::Params,
    /// fuse: registration of proposal descriptors (paper 3.3).
    pub fuse: profuse_fuse::job::Params,
    /// pq: product quantisation (paper 3.4).
    pub pq: profuse_pq::TrainParams,
    /// query: open-vocabulary selection (paper 3.4, 4.2).
    pub query: profuse_query::Params,
    /// vertex-transfer: mesh-vertex labels (paper 4.3).
    pub vertex_transfer: vertex_transfer::Params,
}

/// A section whose values parse but lie outside their stage's domains; the stage's own
/// error names the parameter and the domain.
fn out_of_domain(section: &str, e: impl std::fmt::Display) -> PipelineError {
    PipelineError::Config {
        key: section.into(),
        detail: e.to_string(),
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
        with_overrides(self, assignments)
    }

    /// The configuration as TOML text (every key, defaults included).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every section by converting it to the crates' parameter types.
    pub fn validate(&self) -> Result<()> {
        gs_init::Params::from(self.gs_init)
            .validate()
            .map_err(|e| out_of_domain("gs_init", e))?;
        self.warp_graph
            .validate()
            .map_err(|e| out_of_domain("warp_graph", e))?;
        self.validate_late_stages()
    }

    /// The parameters that used to fail only when their stage ran, after the earlier
    /// stages had spent their time (fuse, pq, query).
    fn validate_late_stages(&self) -> Result<()> {
        let bad = |key: &str, value: String, expected: &str| PipelineError::Config {
            key: key.into(),
            detail: format!("{value}: expected {expected}"),
        };
        let max_k = splat_raster::MAX_TOP_K;
        let f = &self.fuse;
        if f.k == 0 || f.k > max_k {
            return Err(bad("fuse.k", f.k.to_string(), &format!("1..={max_k}")));
        }
        if !(0.0..=1.0).contains(&f.min_share) {
            return Err(bad(
                "fuse.min_share",
                f.min_share.to_string(),
                "a share in [0, 1]",
            ));
        }
        if !(f.pixel_share_power.is_finite() && f.pixel_share_power >= 0.0) {
            let v = f.pixel_share_power.to_string();
            return Err(bad("fuse.pixel_share_power", v, "a finite number >= 0"));
        }
        if self.pq.m == 0 {
            return Err(bad(
                "pq.m",
                "0".into(),
                "a number of sub-quantisers >= 1 dividing the descriptors' dimension",
            ));
        }
        if self.pq.sample < profuse_pq::KSUB {
            let v = self.pq.sample.to_string();
            return Err(bad(
                "pq.sample",
                v,
                &format!(">= {} (one centroid each)", profuse_pq::KSUB),
            ));
        }
        let q = &self.query;
        if !q.threshold.is_finite() {
            return Err(bad(
                "query.threshold",
                q.threshold.to_string(),
                "a finite number",
            ));
        }
        if !q.gamma.is_finite() {
            return Err(bad("query.gamma", q.gamma.to_string(), "a finite number"));
        }
        if q.k == 0 || q.k > max_k {
            return Err(bad("query.k", q.k.to_string(), &format!("1..={max_k}")));
        }
        Ok(())
    }
}

/// Applies `section.key=value` assignments to any sectioned configuration (this one, or
/// `profuse prepare`'s): unknown sections and keys are errors that list the known ones.
pub(crate) fn with_overrides<T>(config: &T, assignments: &[String]) -> Result<T>
where
    T: Serialize + serde::de::DeserializeOwned,
{
    let mut table = toml::Table::try_from(config).map_err(|e| PipelineError::Config {
        key: "config".into(),
        detail: e.to_string(),
    })?;
    let sections: Vec<String> = table
        .iter()
        .filter(|(_, v)| v.is_table())
        .map(|(k, _)| k.clone())
        .collect();
    for a in assignments {
        let (path, value) = a.split_once('=').ok_or_else(|| PipelineError::Config {
            key: a.clone(),
            detail: "expected section.key=value".into(),
        })?;
        let (section, key) = path
            .trim()
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
                    "unknown section {section:?}; sections: {}",
                    sections.join(", ")
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
        assert_eq!(c.gs_init.scale, gs_init::Scale::Knn { k: 3 });
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
        assert_eq!(c.warp_graph, warp_graph::Params::default());
        let off = c
            .with_overrides(&[
                "warp_graph.extent_agreement=0".into(),
                "warp_graph.extent_merge_iou=0.0".into(),
                "warp_graph.same_view_support=0".into(),
            ])
            .unwrap()
            .warp_graph;
        assert_eq!(off.extent_agreement, None);
        assert_eq!(off.extent_merge_iou, None);
        assert_eq!(off.same_view_support, None);
        assert_eq!(off.extent_trim, warp_graph::Params::default().extent_trim);
    }

    #[test]
    fn invalid_choices_are_config_errors() {
        let e = Config::default()
            .with_overrides(&["warp_graph.visibility=sometimes".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("visibility") && e.contains("fwd-bwd"), "{e}");
        let e = Config::default()
            .with_overrides(&["gs_init.scale=huge".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("scale") && e.contains("pixels"), "{e}");
        let c = Config::default()
            .with_overrides(&["warp_graph.tau_iou=1.5".into()])
            .unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("warp_graph") && e.contains("tau_iou"), "{e}");
        let e = Config::default()
            .with_overrides(&["fuse.registration=\"mix\"".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("registration") && e.contains("blend"), "{e}");
        let e = Config::default()
            .with_overrides(&["fuse.orphans=some".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("orphans") && e.contains("singleton"), "{e}");
        let c = Config::default()
            .with_overrides(&["fuse.registration=blend".into()])
            .unwrap();
        assert_eq!(c.fuse.registration, profuse_fuse::job::Register::Blend);
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
