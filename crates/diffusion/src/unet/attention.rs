//! Multi-head attention of the UNet transformer blocks and the attention hook interface.
//!
//! The hook is the one place where editing logic touches the UNet: every attention call reports its layer,
//! whether it is self- or cross-attention, the spatial size of its queries and the batch/head counts, and
//! the hook may replace Q/K/V before the softmax and read or replace the probabilities after it, or,
//! where it changes the probabilities linearly without reading them, describe the change ([`MapEdit`]) so
//! that the fused kernel still runs.

use candle_core::{Device, Result, Tensor};
use candle_nn::VarBuilder;

use crate::kernels::DeviceTensor;
use crate::layers::{linear, linear_weight, Linear};

/// Self-attention (keys from the image tokens) or cross-attention (keys from the text embedding).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AttnKind {
    SelfAttn,
    CrossAttn,
}

/// What one attention call tells its hook.
#[derive(Debug, Clone, Copy)]
pub struct AttnCall<'a> {
    /// diffusers module path, e.g. `"down_blocks.1.attentions.0.transformer_blocks.0.attn2"`.
    pub layer: &'a str,
    pub kind: AttnKind,
    /// Spatial size of the queries: `height * width` query tokens, row-major.
    pub height: usize,
    pub width: usize,
    /// Batch size of the UNet call (the caller knows its layout, e.g. InfEdit's `[S_u,T_u,M_u,S_c,T_c,M_c]`).
    pub batch: usize,
    pub heads: usize,
    /// Key tokens: `height * width` for self-attention, the encoder's sequence length for cross-attention.
    pub keys: usize,
}

/// The queries, keys and values of one attention call, each [batch, heads, tokens, head_dim]: the
/// queries have `height * width` tokens, the keys and values [`AttnCall::keys`].
#[derive(Debug, Clone)]
pub struct Qkv {
    pub q: DeviceTensor,
    pub k: DeviceTensor,
    pub v: DeviceTensor,
}

impl Qkv {
    /// The queries, keys and values each through `f`.
    pub fn try_map(self, mut f: impl FnMut(DeviceTensor) -> Result<DeviceTensor>) -> Result<Self> {
        Ok(Self {
            q: f(self.q)?,
            k: f(self.k)?,
            v: f(self.v)?,
        })
    }
}

/// Observes and rewrites attention inside the UNet. All methods have pass-through defaults.
///
/// The tensors live where the UNet runs ([`DeviceTensor`]: a candle tensor on the CPU, a buffer on the
/// GPU), so a hook that only rearranges or mixes them (InfEdit's controller) costs no transfers; a hook
/// that must read values on the host calls [`DeviceTensor::to_cpu`] itself, for just what it reads.
pub trait AttentionHook {
    /// May replace the queries, keys and values before the scores are computed.
    fn qkv(&mut self, call: &AttnCall, qkv: Qkv) -> Result<Qkv> {
        let _ = call;
        Ok(qkv)
    }

    /// Whether [`AttentionHook::probs`] must see this call's probabilities. When false the memory-bounded
    /// fused path runs (recommended for 64×64 self-attention, whose full maps take gigabytes).
    fn wants_probs(&self, call: &AttnCall) -> bool {
        let _ = call;
        true
    }

    /// May read/replace the probabilities [batch, heads, q_len, k_len] after the softmax.
    fn probs(&mut self, call: &AttnCall, probs: DeviceTensor) -> Result<DeviceTensor> {
        let _ = call;
        Ok(probs)
    }

    /// Linear edits of the probabilities of a call whose maps the hook does not read
    /// ([`AttentionHook::wants_probs`] false), applied to the values so the fused kernel still runs.
    fn map_edits(&self, call: &AttnCall) -> Vec<MapEdit> {
        let _ = call;
        Vec::new()
    }

    /// Whether the hook has seen every call it needs from this pass. Only a pass run for its hook
    /// alone ([`crate::unet::UNet2DConditionModel::forward_observed`]) asks, between blocks, and stops.
    fn finished(&self) -> bool {
        false
    }
}

/// A change of one batch row's probabilities that is linear in the maps (Prompt-to-Prompt's refine, word
/// swap and reweighting are of this form): for every query `q` and key token `j`,
/// `P'[row][q, j] = keep[j] · P[row][q, j] + take[j].1 · P[source][q, take[j].0]`.
///
/// Since the output is `P' · V[row]`, it equals `attention(Q, K, keep ⊙ V)[row]` plus
/// `attention(Q[source], K[source], V')` with `V'[t] = Σ_{j : take[j].0 = t} take[j].1 · V[row][j]`:
/// two fused calls, no probability matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct MapEdit {
    /// The batch row whose probabilities change (at most one edit per row).
    pub row: usize,
    /// The batch row whose maps it takes from.
    pub source: usize,
    /// Per key token of `row`: the weight of its own map.
    pub keep: Vec<f32>,
    /// Per key token of `row`: the source's key token whose map it takes, and that map's weight.
    pub take: Vec<(usize, f32)>,
}

impl MapEdit {
    /// The edit applied to explicit probabilities `[batch, heads, q_len, k_len]` (the reference the fused
    /// form is tested against).
    pub fn apply_to_probs(&self, probs: &Tensor) -> Result<Tensor> {
        self.check(probs.dim(0)?, probs.dim(3)?)?;
        let row = |b| DeviceTensor::Cpu(probs.narrow(0, b, 1).expect("checked row"));
        let edited =
            edit_maps(&row(self.row), &row(self.source), &self.keep, &self.take)?.to_cpu()?;
        let rows = (0..probs.dim(0)?)
            .map(|b| {
                if b == self.row {
                    Ok(edited.clone())
                } else {
                    probs.narrow(0, b, 1)
                }
            })
            .collect::<Result<Vec<_>>>()?;
        Tensor::cat(&rows, 0)
    }

    fn check(&self, batch: usize, k_len: usize) -> Result<()> {
        if self.row >= batch || self.source >= batch {
            candle_core::bail!(
                "map edit of row {} from row {}: the batch has {batch} rows",
                self.row,
                self.source
            );
        }
        if self.keep.len() != k_len
            || self.take.len() != k_len
            || self.take.iter().any(|&(t, _)| t >= k_len)
        {
            candle_core::bail!("map edit: weights for {k_len} key tokens expected");
        }
        Ok(())
    }

    /// `V'` of the source's term, `[1, heads, k_len, head_dim]`: per source token, the weighted sum of
    /// the row's values that take its map. Built from gathers, one per multiplicity of a source token.
    fn source_values(&self, v_row: &DeviceTensor) -> Result<DeviceTensor> {
        let k_len = self.take.len();
        // takers[t]: the row's tokens that take source token t's map (with a weight).
        let mut takers: Vec<Vec<(usize, f32)>> = vec![Vec::new(); k_len];
        for (j, &(t, w)) in self.take.iter().enumerate() {
            if w != 0.0 {
                takers[t].push((j, w));
            }
        }
        let layers = takers.iter().map(Vec::len).max().unwrap_or(0);
        let mut sum: Option<DeviceTensor> = None;
        for l in 0..layers.max(1) {
            let index: Vec<u32> = takers
                .iter()
                .map(|t| t.get(l).map_or(0, |&(j, _)| j as u32))
                .collect();
            let weight: Vec<f32> = takers
                .iter()
                .map(|t| t.get(l).map_or(0.0, |&(_, w)| w))
                .collect();
            let term = v_row
                .index_select(&index, 2)?
                .broadcast_mul(&token_weights(v_row, weight)?)?;
            sum = Some(match sum {
                Some(s) => s.add(&term)?,
                None => term,
            });
        }
        Ok(sum.expect("at least one layer"))
    }
}

/// Per-token weights shaped `[k_len, 1]` (they scale the rows of `[.., k_len, head_dim]` values), on
/// `like`'s device.
fn token_weights(like: &DeviceTensor, weights: Vec<f32>) -> Result<DeviceTensor> {
    let n = weights.len();
    like.same_device(&Tensor::from_vec(weights, (n, 1), &Device::Cpu)?)
}

/// The maps of a [`MapEdit`] (`[.., k_len]`, the key tokens last), from the edited row's maps `own` and
/// the source row's maps `source`: `keep[j] · own[.., j] + take[j].1 · source[.., take[j].0]`. The
/// explicit form, for callers that hold the maps anyway (InfEdit's refinement of the maps it reads).
pub fn edit_maps(
    own: &DeviceTensor,
    source: &DeviceTensor,
    keep: &[f32],
    take: &[(usize, f32)],
) -> Result<DeviceTensor> {
    let last = own.dims().len() - 1;
    let index: Vec<u32> = take.iter().map(|&(t, _)| t as u32).collect();
    let gathered = source.index_select(&index, last)?;
    // Two tiny uploads per call on a GPU (the weights of 77 tokens).
    let weights = |w: Vec<f32>| {
        let n = w.len();
        own.same_device(&Tensor::from_vec(w, n, &Device::Cpu)?)
    };
    gathered
        .broadcast_mul(&weights(take.iter().map(|&(_, w)| w).collect())?)?
        .add(&own.broadcast_mul(&weights(keep.to_vec())?)?)
}

/// The fused attention with `edits` applied to the values ([`MapEdit`]): one call over the batch with the
/// edited rows' values scaled, one over the edits' source rows with their gathered values, summed per row.
fn fused_with_edits(
    q: &DeviceTensor,
    k: &DeviceTensor,
    v: &DeviceTensor,
    scale: f64,
    edits: &[MapEdit],
) -> Result<DeviceTensor> {
    if edits.is_empty() {
        return DeviceTensor::attention(q, k, v, scale);
    }
    let (batch, _, k_len, _) = v.dims4()?;
    let mut edit_of_row: Vec<Option<usize>> = vec![None; batch];
    for (i, e) in edits.iter().enumerate() {
        e.check(batch, k_len)?;
        if edit_of_row[e.row].replace(i).is_some() {
            candle_core::bail!("two map edits of batch row {}", e.row);
        }
    }
    let mut values = Vec::with_capacity(batch);
    let mut extra_values = Vec::with_capacity(edits.len());
    for (b, edit) in edit_of_row.iter().enumerate() {
        let v_row = v.narrow(0, b, 1)?;
        values.push(match edit {
            Some(i) => {
                let e = &edits[*i];
                extra_values.push(e.source_values(&v_row)?);
                v_row.broadcast_mul(&token_weights(&v_row, e.keep.clone())?)?
            }
            None => v_row,
        });
    }
    let sources: Vec<u32> = edit_of_row
        .iter()
        .flatten()
        .map(|&i| edits[i].source as u32)
        .collect();
    let own = DeviceTensor::attention(
        q,
        k,
        &DeviceTensor::cat(&values.iter().collect::<Vec<_>>(), 0)?,
        scale,
    )?;
    let taken = DeviceTensor::attention(
        &q.index_select(&sources, 0)?,
        &k.index_select(&sources, 0)?,
        &DeviceTensor::cat(&extra_values.iter().collect::<Vec<_>>(), 0)?,
        scale,
    )?;
    // Rows in order; runs of unedited rows are copied as one block.
    let mut parts = Vec::new();
    let (mut b, mut next_extra) = (0, 0);
    while b < batch {
        if edit_of_row[b].is_some() {
            parts.push(own.narrow(0, b, 1)?.add(&taken.narrow(0, next_extra, 1)?)?);
            next_extra += 1;
            b += 1;
        } else {
            let run = edit_of_row[b..].iter().take_while(|e| e.is_none()).count();
            parts.push(own.narrow(0, b, run)?);
            b += run;
        }
    }
    DeviceTensor::cat(&parts.iter().collect::<Vec<_>>(), 0)
}

/// An attention layer's query, key and value projections.
#[derive(Debug, Clone)]
enum Projections {
    /// As stored: trainable weights, which the optimiser updates in place.
    Separate {
        to_q: Linear,
        to_k: Linear,
        to_v: Linear,
    },
    /// The projections that read one input stacked into one layer at load (as diffusers'
    /// `fuse_qkv_projections`): self-attention's query, key and value (`[3·inner, query_dim]`,
    /// `to_q: None`), or cross-attention's key and value (`[2·inner, context_dim]`, its query apart).
    /// One larger product instead of three or two: on a GPU each product also rounds its input to f16
    /// once, and a wider product keeps tensor cores busier.
    Stacked {
        to_q: Option<Linear>,
        stacked: Linear,
    },
}

/// diffusers `Attention` inside `BasicTransformerBlock` (keys `to_q`, `to_k`, `to_v` without bias,
/// `to_out.0` with bias).
#[derive(Debug, Clone)]
pub struct Attention {
    /// Query, key and value projections.
    projections: Projections,
    to_out: Linear,
    heads: usize,
    head_dim: usize,
    kind: AttnKind,
    name: String,
}

impl Attention {
    /// `context_dim` is the cross-attention width (`None` for self-attention).
    pub fn load(
        query_dim: usize,
        context_dim: Option<usize>,
        heads: usize,
        head_dim: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let inner = heads * head_dim;
        let kv_dim = context_dim.unwrap_or(query_dim);
        // The f32 weights first: stacked ones are kept (bf16 pairs only, under bf16 products) once
        // stacked.
        let to_q = linear_weight(query_dim, inner, &vb.pp("to_q"))?;
        let to_k = linear_weight(kv_dim, inner, &vb.pp("to_k"))?;
        let to_v = linear_weight(kv_dim, inner, &vb.pp("to_v"))?;
        // Trainable weights (variables) stay separate: a stacked copy would not see the optimiser's
        // updates.
        let projections = if to_q.is_variable() {
            Projections::Separate {
                to_q: Linear::new(to_q, None)?,
                to_k: Linear::new(to_k, None)?,
                to_v: Linear::new(to_v, None)?,
            }
        } else {
            let stack = |weights: &[&Tensor]| Linear::new(Tensor::cat(weights, 0)?, None);
            match context_dim {
                None => Projections::Stacked {
                    to_q: None,
                    stacked: stack(&[&to_q, &to_k, &to_v])?,
                },
                Some(_) => Projections::Stacked {
                    stacked: stack(&[&to_k, &to_v])?,
                    to_q: Some(Linear::new(to_q, None)?),
                },
            }
        };
        Ok(Self {
            projections,
            to_out: linear(inner, query_dim, true, vb.pp("to_out.0"))?,
            heads,
            head_dim,
            kind: if context_dim.is_some() {
                AttnKind::CrossAttn
            } else {
                AttnKind::SelfAttn
            },
            name: vb.prefix(),
        })
    }

    /// `x` [batch, h·w, query_dim]; `context` [batch, tokens, context_dim] for cross-attention, on one
    /// device. Without a hook, or when the hook does not read this call's probabilities, the flash kernel
    /// runs (no probability matrix); the hook sees the tensors on the device they are on. Returns the
    /// output projection plus `residual` (the block's skip connection, added with the bias).
    pub fn forward_device(
        &self,
        x: &DeviceTensor,
        context: Option<&DeviceTensor>,
        (height, width): (usize, usize),
        hook: Option<&mut (dyn AttentionHook + '_)>,
        residual: &DeviceTensor,
    ) -> Result<DeviceTensor> {
        let &[batch, tokens, _] = x.dims() else {
            candle_core::bail!(
                "{}: expected [batch, tokens, dim], got {:?}",
                self.name,
                x.dims()
            );
        };
        let kv_source = match self.kind {
            AttnKind::CrossAttn => context.ok_or_else(|| {
                candle_core::Error::Msg(format!(
                    "{}: cross-attention called without encoder hidden states",
                    self.name
                ))
            })?,
            AttnKind::SelfAttn => x,
        };
        // Part `i` of `parts` stacked projections [batch, n, parts·heads·head_dim] → [batch, heads, n,
        // head_dim], one copy each.
        let (heads, head_dim) = (self.heads, self.head_dim);
        let part = |t: &DeviceTensor, parts: usize, i: usize| -> Result<DeviceTensor> {
            let n = t.dims()[1];
            t.reshape(&[batch, n, parts, heads, head_dim])?
                .narrow_permute(2, i, 1, &[0, 2, 3, 1, 4])?
                .reshape(&[batch, heads, n, head_dim])
        };
        let (q, k, v) = match &self.projections {
            Projections::Separate { to_q, to_k, to_v } => (
                part(&x.linear(to_q)?, 1, 0)?,
                part(&kv_source.linear(to_k)?, 1, 0)?,
                part(&kv_source.linear(to_v)?, 1, 0)?,
            ),
            Projections::Stacked {
                to_q: None,
                stacked,
            } => {
                let qkv = x.linear(stacked)?;
                (part(&qkv, 3, 0)?, part(&qkv, 3, 1)?, part(&qkv, 3, 2)?)
            }
            Projections::Stacked {
                to_q: Some(to_q),
                stacked,
            } => {
                let kv = kv_source.linear(stacked)?;
                (
                    part(&x.linear(to_q)?, 1, 0)?,
                    part(&kv, 2, 0)?,
                    part(&kv, 2, 1)?,
                )
            }
        };
        let scale = 1.0 / (self.head_dim as f64).sqrt();
        let out = match hook {
            None => DeviceTensor::attention(&q, &k, &v, scale)?,
            Some(hook) => {
                let call = AttnCall {
                    layer: &self.name,
                    kind: self.kind,
                    height,
                    width,
                    batch,
                    heads: self.heads,
                    keys: k.dims()[2],
                };
                let Qkv { q, k, v } = hook.qkv(&call, Qkv { q, k, v })?;
                if hook.wants_probs(&call) {
                    let scores = q.matmul_t(&k)?.mul_scalar(scale)?;
                    let probs = hook.probs(&call, scores.softmax_last_dim()?)?;
                    probs.matmul(&v)?
                } else {
                    fused_with_edits(&q, &k, &v, scale, &hook.map_edits(&call))?
                }
            }
        };
        out.permute_contiguous(&[0, 2, 1, 3])?
            .reshape(&[batch, tokens, self.heads * self.head_dim])?
            .linear_add(&self.to_out, residual)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::*;
    use crate::kernels::gpu::testing::{device_or_skip, relative_error};

    /// Two edits over a batch of 4 (one taking from another row with a token taken twice and an unmatched
    /// one, one reweighting only), fused against the explicit maps.
    fn edits() -> Vec<MapEdit> {
        vec![
            MapEdit {
                row: 2,
                source: 0,
                keep: vec![0.0, 0.5, 1.0, 0.3, 0.2],
                take: vec![(0, 1.0), (1, 0.5), (1, 0.4), (4, 0.7), (0, 0.0)],
            },
            MapEdit {
                row: 3,
                source: 3,
                keep: vec![1.0, 2.0, 0.5, 1.0, 1.5],
                take: vec![(0, 0.0); 5],
            },
        ]
    }

    /// Fixed pseudo-random operands (every call the same), Q [4, 2, 6, 3] and K, V [4, 2, 5, 3].
    fn qkv() -> (Tensor, Tensor, Tensor) {
        let r = |shape: (usize, usize, usize, usize), phase: f32| {
            let n = shape.0 * shape.1 * shape.2 * shape.3;
            let values: Vec<f32> = (0..n)
                .map(|i| (i as f32 * 0.731 + phase).sin() * 1.5)
                .collect();
            Tensor::from_vec(values, shape, &Device::Cpu).unwrap()
        };
        (
            r((4, 2, 6, 3), 0.0),
            r((4, 2, 5, 3), 1.0),
            r((4, 2, 5, 3), 2.0),
        )
    }

    fn explicit(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Tensor {
        let scores = (q.matmul(&k.t().unwrap()).unwrap() * scale).unwrap();
        let mut probs = candle_nn::ops::softmax_last_dim(&scores).unwrap();
        for e in edits() {
            probs = e.apply_to_probs(&probs).unwrap();
        }
        probs.matmul(v).unwrap()
    }

    /// `fused_with_edits` on the device `on` puts the operands on, read back.
    fn fused(on: &dyn Fn(&Tensor) -> DeviceTensor, edits: &[MapEdit]) -> Tensor {
        let (q, k, v) = qkv();
        fused_with_edits(&on(&q), &on(&k), &on(&v), 0.5, edits)
            .unwrap()
            .to_cpu()
            .unwrap()
    }

    #[test]
    fn edits_applied_to_the_values_match_the_edited_probabilities() {
        let (q, k, v) = qkv();
        let want = explicit(&q, &k, &v, 0.5);
        let cpu = |t: &Tensor| DeviceTensor::Cpu(t.clone());
        let got = fused(&cpu, &edits());
        let err = relative_error(&got, &want);
        assert!(err < 1e-5, "CPU relative error {err}");
        // Unedited rows are the plain fused attention.
        let plain = fused(&cpu, &[]);
        let rows = |t: &Tensor, start, len| t.narrow(0, start, len).unwrap();
        assert!(relative_error(&rows(&got, 0, 2), &rows(&plain, 0, 2)) < 1e-6);
        assert!(relative_error(&rows(&got, 2, 1), &rows(&plain, 2, 1)) > 1e-2);

        let Some(device) = device_or_skip() else {
            return;
        };
        let got = fused(
            &|t| {
                crate::kernels::Device::Gpu(device.clone())
                    .tensor(t)
                    .unwrap()
            },
            &edits(),
        );
        let err = relative_error(&got, &want);
        assert!(err < 1e-5, "GPU relative error {err}");
    }

    #[test]
    fn malformed_edits_are_errors() {
        let (q, k, v) = qkv();
        let cpu = |t: &Tensor| DeviceTensor::Cpu(t.clone());
        let mut twice = edits();
        twice[1].row = 2;
        let mut short = edits();
        short[0].keep.pop();
        let mut outside = edits();
        outside[0].source = 4;
        for bad in [twice, short, outside] {
            assert!(fused_with_edits(&cpu(&q), &cpu(&k), &cpu(&v), 0.5, &bad).is_err());
        }
    }
}
