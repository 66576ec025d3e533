//! The consistency metric on real renders of a Gaussian scene: renders agree with themselves, a consistent
//! recolouring of the same geometry stays consistent, and per-view colour shifts (what independent
//! per-view editing produces) are clearly detected.

use edit::eval::metrics::{multiview_consistency, render_consistency, ViewGeometry, WarpSettings};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use splat::cameras::orbit_cameras;
use splat::render::{render, Frame, RenderSettings};
use splat::{Camera, GaussianScene, Image};

/// A sphere of radius 1 covered by 6000 small opaque Gaussians, coloured by `color(position)`.
fn textured_sphere(color: impl Fn([f32; 3]) -> [f32; 3]) -> GaussianScene {
    testkit::scenes::textured_sphere(6000, color)
}

/// A smooth texture. Splatting blends a few overlapping Gaussians per pixel, and which ones are in front
/// depends on the view, so even a scene's own renders differ by about (colour gradient) x (Gaussian size)
/// between views: this floor of the metric grows with the texture's contrast (measured: a flat colour gives
/// 0.0007, this texture about 0.005, one with 2x its amplitude and frequency 0.0125).
fn stripes(p: [f32; 3]) -> [f32; 3] {
    [
        0.5 + 0.2 * (1.5 * p[0]).sin(),
        0.5 + 0.2 * (1.2 * p[1] + p[2]).cos(),
        0.5 + 0.15 * (2.0 * p[2]).sin(),
    ]
}

fn spots(p: [f32; 3]) -> [f32; 3] {
    [
        0.4 + 0.2 * (2.0 * p[1]).cos(),
        0.6 - 0.15 * (1.5 * p[0] * p[2]).sin(),
        0.3 + 0.2 * p[0],
    ]
}

fn setup() -> (Vec<Camera>, Vec<Frame>) {
    let scene = textured_sphere(stripes);
    let (lo, hi) = scene.bounds().unwrap();
    let cams = orbit_cameras(lo, hi, 10, 80, 80);
    let settings = RenderSettings::default();
    let renders = cams
        .iter()
        .map(|c| render(&scene, c, &settings, None).into_frame())
        .collect();
    (cams, renders)
}

fn report(
    cams: &[Camera],
    geometry: &[Frame],
    images: &[Image],
) -> edit::eval::metrics::ConsistencySummary {
    let g: Vec<ViewGeometry> = cams
        .iter()
        .zip(geometry)
        .map(|(c, r)| ViewGeometry::from_render(c, r))
        .collect();
    multiview_consistency(
        &images.iter().collect::<Vec<_>>(),
        &g,
        &WarpSettings::default(),
    )
    .unwrap()
    .summary
}

#[test]
fn consistent_images_score_low_and_per_view_shifts_score_high() {
    let (cams, renders) = setup();
    let own = render_consistency(&cams, &renders, &WarpSettings::default()).unwrap();
    let s = &own.summary;
    println!("renders vs themselves: {s:?}");
    assert_eq!(s.pairs, 30);
    assert!(s.covisible_fraction > 0.4, "{s:?}");
    let base = s.mean_abs_error.unwrap();
    assert!(base < 0.01, "identical renders: error {base}");

    // Same geometry, another texture: still one consistent 3D appearance.
    let recoloured = textured_sphere(spots);
    let images: Vec<Image> = cams
        .iter()
        .map(|c| render(&recoloured, c, &RenderSettings::default(), None).rgb_image())
        .collect();
    let r = report(&cams, &renders, &images);
    println!("consistent recolouring: {r:?}");
    assert!(r.mean_abs_error.unwrap() < 0.01);

    // Each view shifted by its own random colour offset in [-0.1, 0.1]: the expected pairwise error is
    // about E|a - b| over channels ≈ 0.067.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let shifted: Vec<Image> = renders
        .iter()
        .map(|r| {
            let mut img = r.rgb_image();
            let shift: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-0.1..0.1));
            for px in img.data.chunks_exact_mut(3) {
                for c in 0..3 {
                    px[c] += shift[c];
                }
            }
            img
        })
        .collect();
    let r = report(&cams, &renders, &shifted);
    println!("per-view shifts: {r:?}");
    let shifted_err = r.mean_abs_error.unwrap();
    assert!(
        shifted_err > 0.03 && shifted_err > 5.0 * base,
        "{shifted_err} vs {base}"
    );
    assert!(r.psnr.unwrap() < s.psnr.unwrap() - 10.0);
}

#[test]
fn background_pixels_are_ignored() {
    // Renders over different background colours agree: background pixels (alpha < 0.5) never count.
    let (cams, renders) = setup();
    let images: Vec<Image> = cams
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let bg = [k as f32 / 10.0, 1.0 - k as f32 / 10.0, 0.5];
            render(
                &textured_sphere(stripes),
                c,
                &RenderSettings { background: bg },
                None,
            )
            .rgb_image()
        })
        .collect();
    let own = render_consistency(&cams, &renders, &WarpSettings::default()).unwrap();
    let r = report(&cams, &renders, &images);
    let (a, b) = (
        r.mean_abs_error.unwrap(),
        own.summary.mean_abs_error.unwrap(),
    );
    // Only the rim pixels with 0.5 < alpha < 1 see a little of the background.
    assert!(a < 2.0 * b + 0.005, "{a} vs {b}");
}
