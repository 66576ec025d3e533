//! Progress of long-running commands: one bar per stage on a terminal, plain lines otherwise.
//!
//! Every command reports through a [`Reporter`]: `stage` starts a stage with a known amount of work,
//! `advance` / `set_position` move it, `set_message` adds a short status (a loss, a PSNR), and `log` prints
//! a line without breaking the bar. When stderr is not a terminal (a log file, CI, `nohup`) indicatif would
//! hide its bars and swallow the lines printed through them, so the reporter writes plain timestamped lines
//! instead: one when a stage starts, one when it ends, and at most one every [`PLAIN_INTERVAL`] between.
//!
//! The ETA is the stage's average pace so far applied to what is left, counting only the work done since
//! the stage started (a resumed stage's earlier work is not "instant progress"), and is "?" until the first
//! unit is done, rather than indicatif's "0s". On a GPU ([`Reporter::on_gpu`]) the first unit of a stage
//! compiles that stage's kernels (half a minute for a UNet on an H100), so the pace is taken from the units
//! after it: "?" until two are done, instead of an ETA of an hour that turns out to be a minute.

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressState, ProgressStyle};

/// Time between two plain progress lines of one stage.
pub const PLAIN_INTERVAL: Duration = Duration::from_secs(30);

/// The bar of one stage on a terminal.
const BAR_TEMPLATE: &str =
    "{prefix} [{bar:30}] {pos}/{len}, {elapsed} elapsed, ETA {honest_eta} {msg}";

/// Progress of a command, stage by stage.
pub struct Reporter {
    started: Instant,
    stage: Stage,
    out: Output,
    /// The first unit of each stage warms up (GPU kernel compilation) and is left out of the pace.
    warm_up: bool,
}

/// The stage in progress.
struct Stage {
    name: String,
    total: u64,
    /// Position when the stage started (non-zero when resuming).
    first: u64,
    done: u64,
    started: Instant,
    message: String,
    /// Microseconds from the stage's start to the end of its first unit (0: not yet), shared with the
    /// bar's ETA; set only when the first unit warms up.
    warmed: Arc<AtomicU64>,
}

enum Output {
    /// A bar per stage on a terminal; `None` before the first stage and after `finish`.
    Bars(Option<ProgressBar>),
    /// Plain lines, and when the last one was written.
    Lines { last_line: Instant },
}

impl Default for Reporter {
    fn default() -> Self {
        Self::new()
    }
}

impl Reporter {
    /// Bars when stderr is a terminal, plain lines otherwise.
    pub fn new() -> Self {
        let now = Instant::now();
        let out = if std::io::stderr().is_terminal() {
            Output::Bars(None)
        } else {
            Output::Lines { last_line: now }
        };
        Self {
            started: now,
            stage: Stage {
                name: String::new(),
                total: 0,
                first: 0,
                done: 0,
                started: now,
                message: String::new(),
                warmed: Arc::default(),
            },
            out,
            warm_up: false,
        }
    }

    /// The work runs on a GPU: each stage's first unit compiles kernels and does not count in its pace.
    pub fn on_gpu(mut self, gpu: bool) -> Self {
        self.warm_up = gpu;
        self
    }

    /// Starts a stage of `total` units.
    pub fn stage(&mut self, name: &str, total: u64) {
        self.resume_stage(name, total, 0);
    }

    /// Starts a stage of `total` units of which `done` were done earlier (a resumed run); the ETA counts
    /// only what is done from here on.
    pub fn resume_stage(&mut self, name: &str, total: u64, done: u64) {
        self.stage = Stage {
            name: name.to_string(),
            total,
            first: done,
            done,
            started: Instant::now(),
            message: String::new(),
            warmed: Arc::default(),
        };
        let warm = self.warm_up.then(|| self.stage.warmed.clone());
        match &mut self.out {
            Output::Bars(bar) => {
                if let Some(old) = bar.take() {
                    old.finish_and_clear();
                }
                *bar = Some(stage_bar(name, total, done, warm));
            }
            Output::Lines { .. } => self.line(),
        }
    }

    /// `n` more units of the current stage are done.
    pub fn advance(&mut self, n: u64) {
        self.set_position(self.stage.done + n);
    }

    /// `done` units of the current stage are done.
    pub fn set_position(&mut self, done: u64) {
        if self.warm_up && self.stage.done == self.stage.first && done > self.stage.first {
            let micros = self.stage.started.elapsed().as_micros().max(1);
            self.stage.warmed.store(micros as u64, Ordering::Relaxed);
        }
        self.stage.done = done;
        let due = match &self.out {
            Output::Bars(bar) => {
                if let Some(bar) = bar {
                    bar.set_position(done);
                }
                false
            }
            Output::Lines { last_line } => {
                last_line.elapsed() >= PLAIN_INTERVAL || done == self.stage.total
            }
        };
        if due {
            self.line();
        }
    }

    /// A short status shown after the bar (or at the end of plain lines) until the next one.
    pub fn set_message(&mut self, message: impl Into<String>) {
        self.stage.message = message.into();
        if let Output::Bars(Some(bar)) = &self.out {
            bar.set_message(self.stage.message.clone());
        }
    }

    /// A line for the log, printed above the bar (plain lines: with the time since the start).
    pub fn log(&mut self, line: &str) {
        match &self.out {
            Output::Bars(Some(bar)) => bar.println(line),
            Output::Bars(None) => eprintln!("{line}"),
            Output::Lines { .. } => eprintln!("[{}] {line}", clock(self.started.elapsed())),
        }
    }

    /// Clears the last bar (plain lines: nothing to do).
    pub fn finish(&mut self) {
        if let Output::Bars(bar) = &mut self.out {
            if let Some(bar) = bar.take() {
                bar.finish_and_clear();
            }
        }
    }

    /// One plain progress line for the current stage.
    fn line(&mut self) {
        let s = &self.stage;
        let mut text = format!(
            "[{}] {}: {}/{}",
            clock(self.started.elapsed()),
            s.name,
            s.done,
            s.total
        );
        // Pace and ETA once this stage has done something and until it is complete.
        let warm = self.warm_up.then(|| &*s.warmed);
        if let Some(each) = pace(s.first, s.done, s.started.elapsed(), warm) {
            if s.done < s.total {
                let eta = short_duration(each * (s.total - s.done) as f64);
                let _ = write!(text, ", {} each, ETA {eta}", seconds(each));
            }
        } else if self.warm_up && s.done > s.first && s.done < s.total {
            text.push_str(", first step compiled GPU kernels, ETA ?");
        }
        if !s.message.is_empty() {
            let _ = write!(text, ", {}", s.message);
        }
        eprintln!("{text}");
        if let Output::Lines { last_line } = &mut self.out {
            *last_line = Instant::now();
        }
    }
}

/// The CLI's progress for the editing pipeline (`vcedit edit`, `vcedit demo`).
impl edit::run::Progress for Reporter {
    fn stage(&mut self, name: &str, total: u64) {
        Reporter::stage(self, name, total);
    }

    fn advance(&mut self, n: u64) {
        Reporter::advance(self, n);
    }

    fn log(&mut self, line: &str) {
        Reporter::log(self, line);
    }
}

/// A terminal bar for one stage of `total` units, `done` of them done before it started; its ETA is the
/// stage's own average pace (see the module notes).
/// `warm`: the first unit is left out of the pace (see [`Reporter::on_gpu`]).
pub fn stage_bar(name: &str, total: u64, done: u64, warm: Option<Arc<AtomicU64>>) -> ProgressBar {
    let style = ProgressStyle::with_template(BAR_TEMPLATE)
        .expect("valid template")
        .with_key(
            "honest_eta",
            move |state: &ProgressState, w: &mut dyn std::fmt::Write| {
                let total = state.len().unwrap_or(0);
                let eta = eta_text(done, state.pos(), total, state.elapsed(), warm.as_deref());
                let _ = w.write_str(&eta);
            },
        )
        .progress_chars("=> ");
    let bar = ProgressBar::new(total).with_style(style);
    bar.set_prefix(name.to_string());
    bar.set_position(done);
    bar
}

/// A stage's pace, seconds per unit: `first` units were done when the stage started `elapsed` ago and
/// `done` are done now. With `warm` (microseconds to the end of the first unit, 0 while unknown) the first
/// unit is left out. `None` until a unit that counts is done.
fn pace(first: u64, done: u64, elapsed: Duration, warm: Option<&AtomicU64>) -> Option<f64> {
    let worked = done.saturating_sub(first);
    let (counted, secs) = match warm.map(|w| w.load(Ordering::Relaxed)) {
        None => (worked, elapsed.as_secs_f64()),
        Some(0) => return None,
        Some(micros) => (
            worked.saturating_sub(1),
            (elapsed.as_secs_f64() - micros as f64 * 1e-6).max(0.0),
        ),
    };
    (counted > 0).then(|| secs / counted as f64)
}

/// The time left at the stage's average pace (see [`pace`]) for `total` units; "?" while unknown.
fn eta_text(
    first: u64,
    done: u64,
    total: u64,
    elapsed: Duration,
    warm: Option<&AtomicU64>,
) -> String {
    if done >= total {
        return "0s".into();
    }
    match pace(first, done, elapsed, warm) {
        Some(each) => short_duration(each * (total - done) as f64),
        None => "?".into(),
    }
}

/// "45s", "12m 05s", "2h 03m".
fn short_duration(secs: f64) -> String {
    let s = secs.round().max(0.0) as u64;
    match s {
        0..=59 => format!("{s}s"),
        60..=3599 => format!("{}m {:02}s", s / 60, s % 60),
        _ => format!("{}h {:02}m", s / 3600, s / 60 % 60),
    }
}

/// A per-unit time: "0.12 s", or "3.1 min" for slow units.
fn seconds(secs: f64) -> String {
    if secs >= 120.0 {
        format!("{:.1} min", secs / 60.0)
    } else {
        format!("{secs:.2} s")
    }
}

/// Elapsed time as h:mm:ss for plain lines.
fn clock(elapsed: Duration) -> String {
    let s = elapsed.as_secs();
    format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eta_counts_only_this_stages_work() {
        // Nothing done yet: unknown, not zero.
        assert_eq!(eta_text(0, 0, 10, Duration::from_secs(5), None), "?");
        // Resumed at 50 of 100, nothing new yet: still unknown.
        assert_eq!(eta_text(50, 50, 100, Duration::from_secs(5), None), "?");
        // 10 units in 20 s, 40 left: 80 s.
        assert_eq!(
            eta_text(50, 60, 100, Duration::from_secs(20), None),
            "1m 20s"
        );
        assert_eq!(eta_text(0, 10, 10, Duration::from_secs(20), None), "0s");
        assert_eq!(
            eta_text(0, 1, 1000, Duration::from_secs(10), None),
            "2h 46m"
        );
    }

    #[test]
    fn on_a_gpu_the_first_unit_is_left_out_of_the_pace() {
        let warm = AtomicU64::new(0);
        // The first unit (kernel compilation) is still running, or just done: unknown.
        assert_eq!(eta_text(0, 0, 5, Duration::from_secs(30), Some(&warm)), "?");
        assert_eq!(eta_text(0, 1, 5, Duration::from_secs(55), Some(&warm)), "?");
        warm.store(55_000_000, Ordering::Relaxed);
        assert_eq!(eta_text(0, 1, 5, Duration::from_secs(55), Some(&warm)), "?");
        // The second took 10 s: 3 left at 10 s, not at (55 + 10) / 2.
        assert_eq!(
            eta_text(0, 2, 5, Duration::from_secs(65), Some(&warm)),
            "30s"
        );
    }

    #[test]
    fn a_gpu_reporter_records_when_the_first_unit_ends() {
        let mut r = Reporter::new().on_gpu(true);
        r.stage("editing", 4);
        assert_eq!(r.stage.warmed.load(Ordering::Relaxed), 0);
        r.advance(1);
        let first = r.stage.warmed.load(Ordering::Relaxed);
        assert!(first > 0);
        r.advance(1);
        assert_eq!(
            r.stage.warmed.load(Ordering::Relaxed),
            first,
            "only the first unit"
        );
        r.stage("fitting", 4);
        assert_eq!(
            r.stage.warmed.load(Ordering::Relaxed),
            0,
            "each stage warms up"
        );
        let mut cpu = Reporter::new();
        cpu.stage("editing", 4);
        cpu.advance(1);
        assert_eq!(cpu.stage.warmed.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn durations_read_well() {
        assert_eq!(short_duration(4.4), "4s");
        assert_eq!(short_duration(125.0), "2m 05s");
        assert_eq!(short_duration(7380.0), "2h 03m");
        assert_eq!(clock(Duration::from_secs(3725)), "1:02:05");
        assert_eq!(seconds(0.123), "0.12 s");
        assert_eq!(seconds(300.0), "5.0 min");
    }

    #[test]
    fn a_reporter_runs_through_stages_without_a_terminal() {
        // Under `cargo test` stderr may or may not be a terminal; either way nothing panics.
        let mut r = Reporter::new();
        r.log("before any stage");
        r.stage("first", 3);
        r.advance(1);
        r.set_message("loss 0.1");
        r.advance(2);
        r.resume_stage("second", 10, 4);
        r.set_position(10);
        r.finish();
        assert_eq!(r.stage.done, 10);
        assert_eq!(r.stage.first, 4);
    }
}
