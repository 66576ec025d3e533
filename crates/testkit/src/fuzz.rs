//! A small mutation fuzzer for vcedit's file readers, run by `cargo test` on stable Rust (no
//! `cargo fuzz`, no nightly): each target starts from valid files and feeds its reader mutated copies
//! (truncated, bytes flipped, pieces spliced in or dropped, numbers made huge, negative or NaN) for a
//! bounded time. A reader may reject any input with an error; it may not panic. A panicking input is
//! saved under the crash folder and fails the test, so it can be replayed and added to the corpus.
//!
//! Time per target: `VCEDIT_FUZZ_SECONDS` (default [`DEFAULT_SECONDS`]); the random sequence starts
//! from `VCEDIT_FUZZ_SEED` (default 1), so a run can be repeated.
//!
//! Memory is measured too: a fuzz binary that installs [`CountingAlloc`] as its global allocator has
//! every input's peak allocation (on the reading thread) measured, and an input whose reader allocates
//! more than [`memory_limit`] for it fails the target like a panic (saved as `NAME-memory-N.bin`): a
//! small file must not make a reader claim gigabytes.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The system allocator, counting each thread's live bytes and their peak. Install it in a fuzz test
/// binary with `#[global_allocator] static ALLOC: testkit::fuzz::CountingAlloc = testkit::fuzz::CountingAlloc;`.
pub struct CountingAlloc;

thread_local! {
    // Const-initialised cells: reading them never allocates, so the allocator may use them.
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}
static COUNTING: AtomicBool = AtomicBool::new(false);

fn note(delta: isize) {
    // `try_with`: a thread's last frees run while its locals are being destroyed.
    let _ = LIVE.try_with(|live| {
        let now = live.get() + delta;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is passed on to `System` unchanged; the bookkeeping only reads and writes
// thread-local cells and one atomic flag, none of which allocates.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            COUNTING.store(true, Ordering::Relaxed);
            note(layout.size() as isize);
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            COUNTING.store(true, Ordering::Relaxed);
            note(layout.size() as isize);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        note(-(layout.size() as isize));
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note(new_size as isize - layout.size() as isize);
        }
        p
    }
}

/// Peak bytes this thread allocated while `f` ran (beyond what it held before); `None` when
/// [`CountingAlloc`] is not the global allocator.
fn peak_during(f: impl FnOnce()) -> Option<u64> {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    f();
    let peak = PEAK.with(Cell::get);
    COUNTING
        .load(Ordering::Relaxed)
        .then(|| (peak - base).max(0) as u64)
}

/// Most bytes a reader may allocate for one input of `len` bytes: 256 MiB plus 1000 bytes per input
/// byte (the compressed formats legitimately expand; a small file claiming gigabytes does not pass).
/// `VCEDIT_FUZZ_MAX_MB` replaces the 256 MiB.
pub fn memory_limit(len: usize) -> u64 {
    let base_mb = std::env::var("VCEDIT_FUZZ_MAX_MB")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .unwrap_or(256);
    base_mb * 1024 * 1024 + 1000 * len as u64
}

/// Seconds per target when `VCEDIT_FUZZ_SECONDS` is not set: short enough for every `cargo test`.
pub const DEFAULT_SECONDS: f64 = 5.0;

/// Numbers that break careless readers: counts and lengths at the edges of their types.
const NASTY_BINARY: [u64; 8] = [
    0,
    1,
    0x7fff_ffff,
    0xffff_ffff,
    0x8000_0000_0000_0000,
    u64::MAX,
    0x0000_0001_0000_0000,
    0x7ff8_0000_0000_0000, // NaN as an f64
];
const NASTY_TEXT: [&str; 10] = [
    "0",
    "-1",
    "4294967295",
    "18446744073709551616",
    "99999999999999999999999",
    "nan",
    "inf",
    "-inf",
    "1e309",
    "",
];

/// What a fuzz run did.
#[derive(Debug, Default)]
pub struct Summary {
    pub inputs: u64,
    /// Files the panicking inputs (and those over the memory limit) were saved to.
    pub crashes: Vec<PathBuf>,
    /// The most any one input made its reader allocate; `None` when allocations are not counted.
    pub peak_bytes: Option<u64>,
}

/// The seconds a target runs for: `VCEDIT_FUZZ_SECONDS`, else [`DEFAULT_SECONDS`].
pub fn budget() -> Duration {
    let secs = std::env::var("VCEDIT_FUZZ_SECONDS")
        .ok()
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v >= 0.0)
        .unwrap_or(DEFAULT_SECONDS);
    Duration::from_secs_f64(secs)
}

/// xorshift64*: tiny, seedable, good enough to pick mutations.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

/// One mutation of `input`; `seeds` supply pieces to splice in.
fn mutate(input: &mut Vec<u8>, seeds: &[Vec<u8>], rng: &mut Rng) {
    let len = input.len();
    match rng.below(9) {
        // Truncate.
        0 => input.truncate(rng.below(len + 1)),
        // Flip a few bits.
        1 => {
            for _ in 0..=rng.below(4) {
                if !input.is_empty() {
                    let i = rng.below(input.len());
                    input[i] ^= 1 << rng.below(8);
                }
            }
        }
        // Overwrite a byte with an arbitrary one.
        2 => {
            if len > 0 {
                let i = rng.below(len);
                input[i] = rng.next() as u8;
            }
        }
        // A huge, zero or NaN number in binary, at any offset (counts and lengths in headers).
        3 => {
            let v = NASTY_BINARY[rng.below(NASTY_BINARY.len())];
            let bytes = if rng.below(2) == 0 {
                v.to_le_bytes().to_vec()
            } else {
                (v as u32).to_le_bytes().to_vec()
            };
            if len >= bytes.len() {
                let at = rng.below(len - bytes.len() + 1);
                input[at..at + bytes.len()].copy_from_slice(&bytes);
            }
        }
        // A number in text replaced by a nasty one.
        4 => {
            let digits: Vec<usize> = (0..len).filter(|&i| input[i].is_ascii_digit()).collect();
            if !digits.is_empty() {
                let start = digits[rng.below(digits.len())];
                let mut end = start;
                while end < len && (input[end].is_ascii_digit() || input[end] == b'.') {
                    end += 1;
                }
                let with = NASTY_TEXT[rng.below(NASTY_TEXT.len())].as_bytes();
                input.splice(start..end, with.iter().copied());
            }
        }
        // Splice in a piece of a seed (or of itself).
        5 => {
            let donor = &seeds[rng.below(seeds.len())];
            if !donor.is_empty() {
                let a = rng.below(donor.len());
                let b = (a + 1 + rng.below(64)).min(donor.len());
                let at = rng.below(len + 1);
                input.splice(at..at, donor[a..b].iter().copied());
            }
        }
        // Drop a range.
        6 => {
            if len > 0 {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(64)).min(len);
                input.drain(a..b);
            }
        }
        // Duplicate a range (repeated lines, repeated records).
        7 => {
            if len > 0 {
                let a = rng.below(len);
                let b = (a + 1 + rng.below(256)).min(len);
                let piece = input[a..b].to_vec();
                input.splice(b..b, piece);
            }
        }
        // Insert random bytes.
        _ => {
            let at = rng.below(len + 1);
            let n = 1 + rng.below(8);
            let bytes: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
            input.splice(at..at, bytes);
        }
    }
}

/// Runs target `name` for `time`: every seed as given, then mutated copies (one to four mutations each)
/// until the time is up. `check` reads one input and must not panic (errors are fine). Panicking inputs
/// are saved to `crash_dir/NAME-N.bin`; the summary lists them.
pub fn run_for(
    name: &str,
    seeds: &[Vec<u8>],
    crash_dir: &Path,
    time: Duration,
    mut check: impl FnMut(&[u8]),
) -> Summary {
    assert!(!seeds.is_empty(), "fuzz target {name} has no seeds");
    let seed = std::env::var("VCEDIT_FUZZ_SEED")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .unwrap_or(1);
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
    let deadline = Instant::now() + time;
    let mut summary = Summary::default();
    let mut try_one = |input: &[u8], summary: &mut Summary| {
        summary.inputs += 1;
        let mut panicked = false;
        let peak = peak_during(|| {
            panicked = catch_unwind(AssertUnwindSafe(|| check(input))).is_err();
        });
        if let Some(bytes) = peak {
            summary.peak_bytes = Some(summary.peak_bytes.unwrap_or(0).max(bytes));
        }
        let too_much = peak.is_some_and(|b| b > memory_limit(input.len()));
        if panicked || too_much {
            let _ = std::fs::create_dir_all(crash_dir);
            let kind = if panicked { "" } else { "memory-" };
            let path = crash_dir.join(format!("{name}-{kind}{}.bin", summary.crashes.len()));
            let _ = std::fs::write(&path, input);
            summary.crashes.push(path);
        }
    };
    for s in seeds {
        try_one(s, &mut summary);
    }
    while Instant::now() < deadline && summary.crashes.len() < 10 {
        let mut input = seeds[rng.below(seeds.len())].clone();
        for _ in 0..=rng.below(4) {
            mutate(&mut input, seeds, &mut rng);
        }
        try_one(&input, &mut summary);
    }
    summary
}

/// Where the targets save the inputs that crashed or over-allocated: `target/fuzz-crashes` at the
/// repository's root, whichever crate's tests run them.
pub fn crash_dir() -> PathBuf {
    crate::paths::repo().join("target/fuzz-crashes")
}

/// [`run_for`] with the [`budget`] from the environment, then a test failure naming the saved inputs if
/// any panicked.
pub fn run_and_assert(name: &str, seeds: &[Vec<u8>], crash_dir: &Path, check: impl FnMut(&[u8])) {
    let summary = run_for(name, seeds, crash_dir, budget(), check);
    let memory = summary
        .peak_bytes
        .map_or("allocations not counted".to_string(), |b| {
            format!("at most {:.1} MB allocated per input", b as f64 / 1e6)
        });
    println!("fuzz {name}: {} inputs, {memory}", summary.inputs);
    assert!(
        summary.crashes.is_empty(),
        "fuzz {name}: {} of {} inputs panicked or allocated more than their limit; saved as {:?} \
         (replay them through the reader)",
        summary.crashes.len(),
        summary.inputs,
        summary.crashes
    );
}

/// A scratch folder for one target's inputs, removed when dropped.
struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("vcedit-fuzz-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("scratch folder for fuzzing");
        Self(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Fuzzes a reader of one file: each input is written to a file named `file_name`, whose path `check`
/// reads.
pub fn run_file_and_assert(
    name: &str,
    file_name: &str,
    seeds: &[Vec<u8>],
    crash_dir: &Path,
    mut check: impl FnMut(&Path),
) {
    let scratch = Scratch::new(name);
    let path = scratch.0.join(file_name);
    run_and_assert(name, seeds, crash_dir, |input| {
        std::fs::write(&path, input).expect("scratch file");
        check(&path);
    });
}

/// The shortest sparse file [`run_sparse_file_and_assert`] makes: 8 times the memory available (2^40
/// bytes when unknown), so what its header claims cannot fit in memory whatever the bytes per item.
pub fn sparse_floor() -> u64 {
    files::available_memory().map_or(1 << 40, |m| m.saturating_mul(8))
}

/// Like [`run_file_and_assert`], for the sparse-file case: after each input is written, the file is
/// extended with a hole to the length `claimed` computes from the input (what its header says the data
/// takes), when that is longer. Such a file passes every check of counts against the file's size while
/// holding almost nothing, so a reader must bound what it allocates by the memory available, not by the
/// file's size. Only claims of at least [`sparse_floor`] get the hole (smaller ones would be read for
/// real); lengths are capped at 2^44 bytes; a file system that cannot hold one skips the hole.
pub fn run_sparse_file_and_assert(
    name: &str,
    file_name: &str,
    seeds: &[Vec<u8>],
    crash_dir: &Path,
    claimed: impl Fn(&[u8]) -> Option<u64>,
    mut check: impl FnMut(&Path),
) {
    let scratch = Scratch::new(name);
    let path = scratch.0.join(file_name);
    run_and_assert(name, seeds, crash_dir, |input| {
        std::fs::write(&path, input).expect("scratch file");
        let floor = sparse_floor();
        if let Some(len) = claimed(input).filter(|&l| l > input.len() as u64 && l >= floor) {
            let file = std::fs::OpenOptions::new().write(true).open(&path);
            let _ = file.and_then(|f| f.set_len(len.min(1 << 44)));
        }
        check(&path);
    });
}

/// Fuzzes a reader of several files in one folder (a COLMAP model, a tokenizer folder): each input
/// replaces one of the files `names` of `valid_dir` (its first byte picks which) while the others stay
/// valid; `check` reads the folder. Seeded from the valid files.
pub fn run_file_set_and_assert(
    name: &str,
    valid_dir: &Path,
    names: &[&str],
    crash_dir: &Path,
    mut check: impl FnMut(&Path),
) {
    let seeds: Vec<Vec<u8>> = names
        .iter()
        .enumerate()
        .map(|(i, file)| {
            let mut v = vec![i as u8];
            v.extend(std::fs::read(valid_dir.join(file)).expect("valid seed file"));
            v
        })
        .collect();
    let scratch = Scratch::new(name);
    run_and_assert(name, &seeds, crash_dir, |input| {
        let Some((&which, content)) = input.split_first() else {
            return;
        };
        for (i, file) in names.iter().enumerate() {
            let path = scratch.0.join(file);
            if i == which as usize % names.len() {
                std::fs::write(path, content).expect("scratch file");
            } else {
                std::fs::copy(valid_dir.join(file), path).expect("scratch file");
            }
        }
        check(&scratch.0);
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[global_allocator]
    static ALLOC: CountingAlloc = CountingAlloc;

    #[test]
    fn readers_that_claim_too_much_memory_fail_like_panics() {
        let dir = tempfile::tempdir().unwrap();
        let time = Duration::from_millis(200);
        // A "reader" that believes a length byte: 'z' asks for 400 MB, anything else for 1 MB.
        let summary = run_for("greedy", &[b"abc".to_vec()], dir.path(), time, |input| {
            let mb = if input.contains(&b'z') { 400 } else { 1 };
            let buffer = vec![1u8; mb << 20];
            std::hint::black_box(&buffer);
        });
        assert!(summary.peak_bytes.unwrap() >= 1 << 20, "{summary:?}");
        for crash in &summary.crashes {
            let name = crash.file_name().unwrap().to_string_lossy().into_owned();
            assert!(name.starts_with("greedy-memory-"), "{name}");
            assert!(std::fs::read(crash).unwrap().contains(&b'z'));
        }
        // A well-behaved reader passes and its peak is measured.
        let summary = run_for("frugal", &[b"abc".to_vec()], dir.path(), time, |input| {
            std::hint::black_box(input.to_vec());
        });
        assert!(summary.crashes.is_empty());
        assert!(summary.peak_bytes.unwrap() < 1 << 20, "{summary:?}");
    }

    #[test]
    fn mutations_stay_in_bounds_and_vary() {
        let seeds = vec![
            b"ply\nelement vertex 12\nend_header\n".to_vec(),
            vec![0u8; 40],
        ];
        let mut rng = Rng(7);
        let mut distinct = std::collections::HashSet::new();
        for i in 0..2000 {
            let mut input = seeds[i % 2].clone();
            mutate(&mut input, &seeds, &mut rng);
            distinct.insert(input);
        }
        assert!(distinct.len() > 500, "{}", distinct.len());
    }

    #[test]
    fn panics_are_caught_and_saved() {
        let dir = tempfile::tempdir().unwrap();
        let time = Duration::from_millis(200);
        let summary = run_for("toy", &[b"abc".to_vec()], dir.path(), time, |input| {
            if input.len() > 5 {
                panic!("too long");
            }
        });
        assert!(summary.inputs > 1);
        assert!(!summary.crashes.is_empty());
        assert!(std::fs::read(&summary.crashes[0]).unwrap().len() > 5);
    }
}
