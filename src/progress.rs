//! Progress bars of long work (training, evaluation), in one style, hidden
//! when the output is not a terminal.

use indicatif::{ProgressBar, ProgressStyle};

/// A progress bar in the style used across the CLI (hidden when not a TTY).
pub fn progress_bar(len: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    if let Ok(style) =
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}")
    {
        pb.set_style(style);
    }
    pb.set_message(what.to_string());
    pb
}
