//! Summaries of measured durations, as the benchmarks and long jobs report
//! them.

use std::time::Duration;

use serde::Serialize;

/// Mean and percentiles of a set of durations, milliseconds (nearest-rank
/// percentiles; all 0 for an empty set).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Timing {
    pub mean_ms: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
}

impl Timing {
    pub fn of(mut durations: Vec<Duration>) -> Self {
        durations.sort();
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        let at = |q: f64| durations.get(((durations.len() as f64 - 1.0) * q).round() as usize).map_or(0.0, |&d| ms(d));
        let mean = durations.iter().map(|&d| ms(d)).sum::<f64>() / durations.len().max(1) as f64;
        Self { mean_ms: mean, p50_ms: at(0.5), p99_ms: at(0.99), max_ms: at(1.0) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_one_to_a_hundred_milliseconds() {
        let timing = Timing::of((1..=100).rev().map(Duration::from_millis).collect());
        assert_eq!((timing.p50_ms, timing.p99_ms, timing.max_ms), (51.0, 99.0, 100.0));
        assert!((timing.mean_ms - 50.5).abs() < 1e-9);
        assert_eq!(Timing::of(Vec::new()).max_ms, 0.0);
    }
}
