//! `vcedit view` end to end: the real binary writes the viewer page for one or two scenes.

use splat::ply::write_ply;
use splat::GaussianScene;
use std::path::Path;
use std::process::{Command, Output};

fn vcedit(args: &[&str], cwd: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .arg("view")
        .args(args)
        .current_dir(cwd)
        .output()
        .expect("run vcedit")
}

/// `n` Gaussians on a line, the later ones larger (so the cap keeps the last ones).
fn line_scene(n: usize) -> GaussianScene {
    let mut s = GaussianScene::new(0);
    for i in 0..n {
        s.means.extend([i as f32 * 0.1, 0.0, 0.0]);
        s.log_scales.extend([-3.0 + 0.01 * i as f32; 3]);
        s.quats.extend([1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(2.0);
        s.sh.extend([1.0, 0.0, -1.0]);
    }
    s
}

/// The base64 text of the scene labelled `label` in the page.
fn embedded<'a>(html: &'a str, label: &str) -> &'a str {
    let tag = format!("data-label=\"{label}\">");
    let start = html.find(&tag).unwrap() + tag.len();
    &html[start..start + html[start..].find('<').unwrap()]
}

#[test]
fn writes_a_page_for_two_scenes_with_the_cap() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("a.ply"), &line_scene(10)).unwrap();
    write_ply(&dir.path().join("b & c.ply"), &line_scene(30)).unwrap();
    let o = vcedit(&["a.ply", "b & c.ply", "--cap", "20"], dir.path());
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The default name, printed last.
    assert_eq!(stdout.lines().last(), Some("a-view.html"), "{stdout}");
    assert!(
        stdout.contains("b & c.ply: 30 Gaussians, 20 embedded"),
        "{stdout}"
    );
    let html = std::fs::read_to_string(dir.path().join("a-view.html")).unwrap();
    // 32 bytes per Gaussian as base64: 10 of 10, and 20 of 30.
    assert_eq!(
        embedded(&html, "a.ply").len(),
        (10 * 32usize).div_ceil(3) * 4
    );
    assert_eq!(
        embedded(&html, "b &amp; c.ply").len(),
        (20 * 32usize).div_ceil(3) * 4
    );
    assert!(html.contains("at most 20 per scene"));
}

#[test]
fn one_scene_to_a_chosen_file_and_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(&dir.path().join("a.ply"), &line_scene(5)).unwrap();
    let o = vcedit(&["a.ply", "--out", "pages/one.html"], dir.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(dir.path().join("pages/one.html")).unwrap();
    assert!(html.contains("data-vcedit-viewer"));
    assert!(
        !html.contains("data-mode=\"after\""),
        "no comparison controls for one scene"
    );

    let o = vcedit(&["missing.ply"], dir.path());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr.contains("missing.ply") && stderr.lines().count() == 1,
        "{stderr}"
    );

    let o = vcedit(&["a.ply", "--out", "a.ply"], dir.path());
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("is one of the scenes"));

    let o = vcedit(&["a.ply", "--cap", "0"], dir.path());
    assert_eq!(o.status.code(), Some(2), "usage error");
}
