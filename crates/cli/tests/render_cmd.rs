//! `vcedit render` end to end: the real binary on a generated scene with orbit and file cameras.

use splat::ply::write_ply;
use splat::Image;
use std::process::{Command, Output};
use testkit::scenes::red_ball;

fn vcedit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vcedit"))
        .arg("render")
        .args(args)
        .output()
        .expect("run vcedit")
}

#[test]
fn renders_an_orbit_with_depth_and_alpha() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("ball.ply");
    write_ply(&ply, &red_ball()).unwrap();
    let out = dir.path().join("out");
    let o = vcedit(&[
        ply.to_str().unwrap(),
        "--orbit",
        "3",
        "--size",
        "48x32",
        "--depth",
        "--alpha",
        "--background",
        "0,0,1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The renders, without the run manifest (`.vcedit-run`).
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n != files::MANIFEST_NAME)
        .collect();
    names.sort();
    assert_eq!(names.len(), 9, "{names:?}");
    let rgb = Image::load(&out.join(&names[0])).unwrap();
    assert_eq!((rgb.width, rgb.height), (48, 32));
    // The centre is the red ball, the corner the blue background.
    let c = rgb.pixel(24, 16);
    assert!(c[0] > 0.8 && c[2] < 0.2, "{c:?}");
    let corner = rgb.pixel(0, 0);
    assert!(corner[2] > 0.9 && corner[0] < 0.1, "{corner:?}");
    let alpha =
        Image::load(&out.join(names.iter().find(|n| n.ends_with("_alpha.png")).unwrap())).unwrap();
    assert!(alpha.pixel(24, 16)[0] > 0.9 && alpha.pixel(0, 0)[0] < 0.05);
}

#[test]
fn renders_from_a_camera_file_and_reports_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("ball.ply");
    write_ply(&ply, &red_ball()).unwrap();
    // Two Blender-convention cameras on the z axis looking at the origin.
    let transforms = r#"{"camera_angle_x": 0.8, "w": 40, "h": 40, "frames": [
        {"file_path": "a", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]]},
        {"file_path": "b", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#;
    let cams = dir.path().join("transforms.json");
    std::fs::write(&cams, transforms).unwrap();
    let out = dir.path().join("out");
    let o = vcedit(&[
        ply.to_str().unwrap(),
        "--cameras",
        cams.to_str().unwrap(),
        "--size",
        "20",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let renders = std::fs::read_dir(&out)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name() != files::MANIFEST_NAME)
        .count();
    assert_eq!(renders, 2);

    let o = vcedit(&[
        dir.path().join("missing.ply").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("missing.ply") && err.lines().count() == 1,
        "{err}"
    );
}

#[test]
fn negative_and_malformed_values_name_the_option() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    for (flag, value, says) in [
        ("--size", "-64", "must be positive"),
        ("--orbit", "-2", "must be positive"),
        ("--background", "purple", "#rrggbb"),
        ("--background", "-1,0,0", "outside 0 to 1"),
    ] {
        let o = vcedit(&["s.ply", flag, value, "--out", out.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{flag} {value}: {err}");
        assert!(
            err.contains(flag) && err.contains(says),
            "{flag} {value}: {err}"
        );
        assert!(!err.contains("unexpected argument"), "{err}");
    }
}

/// `--device gpu` without any Vulkan driver: one error line and a non-zero exit; `--device auto` falls
/// back to the CPU and says so.
#[test]
fn device_gpu_without_a_gpu_is_one_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("ball.ply");
    write_ply(&ply, &red_ball()).unwrap();
    let out = dir.path().join("out");
    let run = |device: &str| {
        Command::new(env!("CARGO_BIN_EXE_vcedit"))
            .args([
                "render",
                ply.to_str().unwrap(),
                "--orbit",
                "1",
                "--size",
                "16",
            ])
            .args(["--out", out.to_str().unwrap(), "--device", device])
            .env("VK_ICD_FILENAMES", "/nonexistent")
            .env_remove("VCEDIT_ALLOW_SOFTWARE_GPU")
            .output()
            .expect("run vcedit")
    };
    let o = run("gpu");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(
        lines,
        ["error: no GPU found (no Vulkan, Metal or DX12 adapter)"],
        "{err}"
    );
    let o = run("auto");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("device: CPU (auto: no GPU found)"));
}
