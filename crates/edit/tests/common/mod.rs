//! Running headless Chromium on a page from disk, for the report and viewer tests.
// Each test binary includes this module and uses a different part of it.
#![allow(dead_code)]

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

pub const CHROMIUM: &str = "/usr/bin/chromium";

/// Whether Chromium is installed; prints the one SKIP line when it is not.
pub fn chromium_available() -> bool {
    let found = Path::new(CHROMIUM).exists();
    if !found {
        println!("SKIP: {CHROMIUM} not installed (Debian: apt-get install -y chromium)");
    }
    found
}

/// The `file://` URL of `path` (spaces and percent signs encoded).
pub fn file_url(path: &Path) -> String {
    format!(
        "file://{}",
        path.to_string_lossy()
            .replace('%', "%25")
            .replace(' ', "%20")
    )
}

/// What one headless run printed: stdout (e.g. `--dump-dom`) and the page's console lines (plus
/// "Uncaught" errors) from the browser log.
pub struct ChromiumRun {
    pub stdout: String,
    pub console: Vec<String>,
}

/// Runs headless Chromium on `url` with `args` (e.g. `--screenshot=...`), a fresh profile under `work`,
/// and at most 120 s.
pub fn run_chromium(url: &str, work: &Path, args: &[String]) -> ChromiumRun {
    let profile = work.join("profile");
    let mut child = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--enable-logging=stderr",
            "--v=0",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(args)
        .arg(url)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start chromium");
    // Read both pipes on threads so a chatty browser cannot block on a full pipe.
    let drain = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = pipe.read_to_string(&mut s);
            s
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(child.stderr.take().unwrap()));
    let start = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if start.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("chromium did not finish within 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let (stdout, stderr) = (out.join().unwrap(), err.join().unwrap());
    assert!(status.success(), "chromium failed: {status}\n{stderr}");
    let console = stderr
        .lines()
        .filter(|l| l.contains(":CONSOLE") || l.contains("Uncaught"))
        .map(str::to_string)
        .collect();
    ChromiumRun { stdout, console }
}
