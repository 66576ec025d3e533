//! Reading a finished `vcedit` process in a test: what it printed, and whether it failed the way a user
//! should see it fail.

use std::process::Output;

/// Everything the process wrote to stderr.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The process's stdout, after asserting that it succeeded (its stderr is the failure message).
#[track_caller]
pub fn stdout_of_success(o: &Output) -> String {
    assert!(o.status.success(), "{}", stderr(o));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Asserts that the process succeeded, showing its stderr when it did not.
#[track_caller]
pub fn assert_success(o: &Output) {
    assert!(o.status.success(), "{}", stderr(o));
}

/// The run failed with `code` and said why in one line starting "error: " (clap's usage errors start so
/// too) that contains every one of `says`, with no part repeated and no backtrace. Progress lines
/// (what was loaded) may come before it; nothing comes after it. Returns that line.
#[track_caller]
pub fn assert_one_clear_error(o: &Output, code: i32, says: &[&str]) -> String {
    let stderr = stderr(o);
    assert_eq!(o.status.code(), Some(code), "{stderr}");
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(errors.len(), 1, "{stderr}");
    let line = errors[0].to_string();
    assert!(line.starts_with("error: "), "{stderr}");
    for s in says {
        assert!(line.contains(s), "'{s}' not in: {stderr}");
    }
    if code == 1 || !stderr.contains("For more information") {
        // Our own errors (usage errors too; clap's add a hint line): the last line, each ": "-separated
        // part said once.
        assert_eq!(stderr.lines().last(), Some(line.as_str()), "{stderr}");
        let parts: Vec<&str> = line["error: ".len()..].split(": ").collect();
        for (i, p) in parts.iter().enumerate() {
            assert!(
                p.len() < 12 || !parts[i + 1..].contains(p),
                "'{p}' repeated in: {stderr}"
            );
        }
    }
    assert!(!stderr.contains("backtrace"), "{stderr}");
    line
}
