//! The memory a run may still use: the host's available memory, or less in a container.

/// Memory available to a new run (Linux `MemAvailable`), if known.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    let host = kb * 1024;
    // In a container /proc/meminfo shows the host's memory; the cgroup's limit is what the kernel
    // enforces (an out-of-memory kill, not an error).
    Some(cgroup_headroom().map_or(host, |room| room.min(host)))
}

/// Memory the process's cgroup may still use (limit − usage), cgroup v2 or v1; `None` without a limit.
fn cgroup_headroom() -> Option<u64> {
    let read =
        |path: &str| -> Option<u64> { std::fs::read_to_string(path).ok()?.trim().parse().ok() };
    let (limit, usage) = match read("/sys/fs/cgroup/memory.max") {
        Some(limit) => (limit, read("/sys/fs/cgroup/memory.current")?),
        // "max" (no limit) does not parse; v1 says "no limit" with a huge number.
        None => (
            read("/sys/fs/cgroup/memory/memory.limit_in_bytes").filter(|&l| l < 1 << 60)?,
            read("/sys/fs/cgroup/memory/memory.usage_in_bytes")?,
        ),
    };
    Some(limit.saturating_sub(usage))
}

/// Refuses to allocate about `bytes` for `what` when that is more than the memory available: a small
/// file may declare a huge content (a count in a header, a texture size, a stream that decompresses a
/// thousandfold), and the allocation would fail or get the process killed instead of reporting.
pub fn check_allocation(bytes: u64, what: &str) -> Result<(), String> {
    match available_memory() {
        Some(available) if bytes > available => Err(format!(
            "{what} need about {:.1} GB, more than the {:.1} GB of memory available",
            bytes as f64 / 1e9,
            available as f64 / 1e9
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_allocations_pass_and_impossible_ones_are_refused() {
        assert!(check_allocation(1 << 20, "a megabyte").is_ok());
        if available_memory().is_some() {
            let e = check_allocation(u64::MAX / 2, "40000000 Gaussians").unwrap_err();
            assert!(e.starts_with("40000000 Gaussians need about"), "{e}");
        }
    }
}
