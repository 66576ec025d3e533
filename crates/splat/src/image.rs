//! Float images and atomic PNG I/O.
//!
//! Every output file in vcedit goes through [`files::atomic_write`]: the bytes go to a temporary file next to the
//! target, then a rename replaces the target, so an interrupted run never leaves a half-written file and
//! never destroys the previous one.

use image::ImageEncoder;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: {msg}")]
    Read { path: PathBuf, msg: String },
    #[error("{path}: cannot write: {msg}")]
    Write { path: PathBuf, msg: String },
}

impl ImageError {
    /// What went wrong, without the path (for callers whose own message names the file).
    pub fn reason(&self) -> &str {
        match self {
            ImageError::Read { msg, .. } | ImageError::Write { msg, .. } => msg,
        }
    }
}

/// A row-major, channel-interleaved float image; values nominally in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub channels: u32,
    pub data: Vec<f32>,
}

impl Image {
    pub fn new(width: u32, height: u32, channels: u32) -> Self {
        Self {
            width,
            height,
            channels,
            data: vec![0.0; (width * height * channels) as usize],
        }
    }

    pub fn from_data(width: u32, height: u32, channels: u32, data: Vec<f32>) -> Self {
        assert_eq!(
            data.len(),
            (width * height * channels) as usize,
            "image data length"
        );
        Self {
            width,
            height,
            channels,
            data,
        }
    }

    pub fn pixel(&self, x: u32, y: u32) -> &[f32] {
        let c = self.channels as usize;
        let i = (y as usize * self.width as usize + x as usize) * c;
        &self.data[i..i + c]
    }

    /// Composites an RGBA image over a background colour (RGB images are returned unchanged).
    pub fn over_background(&self, bg: [f32; 3]) -> Image {
        if self.channels != 4 {
            return self.clone();
        }
        let mut data = Vec::with_capacity((self.width * self.height * 3) as usize);
        for p in self.data.chunks_exact(4) {
            let a = p[3];
            for c in 0..3 {
                data.push(p[c] * a + bg[c] * (1.0 - a));
            }
        }
        Image::from_data(self.width, self.height, 3, data)
    }

    /// The largest centred crop with the aspect ratio `width : height`.
    pub fn center_crop_to_aspect(&self, width: u32, height: u32) -> Image {
        let (w, h) = (self.width as u64, self.height as u64);
        // Crop width if the image is wider than the target aspect, else crop height.
        let (cw, ch) = if w * height as u64 > h * width as u64 {
            (((h * width as u64) / height as u64).max(1), h)
        } else {
            (w, ((w * height as u64) / width as u64).max(1))
        };
        let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
        let c = self.channels as usize;
        let mut data = Vec::with_capacity((cw * ch) as usize * c);
        for y in y0..y0 + ch {
            let row = (y * w + x0) as usize * c;
            data.extend_from_slice(&self.data[row..row + cw as usize * c]);
        }
        Image::from_data(cw as u32, ch as u32, self.channels, data)
    }

    /// Resamples to `width x height` with a Lanczos-3 filter (as PIL's LANCZOS). Values are not clamped.
    pub fn resize(&self, width: u32, height: u32) -> Image {
        if (width, height) == (self.width, self.height) {
            return self.clone();
        }
        let c = self.channels as usize;
        let mut out = Image::new(width, height, self.channels);
        // Resample each channel as a 32-bit float luma image so no precision is lost.
        for ch in 0..c {
            let plane: Vec<f32> = self.data.iter().skip(ch).step_by(c).copied().collect();
            let buf = image::ImageBuffer::<image::Luma<f32>, Vec<f32>>::from_raw(
                self.width,
                self.height,
                plane,
            )
            .expect("plane size");
            let r =
                image::imageops::resize(&buf, width, height, image::imageops::FilterType::Lanczos3);
            for (i, v) in r.into_raw().into_iter().enumerate() {
                out.data[i * c + ch] = v;
            }
        }
        out
    }

    /// Loads a PNG/JPEG as RGB or RGBA floats in [0, 1] (8- or 16-bit inputs; grey is expanded to RGB).
    pub fn load(path: &Path) -> Result<Image, ImageError> {
        let err = |msg: String| ImageError::Read {
            path: path.to_path_buf(),
            msg,
        };
        if path.is_dir() {
            return Err(err(
                "is a folder; give one image file (PNG or JPEG)".to_string()
            ));
        }
        let img = image::open(path).map_err(|e| err(e.to_string()))?;
        let has_alpha = img.color().has_alpha();
        let (w, h) = (img.width(), img.height());
        if has_alpha {
            let buf = img.into_rgba32f();
            Ok(Image::from_data(w, h, 4, buf.into_raw()))
        } else {
            let buf = img.into_rgb32f();
            Ok(Image::from_data(w, h, 3, buf.into_raw()))
        }
    }

    /// Saves as an 8-bit PNG (1 = grey, 3 = RGB, 4 = RGBA), clamping to [0, 1]; written atomically.
    pub fn save_png(&self, path: &Path) -> Result<(), ImageError> {
        let bytes = self.encode_png().map_err(|msg| ImageError::Write {
            path: path.to_path_buf(),
            msg,
        })?;
        files::atomic_write(path, &bytes).map_err(|e| ImageError::Write {
            path: path.to_path_buf(),
            msg: e.to_string(),
        })
    }

    /// PNG bytes of the image (8-bit).
    pub fn encode_png(&self) -> Result<Vec<u8>, String> {
        let color = match self.channels {
            1 => image::ExtendedColorType::L8,
            3 => image::ExtendedColorType::Rgb8,
            4 => image::ExtendedColorType::Rgba8,
            c => return Err(format!("cannot save an image with {c} channels as PNG")),
        };
        let bytes = self.to_u8();
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(&bytes, self.width, self.height, color)
            .map_err(|e| e.to_string())?;
        Ok(out)
    }

    /// Quantises to 8 bits per channel with rounding, clamping to [0, 1] (NaN becomes 0).
    pub fn to_u8(&self) -> Vec<u8> {
        self.data
            .iter()
            .map(|&v| {
                if v.is_nan() {
                    0
                } else {
                    (v.clamp(0.0, 1.0) * 255.0).round() as u8
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_write_names_the_file_once() {
        let dir = tempfile::tempdir().unwrap();
        // A file where the folder should be: the write fails.
        let blocker = dir.path().join("blocker");
        std::fs::write(&blocker, b"x").unwrap();
        let path = blocker.join("view.png");
        let err = Image::from_data(2, 2, 3, vec![0.5; 12])
            .save_png(&path)
            .unwrap_err();
        let text = err.to_string();
        assert_eq!(text.matches(&*path.to_string_lossy()).count(), 1, "{text}");
        assert!(
            text.contains("cannot write") && !err.reason().contains("view.png"),
            "{text}"
        );
    }

    #[test]
    fn png_roundtrip_rgb_and_grey() {
        let dir = tempfile::tempdir().unwrap();
        for channels in [1u32, 3, 4] {
            let mut img = Image::new(5, 3, channels);
            for (i, v) in img.data.iter_mut().enumerate() {
                *v = (i % 7) as f32 / 6.0;
            }
            let p = dir.path().join(format!("x{channels}.png"));
            img.save_png(&p).unwrap();
            let back = Image::load(&p).unwrap();
            assert_eq!((back.width, back.height), (5, 3));
            // Grey loads as RGB; compare the first channel.
            let bc = back.channels as usize;
            for y in 0..3 {
                for x in 0..5 {
                    let a = img.pixel(x, y)[0];
                    let b = back.data[(y as usize * 5 + x as usize) * bc];
                    assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
                }
            }
        }
    }

    #[test]
    fn crop_resize_and_composite() {
        let mut img = Image::new(8, 4, 4);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = if i % 4 == 3 { 0.5 } else { 1.0 };
        }
        let sq = img.center_crop_to_aspect(1, 1);
        assert_eq!((sq.width, sq.height), (4, 4));
        let r = sq.resize(2, 2);
        assert_eq!((r.width, r.height, r.channels), (2, 2, 4));
        assert!(r
            .data
            .iter()
            .all(|v| (v - if *v > 0.75 { 1.0 } else { 0.5 }).abs() < 1e-4));
        let rgb = r.over_background([0.0, 0.0, 0.0]);
        assert_eq!(rgb.channels, 3);
        assert!(rgb.data.iter().all(|v| (v - 0.5).abs() < 1e-4));
        let tall = Image::new(3, 9, 3).center_crop_to_aspect(1, 1);
        assert_eq!((tall.width, tall.height), (3, 3));
    }

    #[test]
    fn load_reports_path_on_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.png");
        std::fs::write(&p, b"not a png").unwrap();
        let e = Image::load(&p).unwrap_err().to_string();
        assert!(e.contains("bad.png"), "{e}");
    }
}
