//! Attention `softmax(q kᵀ · scale) v` on one of three paths: our flash kernel, the library's flash
//! attention, or two products around a row softmax (in chunks of whole heads).

use std::sync::OnceLock;

use candle_core::Result;
use cubecl::prelude::*;

use self::kernel::ATTENTION_QUERIES;
use super::launch::{forced_by_env, to_u32, transient_cap};
use super::layout::{cat, narrow};
use super::matmul::{half_operands, matmul, matmul_path, matmul_scaled, MatmulPath};
use super::norm::softmax_scaled;
use super::GpuTensor;

/// The kernels of this family (their host launchers follow the module).
mod kernel {
    use cubecl::prelude::*;

    /// Query rows per cube and keys per shared-memory tile of [`flash_attention`].
    pub const ATTENTION_QUERIES: u32 = 32;
    pub const ATTENTION_KEYS: u32 = 16;

    /// Rows `key0..key0 + ATTENTION_KEYS` of one batch entry's keys or values (`src` rows of `width`, the
    /// entry's first at `first_row`) into `tile`, zeros past `k_len`; the cube's units share the loads.
    #[cube]
    fn load_key_tile(
        src: &[f32],
        tile: &mut Shared<[f32]>,
        first_row: u32,
        key0: u32,
        k_len: u32,
        #[comptime] width: u32,
    ) {
        let mut e = UNIT_POS_X;
        while e < comptime!(ATTENTION_KEYS) * width {
            let key = key0 + e / width;
            tile[e as usize] = if key < k_len {
                src[((first_row + key0) * width + e) as usize]
            } else {
                0.0f32
            };
            e += comptime!(ATTENTION_QUERIES);
        }
    }

    /// Memory-efficient attention `softmax(q kᵀ · scale) v` that never stores the probabilities: q [batch,
    /// q_len, d], k [batch, k_len, d], v [batch, k_len, dv]. A cube handles `ATTENTION_QUERIES` query rows of
    /// one batch entry (one unit per row); key/value tiles of `ATTENTION_KEYS` rows go through shared memory
    /// and each unit keeps a running max, running sum and output accumulator (online softmax).
    #[cube(launch_unchecked)]
    pub fn flash_attention(
        q: &[f32],
        k: &[f32],
        v: &[f32],
        out: &mut [f32],
        q_len: u32,
        k_len: u32,
        scale: f32,
        #[comptime] d: u32,
        #[comptime] dv: u32,
    ) {
        let tile = comptime!(ATTENTION_KEYS);
        let queries = comptime!(ATTENTION_QUERIES);
        let batch = CUBE_POS_Y;
        let row = CUBE_POS_X * queries + UNIT_POS_X;
        let valid = row < q_len;
        let mut qr = Array::<f32>::new(comptime!(d as usize));
        #[unroll]
        for c in 0..d {
            qr[c as usize] = if valid {
                q[((batch * q_len + row) * d + c) as usize] * scale
            } else {
                0.0f32
            };
        }
        let mut acc = Array::<f32>::new(comptime!(dv as usize));
        #[unroll]
        for c in 0..dv {
            acc[c as usize] = 0.0f32;
        }
        // −∞ stand-in: finite for WGSL; exp(it − any score) = 0. Built at run time so it is a runtime value.
        let mut floor = 0.0f32;
        floor -= 3.0e38f32;
        let mut run_max = floor;
        let mut run_sum = 0.0f32;
        let mut sk = Shared::<[f32]>::new_slice(comptime!((ATTENTION_KEYS * d) as usize));
        let mut sv = Shared::<[f32]>::new_slice(comptime!((ATTENTION_KEYS * dv) as usize));
        let mut scores = Array::<f32>::new(comptime!(ATTENTION_KEYS as usize));
        #[allow(clippy::manual_div_ceil)]
        let tiles = (k_len + tile - 1) / tile;
        for t in 0..tiles {
            let key0 = t * tile;
            // Cooperative loads of the key and value tiles (zeros past k_len).
            load_key_tile(k, &mut sk, batch * k_len, key0, k_len, d);
            load_key_tile(v, &mut sv, batch * k_len, key0, k_len, dv);
            sync_cube();
            let mut tile_max = floor;
            #[unroll]
            for j in 0..tile {
                let mut s = 0.0f32;
                #[unroll]
                for c in 0..d {
                    s += qr[c as usize] * sk[(j * d + c) as usize];
                }
                if key0 + j >= k_len {
                    s = floor;
                }
                scores[j as usize] = s;
                tile_max = f32::max(tile_max, s);
            }
            let new_max = f32::max(run_max, tile_max);
            // exp(−3e38 − finite) = 0: nothing to rescale on the first tile.
            let correction = f32::exp(run_max - new_max);
            run_sum *= correction;
            #[unroll]
            for c in 0..dv {
                acc[c as usize] *= correction;
            }
            #[unroll]
            for j in 0..tile {
                let p = f32::exp(scores[j as usize] - new_max);
                run_sum += p;
                #[unroll]
                for c in 0..dv {
                    acc[c as usize] += p * sv[(j * dv + c) as usize];
                }
            }
            run_max = new_max;
            sync_cube();
        }
        if valid {
            let inv = 1.0f32 / run_sum;
            #[unroll]
            for c in 0..dv {
                out[((batch * q_len + row) * dv + c) as usize] = acc[c as usize] * inv;
            }
        }
    }
}

/// Largest head width the flash kernel is compiled for (its rows live in registers); wider heads go
/// through the explicit-probabilities path.
const FLASH_MAX_HEAD_DIM: usize = 256;

/// Checks q [.., q_len, d], k [.., k_len, d], v [.., k_len, dv]; returns (batch, q_len, k_len, d, dv).
fn attention_dims(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
) -> Result<(usize, usize, usize, usize, usize)> {
    let r = q.dims().len();
    let ok = r >= 2
        && k.dims().len() == r
        && v.dims().len() == r
        && q.dims()[..r - 2] == k.dims()[..r - 2]
        && k.dims()[..r - 2] == v.dims()[..r - 2]
        && q.dims()[r - 1] == k.dims()[r - 1]
        && k.dims()[r - 2] == v.dims()[r - 2];
    if !ok {
        candle_core::bail!(
            "gpu attention: q {:?}, k {:?}, v {:?}",
            q.dims(),
            k.dims(),
            v.dims()
        );
    }
    let batch = q.dims()[..r - 2].iter().product();
    Ok((
        batch,
        q.dims()[r - 2],
        k.dims()[r - 2],
        q.dims()[r - 1],
        v.dims()[r - 1],
    ))
}

/// How attention runs on the GPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttentionPath {
    /// Our flash kernel: one unit per query row, online softmax, no score matrix (scalar f32 arithmetic).
    Flash,
    /// Two products through the matrix-product path (tensor cores where the device has them) around a
    /// row softmax, the scores held in chunks of whole heads of at most [`transient_cap`] bytes.
    Products,
    /// The library's flash attention (`cubek-attention`, what burn runs): its unit routine (one query
    /// row per unit, tiles of the widest vector) without tensor cores, cooperative-matrix tiles with
    /// them. Where it declines a problem (f16 activations, a scale other than 1/√d, a head width its
    /// tiles do not divide) the attention takes the flash kernel or the products as by default.
    Library,
}

impl std::fmt::Display for AttentionPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Flash => "flash",
            Self::Products => "products",
            Self::Library => "library",
        })
    }
}

thread_local! {
    /// Set by tests to pick an attention path on their thread.
    static ATTENTION_OVERRIDE: std::cell::Cell<Option<AttentionPath>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` with the attention of this thread on `path` (tests, benches).
pub fn with_attention_path<T>(path: AttentionPath, f: impl FnOnce() -> T) -> T {
    let before = ATTENTION_OVERRIDE.replace(Some(path));
    let result = f();
    ATTENTION_OVERRIDE.set(before);
    result
}

/// Heads at most this wide take the flash kernel where the library's attention declines them: a score
/// costs the kernel `d` multiply-adds, against a fixed write, softmax and read of it as products.
/// `vcedit bench attention` on lavapipe, 2026-11-26, 8 heads of 1024 queries and keys: d = 8 flash
/// 171 ms / products 359 ms; d = 16 698 / 394; d = 32 1365 / 440. At SD 1.5's d = 40: 16 heads of
/// 1024², 3.4 s / 0.96 s; 8 heads of 4096², 18.8 s / 3.6 s.
const FLASH_DEFAULT_MAX_HEAD_DIM: usize = 8;

/// The attention path of heads `d` wide (values `dv`) on `device`, where none is forced: the library's
/// flash attention, except for heads wider than [`FLASH_DEFAULT_MAX_HEAD_DIM`] on tensor cores, where
/// the products run on them (until `tools/gpu-check` has timed the library's cooperative-matrix tiles
/// against them: `attention`, `unet-library`), and on software adapters (below). Measured on lavapipe
/// (Mesa 25.0.7, WGSL, 2026-11-29, `vcedit bench attention`, 48 entries, the small UNet's shapes):
/// the library took 14.6 ms at 256 queries × 256 keys × d 8 against the flash kernel's 82.6 and the
/// products' 245; 2.2 ms at 64² × 16 against 18.0 / 31.7; 2.0 ms at 16² × 32 against 12.7 / 14.0. Its kernel is compiled per shape, and
/// slowly by lavapipe as heads widen (first call 11 s at d 8, 37 s at d 16, 169 s at d 32; Mesa's
/// shader cache keeps them, but CI machines start cold: the demo model's 16- and 32-wide heads took
/// `vcedit demo --device gpu` in tools/gpu-check's local run from 71 s to 118 s), so software adapters,
/// which only tests and CI use, keep the products for wider heads.
/// `VCEDIT_GPU_ATTENTION=flash|products|library` forces one (A/B switch for benches; `vcedit bench
/// attention` times all three); heads wider than the flash kernel can take run as products instead.
pub fn attention_path(device: &super::GpuDevice, d: usize, dv: usize) -> AttentionPath {
    static FORCED: OnceLock<Option<AttentionPath>> = OnceLock::new();
    let forced = ATTENTION_OVERRIDE.get().or(forced_by_env(
        &FORCED,
        "VCEDIT_GPU_ATTENTION",
        |name| match name {
            "flash" => Some(AttentionPath::Flash),
            "products" => Some(AttentionPath::Products),
            "library" => Some(AttentionPath::Library),
            _ => None,
        },
    ));
    let widest = d.max(dv);
    match forced {
        Some(AttentionPath::Flash) if widest > FLASH_MAX_HEAD_DIM => AttentionPath::Products,
        Some(path) => path,
        None if widest > FLASH_DEFAULT_MAX_HEAD_DIM
            && (matmul_path(device) == MatmulPath::TensorCores || device.context().software) =>
        {
            AttentionPath::Products
        }
        None => AttentionPath::Library,
    }
}

/// Where the library declines a problem: the flash kernel for narrow heads, else products.
fn fallback_attention_path(widest: usize) -> AttentionPath {
    if widest <= FLASH_DEFAULT_MAX_HEAD_DIM {
        AttentionPath::Flash
    } else {
        AttentionPath::Products
    }
}

/// The library's flash attention of q [.., q_len, d], k [.., k_len, d], v [.., k_len, dv] (f32, the
/// scale 1/√d, which the library applies itself), or `None` where it declines the problem.
fn library_attention(q: &GpuTensor, k: &GpuTensor, v: &GpuTensor, scale: f64) -> Option<GpuTensor> {
    use cubecl::ir::{ElemType, FloatKind};
    use cubek_attention::forward::definition::{
        AccumulatorPrecision, AttentionGlobalTypes, AttentionOptions,
    };
    use cubek_attention::forward::launch::{launch_ref, BlueprintStrategy, Strategy};
    use cubek_attention::forward::routines::blackbox_accelerated::BlackboxAcceleratedStrategy;
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v).ok()?;
    let library_scale = 1.0 / (d as f64).sqrt();
    if q.is_f16() || k.is_f16() || v.is_f16() || q_len == 0 || k_len == 0 {
        return None;
    }
    if (scale - library_scale).abs() > 1e-6 * library_scale {
        return None;
    }
    let f32_type = ElemType::Float(FloatKind::F32);
    let dtypes = AttentionGlobalTypes::from_single_float_dtype(
        f32_type,
        AttentionGlobalTypes::mask_dtype(q.client()),
    );
    let options = AttentionOptions {
        causal: false,
        accumulator_precision: AccumulatorPrecision::Strict(f32_type),
    };
    // The library's layout is [batch, heads, seq, dim]: every (batch, head) entry as one batch.
    let bind = |t: &GpuTensor, rows: usize, width: usize| {
        t.binding(
            &[batch, 1, rows, width],
            &[rows * width, rows * width, width, 1],
        )
    };
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    let out = q.empty_like_device(shape);
    let launch = |strategy: Strategy| {
        launch_ref(
            strategy,
            q.client(),
            bind(q, q_len, d),
            bind(k, k_len, d),
            bind(v, k_len, dv),
            None,
            bind(&out, q_len, dv),
            &dtypes,
            options.clone(),
        )
        .is_ok()
    };
    // On tensor cores the cooperative-matrix tiles (burn's middle candidate: four planes, one tile of
    // queries and keys each), else or where those decline, the unit routine.
    let tensor_cores = matmul_path(q.device()) == MatmulPath::TensorCores
        && launch(Strategy::BlackboxAccelerated(BlueprintStrategy::Inferred(
            BlackboxAcceleratedStrategy {
                num_planes: 4,
                seq_q: 1,
                seq_kv: 1,
            },
        )));
    (tensor_cores || launch(Strategy::Unit(BlueprintStrategy::Inferred(())))).then_some(out)
}

/// `softmax(q kᵀ · scale) v` without returning the probabilities, on the [`attention_path`].
pub fn attention(q: &GpuTensor, k: &GpuTensor, v: &GpuTensor, scale: f64) -> Result<GpuTensor> {
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v)?;
    let mut path = attention_path(q.device(), d, dv);
    if path == AttentionPath::Library {
        if let Some(out) = library_attention(q, k, v, scale) {
            return Ok(out);
        }
        path = fallback_attention_path(d.max(dv));
    }
    if path == AttentionPath::Products || k_len == 0 {
        return attention_in_chunks(q, k, v, scale, transient_cap(q));
    }
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    let out = q.empty_like_device(shape);
    let blocks = q_len.div_ceil(ATTENTION_QUERIES as usize);
    // SAFETY: rows past q_len and keys past k_len are masked in the kernel.
    unsafe {
        kernel::flash_attention::launch_unchecked(
            q.client(),
            CubeCount::Static(to_u32(blocks, "query blocks")?, to_u32(batch, "batch")?, 1),
            CubeDim::new_1d(ATTENTION_QUERIES),
            q.arg(),
            k.arg(),
            v.arg(),
            out.arg(),
            to_u32(q_len, "query rows")?,
            to_u32(k_len, "key rows")?,
            scale as f32,
            d as u32,
            dv as u32,
        )
    };
    Ok(out)
}

/// Attention as products, the score matrix in chunks of whole (batch, head) entries of at most `cap`
/// bytes (at least one entry): at SD 1.5's 64² latents one head's scores are 64 MiB, a batch of six
/// branches' 48 heads 3 GiB. The chunks' inputs are copied out and their outputs concatenated: passes
/// over Q/K/V-sized tensors, small beside the score-sized ones.
fn attention_in_chunks(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
    cap: usize,
) -> Result<GpuTensor> {
    let (batch, q_len, k_len, d, dv) = attention_dims(q, k, v)?;
    let per_entry = (q_len * k_len * std::mem::size_of::<f32>()).max(1);
    let entries = (cap / per_entry).max(1);
    if entries >= batch {
        return attention_products(q, k, v, scale);
    }
    let (q3, k3, v3) = (
        q.reshape(&[batch, q_len, d])?,
        k.reshape(&[batch, k_len, d])?,
        v.reshape(&[batch, k_len, dv])?,
    );
    let parts = (0..batch)
        .step_by(entries)
        .map(|b0| {
            let n = entries.min(batch - b0);
            attention_products(
                &narrow(&q3, 0, b0, n)?,
                &narrow(&k3, 0, b0, n)?,
                &narrow(&v3, 0, b0, n)?,
                scale,
            )
        })
        .collect::<Result<Vec<_>>>()?;
    let mut shape = q.dims().to_vec();
    *shape.last_mut().expect("rank >= 2") = dv;
    cat(&parts.iter().collect::<Vec<_>>(), 0)?.reshape(&shape)
}

/// Attention that also returns its probabilities [.., q_len, k_len] (for the attention hook of
/// cross-attention layers, whose maps the edit controller reads): two products and a row softmax that
/// applies the scale.
pub fn attention_with_probs(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
) -> Result<(GpuTensor, GpuTensor)> {
    attention_dims(q, k, v)?;
    let scores = matmul_scaled(q, k, true, 1.0)?;
    let probs = softmax_scaled(&scores, scale as f32, false)?;
    let out = matmul(&probs, v)?;
    Ok((out, probs))
}

/// [`attention_with_probs`] without the probabilities: where the products take f16 operands, the
/// softmax writes them as f16 (the product would narrow them to f16 anyway, in a pass of its own).
fn attention_products(
    q: &GpuTensor,
    k: &GpuTensor,
    v: &GpuTensor,
    scale: f64,
) -> Result<GpuTensor> {
    attention_dims(q, k, v)?;
    let scores = matmul_scaled(q, k, true, 1.0)?;
    let probs = softmax_scaled(&scores, scale as f32, half_operands(q.device()))?;
    matmul(&probs, v)
}

#[cfg(test)]
mod tests {
    //! The attention paths against the CPU.

    use super::*;
    use crate::kernels::gpu::testing::*;

    #[test]
    fn attention_matches_cpu() {
        let Some(dev) = device_or_skip() else {
            return;
        };
        // Query and key counts off the tile sizes; a value width different from the key width.
        let q = randn(&[2, 2, 37, 8]);
        let k = randn(&[2, 2, 45, 8]);
        let v = randn(&[2, 2, 45, 12]);
        let scale = 1.0 / 8f64.sqrt();
        let want = crate::kernels::attention(&q, &k, &v, scale).unwrap();
        let (gq, gk, gv) = (up(&dev, &q), up(&dev, &k), up(&dev, &v));
        for path in [
            AttentionPath::Flash,
            AttentionPath::Products,
            AttentionPath::Library,
        ] {
            check(
                &format!("attention ({path})"),
                &with_attention_path(path, || attention(&gq, &gk, &gv, scale)).unwrap(),
                &want,
            );
        }
        // The library takes this problem itself (were it to decline, the path above would silently test
        // the fallback), and declines a scale other than its own 1/√d; the attention then falls back.
        check(
            "library attention",
            &library_attention(&gq, &gk, &gv, scale).expect("the library takes f32 attention"),
            &want,
        );
        assert!(library_attention(&gq, &gk, &gv, 0.5 * scale).is_none());
        check(
            "attention (library path, another scale)",
            &with_attention_path(AttentionPath::Library, || {
                attention(&gq, &gk, &gv, 0.5 * scale)
            })
            .unwrap(),
            &crate::kernels::attention(&q, &k, &v, 0.5 * scale).unwrap(),
        );
        // Scores in chunks: one (batch, head) entry per chunk, then three entries of four in one, one in another.
        let entry = 37 * 45 * 4;
        for cap in [1, entry, 3 * entry] {
            check(
                &format!("attention in chunks of {cap} bytes"),
                &attention_in_chunks(&gq, &gk, &gv, scale, cap).unwrap(),
                &want,
            );
        }
        let (out, probs) = attention_with_probs(&gq, &gk, &gv, scale).unwrap();
        check("attention with probabilities", &out, &want);
        let want_probs = crate::kernels::softmax_last_dim(
            &(q.matmul(&k.t().unwrap()).unwrap() * scale).unwrap(),
        )
        .unwrap();
        check("attention probabilities", &probs, &want_probs);
        // The default path by head width, and a forced path that the flash kernel cannot take.
        assert_eq!(attention_path(&dev, 8, 8), AttentionPath::Library);
        let wide = if dev.context().software || matmul_path(&dev) == MatmulPath::TensorCores {
            AttentionPath::Products
        } else {
            AttentionPath::Library
        };
        assert_eq!(attention_path(&dev, 40, 40), wide);
        assert_eq!(fallback_attention_path(8), AttentionPath::Flash);
        assert_eq!(fallback_attention_path(40), AttentionPath::Products);
        assert_eq!(
            with_attention_path(AttentionPath::Flash, || attention_path(
                &dev,
                FLASH_MAX_HEAD_DIM + 1,
                8
            )),
            AttentionPath::Products
        );
        // Few keys (one partial tile) and a single query.
        let (q1, k1, v1) = (randn(&[1, 1, 8]), randn(&[1, 3, 8]), randn(&[1, 3, 8]));
        let want = crate::kernels::attention(&q1, &k1, &v1, scale).unwrap();
        for path in [
            AttentionPath::Flash,
            AttentionPath::Products,
            AttentionPath::Library,
        ] {
            check(
                &format!("attention ({path}), 3 keys"),
                &with_attention_path(path, || {
                    attention(&up(&dev, &q1), &up(&dev, &k1), &up(&dev, &v1), scale)
                })
                .unwrap(),
                &want,
            );
        }
    }
}
