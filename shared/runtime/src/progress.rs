//! A progress line for long jobs: redrawn in place on a terminal, a log
//! line every tenth of the work otherwise (CI logs, pipes).

use std::io::{IsTerminal, Write};
use std::time::Instant;

#[derive(Debug)]
pub struct Progress {
    label: &'static str,
    total: u64,
    started: Instant,
    terminal: bool,
    last_logged_tenth: u64,
}

impl Progress {
    pub fn new(label: &'static str, total: u64) -> Self {
        Self { label, total, started: Instant::now(), terminal: std::io::stderr().is_terminal(), last_logged_tenth: 0 }
    }

    /// Reports `done` of the total units, with a short note on the current one.
    pub fn update(&mut self, done: u64, note: &str) {
        let total = self.total.max(1);
        let elapsed = self.started.elapsed().as_secs_f64();
        let remaining = elapsed / done.max(1) as f64 * total.saturating_sub(done) as f64;
        if self.terminal {
            const WIDTH: u64 = 30;
            let filled = (done * WIDTH / total) as usize;
            let bar = format!("{}{}", "█".repeat(filled), "░".repeat(WIDTH as usize - filled));
            let mut err = std::io::stderr().lock();
            let _ = write!(err, "\r{} {bar} {done}/{} {note}  ETA {remaining:.0} s  ", self.label, self.total);
            if done >= self.total {
                let _ = writeln!(err);
            }
            let _ = err.flush();
        } else {
            let tenth = done * 10 / total;
            if tenth > self.last_logged_tenth || done == self.total {
                self.last_logged_tenth = tenth;
                tracing::info!(done, total = self.total, eta_s = remaining.round(), "{} {note}", self.label);
            }
        }
    }
}
