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

/// The camera the page starts from: 3 units in front of the blobs, looking along +z (OpenCV axes).
fn front_camera(width: u32, height: u32) -> splat::Camera {
    splat::cameras::orbit::look_at(
        "front".into(),
        [0.0, 0.0, -3.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        width,
        height,
        150.0 * f64::from(width) / 160.0,
    )
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

/// Opens `url` with software WebGL2 in a 900x800 window, plus `output` (what to write: `--screenshot=...`
/// or `--dump-dom`), and checks that the page wrote nothing on the console.
fn quiet_run(url: &str, work: &Path, output: String) -> ChromiumRun {
    let mut args: Vec<String> = GL_FLAGS.iter().map(|s| s.to_string()).collect();
    args.extend([
        "--window-size=900,800".to_string(),
        "--virtual-time-budget=5000".to_string(),
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

/// Screenshots the page at `url_suffix` (e.g. "#before"); checks the console stays quiet; returns the
/// canvas cut out of the screenshot.
fn screenshot_canvas(page: &Path, work: &Path, url_suffix: &str) -> image::RgbImage {
    let shot = work.join("shot.png");
    let url = format!("{}{url_suffix}", file_url(page));
    quiet_run(&url, work, format!("--screenshot={}", shot.display()));
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
    let canvas = screenshot_canvas(&page, tmp.path(), "");
    // As wide as the 900-pixel window's page allows (the cap is 1280 CSS pixels), at the first camera's 4:3.
    let (w, h) = canvas.dimensions();
    assert!(w > 820 && w <= 900, "canvas {w}x{h}");
    assert!(
        (f64::from(h) - f64::from(w) * 0.75).abs() <= 1.0,
        "canvas {w}x{h}"
    );
    let mut counts = Counts::default();
    for p in canvas.pixels() {
        classify(&mut counts, p.0);
    }
    println!("screenshot: {counts:?}");
    // Split view: the left blob from "before" (red), the right one from "after" (green); blue is hidden.
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
    let mut shaded = GaussianScene::new(1);
    shaded.means = dc.means.clone();
    shaded.log_scales = dc.log_scales.clone();
    shaded.quats = dc.quats.clone();
    shaded.opacity_logits = dc.opacity_logits.clone();
    for i in 0..dc.len() {
        shaded.sh.extend_from_slice(&dc.sh[3 * i..3 * i + 3]);
        // c1 (−y), c2 (z), c3 (−x), each RGB.
        shaded
            .sh
            .extend([0.1, 0.0, -0.1, -0.75, 0.75, 0.0, 0.2, 0.0, -0.2]);
    }
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

/// Mean and 99th-percentile absolute colour error of a viewer screenshot against the CPU renderer's
/// image of `scene` from the front camera at the screenshot's size.
fn errors_against_cpu(canvas: &image::RgbImage, scene: &GaussianScene) -> (f32, f32) {
    let (w, h) = canvas.dimensions();
    let cpu = splat::render::render(
        scene,
        &front_camera(w, h),
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
            (0..3)
                .map(|c| (f32::from(p.0[c]) / 255.0 - q[c]).abs())
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
