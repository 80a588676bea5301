//! Runs COLMAP on a folder of photos and prints the report as JSON.
//!
//! ```text
//! cargo run --release -p profuse-sfm --example sfm -- IMAGES WORK_DIR \
//!     [--backend pycolmap|colmap] [--python PATH] [--colmap PATH] \
//!     [--threads N] [--max-image-size PX] [--sequential OVERLAP] [--deterministic]
//! ```
//!
//! Progress goes to standard error, the report (also in WORK_DIR/sfm_report.json) to
//! standard output; the model is WORK_DIR/sparse/0.

use std::path::PathBuf;
use std::process::ExitCode;

use profuse_sfm::{run_sfm, BackendKind, Locator, Matcher, SfmOptions, SfmProgress};

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let mut positional = Vec::new();
    let mut locator = Locator::default();
    let mut preference = None;
    let mut opts = SfmOptions::default();
    while let Some(arg) = args.next() {
        let mut value = || args.next().ok_or(format!("{arg} needs a value"));
        match arg.as_str() {
            "--backend" => {
                preference = Some(match value()?.as_str() {
                    "colmap" => BackendKind::ColmapCli,
                    "pycolmap" => BackendKind::Pycolmap,
                    other => return Err(format!("unknown backend {other}").into()),
                })
            }
            "--python" => locator.python = PathBuf::from(value()?),
            "--colmap" => locator.colmap = PathBuf::from(value()?),
            "--threads" => opts.threads = Some(value()?.parse()?),
            "--max-image-size" => opts.max_image_size = Some(value()?.parse()?),
            "--sequential" => {
                opts.matcher = Matcher::Sequential {
                    overlap: value()?.parse()?,
                }
            }
            "--deterministic" => opts = opts.deterministic(),
            _ if arg.starts_with("--") => return Err(format!("unknown option {arg}").into()),
            _ => positional.push(PathBuf::from(arg)),
        }
    }
    let [images, work] = <[PathBuf; 2]>::try_from(positional)
        .map_err(|_| "usage: sfm IMAGES WORK_DIR [options] (see the example's source)")?;
    let backend = locator.find(preference)?;
    eprintln!(
        "{} {} ({})",
        backend.kind,
        backend.version,
        backend.program.display()
    );
    let report = run_sfm(&backend, &images, &work, &opts, &mut |p| match p {
        SfmProgress::Started { step, images } => eprintln!("{step}: {images} images"),
        SfmProgress::Advanced { step, done, total } => eprintln!("  {step} {done}/{total}"),
        SfmProgress::Finished { step, seconds } => eprintln!("{step}: done in {seconds:.1} s"),
    })?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
