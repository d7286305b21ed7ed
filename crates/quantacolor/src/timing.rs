//! Wall-clock timing of pipeline stages (reported in `report.toml` and by `bench speed`).
//! Shared by [`crate::burst`] and [`crate::pipeline`] so that neither imports the other for it.
//! Timings are reported, never used to decide anything, so outputs stay deterministic.
#![forbid(unsafe_code)]

use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Wall-clock time of one stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageTiming {
    pub stage: String,
    pub seconds: f64,
}

impl StageTiming {
    /// The time from `start` until now, recorded as `stage`.
    pub fn since(stage: &str, start: Instant) -> Self {
        StageTiming {
            stage: stage.to_string(),
            seconds: start.elapsed().as_secs_f64(),
        }
    }
}

/// Wall-clock laps of consecutive stages: each [`Laps::lap`] records the time since the
/// previous lap (or since [`Laps::new`]).
pub struct Laps {
    last: Instant,
    pub timings: Vec<StageTiming>,
}

impl Laps {
    pub fn new() -> Self {
        Laps {
            last: Instant::now(),
            timings: Vec::new(),
        }
    }

    /// Records the time since the previous lap as `stage` (added to its time when the stage
    /// ran before: a stage run once per span of frames is reported once) and starts the next
    /// lap.
    pub fn lap(&mut self, stage: &str) {
        let timing = StageTiming::since(stage, self.last);
        match self.timings.iter_mut().find(|t| t.stage == stage) {
            Some(earlier) => earlier.seconds += timing.seconds,
            None => self.timings.push(timing),
        }
        self.last = Instant::now();
    }
}

impl Default for Laps {
    fn default() -> Self {
        Laps::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laps_record_one_timing_per_stage_in_order() {
        let mut laps = Laps::new();
        laps.lap("align");
        laps.lap("merge");
        let names: Vec<_> = laps.timings.iter().map(|t| t.stage.as_str()).collect();
        assert_eq!(names, ["align", "merge"]);
        assert!(laps.timings.iter().all(|t| t.seconds >= 0.0));
        std::thread::sleep(std::time::Duration::from_millis(2));
        laps.lap("align");
        let names: Vec<_> = laps.timings.iter().map(|t| t.stage.as_str()).collect();
        assert_eq!(names, ["align", "merge"], "a stage run again is added to");
        assert!(laps.timings[0].seconds >= 0.002);
    }
}
