//! Animated GIFs (the turntable of an edited scene), written atomically.
//!
//! Every frame gets its own 256-colour palette (NeuQuant, as the `image` crate's encoder does), the
//! animation loops forever, and RGBA frames are composited over white (GIF has only on/off transparency).

use std::path::{Path, PathBuf};

use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};
use splat::Image;

#[derive(Debug, thiserror::Error)]
pub enum GifError {
    #[error("{}: {msg}", .path.display())]
    Input { path: PathBuf, msg: String },
    #[error("{}: cannot write: {msg}", .path.display())]
    Write { path: PathBuf, msg: String },
}

/// Options of [`write_gif`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GifOptions {
    /// Time each frame is shown, in milliseconds (GIF stores hundredths of a second).
    pub delay_ms: u32,
    /// Palette quantisation speed, 1 (best) to 30 (fastest).
    pub speed: i32,
}

impl Default for GifOptions {
    fn default() -> Self {
        Self {
            delay_ms: 100,
            speed: 10,
        }
    }
}

fn to_rgba8(img: &Image) -> Result<RgbaImage, String> {
    let c = img.channels as usize;
    if !matches!(c, 1 | 3 | 4) {
        return Err(format!("a frame has {c} channels (need 1, 3 or 4)"));
    }
    let q = |v: f32| -> u8 {
        if v.is_nan() {
            0
        } else {
            (v.clamp(0.0, 1.0) * 255.0).round() as u8
        }
    };
    let mut out = Vec::with_capacity(img.data.len() / c * 4);
    for p in img.data.chunks_exact(c) {
        let rgb = match c {
            1 => [p[0]; 3],
            3 => [p[0], p[1], p[2]],
            _ => {
                let a = p[3].clamp(0.0, 1.0);
                [0, 1, 2].map(|k| p[k] * a + (1.0 - a))
            }
        };
        out.extend(rgb.map(q));
        out.push(255);
    }
    RgbaImage::from_raw(img.width, img.height, out).ok_or_else(|| "frame size".to_string())
}

/// Frames of a turntable: `frames` views of `scene` on one orbit around its 1st-99th percentile bounds
/// (the orbit of `splat::cameras::orbit_cameras`), rendered over `background`. Empty for an empty scene.
pub fn turntable_frames(
    scene: &splat::GaussianScene,
    frames: usize,
    width: u32,
    height: u32,
    background: [f32; 3],
) -> Vec<Image> {
    use rayon::prelude::*;
    let Some((lo, hi)) = splat::cameras::robust_bounds(scene, 0.01) else {
        return Vec::new();
    };
    let settings = splat::render::RenderSettings { background };
    splat::cameras::orbit_cameras(lo, hi, frames, width, height)
        .par_iter()
        .map(|c| splat::render::render(scene, c, &settings, None).rgb_image())
        .collect()
}

/// The GIF bytes of an animation of `frames` (all the same size, at most 65535 pixels a side).
pub fn encode_gif(frames: &[Image], options: &GifOptions) -> Result<Vec<u8>, String> {
    let first = frames.first().ok_or("no frames to animate")?;
    let (w, h) = (first.width, first.height);
    if w == 0 || h == 0 || w > u16::MAX as u32 || h > u16::MAX as u32 {
        return Err(format!("frame size {w}x{h} is not possible in a GIF"));
    }
    if let Some((k, f)) = frames
        .iter()
        .enumerate()
        .find(|(_, f)| (f.width, f.height) != (w, h))
    {
        return Err(format!(
            "frame {k} is {}x{}, the first is {w}x{h}",
            f.width, f.height
        ));
    }
    let mut bytes = Vec::new();
    {
        let mut enc = GifEncoder::new_with_speed(&mut bytes, options.speed.clamp(1, 30));
        enc.set_repeat(Repeat::Infinite)
            .map_err(|e| e.to_string())?;
        let delay = Delay::from_numer_denom_ms(options.delay_ms, 1);
        for f in frames {
            let frame = Frame::from_parts(to_rgba8(f)?, 0, 0, delay);
            enc.encode_frame(frame).map_err(|e| e.to_string())?;
        }
    }
    Ok(bytes)
}

/// Writes an endlessly looping animated GIF of `frames` to `path` (atomically).
pub fn write_gif(path: &Path, frames: &[Image], options: &GifOptions) -> Result<(), GifError> {
    let bytes = encode_gif(frames, options).map_err(|msg| GifError::Input {
        path: path.to_path_buf(),
        msg,
    })?;
    files::atomic_write(path, &bytes).map_err(|e| GifError::Write {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::AnimationDecoder;

    fn frame(w: u32, h: u32, k: usize) -> Image {
        let mut img = Image::new(w, h, 3);
        for (i, px) in img.data.chunks_exact_mut(3).enumerate() {
            let x = (i as u32 % w) as f32 / w as f32;
            px.copy_from_slice(&[x, k as f32 / 4.0, 1.0 - x]);
        }
        img
    }

    #[test]
    fn writes_a_looping_animation_that_decodes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("turn.gif");
        let frames: Vec<Image> = (0..4).map(|k| frame(24, 16, k)).collect();
        write_gif(
            &path,
            &frames,
            &GifOptions {
                delay_ms: 80,
                ..Default::default()
            },
        )
        .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // The NETSCAPE2.0 application extension with loop count 0 = forever.
        let pos = bytes
            .windows(11)
            .position(|w| w == b"NETSCAPE2.0")
            .expect("loop extension");
        assert_eq!(&bytes[pos + 11..pos + 15], &[3, 1, 0, 0]);
        let dec = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(bytes)).unwrap();
        let decoded = dec.into_frames().collect_frames().unwrap();
        assert_eq!(decoded.len(), 4);
        for (k, f) in decoded.iter().enumerate() {
            assert_eq!(f.delay().numer_denom_ms(), (80, 1));
            let buf = f.buffer();
            assert_eq!(buf.dimensions(), (24, 16));
            // Colours survive quantisation closely (smooth gradients, per-frame palettes).
            let want = frame(24, 16, k).to_u8();
            let got: Vec<u8> = buf.pixels().flat_map(|p| [p[0], p[1], p[2]]).collect();
            let mean_err = want
                .iter()
                .zip(&got)
                .map(|(a, b)| (*a as f64 - *b as f64).abs())
                .sum::<f64>()
                / want.len() as f64;
            assert!(mean_err < 4.0, "frame {k}: mean error {mean_err}");
        }
        // Only the target file remains (no temporary).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn bad_frame_lists_are_errors_naming_the_file() {
        let p = Path::new("/nonexistent/x.gif");
        let e = write_gif(p, &[], &GifOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.gif") && e.contains("no frames"), "{e}");
        let e = write_gif(p, &[frame(4, 4, 0), frame(5, 4, 1)], &GifOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame 1"), "{e}");
        let e = write_gif(p, &[Image::new(4, 4, 2)], &GifOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("channels"), "{e}");
    }

    #[test]
    fn turntable_frames_circle_the_scene() {
        // Two coloured blobs: every frame sees something, and frames differ as the camera moves.
        let mut scene = splat::GaussianScene::new(0);
        for (p, c) in [
            ([0.5f32, 0.0, 0.0], [2.0f32, -1.0, -1.0]),
            ([-0.5, 0.0, 0.2], [-1.0, 2.0, -1.0]),
        ] {
            scene.means.extend_from_slice(&p);
            scene.log_scales.extend_from_slice(&[-1.5; 3]);
            scene.quats.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
            scene.opacity_logits.push(4.0);
            scene.sh.extend_from_slice(&c);
        }
        let frames = turntable_frames(&scene, 6, 32, 24, [1.0; 3]);
        assert_eq!(frames.len(), 6);
        assert!(frames.iter().all(|f| (f.width, f.height) == (32, 24)));
        assert!(frames.iter().all(|f| f.data.iter().any(|&v| v < 0.5)));
        assert_ne!(frames[0].data, frames[3].data);
        assert!(turntable_frames(&splat::GaussianScene::new(0), 4, 8, 8, [0.0; 3]).is_empty());
    }

    #[test]
    fn rgba_frames_are_composited_over_white() {
        let mut img = Image::new(2, 1, 4);
        img.data = vec![1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0];
        let rgba = to_rgba8(&img).unwrap();
        assert_eq!(rgba.get_pixel(0, 0).0, [255, 0, 0, 255]);
        assert_eq!(rgba.get_pixel(1, 0).0, [255, 255, 255, 255]);
    }
}
