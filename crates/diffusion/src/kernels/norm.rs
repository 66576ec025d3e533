//! Group norm (optionally fused with SiLU) and layer norm, each with an affine weight and bias.

use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

use super::approx;
use super::{cpu_f32, f32_slices, needs_grad, rows_per_task, split_grads, Grads3};

/// Group norm of `x` [batch, channels, ...] with affine `weight`/`bias` [channels], then SiLU if `silu`
/// (the pairing used throughout ResNet blocks, fused into one pass on the CPU).
pub fn group_norm(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let operands = [x, weight, bias];
    if !cpu_f32(&operands) {
        return group_norm_composite(x, weight, bias, groups, eps, silu);
    }
    let op = GroupNorm { groups, eps, silu };
    let (x, weight, bias) = (x.contiguous()?, weight.contiguous()?, bias.contiguous()?);
    if needs_grad(&operands) {
        x.apply_op3(&weight, &bias, op)
    } else {
        x.apply_op3_no_bwd(&weight, &bias, &op)
    }
}

/// Layer norm over the last dimension of `x` with `weight` and `bias` [dim].
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let operands = [x, weight, bias];
    match (needs_grad(&operands), x.device().is_cpu()) {
        // Inference: candle's fused kernel (every dtype).
        (false, true) => candle_nn::ops::layer_norm(&x.contiguous()?, weight, bias, eps as f32),
        (true, true) if cpu_f32(&operands) => x.contiguous()?.apply_op3(
            &weight.contiguous()?,
            &bias.contiguous()?,
            LayerNorm { eps },
        ),
        _ => {
            let dim = x.dim(D::Minus1)? as f64;
            let mean = (x.sum_keepdim(D::Minus1)? / dim)?;
            let centred = x.broadcast_sub(&mean)?;
            let var = (centred.sqr()?.sum_keepdim(D::Minus1)? / dim)?;
            centred
                .broadcast_div(&(var + eps)?.sqrt()?)?
                .broadcast_mul(weight)?
                .broadcast_add(bias)
        }
    }
}

/// Group norm from differentiable candle ops (other dtypes and devices).
fn group_norm_composite(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    if dims.len() < 2 {
        candle_core::bail!("group norm expects [batch, channels, ...], got {dims:?}");
    }
    let (batch, channels) = (dims[0], dims[1]);
    // Half-precision inputs are normalised in f32; f32/f64 stay as they are.
    let internal = match x.dtype() {
        DType::F16 | DType::BF16 => DType::F32,
        other => other,
    };
    let grouped = x.to_dtype(internal)?.reshape((batch, groups, ()))?;
    let n = grouped.dim(2)? as f64;
    let mean = (grouped.sum_keepdim(2)? / n)?;
    let centred = grouped.broadcast_sub(&mean)?;
    let var = (centred.sqr()?.sum_keepdim(2)? / n)?;
    let normed = centred.broadcast_div(&(var + eps)?.sqrt()?)?;
    let mut affine_shape = vec![1usize; dims.len()];
    affine_shape[1] = channels;
    let affine = |t: &Tensor| t.to_dtype(internal)?.reshape(affine_shape.as_slice());
    let out = normed
        .reshape(dims.as_slice())?
        .broadcast_mul(&affine(weight)?)?
        .broadcast_add(&affine(bias)?)?;
    let out = if silu { out.silu()? } else { out };
    out.to_dtype(x.dtype())
}

/// Mean and 1/std of a group or row: two passes in f64, cheap next to the data pass and robust for large
/// groups. `eps` is rounded to f32 first, as the model's f32 parameters would hold it.
fn moments(values: &[f32], eps: f64) -> (f32, f32) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().map(|&v| v as f64).sum::<f64>() / n;
    let var = values
        .iter()
        .map(|&v| {
            let d = v as f64 - mean;
            d * d
        })
        .sum::<f64>()
        / n;
    let eps = eps as f32 as f64;
    (mean as f32, (1.0 / (var + eps).sqrt()) as f32)
}

#[inline(always)]
fn affine_silu_kernel(out: &mut [f32], inp: &[f32], scale: f32, shift: f32, silu: bool) {
    if silu {
        for (o, &i) in out.iter_mut().zip(inp) {
            *o = approx::silu(i * scale + shift);
        }
    } else {
        for (o, &i) in out.iter_mut().zip(inp) {
            *o = i * scale + shift;
        }
    }
}

simd_dispatch!(
    /// `out = inp · scale + shift`, then SiLU if `silu`.
    fn affine_silu(out: &mut [f32], inp: &[f32], scale: f32, shift: f32, silu: bool) => affine_silu_kernel
);

/// Group norm (+ SiLU) of contiguous f32 operands (x, weight, bias); one rayon task per (sample, group).
#[derive(Clone, Copy)]
struct GroupNorm {
    groups: usize,
    eps: f64,
    silu: bool,
}

impl GroupNorm {
    /// (channels, elements per channel) of a [batch, channels, ...] shape.
    fn layout(&self, shape: &Shape) -> Result<(usize, usize)> {
        let dims = shape.dims();
        if dims.len() < 2 || self.groups == 0 || !dims[1].is_multiple_of(self.groups) {
            candle_core::bail!(
                "group norm: {dims:?} does not split into {} groups",
                self.groups
            );
        }
        Ok((dims[1], dims[2..].iter().product()))
    }
}

impl CustomOp3 for GroupNorm {
    fn name(&self) -> &'static str {
        "group-norm"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let [x, weight, bias] = f32_slices([(xs, xl), (ws, wl), (bs, bl)], name)?;
        let (channels, per_channel) = self.layout(xl.shape())?;
        if weight.len() != channels || bias.len() != channels {
            candle_core::bail!("group norm: affine parameters do not have {channels} entries");
        }
        let group_channels = channels / self.groups;
        let per_group = group_channels * per_channel;
        let mut out = vec![0f32; x.len()];
        if per_group > 0 {
            out.par_chunks_mut(per_group)
                .zip(x.par_chunks(per_group))
                .enumerate()
                .for_each(|(index, (out, inp))| {
                    let (mean, rstd) = moments(inp, self.eps);
                    let first = (index % self.groups) * group_channels;
                    for c in 0..group_channels {
                        let scale = weight[first + c] * rstd;
                        let shift = bias[first + c] - mean * scale;
                        let range = c * per_channel..(c + 1) * per_channel;
                        affine_silu(
                            &mut out[range.clone()],
                            &inp[range],
                            scale,
                            shift,
                            self.silu,
                        );
                    }
                });
        }
        Ok((CpuStorage::F32(out), xl.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<Grads3> {
        let affine = Tensor::cat(&[weight, bias], 0)?;
        let packed = x.apply_op3_no_bwd(&affine, &grad.contiguous()?, &GroupNormBackward(*self))?;
        split_grads(&packed, x, weight, bias)
    }
}

/// Gradients of [`GroupNorm`] from (input, [weight, bias], output gradient), packed [dx, dw, db].
struct GroupNormBackward(GroupNorm);

impl CustomOp3 for GroupNormBackward {
    fn name(&self) -> &'static str {
        "group-norm-backward"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        affs: &CpuStorage,
        affl: &Layout,
        gs: &CpuStorage,
        gl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let op = self.0;
        let [x, affine, grad] = f32_slices([(xs, xl), (affs, affl), (gs, gl)], name)?;
        let (channels, per_channel) = op.layout(xl.shape())?;
        if affine.len() != 2 * channels || grad.len() != x.len() {
            candle_core::bail!("{name}: operands do not fit input {:?}", xl.shape());
        }
        let (weight, bias) = affine.split_at(channels);
        let group_channels = channels / op.groups;
        let per_group = group_channels * per_channel;
        let mut dx = vec![0f32; x.len()];
        // Per group: the gradient of each of its channels' weight and bias.
        let partials: Vec<Vec<[f64; 2]>> = if per_group == 0 {
            Vec::new()
        } else {
            dx.par_chunks_mut(per_group)
                .zip(x.par_chunks(per_group))
                .zip(grad.par_chunks(per_group))
                .enumerate()
                .map(|(index, ((dx, inp), g))| {
                    let (mean, rstd) = moments(inp, op.eps);
                    let first = (index % op.groups) * group_channels;
                    let mut affine_grads = vec![[0f64; 2]; group_channels];
                    // Pass 1: dy (gradient before the affine map, through SiLU) into dx as scratch, and
                    // the group sums of dx̂ = dy·γ and dx̂·x̂.
                    let (mut sum_dxhat, mut sum_dxhat_xhat) = (0f64, 0f64);
                    for c in 0..group_channels {
                        let (gamma, beta) = (weight[first + c], bias[first + c]);
                        let range = c * per_channel..(c + 1) * per_channel;
                        let (mut dgamma, mut dbeta) = (0f64, 0f64);
                        for ((d, &i), &go) in dx[range.clone()]
                            .iter_mut()
                            .zip(&inp[range.clone()])
                            .zip(&g[range])
                        {
                            let xhat = (i - mean) * rstd;
                            let dy = if op.silu {
                                let y = xhat * gamma + beta;
                                let s = approx::sigmoid(y);
                                go * s * (1.0 + y * (1.0 - s))
                            } else {
                                go
                            };
                            *d = dy;
                            dgamma += (dy * xhat) as f64;
                            dbeta += dy as f64;
                        }
                        affine_grads[c] = [dgamma, dbeta];
                        sum_dxhat += dbeta * gamma as f64;
                        sum_dxhat_xhat += dgamma * gamma as f64;
                    }
                    let n = per_group as f64;
                    let (m1, m2) = ((sum_dxhat / n) as f32, (sum_dxhat_xhat / n) as f32);
                    // Pass 2: dx = rstd·(dx̂ − mean(dx̂) − x̂·mean(dx̂·x̂)).
                    for c in 0..group_channels {
                        let gamma = weight[first + c];
                        let range = c * per_channel..(c + 1) * per_channel;
                        for (d, &i) in dx[range.clone()].iter_mut().zip(&inp[range]) {
                            let xhat = (i - mean) * rstd;
                            *d = rstd * (*d * gamma - m1 - xhat * m2);
                        }
                    }
                    affine_grads
                })
                .collect()
        };
        let mut dw = vec![0f64; channels];
        let mut db = vec![0f64; channels];
        for (index, group) in partials.iter().enumerate() {
            let first = (index % op.groups) * group_channels;
            for (c, [gw, gb]) in group.iter().enumerate() {
                dw[first + c] += gw;
                db[first + c] += gb;
            }
        }
        let n = dx.len() + 2 * channels;
        let mut packed = dx;
        packed.extend(dw.iter().chain(&db).map(|&v| v as f32));
        Ok((CpuStorage::F32(packed), Shape::from(n)))
    }
}

/// Layer norm of contiguous f32 operands (x, weight, bias) over the last dimension.
#[derive(Clone, Copy)]
struct LayerNorm {
    eps: f64,
}

impl CustomOp3 for LayerNorm {
    fn name(&self) -> &'static str {
        "layer-norm"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let [x, weight, bias] = f32_slices([(xs, xl), (ws, wl), (bs, bl)], name)?;
        let dim = xl.shape().dims().last().copied().unwrap_or(0);
        if dim == 0 || weight.len() != dim || bias.len() != dim {
            candle_core::bail!("layer norm: parameters do not fit input {:?}", xl.shape());
        }
        let mut out = vec![0f32; x.len()];
        let chunk = dim * rows_per_task(dim);
        out.par_chunks_mut(chunk)
            .zip(x.par_chunks(chunk))
            .for_each(|(out, inp)| {
                for (o, i) in out.chunks_mut(dim).zip(inp.chunks(dim)) {
                    let (mean, rstd) = moments(i, self.eps);
                    for (((o, &v), &w), &b) in o.iter_mut().zip(i).zip(weight).zip(bias) {
                        *o = (v - mean) * rstd * w + b;
                    }
                }
            });
        Ok((CpuStorage::F32(out), xl.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<Grads3> {
        let packed = x.apply_op3_no_bwd(weight, &grad.contiguous()?, &LayerNormBackward(*self))?;
        split_grads(&packed, x, weight, bias)
    }
}

/// Gradients of [`LayerNorm`] from (input, weight, output gradient), packed [dx, dw, db].
struct LayerNormBackward(LayerNorm);

impl CustomOp3 for LayerNormBackward {
    fn name(&self) -> &'static str {
        "layer-norm-backward"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        gs: &CpuStorage,
        gl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let name = self.name();
        let [x, weight, grad] = f32_slices([(xs, xl), (ws, wl), (gs, gl)], name)?;
        let dim = weight.len();
        if dim == 0 || x.len() % dim != 0 || grad.len() != x.len() {
            candle_core::bail!("{name}: operands do not fit input {:?}", xl.shape());
        }
        let mut dx = vec![0f32; x.len()];
        let chunk = dim * rows_per_task(dim);
        let zeros = || (vec![0f64; dim], vec![0f64; dim]);
        let (dw, db) = dx
            .par_chunks_mut(chunk)
            .zip(x.par_chunks(chunk))
            .zip(grad.par_chunks(chunk))
            .fold(zeros, |(mut dw, mut db), ((dx, inp), g)| {
                for ((dx, i), g) in dx.chunks_mut(dim).zip(inp.chunks(dim)).zip(g.chunks(dim)) {
                    let (mean, rstd) = moments(i, self.0.eps);
                    let (mut s1, mut s2) = (0f64, 0f64);
                    for k in 0..dim {
                        let xhat = (i[k] - mean) * rstd;
                        let dxhat = g[k] * weight[k];
                        dw[k] += (g[k] * xhat) as f64;
                        db[k] += g[k] as f64;
                        s1 += dxhat as f64;
                        s2 += (dxhat * xhat) as f64;
                    }
                    let (m1, m2) = ((s1 / dim as f64) as f32, (s2 / dim as f64) as f32);
                    for k in 0..dim {
                        let xhat = (i[k] - mean) * rstd;
                        dx[k] = rstd * (g[k] * weight[k] - m1 - xhat * m2);
                    }
                }
                (dw, db)
            })
            .reduce(zeros, |(mut a, mut b), (c, d)| {
                a.iter_mut().zip(&c).for_each(|(a, c)| *a += c);
                b.iter_mut().zip(&d).for_each(|(b, d)| *b += d);
                (a, b)
            });
        let n = dx.len() + 2 * dim;
        let mut packed = dx;
        packed.extend(dw.iter().chain(&db).map(|&v| v as f32));
        Ok((CpuStorage::F32(packed), Shape::from(n)))
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::{check_gradients, max_diff, var};
    use super::*;

    #[test]
    fn group_norm_matches_composite_with_gradients() {
        for (shape, groups, silu) in [
            (vec![2, 8, 5, 3], 4, false),
            (vec![2, 8, 5, 3], 4, true),
            (vec![3, 6, 7], 3, true),
            (vec![1, 4, 2, 2], 1, false),
        ] {
            let c = shape[1];
            let vars = [
                var(&shape, 1.5, 3.0),
                var(&[c], 1.0, 0.3),
                var(&[c], 0.0, 0.5),
            ];
            check_gradients(
                &vars,
                |t| group_norm(&t[0], &t[1], &t[2], groups, 1e-5, silu).unwrap(),
                |t| group_norm_composite(&t[0], &t[1], &t[2], groups, 1e-5, silu).unwrap(),
                &format!("group norm {shape:?} {groups} silu {silu}"),
            );
        }
    }

    #[test]
    fn group_norm_inference_and_training_agree() {
        let x = var(&[2, 8, 5, 3], 1.5, 3.0);
        let (w, b) = (var(&[8], 1.0, 0.3), var(&[8], 0.0, 0.5));
        let plain = |v: &candle_core::Var| v.as_tensor().detach();
        for silu in [false, true] {
            let training = group_norm(x.as_tensor(), w.as_tensor(), b.as_tensor(), 4, 1e-6, silu);
            let inference = group_norm(&plain(&x), &plain(&w), &plain(&b), 4, 1e-6, silu);
            assert_eq!(max_diff(&training.unwrap(), &inference.unwrap()), 0.0);
        }
    }

    #[test]
    fn layer_norm_matches_composite_with_gradients() {
        for shape in [vec![2, 7, 16], vec![130, 5], vec![3, 1]] {
            let d = *shape.last().unwrap();
            let vars = [
                var(&shape, 0.5, 2.0),
                var(&[d], 1.0, 0.3),
                var(&[d], 0.0, 0.3),
            ];
            check_gradients(
                &vars,
                |t| layer_norm(&t[0], &t[1], &t[2], 1e-5).unwrap(),
                |t| {
                    let mean = t[0].mean_keepdim(D::Minus1).unwrap();
                    let c = t[0].broadcast_sub(&mean).unwrap();
                    let var = c.sqr().unwrap().mean_keepdim(D::Minus1).unwrap();
                    c.broadcast_div(&(var + 1e-5).unwrap().sqrt().unwrap())
                        .unwrap()
                        .broadcast_mul(&t[1])
                        .unwrap()
                        .broadcast_add(&t[2])
                        .unwrap()
                },
                &format!("layer norm {shape:?}"),
            );
        }
    }

    #[test]
    fn layer_norm_inference_and_training_agree() {
        let x = var(&[2, 7, 16], 0.5, 2.0);
        let (w, b) = (var(&[16], 1.0, 0.1), var(&[16], 0.0, 0.1));
        let training = layer_norm(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
        let detached = |v: &candle_core::Var| v.as_tensor().detach();
        let inference = layer_norm(&detached(&x), &detached(&w), &detached(&b), 1e-5).unwrap();
        assert!(max_diff(&training, &inference) < 1e-5);
    }
}
