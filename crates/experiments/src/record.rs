//! What `profuse run`, `demo` and `sweep` do besides parsing arguments when a scene may
//! carry ground truth: the demo's configuration, and running, scoring and recording a scene.

use std::path::Path;

use serde_json::{json, Value};

use profuse_pipeline::cli::read_config_file;
use profuse_pipeline::config::Config;
use profuse_pipeline::support::write_text;
use profuse_pipeline::{run, Event, Paths, Result, RunOptions};

use crate::evaluate::evaluate_run;

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
