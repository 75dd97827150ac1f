//! Progress of long jobs (render, observe, eval, the simulations, soak): a
//! bar redrawn in place when stderr is a terminal, a log line every tenth of
//! the work otherwise (CI logs, pipes, JSON logging).

use std::io::IsTerminal;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

#[derive(Debug)]
pub struct Progress {
    label: &'static str,
    total: u64,
    started: Instant,
    /// Only on a terminal.
    bar: Option<ProgressBar>,
    last_logged_tenth: u64,
}

const BAR_TEMPLATE: &str = "{prefix} {wide_bar} {pos}/{len} {msg}  ETA {eta}";

impl Progress {
    pub fn new(label: &'static str, total: u64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
            bar.set_style(ProgressStyle::with_template(BAR_TEMPLATE).unwrap_or_else(|_| ProgressStyle::default_bar()));
            bar.set_prefix(label);
            bar
        });
        Self { label, total, started: Instant::now(), bar, last_logged_tenth: 0 }
    }

    /// Reports `done` of the total units, with a short note on the current one.
    pub fn update(&mut self, done: u64, note: &str) {
        if let Some(bar) = &self.bar {
            bar.set_message(note.to_owned());
            bar.set_position(done);
            if done >= self.total {
                bar.finish();
            }
            return;
        }
        let tenth = done * 10 / self.total.max(1);
        if tenth > self.last_logged_tenth || done == self.total {
            self.last_logged_tenth = tenth;
            let eta_s = remaining_s(self.started.elapsed().as_secs_f64(), done, self.total).round();
            tracing::info!(done, total = self.total, eta_s, "{} {note}", self.label);
        }
    }
}

/// Seconds left at the rate so far, after `elapsed_s` for `done` of `total`.
fn remaining_s(elapsed_s: f64, done: u64, total: u64) -> f64 {
    elapsed_s / done.max(1) as f64 * total.saturating_sub(done) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_remaining_time_extrapolates_the_rate_so_far() {
        assert_eq!(remaining_s(10.0, 1, 4), 30.0);
        assert_eq!(remaining_s(10.0, 4, 4), 0.0);
        // Nothing done yet: the elapsed time stands for one unit.
        assert_eq!(remaining_s(2.0, 0, 3), 6.0);
        assert_eq!(remaining_s(5.0, 9, 3), 0.0);
    }
}
