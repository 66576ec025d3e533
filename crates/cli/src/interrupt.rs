//! Ctrl-C (SIGINT) or SIGTERM during a run: one line saying the run can be resumed, then exit 130.
//!
//! A run's files are written atomically and every iteration ends with a checkpoint, so stopping at any
//! moment loses at most the unfinished iteration; what a user needs at that moment is to hear so, and the
//! command that continues. The line is formatted before the run starts and the handler only writes it and
//! exits: `write` and `_exit` are async-signal-safe, formatting and locks are not.

use std::sync::atomic::{AtomicPtr, AtomicUsize, Ordering};

/// The prepared line (leaked once per process: a run sets it once).
static MESSAGE: AtomicPtr<u8> = AtomicPtr::new(std::ptr::null_mut());
static MESSAGE_LEN: AtomicUsize = AtomicUsize::new(0);

/// The shell's status for a process ended by SIGINT (128 + 2).
pub const INTERRUPTED_STATUS: i32 = 130;

/// From now on, Ctrl-C or SIGTERM prints `line` (plus a newline) on stderr and ends the process with
/// [`INTERRUPTED_STATUS`]. Without a call, the signals keep their default action.
pub fn on_interrupt_say(line: &str) {
    let bytes: &'static [u8] = Box::leak(format!("\n{line}\n").into_bytes().into_boxed_slice());
    MESSAGE_LEN.store(bytes.len(), Ordering::SeqCst);
    MESSAGE.store(bytes.as_ptr().cast_mut(), Ordering::SeqCst);
    #[cfg(unix)]
    install();
}

/// A run writing into `out` with checkpoints: an interruption says the run continues with `--resume`.
pub fn resumable_run_in(out: &std::path::Path) {
    on_interrupt_say(&format!(
        "interrupted: {} keeps every finished iteration; the same command with --resume continues",
        out.display()
    ));
}

#[cfg(unix)]
fn install() {
    extern "C" fn handler(_signal: libc::c_int) {
        let ptr = MESSAGE.load(Ordering::SeqCst);
        let len = MESSAGE_LEN.load(Ordering::SeqCst);
        // SAFETY: `ptr` is null or a leaked, never-freed buffer of `len` bytes; write and _exit are
        // async-signal-safe.
        unsafe {
            if !ptr.is_null() {
                libc::write(2, ptr.cast(), len);
            }
            libc::_exit(INTERRUPTED_STATUS);
        }
    }
    let handler: extern "C" fn(libc::c_int) = handler;
    // SAFETY: the handler only calls async-signal-safe functions and reads atomics.
    unsafe {
        libc::signal(libc::SIGINT, handler as libc::sighandler_t);
        libc::signal(libc::SIGTERM, handler as libc::sighandler_t);
    }
}
