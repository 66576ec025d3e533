//! The memory check of commands whose memory grows with their settings (edit, fit): each command
//! estimates its peak; this refuses to start a run that would not fit, before any work.

use anyhow::{bail, Result};

/// `--ignore-memory-check`.
#[derive(clap::Args, Debug, Clone)]
pub struct MemoryCheckArg {
    /// Start even if a memory estimate exceeds what is available (host memory; GPU memory where the
    /// card reports its free memory: NVIDIA, AMD).
    #[arg(long)]
    pub ignore_memory_check: bool,
}

impl MemoryCheckArg {
    /// Refuses a run that needs about `needed` bytes when less is available (Linux `MemAvailable`;
    /// elsewhere nothing is refused). `reduce` names the options that lower the need.
    pub fn check(&self, needed: u64, reduce: &str) -> Result<()> {
        check_against(
            needed,
            files::available_memory(),
            self.ignore_memory_check,
            Memory::Host,
            reduce,
        )
    }

    /// Refuses a GPU run that needs about `needed` bytes of device memory when the card reported less
    /// free when it was opened (NVIDIA and AMD drivers report it; elsewhere nothing is refused).
    pub fn check_gpu(&self, needed: Option<u64>, free: Option<u64>, reduce: &str) -> Result<()> {
        match needed {
            Some(needed) => {
                check_against(needed, free, self.ignore_memory_check, Memory::Gpu, reduce)
            }
            None => Ok(()),
        }
    }
}

/// Which memory a check is about.
#[derive(Clone, Copy)]
enum Memory {
    Host,
    Gpu,
}

fn check_against(
    needed: u64,
    available: Option<u64>,
    ignore: bool,
    memory: Memory,
    reduce: &str,
) -> Result<()> {
    let (what, avail_on, alternative) = match memory {
        Memory::Host => ("", "are available", ""),
        Memory::Gpu => (
            " of GPU memory",
            "are free on the GPU",
            ", run with --device cpu,",
        ),
    };
    match available {
        Some(avail) if needed > avail && !ignore => bail!(
            "this run needs about {:.1} GB{what} but {:.1} GB {avail_on}; reduce {reduce}{alternative} \
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
        let host =
            |needed, avail, ignore| check_against(needed, avail, ignore, Memory::Host, "--size");
        let err = host(8_000_000_000, Some(2_000_000_000), false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("8.0 GB") && err.contains("2.0 GB") && err.contains("reduce --size"),
            "{err}"
        );
        assert!(host(8_000_000_000, Some(2_000_000_000), true).is_ok());
        assert!(host(1, Some(2), false).is_ok());
        assert!(host(8, None, false).is_ok());
    }

    #[test]
    fn gpu_check_names_the_gpu_and_the_way_out() {
        let arg = MemoryCheckArg {
            ignore_memory_check: false,
        };
        let err = arg
            .check_gpu(
                Some(30_000_000_000),
                Some(11_500_000_000),
                "--view-batch or --size",
            )
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "this run needs about 30.0 GB of GPU memory but 11.5 GB are free on the GPU; reduce \
             --view-batch or --size, run with --device cpu, or pass --ignore-memory-check"
        );
        // The CPU (no GPU estimate) and cards that report no free memory are never refused.
        assert!(arg.check_gpu(None, Some(1), "--size").is_ok());
        assert!(arg.check_gpu(Some(30_000_000_000), None, "--size").is_ok());
        assert!(arg.check_gpu(Some(1_000), Some(2_000), "--size").is_ok());
        let ignoring = MemoryCheckArg {
            ignore_memory_check: true,
        };
        assert!(ignoring
            .check_gpu(Some(30_000_000_000), Some(1), "--size")
            .is_ok());
    }
}
