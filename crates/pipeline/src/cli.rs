//! What `profuse run` does besides parsing arguments: read the configuration files and lay
//! out the paper's Table 4 timing. (The tool only parses, displays progress and prints;
//! running, scoring and recording a synthetic scene is `profuse_experiments::record`.)

use std::collections::BTreeMap;
use std::path::Path;

use crate::config::Config;
use crate::error::{io_err, Result};

/// The text of a configuration file and its name for messages (`None`: no file).
pub fn read_config_file(path: Option<&Path>) -> Result<Option<(String, String)>> {
    path.map(|p| {
        std::fs::read_to_string(p)
            .map(|text| (text, p.display().to_string()))
            .map_err(io_err(p, "cannot read the configuration"))
    })
    .transpose()
}

/// The configuration of `profuse run`: the file's keys over the paper's defaults (or the
/// defaults alone), then the `section.key=value` assignments.
pub fn run_config(path: Option<&Path>, set: &[String]) -> Result<Config> {
    let base = match read_config_file(path)? {
        Some((text, label)) => Config::from_toml(&text, &label)?,
        None => Config::default(),
    };
    base.with_overrides(set)
}

/// The timing table in the shape of the paper's Table 4, from a summary's `timing_s`.
pub fn timing_table(t: &BTreeMap<String, f64>) -> String {
    let get = |k: &str| t.get(k).copied().unwrap_or(0.0);
    format!(
        "\n{:<12} {:>10} {:>10} {:>10} {:>10}\n\
         {:<12} {:>9.2}s {:>9.2}s {:>9.2}s {:>9.2}s   (PQ)\n\
         {:<12} gs-init {:.2} s; warp-graph {:.2} s + fuse {:.2} s; evaluation outputs (query, vertex-transfer) {:.2} s",
        "",
        "Geometry",
        "Semantics",
        "Total",
        "Indexing",
        "ProFuse-rs",
        get("geometry"),
        get("semantics"),
        get("total"),
        get("indexing"),
        "",
        get("gs-init"),
        get("warp-graph"),
        get("fuse") + get("fuse_baseline"),
        get("evaluation")
    )
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn timing_table_lays_out_the_groups() {
        let t: BTreeMap<String, f64> = [("geometry", 1.5), ("semantics", 2.25), ("total", 4.0)]
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect();
        let text = timing_table(&t);
        let row = text.lines().nth(2).unwrap();
        assert!(row.starts_with("ProFuse-rs"), "{text}");
        assert!(
            row.contains("1.50s") && row.contains("2.25s") && row.contains("4.00s"),
            "{row}"
        );
    }

    #[test]
    fn a_missing_configuration_file_is_named() {
        let e = run_config(Some(Path::new("/nonexistent/c.toml")), &[]).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/c.toml"), "{e}");
        let c = run_config(None, &["fuse.k=12".into()]).unwrap();
        assert_eq!(c.fuse.k, 12);
    }
}
