//! Progress of the pipeline's stages on stderr: one bar per running stage, then a line
//! saying how long it took or that it was up to date.

use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressStyle};
use profuse_pipeline::Event;

/// Draws [`Event`]s when on (see [`crate::chatty`]).
#[derive(Debug)]
pub struct StageBars {
    on: bool,
    bar: Mutex<Option<ProgressBar>>,
}

impl StageBars {
    /// Bars drawn when `on`.
    pub fn new(on: bool) -> StageBars {
        StageBars {
            on,
            bar: Mutex::new(None),
        }
    }

    /// Shows one event.
    pub fn event(&self, e: Event<'_>) {
        if !self.on {
            return;
        }
        let Ok(mut bar) = self.bar.lock() else {
            return;
        };
        match e {
            Event::Start { stage, reason } => {
                let b = ProgressBar::new(0);
                b.set_style(
                    ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} {msg}")
                        .unwrap_or_else(|_| ProgressStyle::default_bar())
                        .progress_chars("=> "),
                );
                b.set_prefix(stage.to_string());
                b.set_message(format!("({reason})"));
                *bar = Some(b);
            }
            Event::Progress { done, total } => {
                if let Some(b) = bar.as_ref() {
                    b.set_length(total);
                    b.set_position(done);
                }
            }
            Event::Done {
                stage,
                ran,
                seconds,
            } => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
                if ran {
                    eprintln!("{stage:>16} done in {seconds:.2} s");
                } else {
                    eprintln!("{stage:>16} up to date");
                }
            }
        }
    }
}
