//! What commands print on standard output goes through here, so that an unwritable stdout (a full disk,
//! `> /dev/full`, a closed descriptor) ends the command with one error line and exit status 1 instead of
//! the panic `println!` makes of it. (A closed pipe still ends the program quietly: see main.rs.)

use std::io::Write;

/// Writes `text` to standard output, flushed, or says why it cannot.
pub fn write(text: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())
        .and_then(|()| out.flush())
        .map_err(|e| anyhow::Error::new(e).context("cannot write to standard output"))
}

/// `println!` that returns the error instead of panicking (`?` is applied).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::stdout::write(&(format!($($arg)*) + "\n"))?
    };
}
