//! What `profuse run`, `demo` and `sweep` do besides parsing arguments: read the
//! configuration files, run and score a scene and record its summary, and lay out the
//! paper's Table 4 timing. (The tool only parses, displays progress and prints.)

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{json, Value};

use crate::config::Config;
use crate::error::{io_err, Result};
use crate::evaluate::evaluate_run;
use crate::run::{run, write_text, Event, Paths, RunOptions};

/// The text of a configuration file and its name for messages (`None`: no file).
fn read_config_file(path: Option<&Path>) -> Result<Option<(String, String)>> {
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

/// The configuration of `profuse demo` and `sweep`: the demo's settings, then the file's
/// keys, then the assignments ([`crate::demo::demo_config`]).
pub fn demo_config(path: Option<&Path>, set: &[String]) -> Result<Config> {
    let file = read_config_file(path)?;
    crate::demo::demo_config(file.as_ref().map(|(t, l)| (t.as_str(), l.as_str())), set)
}

/// Runs the pipeline on a scene, scores it against the scene's ground truth when it has
/// one, and writes the summary (with the scores) as `summary[_baseline].json` next to the
/// outputs. Returns that summary.
pub fn run_and_record(
    scene: &Path,
    config: &Config,
    opts: &RunOptions,
    events: &(dyn Fn(Event<'_>) + Sync),
) -> Result<Value> {
    let summary = run(scene, config, opts, events)?;
    let paths = Paths::new(scene, &summary.out, config.fuse.no_proposals);
    // A run that stopped early has nothing to score yet.
    let scores = match opts.until {
        None => json!(evaluate_run(&paths, config, &summary)?),
        Some(_) => Value::Null,
    };
    let mut value = serde_json::to_value(&summary).unwrap_or(Value::Null);
    if let Value::Object(map) = &mut value {
        map.insert("metrics".into(), json!(scores));
        map.insert("config".into(), json!(summary.out.join("config.toml")));
    }
    let text = serde_json::to_string_pretty(&value).unwrap_or_default();
    write_text(
        &summary.out.join(format!("summary{}.json", paths.suffix)),
        &text,
    )?;
    Ok(value)
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
