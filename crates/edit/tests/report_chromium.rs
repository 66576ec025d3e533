//! The report opens in headless Chromium from disk: every linked image loads (no console messages, which
//! would include "Failed to load resource"), no script errors, and the screenshot shows the images.
//! Skips (with the reason printed) when /usr/bin/chromium is absent; Debian: `apt-get install -y chromium`.

mod common;

use std::path::{Path, PathBuf};

use common::{chromium_available, file_url, run_chromium};

use edit::eval::metrics::{ConsistencySummary, PreservationReport};
use edit::present::gif::{write_gif, GifOptions};
use edit::present::report::{
    write_report, write_report_with_viewer, IterationInfo, MetricsSummary, ReportData,
    ReportOptions, RunSummary, StageTiming, ViewPair, WordImage,
};
use edit::present::viewer::{viewer_html, InitialView, ViewerOptions, ViewerScene};
use splat::Image;

fn solid(w: u32, h: u32, rgb: [f32; 3], k: usize) -> Image {
    let mut img = Image::new(w, h, 3);
    for (i, px) in img.data.chunks_exact_mut(3).enumerate() {
        // A faint diagonal pattern so images are not flat, but the dominant colour stays recognisable.
        let stripe = if (i as u32 % w + i as u32 / w + k as u32) % 16 < 2 {
            0.1
        } else {
            0.0
        };
        for c in 0..3 {
            px[c] = (rgb[c] - stripe).max(0.0);
        }
    }
    img
}

fn consistency(e: f64) -> ConsistencySummary {
    ConsistencySummary {
        mean_abs_error: Some(e),
        psnr: Some(-20.0 * e.log10()),
        pairs: 24,
        covisible_fraction: 0.61,
        covisible_pixels: 123_456,
    }
}

/// A complete run folder with dummy images, and its report.
fn write_dummy_run(dir: &Path) -> PathBuf {
    write_report(dir, &dummy_run(dir), &ReportOptions::default()).unwrap()
}

/// Writes the dummy images of a run into `dir` and returns the report's data for them.
fn dummy_run(dir: &Path) -> ReportData {
    let (w, h) = (128, 96);
    let mut views = Vec::new();
    let mut guidance = Vec::new();
    for k in 0..10 {
        let before = PathBuf::from(format!("renders/source view {k}.png"));
        let after = PathBuf::from(format!("renders/edited_{k:03}.png"));
        solid(w, h, [0.9, 0.1, 0.1], k)
            .save_png(&dir.join(&before))
            .unwrap();
        solid(w, h, [0.1, 0.8, 0.2], k)
            .save_png(&dir.join(&after))
            .unwrap();
        views.push(ViewPair {
            name: format!("view {k}"),
            before,
            after,
        });
        let g = PathBuf::from(format!("iter_0/guidance/{k:03}.png"));
        solid(w, h, [0.1, 0.2, 0.9], k)
            .save_png(&dir.join(&g))
            .unwrap();
        guidance.push(g);
    }
    let heat: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 / w as f32).collect();
    let att = PathBuf::from("attention/clown.png");
    edit::present::viz::heat_image(&heat, w, h)
        .save_png(&dir.join(&att))
        .unwrap();
    let mask = PathBuf::from("mask/000.png");
    edit::present::viz::mask_image(&heat, w, h)
        .save_png(&dir.join(&mask))
        .unwrap();
    let frames: Vec<Image> = (0..6)
        .map(|k| solid(w, h, [0.2, 0.6, 0.9], k * 3))
        .collect();
    write_gif(&dir.join("turntable.gif"), &frames, &GifOptions::default()).unwrap();

    let metrics = MetricsSummary {
        source_consistency: Some(consistency(0.004)),
        guidance_consistency: Some(consistency(0.031)),
        final_consistency: Some(consistency(0.009)),
        preservation_outside_mask: Some(PreservationReport {
            psnr: Some(41.2),
            ssim: Some(0.991),
            pixels: 1000,
            fraction: 0.7,
            views: 10,
        }),
        ..Default::default()
    };
    let data = ReportData {
        title: "Turn the man into a clown".into(),
        source_prompt: "a photo of a man <b>".into(),
        target_prompt: "a photo of a clown & \"friends\"".into(),
        scene: Some("scenes/man.ply".into()),
        cameras: Some("scenes/cameras.json".into()),
        edited_scene: Some("edited.ply".into()),
        // Long unbreakable values, as paths are: they must wrap inside their boxes on a narrow screen.
        settings: serde_json::json!({
            "steps": 15, "guidance": 2.0, "ccm": [6, 13], "taesd": null,
            "lpips": "/home/someone/models/lpips_vgg_weights_converted_from_the_reference_checkpoint.safetensors",
            "fit": {"schedule": "cosine_with_warmup_and_a_very_long_name_that_does_not_break", "steps": [100, 200, 300]}
        }),
        notes: vec!["No LPIPS weights given: fitted with 10·L1 + D-SSIM.".into()],
        views,
        iterations: vec![IterationInfo {
            index: 0,
            source_prompt: Some("a photo of a man <b>".into()),
            guidance,
            renders: Vec::new(),
            guidance_consistency: Some(consistency(0.031)),
            seconds: Some(75.5),
            geometry_rate: Some(0.1),
            footprint_change: Some(0.0),
        }],
        attention: vec![WordImage {
            word: "clown".into(),
            path: att,
        }],
        masks: vec![mask],
        metrics: metrics.clone(),
        runs: vec![
            RunSummary {
                name: "VcEdit".into(),
                metrics: metrics.clone(),
                report: None,
            },
            RunSummary {
                name: "per-view guidance".into(),
                metrics: MetricsSummary {
                    guidance_consistency: Some(consistency(0.08)),
                    ..metrics
                },
                report: None,
            },
        ],
        timings: vec![
            StageTiming {
                stage: "render".into(),
                seconds: 3.2,
            },
            StageTiming {
                stage: "edit (UNet)".into(),
                seconds: 312.0,
            },
            StageTiming {
                stage: "fit".into(),
                seconds: 95.0,
            },
        ],
        turntable: Some("turntable.gif".into()),
    };
    std::fs::write(dir.join("edited.ply"), b"ply\n").unwrap();
    data
}

/// Every `src="..."` / `href="..."` of the page resolves to an existing file.
fn check_links(report: &Path) {
    let html = std::fs::read_to_string(report).unwrap();
    let dir = report.parent().unwrap();
    let mut n = 0;
    for attr in ["src=\"", "href=\""] {
        for part in html.split(attr).skip(1) {
            let url = &part[..part.find('"').unwrap()];
            assert!(!url.contains("://"), "external or absolute link {url}");
            let mut bytes = Vec::new();
            let b = url.as_bytes();
            let mut i = 0;
            while i < b.len() {
                if b[i] == b'%' {
                    bytes.push(u8::from_str_radix(&url[i + 1..i + 3], 16).unwrap());
                    i += 3;
                } else {
                    bytes.push(b[i]);
                    i += 1;
                }
            }
            let rel = String::from_utf8(bytes).unwrap();
            assert!(dir.join(&rel).is_file(), "link {url} does not resolve");
            n += 1;
        }
    }
    assert!(n > 20, "only {n} links");
}

#[test]
fn report_links_resolve() {
    let tmp = tempfile::tempdir().unwrap();
    let report = write_dummy_run(tmp.path());
    check_links(&report);
    let html = std::fs::read_to_string(&report).unwrap();
    assert!(html.contains("a photo of a man &lt;b&gt;"));
    // The one script of the page (the broken-image check); user text never becomes markup.
    assert_eq!(html.matches("<script").count(), 1);
    // 8 of 10 views in the grid (evenly spaced, first and last included).
    assert!(html.contains("8 of 10 views"));
    assert!(html.contains("source%20view%209.png"));
}

/// Runs headless Chromium on `report`; returns its console lines (and "Uncaught" errors) and the
/// screenshot.
fn open_in_chromium(report: &Path, work: &Path) -> (Vec<String>, image::RgbImage) {
    let shot = work.join("shot.png");
    let run = run_chromium(
        &file_url(report),
        work,
        &[
            "--disable-gpu".to_string(),
            "--window-size=1280,2000".to_string(),
            format!("--screenshot={}", shot.display()),
        ],
    );
    if let Ok(keep) = std::env::var("VCEDIT_KEEP_SCREENSHOT") {
        std::fs::copy(&shot, keep).unwrap();
    }
    let img = image::open(&shot).expect("screenshot").to_rgb8();
    (run.console, img)
}

#[test]
fn report_renders_in_headless_chromium() {
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run dir");
    std::fs::create_dir_all(&run).unwrap();
    let report = write_dummy_run(&run);
    let (console, img) = open_in_chromium(&report, tmp.path());
    assert!(
        console.is_empty(),
        "console messages:\n{}",
        console.join("\n")
    );
    assert_eq!(img.dimensions(), (1280, 2000));
    let mut colours = std::collections::HashSet::new();
    let (mut red, mut green, mut turntable) = (0usize, 0usize, 0usize);
    for p in img.pixels() {
        colours.insert(p.0);
        let [r, g, b] = p.0.map(|v| v as i32);
        if r > 200 && g < 60 && b < 60 {
            red += 1;
        }
        if g > 170 && r < 60 && b < 80 {
            green += 1;
        }
        // The GIF's (0.2, 0.6, 0.9), give or take its palette.
        if (r - 51).abs() < 12 && (g - 153).abs() < 12 && (b - 230).abs() < 12 {
            turntable += 1;
        }
    }
    println!(
        "screenshot: {} colours, red {red}, green {green}, turntable {turntable} px",
        colours.len()
    );
    assert!(colours.len() > 50, "screenshot looks blank");
    // Before (red) and after (green) thumbnails: 8 views of 200x150 px each, minus the stripes.
    assert!(red > 8 * 200 * 150 / 2, "before images missing ({red} px)");
    assert!(
        green > 8 * 200 * 150 / 2,
        "after images missing ({green} px)"
    );
    // The turntable is shown 400x300.
    assert!(
        turntable > 400 * 300 / 2,
        "turntable missing ({turntable} px)"
    );
}

#[test]
fn chromium_check_sees_a_file_that_fails_to_load() {
    // The console check above is meaningful: a linked image that is gone (deleted after the report was
    // written) shows up as a console message.
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    let report = write_dummy_run(&run);
    std::fs::remove_file(run.join("renders/edited_000.png")).unwrap();
    let (console, _) = open_in_chromium(&report, tmp.path());
    assert!(
        console
            .iter()
            .any(|l| l.contains("edited_000.png") || l.contains("Failed to load")),
        "no console message for the missing file: {console:?}"
    );
}

/// A page that shows the report in a frame `{WIDTH}` CSS pixels wide (headless Chromium's windows are at
/// least 500 px wide; a frame can be narrower, and is its own window to the report) and, once it has
/// loaded, measures what sticks out sideways. Writes JSON into `<pre id="layout">`: the report's width
/// against its window's, every element whose right edge is past the window (unless a box that scrolls or
/// clips holds it), each image's width against its box's, and whether the Settings JSON fits its own
/// box. Reading the frame needs `--allow-file-access-from-files`.
const LAYOUT_PROBE: &str = r#"<!DOCTYPE html><html><body style="margin:0">
<iframe id="report" src="report.html" style="border:0;width:{WIDTH}px;height:1000px"></iframe>
<pre id="layout">not run</pre><script>
const frame = document.getElementById('report');
frame.addEventListener('load', () => setTimeout(() => {
  const doc = frame.contentDocument, win = frame.contentWindow, root = doc.documentElement;
  const width = root.clientWidth;
  const clipped = (e) => {
    for (let p = e.parentElement; p && p !== doc.body; p = p.parentElement) {
      if (['auto', 'scroll', 'hidden'].includes(win.getComputedStyle(p).overflowX)) return true;
    }
    return false;
  };
  const name = (e) => e.tagName.toLowerCase() + (e.className ? '.' + String(e.className).split(' ').join('.') : '');
  const sticking_out = [...doc.body.querySelectorAll('*')]
    .filter((e) => e.getClientRects().length > 0)
    .filter((e) => e.getBoundingClientRect().right > width + 0.5 && !clipped(e))
    .map((e) => name(e) + ' right ' + Math.round(e.getBoundingClientRect().right));
  const images = [...doc.images].map((img) => ({
    src: img.getAttribute('src'),
    shown: img.getBoundingClientRect().width,
    attribute: Number(img.getAttribute('width')),
    box: img.parentElement.getBoundingClientRect().width,
  }));
  const json = [...doc.querySelectorAll('pre.json')].map((pre) => ({
    right: pre.getBoundingClientRect().right,
    overflow: pre.scrollWidth - pre.clientWidth,
  }));
  document.getElementById('layout').textContent = JSON.stringify({
    window: win.innerWidth, client: width, scroll: root.scrollWidth, sticking_out, images, json,
  });
}, 0));
</script></body></html>"#;

/// The report with the 3D viewer at a desktop width and at a phone's: nothing wider than the window
/// (the page does not scroll sideways), images scaled down to their boxes, the Settings JSON wrapped
/// inside its box.
#[test]
fn report_fits_wide_and_narrow_windows() {
    if !chromium_available() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    let data = dummy_run(&run);
    let mut scene = splat::GaussianScene::new(0);
    for i in 0..50 {
        let t = i as f32 * 0.1;
        scene.means.extend([t.sin(), t.cos(), 0.2 * t]);
        scene.log_scales.extend([-3.0; 3]);
        scene.quats.extend([1.0, 0.0, 0.0, 0.0]);
        scene.opacity_logits.push(2.0);
        scene.sh.extend([1.0, -0.5, 0.2]);
    }
    let scenes = [ViewerScene {
        label: "source",
        scene: &scene,
    }];
    let viewer = viewer_html(
        &scenes,
        &InitialView::around(&scene),
        &ViewerOptions::default(),
    );
    write_report_with_viewer(&run, &data, &ReportOptions::default(), &viewer).unwrap();

    for width in [1280u32, 420] {
        let probe = run.join("layout.html");
        std::fs::write(&probe, LAYOUT_PROBE.replace("{WIDTH}", &width.to_string())).unwrap();
        let out = run_chromium(
            &file_url(&probe),
            tmp.path(),
            &[
                "--use-gl=angle".to_string(),
                "--use-angle=swiftshader".to_string(),
                "--enable-unsafe-swiftshader".to_string(),
                "--allow-file-access-from-files".to_string(),
                format!("--window-size={},1100", width.max(500) + 20),
                "--virtual-time-budget=5000".to_string(),
                "--dump-dom".to_string(),
            ],
        );
        assert!(
            out.console.is_empty(),
            "console messages:\n{}",
            out.console.join("\n")
        );
        let start = out
            .stdout
            .find("<pre id=\"layout\">")
            .expect("layout element")
            + 17;
        let text = &out.stdout[start..start + out.stdout[start..].find("</pre>").unwrap()];
        println!("{width} px: {text}");
        let r: serde_json::Value = serde_json::from_str(text).expect("layout result");
        let client = r["client"].as_f64().unwrap();
        assert_eq!(r["window"].as_f64(), Some(f64::from(width)), "{r}");
        assert!(client > f64::from(width) - 20.0, "{width}: {r}");
        assert!(
            r["scroll"].as_f64().unwrap() <= client,
            "{width}: the page scrolls sideways: {r}"
        );
        assert_eq!(r["sticking_out"], serde_json::json!([]), "{width}: {r}");
        let images = r["images"].as_array().unwrap();
        assert!(images.len() > 20, "{r}");
        for img in images {
            let (shown, box_width) = (img["shown"].as_f64().unwrap(), img["box"].as_f64().unwrap());
            assert!(
                shown <= box_width + 0.5 && shown <= client,
                "{width}: {img}"
            );
        }
        // At 420 px the 400-px turntable and the 200-px before/after pairs are scaled down.
        let scaled = images
            .iter()
            .filter(|img| img["shown"].as_f64().unwrap() < img["attribute"].as_f64().unwrap() - 1.0)
            .count();
        if width == 420 {
            assert!(scaled >= 17, "{scaled} images scaled down: {r}");
        } else {
            assert_eq!(scaled, 0, "nothing scaled down at {width} px: {r}");
        }
        let json = r["json"].as_array().unwrap();
        assert!(!json.is_empty(), "{r}");
        for pre in json {
            assert!(pre["right"].as_f64().unwrap() <= client, "{width}: {pre}");
            assert!(pre["overflow"].as_f64().unwrap() <= 0.0, "{width}: {pre}");
        }
    }
}
