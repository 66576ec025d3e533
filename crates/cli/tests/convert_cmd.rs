//! `vcedit convert` end to end: every output format, reading back through `inspect`, and refusals.

use splat::GaussianScene;
use std::path::Path;
use std::process::{Command, Output};
use testkit::output::stdout_of_success;

fn vcedit(args: &[&Path]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .args(args)
        .output()
        .expect("run vcedit")
}

fn convert(input: &Path, output: &Path) -> Output {
    vcedit(&[Path::new("convert"), input, output])
}

/// 300 Gaussians of SH degree 2 on a small spiral.
fn spiral() -> GaussianScene {
    let n = 300;
    let k = splat::scene::sh_coeffs(2);
    GaussianScene {
        sh_degree: 2,
        means: (0..n)
            .flat_map(|i| {
                let t = i as f32 * 0.1;
                [t.cos(), t.sin(), t * 0.05]
            })
            .collect(),
        log_scales: (0..n)
            .flat_map(|i| [-3.0 - (i % 5) as f32 * 0.1, -3.5, -4.0])
            .collect(),
        quats: (0..n)
            .flat_map(|i| [1.0, (i % 7) as f32 * 0.1, 0.2, -0.1])
            .collect(),
        opacity_logits: (0..n).map(|i| (i % 11) as f32 - 5.0).collect(),
        sh: (0..3 * k * n)
            .map(|j| ((j % 13) as f32 - 6.0) * 0.05)
            .collect(),
    }
}

#[test]
fn converts_between_every_format_and_states_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("spiral.ply");
    splat::ply::write_ply(&source, &spiral()).unwrap();
    std::fs::create_dir(dir.path().join("sog")).unwrap();
    let mut previous = source.clone();
    for name in [
        "a.compressed.ply",
        "b.spz",
        "c.sog",
        "sog/meta.json",
        "d.ply",
        "e.splat",
    ] {
        let out = dir.path().join(name);
        let text = stdout_of_success(&convert(&previous, &out));
        assert!(text.contains("300 Gaussians"), "{name}: {text}");
        if name == "d.ply" {
            assert!(text.contains("lossless"), "{text}");
        } else {
            assert!(text.contains("lossy: largest error position"), "{text}");
        }
        if name == "e.splat" {
            assert!(
                text.contains("SH degree 0") && text.contains("cannot hold"),
                "{text}"
            );
        } else {
            assert!(text.contains("SH degree 2"), "{text}");
        }
        // Every other command reads the result too.
        let inspected = stdout_of_success(&vcedit(&[Path::new("inspect"), &out]));
        assert!(inspected.contains("300"), "{inspected}");
        previous = out;
    }
}

#[test]
fn refuses_the_input_as_output_and_unknown_names() {
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("s.ply");
    splat::ply::write_ply(&source, &spiral()).unwrap();
    let out = convert(&source, &source);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("also an input"),
        "{err}"
    );
    let out = convert(&source, &dir.path().join("s.obj"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("unknown output format") && err.lines().count() == 1,
        "{err}"
    );
    assert!(!dir.path().join("s.obj").exists());
    let broken = dir.path().join("broken.spz");
    std::fs::write(&broken, b"NGSP\x04\x00\x00\x00").unwrap();
    let out = convert(&broken, &dir.path().join("x.ply"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("broken.spz") && err.contains(".spz") && err.lines().count() == 1,
        "{err}"
    );
}

/// Outputs that are the input under another name, or that would mix with it or with someone else's files,
/// are refused and change nothing.
#[test]
fn refuses_outputs_that_replace_or_mix_with_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("s.ply");
    splat::ply::write_ply(&source, &spiral()).unwrap();
    let before = std::fs::read(&source).unwrap();
    // A hard link to the input.
    let link = dir.path().join("h.ply");
    std::fs::hard_link(&source, &link).unwrap();
    let out = convert(&source, &link);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("also an input"),
        "{err}"
    );
    // A SOG folder written into the input SOG folder.
    let sog = dir.path().join("sog");
    std::fs::create_dir(&sog).unwrap();
    assert!(convert(&source, &sog.join("meta.json")).status.success());
    let sog_meta = std::fs::read(sog.join("meta.json")).unwrap();
    for input in [sog.clone(), sog.join("meta.json")] {
        let out = convert(&input, &sog.join("meta.json"));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.lines().count() == 1, "{err}");
    }
    assert_eq!(std::fs::read(sog.join("meta.json")).unwrap(), sog_meta);
    // Someone else's folder: files, no meta.json.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("means_l.webp"), b"mine").unwrap();
    let out = convert(&source, &other.join("meta.json"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("not a SOG scene"),
        "{err}"
    );
    assert_eq!(std::fs::read(other.join("means_l.webp")).unwrap(), b"mine");
    assert!(!other.join("meta.json").exists());
    // A previous SOG folder is replaced only with --force, as any output file.
    let out = convert(&source, &sog.join("meta.json"));
    assert!(!out.status.success(), "replaced without --force");
    let out = vcedit(&[
        Path::new("convert"),
        &source,
        &sog.join("meta.json"),
        Path::new("--force"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(std::fs::read(&source).unwrap(), before);
}
