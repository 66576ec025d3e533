//! The 3D viewer page in headless Chromium with software WebGL2 (SwiftShader): it loads without console
//! messages, draws the scenes, and its controls (before/after buttons, dragging) change the picture.
//! The scene is two blobs: left red in both scenes, right blue before and green after.
//! Skips (with the reason printed) when /usr/bin/chromium is absent; Debian: `apt-get install -y chromium`.

mod common;

use std::path::Path;

use common::{chromium_available, file_url, run_chromium, ChromiumRun};
use edit::present::viewer::{write_viewer_page, InitialView, ViewerOptions, ViewerScene};
use splat::GaussianScene;

/// Software WebGL2 in headless Chromium (opting in to SwiftShader, which is no longer automatic).
const GL_FLAGS: [&str; 3] = [
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
];
const BACKGROUND: [f32; 3] = [0.1, 0.1, 0.1];

/// `n` Gaussians in a ball of radius 0.25 around `centre`, all of colour `rgb`.
fn blob(scene: &mut GaussianScene, centre: [f32; 3], rgb: [f32; 3], n: usize) {
    const SH_C0: f32 = 0.282_094_8;
    for i in 0..n {
        // A deterministic spread: golden-angle spiral on shells.
        let t = i as f32;
        let r = 0.25 * ((t + 0.5) / n as f32).cbrt();
        let (phi, cos_theta) = (t * 2.399_963, 1.0 - 2.0 * (t + 0.5) / n as f32);
        let sin_theta = (1.0 - cos_theta * cos_theta).sqrt();
        scene.means.extend([
            centre[0] + r * sin_theta * phi.cos(),
            centre[1] + r * sin_theta * phi.sin(),
            centre[2] + r * cos_theta,
        ]);
        scene.log_scales.extend([0.06f32.ln(); 3]);
        scene.quats.extend([1.0, 0.0, 0.0, 0.0]);
        scene.opacity_logits.push(3.0);
        scene.sh.extend(rgb.map(|c| (c - 0.5) / SH_C0));
    }
}

fn two_blobs(right: [f32; 3]) -> GaussianScene {
    let mut s = GaussianScene::new(0);
    blob(&mut s, [-0.6, 0.0, 0.0], [0.95, 0.1, 0.1], 300);
    blob(&mut s, [0.6, 0.0, 0.0], right, 300);
    // White, upper left (y points down) and nearer the camera, overlapping the red blob: a flipped axis
    // or a wrong drawing order would show.
    blob(&mut s, [-0.25, -0.3, -0.5], [0.9, 0.9, 0.9], 100);
    s
}

/// The camera the page starts from: 3 units in front of the blobs, looking along +z (OpenCV axes), with a
/// focal length of 150 px at 160x120.
fn front_camera(width: u32, height: u32) -> splat::Camera {
    front_camera_with_focal(width, height, 150.0 * f64::from(width) / 160.0)
}

fn front_camera_with_focal(width: u32, height: u32, focal: f64) -> splat::Camera {
    splat::cameras::orbit::look_at(
        "front".into(),
        [0.0, 0.0, -3.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        width,
        height,
        focal,
    )
}

/// The 160x120 front camera as the viewer fits it into a canvas of `width` x `height`: one scale for
/// both axes, so that all of its image shows, centred.
fn front_camera_fitted(width: u32, height: u32) -> splat::Camera {
    let fit = (f64::from(width) / 160.0).min(f64::from(height) / 120.0);
    front_camera_with_focal(width, height, 150.0 * fit)
}

fn before_scene() -> GaussianScene {
    two_blobs([0.1, 0.2, 0.95])
}

/// Writes the viewer page for the two scenes, starting from [`front_camera`].
fn write_page(path: &Path) {
    write_page_of(path, &before_scene(), &two_blobs([0.1, 0.9, 0.15]));
}

/// [`write_page`] for any two scenes.
fn write_page_of(path: &Path, before: &GaussianScene, after: &GaussianScene) {
    let cameras = [front_camera(160, 120)];
    let view = InitialView::from_cameras(&cameras, before, None);
    write_viewer_page(
        path,
        "two blobs <test>",
        &[
            ViewerScene {
                label: "before",
                scene: before,
            },
            ViewerScene {
                label: "after",
                scene: after,
            },
        ],
        &view,
        &ViewerOptions {
            background: BACKGROUND,
            ..Default::default()
        },
    )
    .unwrap();
}

#[derive(Debug, Default)]
struct Counts {
    red: usize,
    green: usize,
    blue: usize,
    background: usize,
    total: usize,
}

fn classify(counts: &mut Counts, [r, g, b]: [u8; 3]) {
    let [r, g, b] = [r, g, b].map(i32::from);
    counts.total += 1;
    if r > 150 && g < 90 && b < 90 {
        counts.red += 1;
    }
    if g > 150 && r < 90 && b < 110 {
        counts.green += 1;
    }
    if b > 150 && r < 90 && g < 120 {
        counts.blue += 1;
    }
    if [r, g, b].iter().all(|&c| (c - 26).abs() <= 3) {
        counts.background += 1;
    }
}

/// The window [`quiet_run`] opens, and the page's padding left and right of the viewer (`page` in
/// viewer.rs: 28 CSS px each side).
const WINDOW: (u32, u32) = (900, 800);
const PAGE_PADDING: u32 = 2 * 28;

/// Opens `url` with software WebGL2 in a [`WINDOW`]-sized window, plus `output` (what to write:
/// `--screenshot=...` or `--dump-dom`), and checks that the page wrote nothing on the console.
fn quiet_run(url: &str, work: &Path, output: String) -> ChromiumRun {
    quiet_run_in(url, work, output, WINDOW)
}

/// [`quiet_run`] in a window of `(width, height)` CSS pixels.
fn quiet_run_in(
    url: &str,
    work: &Path,
    output: String,
    (width, height): (u32, u32),
) -> ChromiumRun {
    let mut args: Vec<String> = GL_FLAGS.iter().map(|s| s.to_string()).collect();
    args.extend([
        format!("--window-size={width},{height}"),
        "--virtual-time-budget=5000".to_string(),
        "--hide-scrollbars".to_string(),
        output,
    ]);
    let run = run_chromium(url, work, &args);
    assert!(
        run.console.is_empty(),
        "console messages:\n{}",
        run.console.join("\n")
    );
    run
}

/// Screenshots the page at `url_suffix` (e.g. "#before") in the [`WINDOW`]; checks the console stays
/// quiet; returns the canvas cut out of the screenshot.
fn screenshot_canvas(page: &Path, work: &Path, url_suffix: &str) -> image::RgbImage {
    screenshot_canvas_in(page, work, url_suffix, WINDOW)
}

/// [`screenshot_canvas`] in a window of `(width, height)` CSS pixels.
fn screenshot_canvas_in(
    page: &Path,
    work: &Path,
    url_suffix: &str,
    window: (u32, u32),
) -> image::RgbImage {
    let shot = work.join("shot.png");
    let url = format!("{}{url_suffix}", file_url(page));
    quiet_run_in(
        &url,
        work,
        format!("--screenshot={}", shot.display()),
        window,
    );
    if let Ok(keep) = std::env::var("VCEDIT_KEEP_SCREENSHOT") {
        std::fs::copy(&shot, keep).unwrap();
    }
    let img = image::open(&shot).expect("screenshot").to_rgb8();
    // The canvas: the rows and columns mostly of the background colour (the page around it is near-white).
    let is_background = |p: &image::Rgb<u8>| p.0.iter().all(|&c| (i32::from(c) - 26).abs() <= 3);
    let (w, h) = img.dimensions();
    let rows: Vec<u32> = (0..h)
        .filter(|&y| {
            (0..w)
                .filter(|&x| is_background(img.get_pixel(x, y)))
                .count()
                > 300
        })
        .collect();
    let cols: Vec<u32> = (0..w)
        .filter(|&x| {
            (0..h)
                .filter(|&y| is_background(img.get_pixel(x, y)))
                .count()
                > 300
        })
        .collect();
    assert!(
        rows.len() > 300 && cols.len() > 400,
        "no canvas in the screenshot"
    );
    let (x0, x1, y0, y1) = (cols[0], cols[cols.len() - 1], rows[0], rows[rows.len() - 1]);
    image::imageops::crop_imm(&img, x0, y0, x1 - x0 + 1, y1 - y0 + 1).to_image()
}

#[test]
fn viewer_draws_both_scenes_in_headless_chromium() {
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer page.html");
    write_page(&page);
    // The canvas takes the page's whole width, whatever the window's: in the first camera's 4:3 where the
    // window is tall enough, else 78 % of the window's height (the camera is fitted into that shape).
    for window in [(900, 1200), (1400, 800)] {
        let canvas = screenshot_canvas_in(&page, tmp.path(), "", window);
        let (w, h) = canvas.dimensions();
        let want_w = window.0 - PAGE_PADDING;
        let want_h = (f64::from(want_w) * 0.75).min(0.78 * f64::from(window.1));
        println!("window {window:?}: canvas {w}x{h}");
        assert!(w.abs_diff(want_w) <= 2, "window {window:?}: canvas {w}x{h}");
        assert!(
            (f64::from(h) - want_h).abs() <= 2.0,
            "window {window:?}: canvas {w}x{h}, want height {want_h}"
        );
        let mut counts = Counts::default();
        for p in canvas.pixels() {
            classify(&mut counts, p.0);
        }
        println!("screenshot: {counts:?}");
        // Split view: the left blob from "before" (red), the right one from "after" (green); blue is
        // hidden.
        assert!(
            counts.background > 100_000,
            "no canvas background: {counts:?}"
        );
        assert!(counts.red > 2_000, "left blob missing: {counts:?}");
        assert!(
            counts.green > 2_000,
            "right blob (after) missing: {counts:?}"
        );
        assert!(
            counts.blue < 50,
            "right blob (before) should be hidden: {counts:?}"
        );
    }
}

#[test]
fn viewer_matches_the_cpu_renderer() {
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer.html");
    write_page(&page);
    let canvas = screenshot_canvas(&page, tmp.path(), "#before");
    let (mean, p99) = errors_against_cpu(&canvas, &before_scene());
    println!("WebGL vs CPU renderer: mean abs error {mean:.4}, 99th percentile {p99:.4}");
    assert!(mean < 0.01, "mean abs error {mean}");
    assert!(p99 < 0.1, "99th percentile error {p99}");
}

/// [`before_scene`] at SH degree 1 with strong degree-1 coefficients (seen from the front camera, the z
/// term moves red down and green up by ~0.35): the viewer shows what the renderer shows, and not the
/// DC colours alone.
#[test]
fn viewer_shows_degree_1_shading_as_the_cpu_renderer() {
    if !chromium_available() {
        return;
    }
    let dc = before_scene();
    let shaded = with_sh(&dc, 1, |i| {
        let mut sh = dc.sh[3 * i..3 * i + 3].to_vec();
        // c1 (−y), c2 (z), c3 (−x), each RGB.
        sh.extend([0.1, 0.0, -0.1, -0.75, 0.75, 0.0, 0.2, 0.0, -0.2]);
        sh
    });
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer.html");
    write_page_of(&page, &shaded, &dc);
    let canvas = screenshot_canvas(&page, tmp.path(), "#before");
    let (mean, p99) = errors_against_cpu(&canvas, &shaded);
    let (dc_mean, _) = errors_against_cpu(&canvas, &dc);
    println!(
        "WebGL vs CPU renderer at SH degree 1: mean abs error {mean:.4}, 99th percentile {p99:.4}; \
         against the DC colours alone {dc_mean:.4}"
    );
    assert!(mean < 0.012, "mean abs error {mean}");
    assert!(p99 < 0.12, "99th percentile error {p99}");
    assert!(
        dc_mean > 2.0 * mean,
        "the shading shows: {dc_mean} vs {mean}"
    );
}

/// `scene` with only its SH bands up to `degree` (the higher ones dropped).
fn truncated(scene: &GaussianScene, degree: u32) -> GaussianScene {
    let (from, to) = (scene.sh_coeffs(), splat::scene::sh_coeffs(degree));
    with_sh(scene, degree, |i| {
        scene.sh[3 * from * i..3 * (from * i + to)].to_vec()
    })
}

/// `scene`'s Gaussians at SH degree `degree`, Gaussian `i` with the coefficients `sh_of(i)` (DC first).
fn with_sh(scene: &GaussianScene, degree: u32, sh_of: impl Fn(usize) -> Vec<f32>) -> GaussianScene {
    let mut out = GaussianScene::new(degree);
    out.means = scene.means.clone();
    out.log_scales = scene.log_scales.clone();
    out.quats = scene.quats.clone();
    out.opacity_logits = scene.opacity_logits.clone();
    for i in 0..scene.len() {
        out.sh.extend(sh_of(i));
    }
    out
}

/// [`before_scene`] at SH degree 3 whose bands 2 and 3 change the colours more than band 1 does. Seen
/// from the front camera the directions to the blobs are about (±0.2, 0, 0.98): the zz terms of band 2
/// (coefficient 6) and band 3 (coefficient 12) shift every blob, the x z term of band 2 (7) and the
/// x (4zz − xx − yy) term of band 3 (13) shift the left and right blobs in opposite directions, so a
/// wrong constant, sign or axis shows. All values are multiples of 1/128 (the page's quantisation step).
fn degree_3_scene() -> GaussianScene {
    let dc = before_scene();
    let mut coefficients = [[0.0f32; 3]; 15];
    coefficients[1] = [0.25, -0.25, 0.0]; // band 1, z
    coefficients[5] = [-0.5, 0.5, 0.25]; // band 2, 2zz − xx − yy
    coefficients[6] = [0.0, 0.5, -0.25]; // band 2, x z
    coefficients[11] = [0.0, -0.375, 0.375]; // band 3, z (2zz − 3xx − 3yy)
    coefficients[12] = [0.5, 0.0, -0.5]; // band 3, x (4zz − xx − yy)
    with_sh(&dc, 3, |i| {
        let mut sh = dc.sh[3 * i..3 * i + 3].to_vec();
        sh.extend(coefficients.iter().flatten());
        sh
    })
}

/// A degree-3 scene shown on the left ("before") and its degree-2 truncation on the right ("after"):
/// each matches the CPU renderer at its own degree, and clearly not with its top bands dropped.
#[test]
fn viewer_shows_degree_2_and_3_shading_as_the_cpu_renderer() {
    if !chromium_available() {
        return;
    }
    let degree_3 = degree_3_scene();
    let degree_2 = truncated(&degree_3, 2);
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer.html");
    write_page_of(&page, &degree_3, &degree_2);
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("data-label=\"before\" data-sh-degree=\"3\""));
    assert!(html.contains("data-label=\"after\" data-sh-degree=\"2\""));

    let canvas = screenshot_canvas(&page, tmp.path(), "#before");
    let (mean, p99) = errors_against_cpu(&canvas, &degree_3);
    let (degree_1_mean, _) = errors_against_cpu(&canvas, &truncated(&degree_3, 1));
    let (degree_2_mean, _) = errors_against_cpu(&canvas, &degree_2);
    let (dc_mean, _) = errors_against_cpu(&canvas, &truncated(&degree_3, 0));
    println!(
        "WebGL vs CPU renderer at SH degree 3: mean abs error {mean:.4}, 99th percentile {p99:.4}; \
         against degree 2 {degree_2_mean:.4}, degree 1 {degree_1_mean:.4}, DC alone {dc_mean:.4}"
    );
    assert!(mean < 0.006, "mean abs error {mean}");
    assert!(p99 < 0.06, "99th percentile error {p99}");
    for (name, other) in [
        ("degree 2", degree_2_mean),
        ("degree 1", degree_1_mean),
        ("DC", dc_mean),
    ] {
        assert!(
            other > 2.0 * mean,
            "band 3 shows: against {name} {other} vs {mean}"
        );
    }

    let canvas = screenshot_canvas(&page, tmp.path(), "#after");
    let (mean, p99) = errors_against_cpu(&canvas, &degree_2);
    let (degree_1_mean, _) = errors_against_cpu(&canvas, &truncated(&degree_3, 1));
    println!(
        "WebGL vs CPU renderer at SH degree 2: mean abs error {mean:.4}, 99th percentile {p99:.4}; \
         against degree 1 {degree_1_mean:.4}"
    );
    assert!(mean < 0.006, "mean abs error {mean}");
    assert!(p99 < 0.06, "99th percentile error {p99}");
    assert!(
        degree_1_mean > 2.0 * mean,
        "band 2 shows: {degree_1_mean} vs {mean}"
    );
}

/// Mean and 99th-percentile absolute colour error of a viewer screenshot against the CPU renderer's
/// image of `scene` from the front camera as the viewer fits it into the screenshot's size.
fn errors_against_cpu(canvas: &image::RgbImage, scene: &GaussianScene) -> (f32, f32) {
    let (w, h) = canvas.dimensions();
    let cpu = splat::render::render(
        scene,
        &front_camera_fitted(w, h),
        &splat::render::RenderSettings {
            background: BACKGROUND,
        },
        None,
    )
    .rgb_image();
    let mut errors: Vec<f32> = canvas
        .pixels()
        .zip(cpu.data.chunks_exact(3))
        .map(|(p, q)| {
            // The renderer's colours may exceed 1 (bright SH); a screen shows them as 1.
            (0..3)
                .map(|c| (f32::from(p.0[c]) / 255.0 - q[c].clamp(0.0, 1.0)).abs())
                .sum::<f32>()
                / 3.0
        })
        .collect();
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    errors.sort_by(f32::total_cmp);
    let p99 = errors[errors.len() * 99 / 100];
    if let Ok(keep) = std::env::var("VCEDIT_KEEP_SCREENSHOT") {
        cpu.save_png(Path::new(&format!("{keep}.cpu.png"))).unwrap();
    }
    (mean, p99)
}

/// Runs after the viewer's own script: clicks the buttons and drags on the canvas, reads the canvas back
/// each time and writes the colour counts and how much each step changed the picture as JSON into
/// `<pre id=result>`.
const HARNESS: &str = r#"<pre id="result">not run</pre><script>
(function () {
  const v = window.vceditViewers[0];
  const gl = v.gl;
  function read() {
    v.render();
    const [w, h] = [gl.drawingBufferWidth, gl.drawingBufferHeight];
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    return px;
  }
  function counts(px) {
    const c = { red: 0, green: 0, blue: 0, lit: 0 };
    for (let i = 0; i < px.length; i += 4) {
      const [r, g, b] = [px[i], px[i + 1], px[i + 2]];
      if (r > 150 && g < 90 && b < 90) c.red++;
      if (g > 150 && r < 90 && b < 110) c.green++;
      if (b > 150 && r < 90 && g < 120) c.blue++;
      if (r + g + b > 120) c.lit++;
    }
    return c;
  }
  function changed(a, b) {
    let n = 0;
    for (let i = 0; i < a.length; i += 4) {
      if (Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]) > 60) n++;
    }
    return n;
  }
  const click = (sel) => document.querySelector(sel).click();
  const pointer = (type, x, y) => v.canvas.dispatchEvent(new PointerEvent(type, { clientX: x, clientY: y, button: 0, pointerId: 1, bubbles: true }));
  const result = {};
  click('button[data-mode=before]');
  const before = read();
  result.mode_before = v.root.dataset.mode;
  click('button[data-mode=after]');
  const after = read();
  result.mode_after = v.root.dataset.mode;
  result.before = counts(before);
  result.after = counts(after);
  result.before_vs_after = changed(before, after);
  pointer('pointerdown', 300, 300);
  pointer('pointermove', 380, 300);
  pointer('pointerup', 380, 300);
  const turned = read();
  result.turned = counts(turned);
  result.turn_changed = changed(after, turned);
  v.canvas.dispatchEvent(new WheelEvent('wheel', { deltaY: 200, bubbles: true, cancelable: true }));
  result.zoom_changed = changed(turned, read());
  v.canvas.dispatchEvent(new MouseEvent('dblclick', { bubbles: true }));
  result.reset_changed = changed(after, read());
  result.pixels = before.length / 4;
  document.getElementById('result').textContent = JSON.stringify(result);
})();
</script>"#;

#[test]
fn viewer_controls_change_the_picture() {
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer.html");
    write_page(&page);
    let html = std::fs::read_to_string(&page).unwrap();
    std::fs::write(&page, html.replace("</body>", &format!("{HARNESS}</body>"))).unwrap();
    let run = quiet_run(&file_url(&page), tmp.path(), "--dump-dom".to_string());
    let start = run
        .stdout
        .find("<pre id=\"result\">")
        .expect("result element")
        + 17;
    let text = &run.stdout[start..start + run.stdout[start..].find("</pre>").unwrap()];
    println!("{text}");
    let r: serde_json::Value = serde_json::from_str(text).expect("harness result");
    let n = |path: &str| r.pointer(path).and_then(|v| v.as_u64()).unwrap_or(0);
    let pixels = n("/pixels");
    assert!(pixels > 100_000, "{r}");
    assert_eq!(r["mode_before"], "before");
    assert_eq!(r["mode_after"], "after");
    // Before: red and blue blobs, no green; after: red and green, no blue.
    assert!(n("/before/red") > 2_000 && n("/before/blue") > 2_000, "{r}");
    assert!(n("/before/green") < 50, "{r}");
    assert!(n("/after/red") > 2_000 && n("/after/green") > 2_000, "{r}");
    assert!(n("/after/blue") < 50, "{r}");
    assert!(n("/before_vs_after") > 2_000, "{r}");
    // Turning, zooming and resetting the view all redraw something else.
    assert!(n("/turned/lit") > 2_000, "nothing left after turning: {r}");
    assert!(n("/turn_changed") > 1_000, "{r}");
    assert!(n("/zoom_changed") > 1_000, "{r}");
    assert_eq!(
        n("/reset_changed"),
        0,
        "reset goes back to the first view: {r}"
    );
}

/// Headless Chromium driven over the DevTools protocol, for what a page cannot do to itself: a user
/// gesture (full screen needs one) and trusted key presses, which go wherever the focus is. The protocol
/// runs over `--remote-debugging-pipe` (JSON messages ended by NUL, read on fd 3 and written on fd 4),
/// here two FIFOs that a shell connects before it starts the browser.
struct DevTools {
    browser: std::process::Child,
    to_browser: std::fs::File,
    from_browser: std::sync::mpsc::Receiver<serde_json::Value>,
    next_id: u64,
    session: String,
    /// Console calls and uncaught exceptions of the page, as the protocol reported them.
    console: Vec<String>,
}

impl DevTools {
    fn open(url: &str, work: &Path, window: (u32, u32)) -> DevTools {
        use std::io::{BufRead, BufReader};
        let (commands, replies) = (work.join("devtools-in"), work.join("devtools-out"));
        for fifo in [&commands, &replies] {
            let made = std::process::Command::new("mkfifo")
                .arg(fifo)
                .status()
                .unwrap();
            assert!(made.success(), "mkfifo {}", fifo.display());
        }
        let mut args: Vec<String> = GL_FLAGS.iter().map(|s| s.to_string()).collect();
        args.extend([
            "--headless".to_string(),
            "--no-sandbox".to_string(),
            "--disable-background-networking".to_string(),
            "--disable-component-update".to_string(),
            "--no-first-run".to_string(),
            "--hide-scrollbars".to_string(),
            "--remote-debugging-pipe".to_string(),
            format!("--window-size={},{}", window.0, window.1),
            format!("--user-data-dir={}", work.join("profile").display()),
            url.to_string(),
        ]);
        let browser = std::process::Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$0" "$@" 3<"$COMMANDS" 4>"$REPLIES""#)
            .arg(common::CHROMIUM)
            .args(&args)
            .env("COMMANDS", &commands)
            .env("REPLIES", &replies)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start chromium");
        // The shell opens the command FIFO first, then the reply FIFO: open them in that order.
        let to_browser = std::fs::OpenOptions::new()
            .write(true)
            .open(&commands)
            .unwrap();
        let replies = std::fs::File::open(&replies).unwrap();
        let (send, from_browser) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut reader = BufReader::new(replies);
            let mut message = Vec::new();
            while reader.read_until(0, &mut message).unwrap_or(0) > 0 {
                message.pop();
                if let Ok(value) = serde_json::from_slice(&message) {
                    if send.send(value).is_err() {
                        break;
                    }
                }
                message.clear();
            }
        });
        let mut tools = DevTools {
            browser,
            to_browser,
            from_browser,
            next_id: 0,
            session: String::new(),
            console: Vec::new(),
        };
        let targets = tools.call("Target.getTargets", serde_json::json!({}));
        let page = targets["targetInfos"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["type"] == "page")
            .expect("a page target")["targetId"]
            .clone();
        let attached = tools.call(
            "Target.attachToTarget",
            serde_json::json!({ "targetId": page, "flatten": true }),
        );
        tools.session = attached["sessionId"].as_str().unwrap().to_string();
        tools.call("Runtime.enable", serde_json::json!({}));
        tools
    }

    /// Sends one command (to the page once attached) and returns its result.
    fn call(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        self.try_call(method, params)
            .unwrap_or_else(|error| panic!("{method}: {error}"))
    }

    /// [`DevTools::call`], with the protocol's error as the `Err`.
    fn try_call(
        &mut self,
        method: &str,
        params: serde_json::Value,
    ) -> Result<serde_json::Value, serde_json::Value> {
        use std::io::Write;
        self.next_id += 1;
        let mut message =
            serde_json::json!({ "id": self.next_id, "method": method, "params": params });
        if !self.session.is_empty() {
            message["sessionId"] = self.session.clone().into();
        }
        let mut bytes = serde_json::to_vec(&message).unwrap();
        bytes.push(0);
        self.to_browser.write_all(&bytes).unwrap();
        loop {
            let reply = self
                .from_browser
                .recv_timeout(std::time::Duration::from_secs(60))
                .unwrap_or_else(|_| panic!("no reply to {method}"));
            match reply["method"].as_str() {
                Some("Runtime.consoleAPICalled") => {
                    self.console.push(reply["params"]["args"].to_string())
                }
                Some("Runtime.exceptionThrown") => self
                    .console
                    .push(reply["params"]["exceptionDetails"].to_string()),
                _ => {}
            }
            if reply["id"] == self.next_id {
                return match reply.get("error") {
                    Some(error) => Err(error.clone()),
                    None => Ok(reply["result"].clone()),
                };
            }
        }
    }

    /// Evaluates `expression` in the page as if the user had just clicked (so it may go full screen),
    /// waits for the promise it may return, and gives back its JSON value.
    fn evaluate(&mut self, expression: &str) -> serde_json::Value {
        let result = self.call(
            "Runtime.evaluate",
            serde_json::json!({
                "expression": expression,
                "awaitPromise": true,
                "returnByValue": true,
                "userGesture": true,
            }),
        );
        assert!(
            result.get("exceptionDetails").is_none(),
            "{expression}: {result}"
        );
        result["result"]["value"].clone()
    }

    /// Presses (`down`) or releases a key as the keyboard would: it goes to the focused element, and a
    /// one-character `key` types itself into a text field.
    fn key(&mut self, down: bool, key: &str, code: &str, key_code: u32, shift: bool) {
        let mut event = serde_json::json!({
            "type": if down { "rawKeyDown" } else { "keyUp" },
            "key": key,
            "code": code,
            "windowsVirtualKeyCode": key_code,
            "modifiers": if shift { 8 } else { 0 },
        });
        if down && key.chars().count() == 1 {
            event["type"] = "keyDown".into();
            event["text"] = key.into();
        }
        self.call("Input.dispatchKeyEvent", event);
    }
}

impl Drop for DevTools {
    fn drop(&mut self) {
        let _ = self.browser.kill();
        let _ = self.browser.wait();
    }
}

/// Helpers the test's expressions use: the viewer, its camera, and waiting for frames or events.
const PAGE_HELPERS: &str = r#"
window.t = {
  v: () => window.vceditViewers[0],
  frames: (n) => new Promise((done) => { const step = () => (n-- > 0 ? requestAnimationFrame(step) : done()); step(); }),
  sleep: (ms) => new Promise((done) => setTimeout(done, ms)),
  camera: () => { const v = window.vceditViewers[0].view; return { center: v.center, pivot: v.pivot, rows: v.rows }; },
  // Counts the frames drawn from now on.
  countRenders: () => {
    const v = window.vceditViewers[0];
    if (!v.countedRender) { const render = v.render.bind(v); v.countedRender = true; v.renders = 0; v.render = () => { v.renders++; render(); }; }
    v.renders = 0;
  },
  lit: () => {
    const v = window.vceditViewers[0], gl = v.gl;
    const [w, h] = [gl.drawingBufferWidth, gl.drawingBufferHeight];
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let n = 0;
    for (let i = 0; i < px.length; i += 4) if (px[i] + px[i + 1] + px[i + 2] > 120) n++;
    return n;
  },
  layout: () => {
    const v = window.vceditViewers[0], r = v.canvas.getBoundingClientRect();
    const button = v.root.querySelector('button[data-action=fullscreen]');
    return { fullscreen: document.fullscreenElement === v.root, left: r.left, top: r.top, width: r.width, height: r.height,
      buffer: [v.canvas.width, v.canvas.height], window: [innerWidth, innerHeight], label: button.textContent,
      hidden: button.hidden, focused: document.activeElement === v.canvas };
  },
  fullscreenChange: () => new Promise((done) => {
    document.addEventListener('fullscreenchange', done, { once: true });
    setTimeout(done, 5000);
  }),
};
'ready'"#;

fn dot3(a: &serde_json::Value, b: &serde_json::Value) -> f64 {
    (0..3)
        .map(|k| a[k].as_f64().unwrap() * b[k].as_f64().unwrap())
        .sum()
}

fn minus3(a: &serde_json::Value, b: &serde_json::Value) -> serde_json::Value {
    serde_json::json!([0, 1, 2].map(|k| a[k].as_f64().unwrap() - b[k].as_f64().unwrap()))
}

/// The full-screen button: it shows the viewer alone with the canvas filling the screen, its label says
/// how to leave, Escape leaves, and the canvas goes back to its place and size.
#[test]
fn viewer_goes_full_screen_and_back() {
    let Some((_tmp, mut tools)) = viewer_under_devtools() else {
        return;
    };
    let before = tools.evaluate("t.layout()");
    println!("before: {before}");
    assert_eq!(before["hidden"], false, "the button shows: {before}");
    assert_eq!(before["label"], "full screen");
    assert!(before["width"].as_f64().unwrap() < f64::from(WINDOW.0 - 40));

    let full = tools.evaluate(
        "(async () => { const change = t.fullscreenChange(); \
         t.v().root.querySelector('button[data-action=fullscreen]').click(); \
         await change; await t.frames(3); return t.layout(); })()",
    );
    println!("full screen: {full}");
    assert_eq!(full["fullscreen"], true, "{full}");
    assert_eq!(full["label"], "exit full screen");
    assert_eq!(full["focused"], true, "keys fly at once: {full}");
    let window = &full["window"];
    for (edge, want) in [
        ("left", 0.0),
        ("top", 0.0),
        ("width", window[0].as_f64().unwrap()),
        ("height", window[1].as_f64().unwrap()),
    ] {
        let got = full[edge].as_f64().unwrap();
        assert!((got - want).abs() <= 1.0, "{edge}: {got} vs {want}: {full}");
    }
    // The drawing buffer follows (one device pixel per CSS pixel here).
    assert_eq!(full["buffer"][0].as_f64(), window[0].as_f64(), "{full}");
    assert_eq!(full["buffer"][1].as_f64(), window[1].as_f64(), "{full}");

    // Escape is the browser's way out: the viewer does not claim it (headless Chromium has no browser
    // window to leave full screen by it, so the button leaves here).
    tools.evaluate(
        "window.escape = null; window.addEventListener('keydown', (e) => { \
         if (e.key === 'Escape') window.escape = { prevented: e.defaultPrevented }; }); 0",
    );
    tools.key(true, "Escape", "Escape", 27, false);
    tools.key(false, "Escape", "Escape", 27, false);
    let escape = tools.evaluate("window.escape");
    assert_eq!(
        escape["prevented"], false,
        "Escape reached the page: {escape}"
    );
    let after = tools.evaluate(
        "(async () => { const change = t.fullscreenChange(); if (document.fullscreenElement) \
         t.v().root.querySelector('button[data-action=fullscreen]').click(); \
         await change; await t.frames(3); return t.layout(); })()",
    );
    println!("after leaving: {after}");
    assert_eq!(after["fullscreen"], false, "{after}");
    assert_eq!(after["label"], "full screen");
    for edge in ["width", "height"] {
        let (got, want) = (
            after[edge].as_f64().unwrap(),
            before[edge].as_f64().unwrap(),
        );
        assert!((got - want).abs() <= 1.0, "{edge}: {got} vs {want}");
    }
    assert_eq!(after["buffer"], before["buffer"]);
    assert!(tools.console.is_empty(), "console: {:?}", tools.console);
}

/// The test page open in Chromium under its debugging interface, with [`PAGE_HELPERS`] loaded (and the
/// folder it lives in); `None` without Chromium.
fn viewer_under_devtools() -> Option<(tempfile::TempDir, DevTools)> {
    if !chromium_available() {
        return None;
    }
    let tmp = tempfile::tempdir().unwrap();
    let page = tmp.path().join("viewer.html");
    write_page(&page);
    let mut tools = DevTools::open(&file_url(&page), tmp.path(), WINDOW);
    wait_for_viewer(&mut tools);
    Some((tmp, tools))
}

/// Loads [`PAGE_HELPERS`] once the viewer is there.
fn wait_for_viewer(tools: &mut DevTools) {
    let started =
        "!!(window.vceditViewers && window.vceditViewers[0]) && document.readyState === 'complete'";
    // The browser starts on a blank page and then loads ours: an evaluation may meet either, or be cut
    // short by the switch.
    let ready = (0..600).any(|_| {
        let reply = tools.try_call(
            "Runtime.evaluate",
            serde_json::json!({ "expression": started, "returnByValue": true }),
        );
        let ready = reply.is_ok_and(|r| r["result"]["value"] == true);
        if !ready {
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        ready
    });
    assert!(ready, "the viewer did not start");
    assert_eq!(tools.evaluate(PAGE_HELPERS), "ready");
}

/// Keys fly the camera only while the canvas has the focus; they move it by the frame time, draw frames
/// only while held, keep the horizon level, and go by the scene's size.
#[test]
fn viewer_flies_with_the_keys_only_when_focused() {
    let Some((_tmp, mut tools)) = viewer_under_devtools() else {
        return;
    };
    // Holds W for at least 0.5 s; where frames are expected, until two were drawn too (at most 20 s: a
    // loaded machine may hold back a headless page's animation frames longer than the 0.5 s, and then
    // the key would be released before the first flying step). Returns the frames drawn while held, those
    // drawn after the release, and the seconds the key was held (page clock).
    let hold_w = |tools: &mut DevTools, shift: bool, frames_expected: bool| {
        tools.evaluate("t.countRenders(); t.heldSince = performance.now(); 0");
        tools.key(true, "w", "KeyW", 87, shift);
        let wait = format!(
            "(async () => {{ await t.sleep(500); const until = performance.now() + 20000; \
             while ({frames_expected} && t.v().renders < 2 && performance.now() < until) await t.sleep(20); \
             return 0; }})()"
        );
        tools.evaluate(&wait);
        tools.key(false, "w", "KeyW", 87, shift);
        let held = tools.evaluate("t.v().renders");
        let seconds = tools.evaluate("(performance.now() - t.heldSince) / 1000");
        // Frames after the release: none, the loop has ended.
        let idle = tools.evaluate("(async () => { await t.frames(2); t.countRenders(); await t.sleep(400); return t.v().renders; })()");
        (
            held.as_u64().unwrap(),
            idle.as_u64().unwrap(),
            seconds.as_f64().unwrap(),
        )
    };

    // Typing in a text field elsewhere on the page moves nothing. The field changes the page's layout,
    // and the canvas's resize observer may then ask for a frame of its own (CI once counted it, on a loaded
    // machine, as a frame for the key): the page settles, that frame drawn, before the key is pressed.
    let start = tools.evaluate(
        "(async () => { const input = document.createElement('input'); input.id = 'elsewhere'; \
         document.body.append(input); input.focus(); await t.frames(2); \
         while (t.v().pending) await t.frames(1); return t.camera(); })()",
    );
    let (held, _, _) = hold_w(&mut tools, false, false);
    let unmoved = tools.evaluate("t.camera()");
    assert_eq!(start, unmoved, "a key for a text field moved the camera");
    assert_eq!(held, 0, "frames drawn for a key the viewer did not get");
    assert_eq!(
        tools.evaluate("document.getElementById('elsewhere').value"),
        "w"
    );

    // With the canvas focused, W flies forward along the view while held, then the drawing stops.
    let lit_before = tools.evaluate("t.v().canvas.focus(); t.v().render(); t.lit()");
    let (held, idle, held_seconds) = hold_w(&mut tools, false, true);
    let flown = tools.evaluate("t.camera()");
    let moved = minus3(&flown["center"], &start["center"]);
    let forward = dot3(&moved, &start["rows"][2]);
    let sideways = dot3(&moved, &start["rows"][0]).abs() + dot3(&moved, &start["rows"][1]).abs();
    let lit_after = tools.evaluate("t.lit()");
    println!(
        "W held {held_seconds:.2} s: {forward:.3} forward ({sideways:.2e} sideways), {held} frames while \
         held, {idle} after; lit pixels {lit_before} → {lit_after}"
    );
    // Half the first camera's distance to the pivot (about 3) per second of holding (0.75 for 0.5 s),
    // less the frames the release cut short, more where a slow frame took longer than the key was held.
    // (The speed itself is checked exactly below, with the frame time given.)
    assert!(
        forward > 0.1 && forward < 2.0 * 1.5 * held_seconds.max(0.5),
        "moved {forward} in {held_seconds} s"
    );
    assert!(sideways < 1e-6, "moved sideways {sideways}");
    assert!(held >= 2, "{held} frames while W was held");
    assert_eq!(idle, 0, "frames drawn with no key held");
    assert!(
        lit_after.as_u64() > lit_before.as_u64(),
        "closer, the blobs look larger"
    );
    // The pivot came along: orbiting afterwards turns around what is ahead.
    let pivot_moved = minus3(&flown["pivot"], &start["pivot"]);
    assert!((dot3(&pivot_moved, &start["rows"][2]) - forward).abs() < 1e-9);

    // Speeds, with the frame time given: per second half the distance from the first camera to the
    // pivot (3 units), four times that with Shift; E up along the world's up axis, D to the right.
    let steps = tools.evaluate(
        r#"(() => {
      const v = t.v(), out = {};
      const step = (keys, fast, seconds) => {
        const before = t.camera();
        v.heldKeys = new Set(keys); v.flyFast = fast; v.fly(seconds); v.heldKeys = new Set(); v.flyFast = false;
        return { before, after: t.camera() };
      };
      out.w = step(['KeyW'], false, 0.5);
      out.shift_w = step(['KeyW'], true, 0.5);
      out.e = step(['KeyE'], false, 0.5);
      out.d = step(['KeyD'], false, 0.5);
      out.left = step(['ArrowLeft'], false, 0.5);
      out.up = step(['ArrowUp'], false, 0.5);
      out.up_vector = v.up;
      out.home_distance = v.homeDistance;
      return out;
    })()"#,
    );
    let moved = |name: &str| {
        minus3(
            &steps[name]["after"]["center"],
            &steps[name]["before"]["center"],
        )
    };
    let rows = |name: &str, k: usize| steps[name]["before"]["rows"][k].clone();
    let up = &steps["up_vector"];
    let length = |v: &serde_json::Value| dot3(v, v).sqrt();
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
    // The first camera is 3 units from the blobs; the pivot is the scene's median, near their middle.
    let home = steps["home_distance"].as_f64().unwrap();
    assert!((home - 3.0).abs() < 0.1, "{steps}");
    let half_second = 0.5 * 0.5 * home;
    assert!(
        close(dot3(&moved("w"), &rows("w", 2)), half_second),
        "{steps}"
    );
    assert!(
        close(
            dot3(&moved("shift_w"), &rows("shift_w", 2)),
            4.0 * half_second
        ),
        "{steps}"
    );
    assert!(close(dot3(&moved("e"), up), half_second), "{steps}");
    assert!(close(length(&moved("e")), half_second), "{steps}");
    assert!(
        close(dot3(&moved("d"), &rows("d", 0)), half_second),
        "{steps}"
    );
    // Turning stays where it is; the left arrow turns the view towards the old left, the up arrow
    // towards the sky, by 60° per second; the camera's right axis stays horizontal (a level horizon).
    for turn in ["left", "up"] {
        assert!(length(&moved(turn)) < 1e-12, "{turn}: {steps}");
        let right = &steps[turn]["after"]["rows"][0];
        assert!(
            dot3(right, up).abs() < 1e-9,
            "{turn} tilted the horizon: {steps}"
        );
    }
    let forward_after = |name: &str| steps[name]["after"]["rows"][2].clone();
    let thirty_degrees = (std::f64::consts::PI / 6.0).sin();
    assert!(
        close(
            dot3(&forward_after("left"), &rows("left", 0)),
            -thirty_degrees
        ),
        "{steps}"
    );
    assert!(dot3(&forward_after("up"), up) > 0.4, "{steps}");
    assert!(tools.console.is_empty(), "console: {:?}", tools.console);
}
