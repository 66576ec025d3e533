//! The training set: world samples rendered once into memory (8 bits per channel), and batch assembly.

use candle_core::{Device, Result, Tensor};
use rand::Rng;

use crate::world::dataset::{samples, DatasetConfig};

/// Rendered samples `0..len` of one world stream.
pub struct RenderedSet {
    pub size: usize,
    /// RGB, row-major, `size`² pixels per image, images back to back.
    pub pixels: Vec<u8>,
    pub captions: Vec<String>,
}

/// Samples rendered per parallel chunk (progress is reported per chunk).
const CHUNK: u64 = 256;

impl RenderedSet {
    /// Renders samples `0..n` of stream `seed`; `progress(done)` after each chunk.
    pub fn render(
        config: &DatasetConfig,
        seed: u64,
        n: usize,
        progress: &mut dyn FnMut(usize),
    ) -> Self {
        assert_eq!(config.width, config.height, "square training images");
        let size = config.width as usize;
        let mut pixels = Vec::with_capacity(n * size * size * 3);
        let mut captions = Vec::with_capacity(n);
        let mut start = 0u64;
        while (start as usize) < n {
            let end = (start + CHUNK).min(n as u64);
            for s in samples(config, seed, start..end) {
                pixels.extend(s.image.to_u8());
                captions.push(s.caption);
            }
            start = end;
            progress(start as usize);
        }
        Self {
            size,
            pixels,
            captions,
        }
    }

    pub fn len(&self) -> usize {
        self.captions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.captions.is_empty()
    }

    /// Images `indices` as a [B, 3, crop, crop] tensor in [-1, 1]. Each image is cropped at a random
    /// position (the full image when `crop` equals the size) and mirrored left-right with probability ½.
    pub fn batch<R: Rng>(&self, indices: &[usize], crop: usize, rng: &mut R) -> Result<Tensor> {
        let (s, c) = (self.size, crop.min(self.size));
        let mut data = vec![0f32; indices.len() * 3 * c * c];
        for (b, &i) in indices.iter().enumerate() {
            let image = &self.pixels[i * s * s * 3..(i + 1) * s * s * 3];
            let (x0, y0) = (rng.gen_range(0..=s - c), rng.gen_range(0..=s - c));
            let mirror = rng.gen_bool(0.5);
            let out = &mut data[b * 3 * c * c..(b + 1) * 3 * c * c];
            for y in 0..c {
                for x in 0..c {
                    let sx = if mirror { x0 + c - 1 - x } else { x0 + x };
                    let p = &image[((y0 + y) * s + sx) * 3..][..3];
                    for ch in 0..3 {
                        out[(ch * c + y) * c + x] = p[ch] as f32 / 127.5 - 1.0;
                    }
                }
            }
        }
        Tensor::from_vec(data, (indices.len(), 3, c, c), &Device::Cpu)
    }

    /// Images `range` uncropped and unmirrored, [B, 3, size, size] in [-1, 1].
    pub fn images(&self, range: std::ops::Range<usize>) -> Result<Tensor> {
        let s = self.size;
        let n = range.len();
        let src = &self.pixels[range.start * s * s * 3..range.end * s * s * 3];
        let hwc = Tensor::from_vec(
            src.iter()
                .map(|&v| v as f32 / 127.5 - 1.0)
                .collect::<Vec<f32>>(),
            (n, s, s, 3),
            &Device::Cpu,
        )?;
        hwc.permute((0, 3, 1, 2))?.contiguous()
    }
}

/// `n` distinct-ish random indices below `len` (with replacement: cheap and unbiased).
pub fn random_indices<R: Rng>(len: usize, n: usize, rng: &mut R) -> Vec<usize> {
    (0..n).map(|_| rng.gen_range(0..len)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn batches_crop_and_mirror_the_rendered_pixels() {
        let config = DatasetConfig {
            width: 16,
            height: 16,
            ..Default::default()
        };
        let mut reported = Vec::new();
        let set = RenderedSet::render(&config, 3, 5, &mut |d| reported.push(d));
        assert_eq!(reported, vec![5]);
        assert_eq!((set.len(), set.pixels.len()), (5, 5 * 16 * 16 * 3));
        let direct = samples(&config, 3, 2..3);
        assert_eq!(set.captions[2], direct[0].caption);
        let full = set.images(2..3).unwrap();
        // Pixel (x 4, y 7), green channel, equals the render (after 8-bit quantisation).
        let v = full
            .get(0)
            .unwrap()
            .get(1)
            .unwrap()
            .get(7)
            .unwrap()
            .get(4)
            .unwrap();
        let want = direct[0].image.pixel(4, 7)[1];
        assert!((v.to_scalar::<f32>().unwrap() - (want * 2.0 - 1.0)).abs() < 1.0 / 127.0);
        // A full-size "crop" is the image or its mirror.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mirror = full.flip(&[3]).unwrap();
        for _ in 0..8 {
            let b = set.batch(&[2], 16, &mut rng).unwrap();
            let max_diff = |other: &Tensor| testkit::diff::tensor_max_abs_diff(&b, other);
            assert!(max_diff(&full) == 0.0 || max_diff(&mirror) == 0.0);
        }
        let crops = set.batch(&[0, 1, 4], 8, &mut rng).unwrap();
        assert_eq!(crops.dims(), &[3, 3, 8, 8]);
    }
}
