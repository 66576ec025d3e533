//! The memory check of commands whose memory grows with their settings (edit, fit): each command
//! estimates its peak; this refuses to start a run that would not fit, before any work.

use anyhow::{bail, Result};

/// `--ignore-memory-check`.
#[derive(clap::Args, Debug, Clone)]
pub struct MemoryCheckArg {
    /// Start even if the memory estimate exceeds the available memory.
    #[arg(long)]
    pub ignore_memory_check: bool,
}

impl MemoryCheckArg {
    /// Refuses a run that needs about `needed` bytes when less is available (Linux `MemAvailable`;
    /// elsewhere nothing is refused). `reduce` names the options that lower the need.
    pub fn check(&self, needed: u64, reduce: &str) -> Result<()> {
        check_against(
            needed,
            edit::run::available_memory(),
            self.ignore_memory_check,
            reduce,
        )
    }
}

fn check_against(needed: u64, available: Option<u64>, ignore: bool, reduce: &str) -> Result<()> {
    match available {
        Some(avail) if needed > avail && !ignore => bail!(
            "this run needs about {:.1} GB but {:.1} GB are available; reduce {reduce}, \
             or pass --ignore-memory-check",
            needed as f64 / 1e9,
            avail as f64 / 1e9
        ),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_only_what_does_not_fit() {
        let err = check_against(8_000_000_000, Some(2_000_000_000), false, "--size")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("8.0 GB") && err.contains("2.0 GB") && err.contains("reduce --size"),
            "{err}"
        );
        assert!(check_against(8_000_000_000, Some(2_000_000_000), true, "--size").is_ok());
        assert!(check_against(1, Some(2), false, "--size").is_ok());
        assert!(check_against(8, None, false, "--size").is_ok());
    }
}
