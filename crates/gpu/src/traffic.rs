//! What the host asks of the device, counted for the whole process: kernel launches (through cubecl's
//! launch observer, installed at the first count) and reads back to the host with their bytes (through
//! [`crate::prims`]' read functions, which every engine's read goes through). A run attributes them to
//! its stages by differences of snapshots ([`DeviceTraffic::now`], [`DeviceTraffic::since`]), so a card's
//! timings can be read per launch and per read.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

use cubecl::logging::{LaunchObservation, LaunchObserver};

static LAUNCHES: AtomicU64 = AtomicU64::new(0);
static READS: AtomicU64 = AtomicU64::new(0);
static READ_BYTES: AtomicU64 = AtomicU64::new(0);
static READ_NANOS: AtomicU64 = AtomicU64::new(0);

/// Counts of device work issued by this process (all of it, or between two snapshots).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DeviceTraffic {
    /// Kernels launched.
    pub launches: u64,
    /// Reads of device buffers back to the host, and their bytes.
    pub reads: u64,
    pub read_bytes: u64,
}

impl DeviceTraffic {
    /// The counts so far (the launch counter starts with the first call).
    pub fn now() -> Self {
        watch_launches();
        Self {
            launches: LAUNCHES.load(Ordering::Relaxed),
            reads: READS.load(Ordering::Relaxed),
            read_bytes: READ_BYTES.load(Ordering::Relaxed),
        }
    }

    /// What was issued between `earlier` and this snapshot.
    pub fn since(self, earlier: DeviceTraffic) -> DeviceTraffic {
        DeviceTraffic {
            launches: self.launches.saturating_sub(earlier.launches),
            reads: self.reads.saturating_sub(earlier.reads),
            read_bytes: self.read_bytes.saturating_sub(earlier.read_bytes),
        }
    }
}

/// How many reads the process made so far and how long the host waited in them (a read waits for all
/// work queued before it: the time the host stood still while the device caught up).
pub(crate) fn read_waits() -> (u64, std::time::Duration) {
    (
        READS.load(Ordering::Relaxed),
        std::time::Duration::from_nanos(READ_NANOS.load(Ordering::Relaxed)),
    )
}

/// Runs the read `f` of `bytes` bytes, counted.
pub(crate) fn counted_read<T>(bytes: usize, f: impl FnOnce() -> T) -> T {
    let start = std::time::Instant::now();
    let out = f();
    READS.fetch_add(1, Ordering::Relaxed);
    READ_BYTES.fetch_add(bytes as u64, Ordering::Relaxed);
    READ_NANOS.fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
    out
}

/// Counts every launch from here on (the observer cubecl calls on the launching thread; one relaxed
/// add per launch).
struct LaunchCounter;

impl LaunchObserver for LaunchCounter {
    fn launched(&self, _kernel: &'static str) {
        LAUNCHES.fetch_add(1, Ordering::Relaxed);
    }
}

fn watch_launches() {
    static WATCHING: OnceLock<LaunchObservation> = OnceLock::new();
    WATCHING.get_or_init(|| LaunchObservation::new(Arc::new(LaunchCounter)));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prims::{read_f32, upload_f32, zeros32};

    #[test]
    fn launches_and_reads_are_counted() {
        let Some(ctx) = crate::testing::context_or_skip() else {
            return;
        };
        let before = DeviceTraffic::now();
        let zeros = zeros32(&ctx.client, 16);
        let up = upload_f32(&ctx.client, &[1.0, 2.0, 3.0]);
        read_f32(&ctx.client, &zeros, 16).unwrap();
        read_f32(&ctx.client, &up, 3).unwrap();
        let done = DeviceTraffic::now().since(before);
        // Other tests of this binary may run beside this one: at least what this test did.
        assert!(done.launches >= 1, "the zero fill is a kernel: {done:?}");
        assert!(done.reads >= 2 && done.read_bytes >= 4 * 19, "{done:?}");
    }
}
