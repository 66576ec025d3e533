//! Turning maps into pictures: per-word attention heat maps and mask images for users to inspect.

use candle_core::{DType, Device, Result, Tensor};
use splat::Image;

use splat::lift::{resample, Resample};

/// A heat-map colour for v in [0, 1]: black → purple → orange → light yellow (inferno-like, readable in
/// print and for most colour-blind viewers).
pub fn heat_color(v: f32) -> [f32; 3] {
    const STOPS: [(f32, [f32; 3]); 5] = [
        (0.0, [0.0, 0.0, 0.02]),
        (0.3, [0.34, 0.06, 0.43]),
        (0.6, [0.8, 0.26, 0.3]),
        (0.85, [0.98, 0.6, 0.1]),
        (1.0, [0.99, 1.0, 0.64]),
    ];
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    for w in STOPS.windows(2) {
        let ((a, ca), (b, cb)) = (w[0], w[1]);
        if v <= b {
            let t = (v - a) / (b - a);
            return [
                ca[0] + t * (cb[0] - ca[0]),
                ca[1] + t * (cb[1] - ca[1]),
                ca[2] + t * (cb[2] - ca[2]),
            ];
        }
    }
    STOPS[4].1
}

/// A scalar map (row-major `h*w`, any range) as a heat-map image, normalised by its maximum.
pub fn heat_image(map: &[f32], width: u32, height: u32) -> Image {
    let max = map
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f32, f32::max);
    let scale = if max > 0.0 { 1.0 / max } else { 0.0 };
    let data = map.iter().flat_map(|&v| heat_color(v * scale)).collect();
    Image::from_data(width, height, 3, data)
}

/// A binary or soft mask in [0, 1] as a grey image.
pub fn mask_image(mask: &[f32], width: u32, height: u32) -> Image {
    Image::from_data(
        width,
        height,
        1,
        mask.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
    )
}

/// Bilinear resampling of a `[h, w]` tensor map to `(out_h, out_w)` (align_corners = false, as torch).
pub fn resize_map(map: &Tensor, out_h: usize, out_w: usize) -> Result<Vec<f32>> {
    let (h, w) = map.dims2()?;
    let src: Vec<f32> = map.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
    Ok(resample(
        &src,
        (h, w),
        (out_h, out_w),
        1,
        Resample::Bilinear,
    ))
}

/// One attention map per target word.
pub struct WordMap {
    pub word: String,
    /// Row-major map of `size` (h, w), unnormalised.
    pub map: Vec<f32>,
    pub size: (usize, usize),
}

/// Groups target tokens (SOT .. EOT as strings) into words: a word ends with a token ending in `</w>`.
/// Returns (word, token positions).
pub fn words_of(tokens: &[String]) -> Vec<(String, Vec<usize>)> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut pos = Vec::new();
    let inner = tokens.len().saturating_sub(1);
    for (i, t) in tokens.iter().enumerate().take(inner).skip(1) {
        let (piece, end) = match t.strip_suffix("</w>") {
            Some(p) => (p, true),
            None => (t.as_str(), false),
        };
        cur.push_str(piece);
        pos.push(i);
        if end {
            out.push((std::mem::take(&mut cur), std::mem::take(&mut pos)));
        }
    }
    if !pos.is_empty() {
        out.push((cur, pos));
    }
    out
}

/// Per-word maps from a controller's blend store (the layout branch's maps refined onto the target tokens,
/// averaged over layers and heads, max over a word's tokens), upsampled bilinearly to `out` (h, w).
pub fn word_maps(
    store: &[(String, Tensor)],
    map_size: (usize, usize),
    target_tokens: &[String],
    out: (usize, usize),
) -> Result<Vec<WordMap>> {
    if store.is_empty() {
        return Ok(Vec::new());
    }
    // [hw, tokens] of the layout branch.
    let mean = crate::sampler::mean_over_layers_and_heads(store)?.get(1)?;
    let tokens = mean.dim(1)?;
    let mut maps = Vec::new();
    for (word, pos) in words_of(target_tokens) {
        let idx: Vec<u32> = pos
            .iter()
            .filter(|&&p| p < tokens)
            .map(|&p| p as u32)
            .collect();
        if idx.is_empty() {
            continue;
        }
        let sel = mean
            .index_select(&Tensor::new(idx, &Device::Cpu)?, 1)?
            .max(1)?
            .reshape(map_size)?;
        maps.push(WordMap {
            word,
            map: resize_map(&sel, out.0, out.1)?,
            size: out,
        });
    }
    Ok(maps)
}

/// A file-name-safe version of a word.
pub fn file_safe(word: &str) -> String {
    let s: String = word
        .chars()
        .map(|c| {
            if c.is_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if s.is_empty() {
        "token".into()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_group_bpe_pieces() {
        let toks: Vec<String> = [
            "<|startoftext|>",
            "a</w>",
            "clo",
            "wn</w>",
            "hat</w>",
            "<|endoftext|>",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let w = words_of(&toks);
        assert_eq!(
            w,
            vec![
                ("a".into(), vec![1]),
                ("clown".into(), vec![2, 3]),
                ("hat".into(), vec![4])
            ]
        );
    }

    #[test]
    fn heat_colors_are_monotone_in_brightness() {
        let lum = |c: [f32; 3]| c[0] + c[1] + c[2];
        let mut prev = -1.0;
        for i in 0..=10 {
            let l = lum(heat_color(i as f32 / 10.0));
            assert!(l > prev);
            prev = l;
        }
        assert_eq!(heat_image(&[0.0, 2.0], 2, 1).data.len(), 6);
    }
}
