//! InfEdit's local blend: where the edit may change the latents.
//!
//! From the controller's accumulated blend-layer maps (sum over steps of the refined source and layout maps),
//! three maps are computed at latent resolution: `e` (target-blend words, from the layout branch's maps),
//! `m` (source-blend words that are not also target-blend words, from the source's maps) and `me` (words in
//! both). Each is averaged over layers and heads, restricted to the target's word tokens, maxed over tokens,
//! nearest-upsampled and divided by its maximum. Thresholding gives masks; the target latents then take
//! the layout branch outside the `e` region, the source inside `m`, and (second-to-last step) the layout
//! branch inside `me`. There is no dilation: the reference uses none.

use candle_core::{DType, Device, Result, Tensor, D};

use super::align::TokenAlignment;

/// Thresholds of the local blend.
#[derive(Clone, Copy, Debug)]
pub struct BlendThresholds {
    /// Threshold of the target-blend mask; the effective one is max(thresh_e, temperature / √ᾱ_t).
    pub thresh_e: f64,
    /// Threshold of the source-blend mask.
    pub thresh_m: f64,
    /// The reference's 0.15: early, noisy steps get a threshold above 1, i.e. an empty target region.
    pub temperature: f64,
    /// VcEdit's consistent-maps path thresholds `me` with the dynamic τ_e; InfEdit uses the static thresh_e.
    pub dynamic_me: bool,
}

impl BlendThresholds {
    /// (τ_e, τ_m, τ_me) for a step whose ᾱ_t is `alpha_prod_t`.
    pub fn at(&self, alpha_prod_t: f64) -> (f64, f64, f64) {
        let tau_e = (self.temperature / alpha_prod_t.sqrt()).max(self.thresh_e);
        (
            tau_e,
            self.thresh_m,
            if self.dynamic_me {
                tau_e
            } else {
                self.thresh_e
            },
        )
    }
}

/// The three token indicators of an alignment: (alpha_e, alpha_m − alpha_me, alpha_me).
fn indicators(al: &TokenAlignment, tokens: usize, device: &Device) -> Result<[Tensor; 3]> {
    let me = al.alpha_me();
    let m_only: Vec<f32> = al.alpha_m.iter().zip(&me).map(|(m, b)| m - b).collect();
    let fit = |v: &[f32]| {
        let mut v = v.to_vec();
        v.resize(tokens, 0.0);
        Tensor::from_vec(v, tokens, device)
    };
    Ok([fit(&al.alpha_e)?, fit(&m_only)?, fit(&me)?])
}

/// The stored cross-attention maps (each [2, heads, h·w, tokens]) averaged over layers and heads:
/// [2, h·w, tokens], in f32.
pub(crate) fn mean_over_layers_and_heads(store: &[(String, Tensor)]) -> Result<Tensor> {
    let maps = store
        .iter()
        .map(|(_, t)| t.to_dtype(DType::F32))
        .collect::<Result<Vec<_>>>()?;
    Tensor::cat(&maps, 1)?.mean(1)
}

/// The blend maps `[3, H, W]` (e, m, me) at latent size `(H, W)` from a blend store
/// (`[2, heads, h*w, tokens]` per layer, all layers of the same h×w), each divided by (its max + `eps`).
/// The reference uses eps = 0 for InfEdit's masks and 1e-6 when it makes the maps consistent (VcEdit).
pub fn blend_maps(
    store: &[(String, Tensor)],
    map_size: (usize, usize),
    alignment: &TokenAlignment,
    latent: (usize, usize),
    eps: f64,
) -> Result<Tensor> {
    let device = Device::Cpu;
    let (lh, lw) = latent;
    if store.is_empty() {
        return Tensor::zeros((3, lh, lw), DType::F32, &device);
    }
    // Average over layers and heads: [2, h*w, tokens].
    let mean = mean_over_layers_and_heads(store)?;
    let tokens = mean.dim(D::Minus1)?;
    let [ind_e, ind_m, ind_me] = indicators(alignment, tokens, &device)?;
    // Word tokens of the target: 1 .. len−1 (SOT and EOT excluded).
    let words = alignment
        .target_len
        .saturating_sub(2)
        .min(tokens.saturating_sub(1));
    let (h, w) = map_size;
    let one = |maps: &Tensor, ind: &Tensor| -> Result<Tensor> {
        let m = if words == 0 {
            Tensor::zeros((h, w), DType::F32, &device)?
        } else {
            maps.broadcast_mul(ind)?
                .narrow(1, 1, words)?
                .max(1)?
                .reshape((h, w))?
        };
        let up = m
            .reshape((1, 1, h, w))?
            .upsample_nearest2d(lh, lw)?
            .reshape((lh, lw))?;
        let max = up.max_all()?.to_scalar::<f32>()? as f64;
        up.affine(1.0 / (max + eps), 0.0)
    };
    let (maps_s, maps_m) = (mean.get(0)?, mean.get(1)?);
    let e = one(&maps_m, &ind_e)?;
    let m = one(&maps_s, &ind_m)?;
    let me = one(&maps_m, &ind_me)?;
    Tensor::stack(&[&e, &m, &me], 0)
}

/// Masks `[3, H, W]` (u8) from maps: each map divided by its maximum, compared with its threshold.
/// An all-zero map gives an empty mask (the reference's 0/0 = NaN compares false).
pub fn blend_masks(maps: &Tensor, thresholds: (f64, f64, f64)) -> Result<Tensor> {
    let th = [thresholds.0, thresholds.1, thresholds.2];
    let mut out = Vec::with_capacity(3);
    for (i, &t) in th.iter().enumerate() {
        let map = maps.get(i)?;
        let max = map.max_all()?.to_scalar::<f32>()? as f64;
        let mask = if max > 0.0 {
            map.affine(1.0 / max, 0.0)?.gt(t)?
        } else {
            map.zeros_like()?.to_dtype(DType::U8)?
        };
        out.push(mask);
    }
    Tensor::stack(&out, 0)
}

/// Applies the local blend to the target latents `[1, C, H, W]` given masks `[3, H, W]`.
/// `has_target_words`: without target-blend words the target latents are kept as they are.
/// `use_layout`: the second-to-last step, where `me` takes the layout branch.
pub fn apply_local_blend(
    z_s: &Tensor,
    z_t: &Tensor,
    z_m: &Tensor,
    masks: &Tensor,
    has_target_words: bool,
    use_layout: bool,
) -> Result<Tensor> {
    let shape = z_t.dims().to_vec();
    let (h, w) = (shape[shape.len() - 2], shape[shape.len() - 1]);
    let mask = |i: usize| -> Result<Tensor> {
        masks
            .get(i)?
            .reshape((1, 1, h, w))?
            .broadcast_as(shape.as_slice())
    };
    let mut x = if has_target_words {
        mask(0)?.where_cond(z_t, z_m)?
    } else {
        z_t.clone()
    };
    x = mask(1)?.where_cond(z_s, &x)?;
    if use_layout {
        x = mask(2)?.where_cond(z_m, &x)?;
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn alignment_with(e: &[usize], m: &[usize], len: usize, tokens: usize) -> TokenAlignment {
        let mut alpha_e = vec![0.0; tokens];
        let mut alpha_m = vec![0.0; tokens];
        for &i in e {
            alpha_e[i] = 1.0;
        }
        for &i in m {
            alpha_m[i] = 1.0;
        }
        TokenAlignment {
            mapper: (0..tokens).map(Some).collect(),
            alphas: vec![1.0; tokens],
            alpha_e,
            alpha_m,
            target_len: len,
        }
    }

    #[test]
    fn maps_follow_the_blend_word_attention() {
        // 2x2 map, 4 tokens; token 1 attends to the top-left cell in the layout branch.
        let tokens = 4;
        let mut v = vec![0.0f32; 2 * 4 * tokens];
        v[4 * tokens + 1] = 1.0; // branch 1 (layout), cell 0, token 1
        v[4 * tokens + 3 * tokens + 1] = 0.5; // cell 3
        let store = vec![(
            "up".to_string(),
            Tensor::from_vec(v, (2, 1, 4, tokens), &Device::Cpu).unwrap(),
        )];
        let al = alignment_with(&[1], &[], 4, tokens);
        let maps = blend_maps(&store, (2, 2), &al, (4, 4), 0.0).unwrap();
        let e = maps.get(0).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(e[0], vec![1.0, 1.0, 0.0, 0.0]);
        assert_eq!(e[3], vec![0.0, 0.0, 0.5, 0.5]);
        // No source-blend words: m and me are zero, their masks empty.
        let masks = blend_masks(&maps, (0.6, 0.6, 0.6)).unwrap();
        let mm = masks.flatten_all().unwrap().to_vec1::<u8>().unwrap();
        assert_eq!(mm[..16].iter().filter(|&&x| x == 1).count(), 4);
        assert!(mm[16..].iter().all(|&x| x == 0));
    }

    #[test]
    fn local_blend_takes_target_inside_and_layout_outside() {
        let d = Device::Cpu;
        let zs = Tensor::full(1f32, (1, 1, 2, 2), &d).unwrap();
        let zt = Tensor::full(2f32, (1, 1, 2, 2), &d).unwrap();
        let zm = Tensor::full(3f32, (1, 1, 2, 2), &d).unwrap();
        let masks =
            Tensor::from_vec(vec![1u8, 0, 0, 0, 0, 0, 0, 1, 0, 1, 0, 0], (3, 2, 2), &d).unwrap();
        let x = apply_local_blend(&zs, &zt, &zm, &masks, true, false).unwrap();
        assert_eq!(
            x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            vec![2.0, 3.0, 3.0, 1.0]
        );
        let x = apply_local_blend(&zs, &zt, &zm, &masks, true, true).unwrap();
        assert_eq!(
            x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            vec![2.0, 3.0, 3.0, 1.0]
        );
        let x = apply_local_blend(&zs, &zt, &zm, &masks, false, false).unwrap();
        assert_eq!(
            x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            vec![2.0, 2.0, 2.0, 1.0]
        );
    }

    #[test]
    fn dynamic_threshold_matches_the_reference_table() {
        let t = BlendThresholds {
            thresh_e: 0.6,
            thresh_m: 0.6,
            temperature: 0.15,
            dynamic_me: true,
        };
        // ᾱ small at early steps → τ_e > 1: empty target region.
        assert!(t.at(0.004).0 > 1.0);
        assert_eq!(t.at(0.9).0, 0.6);
    }
}
