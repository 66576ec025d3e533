//! Every GPU op against its CPU twin on tiny random shapes (lavapipe runs ~0.3 GFLOP/s): f32 results agree
//! to a relative error of 1e-4 (max abs difference over the reference's max abs value).

use candle_core::{Device, Tensor};

use super::super::testing::{device_or_skip, relative_error};
use super::super::{GpuDevice, GpuTensor, Precision};
use super::*;
use crate::kernels::device::Addend;

const TOLERANCE: f32 = 1e-4;

fn randn(shape: &[usize]) -> Tensor {
    Tensor::randn(0f32, 1.0, shape, &Device::Cpu).unwrap()
}

fn up(device: &GpuDevice, t: &Tensor) -> GpuTensor {
    GpuTensor::upload(device, t).unwrap()
}

/// Asserts `gpu` matches `cpu` in shape and to the relative tolerance.
fn check(what: &str, gpu: &GpuTensor, cpu: &Tensor) {
    check_within(what, gpu, cpu, TOLERANCE);
}

/// Asserts `gpu` matches `cpu` in shape and to `tolerance` (max abs difference over max abs value);
/// returns the relative error.
fn check_within(what: &str, gpu: &GpuTensor, cpu: &Tensor, tolerance: f32) -> f32 {
    let rel = relative_error(&gpu.to_cpu().unwrap(), cpu);
    assert!(rel <= tolerance, "{what}: relative error {rel:.3e}");
    rel
}

/// `t` rounded to f16 and back (what an f16 weight or operand holds).
fn rounded_f16(t: &Tensor) -> Tensor {
    t.to_dtype(candle_core::DType::F16)
        .unwrap()
        .to_dtype(candle_core::DType::F32)
        .unwrap()
}

#[test]
fn elementwise_ops_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let x = (randn(&[3, 5, 7]) * 3.0).unwrap();
    let g = up(&dev, &x);
    check(
        "affine",
        &affine(&g, 0.5, -2.0),
        &x.affine(0.5, -2.0).unwrap(),
    );
    check("relu", &relu(&g), &x.relu().unwrap());
    check("silu", &silu(&g), &candle_nn::ops::silu(&x).unwrap());
    check("gelu", &gelu(&g), &x.gelu_erf().unwrap());
    check("tanh", &tanh(&g), &x.tanh().unwrap());
    check(
        "scaled tanh",
        &scaled_tanh(&g, 1.0 / 3.0, 3.0),
        &((&x / 3.0).unwrap().tanh().unwrap() * 3.0).unwrap(),
    );
    check("exp", &exp(&g), &x.exp().unwrap());
    let quick = (&x * candle_nn::ops::sigmoid(&(&x * 1.702).unwrap()).unwrap()).unwrap();
    check("quick gelu", &quick_gelu(&g), &quick);
    check("gelu tanh", &gelu_tanh(&g), &x.gelu().unwrap());
    let mish_cpu = candle_nn::Activation::Mish;
    check(
        "mish",
        &mish(&g),
        &candle_core::Module::forward(&mish_cpu, &x).unwrap(),
    );
}

#[test]
fn broadcasting_binary_ops_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let a = randn(&[2, 3, 4, 5]);
    for shape in [
        vec![2, 3, 4, 5],
        vec![3, 1, 1],
        vec![1, 3, 1, 5],
        vec![5],
        vec![2, 1, 4, 1],
    ] {
        let b = (randn(&shape).abs().unwrap() + 0.5).unwrap();
        let (ga, gb) = (up(&dev, &a), up(&dev, &b));
        check(
            "add",
            &add(&ga, &gb).unwrap(),
            &a.broadcast_add(&b).unwrap(),
        );
        check(
            "sub",
            &sub(&ga, &gb).unwrap(),
            &a.broadcast_sub(&b).unwrap(),
        );
        check(
            "mul",
            &mul(&ga, &gb).unwrap(),
            &a.broadcast_mul(&b).unwrap(),
        );
        check(
            "div",
            &div(&ga, &gb).unwrap(),
            &a.broadcast_div(&b).unwrap(),
        );
        // The broadcast operand on the left.
        check(
            "add (swapped)",
            &add(&gb, &ga).unwrap(),
            &b.broadcast_add(&a).unwrap(),
        );
    }
    assert!(add(&up(&dev, &a), &up(&dev, &randn(&[3]))).is_err());
}

#[test]
fn copies_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let x = randn(&[2, 3, 4, 5]);
    let g = up(&dev, &x);
    check(
        "permute",
        &permute(&g, &[0, 2, 3, 1]).unwrap(),
        &x.permute((0, 2, 3, 1)).unwrap().contiguous().unwrap(),
    );
    check(
        "transpose",
        &transpose(&g, 1, 2).unwrap(),
        &x.transpose(1, 2).unwrap().contiguous().unwrap(),
    );
    check(
        "narrow",
        &narrow(&g, 1, 1, 2).unwrap(),
        &x.narrow(1, 1, 2).unwrap().contiguous().unwrap(),
    );
    check(
        "narrow_permute",
        &narrow_permute(&g, 1, 1, 2, &[0, 2, 3, 1]).unwrap(),
        &x.narrow(1, 1, 2)
            .unwrap()
            .permute((0, 2, 3, 1))
            .unwrap()
            .contiguous()
            .unwrap(),
    );
    let y = randn(&[2, 6, 4, 5]);
    check(
        "cat",
        &cat(&[&g, &up(&dev, &y)], 1).unwrap(),
        &Tensor::cat(&[&x, &y], 1).unwrap(),
    );
    check(
        "reshape",
        &g.reshape(&[6, 20]).unwrap(),
        &x.reshape((6, 20)).unwrap(),
    );
    check(
        "upsample",
        &upsample_nearest2d(&g, 8, 15).unwrap(),
        &x.upsample_nearest2d(8, 15).unwrap(),
    );
    let padded = x
        .pad_with_zeros(3, 0, 1)
        .unwrap()
        .pad_with_zeros(2, 0, 1)
        .unwrap();
    check("pad", &pad_bottom_right(&g, 1, 1).unwrap(), &padded);
    for (dim, idx) in [(0, vec![1u32, 0, 1]), (3, vec![4, 0, 0, 2]), (1, vec![2])] {
        let cpu_idx = Tensor::new(idx.as_slice(), &Device::Cpu).unwrap();
        check(
            "index_select",
            &index_select(&g, &idx, dim).unwrap(),
            &x.index_select(&cpu_idx, dim).unwrap(),
        );
    }
    assert_eq!(index_select(&g, &[], 1).unwrap().dims(), &[2, 0, 4, 5]);
    assert!(index_select(&g, &[5], 3).is_err());
    assert!(permute(&g, &[0, 0, 1, 2]).is_err());
}

/// Runs a product test on both engines: CubeCL's matrix-product library (the default) and our own
/// register-blocked kernel (`VCEDIT_GPU_MATMUL=own`, and the fallback where the library declines).
fn on_both_engines(test: impl Fn()) {
    test();
    with_own_matmul(test);
}

#[test]
fn matmul_and_linear_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    on_both_engines(|| matmul_and_linear_match_cpu_on(&dev));
}

fn matmul_and_linear_match_cpu_on(dev: &GpuDevice) {
    let dev = dev.clone();
    let a = randn(&[2, 3, 17, 19]);
    let b = randn(&[2, 3, 19, 21]);
    check(
        "batched",
        &matmul(&up(&dev, &a), &up(&dev, &b)).unwrap(),
        &a.matmul(&b).unwrap(),
    );
    let shared = randn(&[19, 5]);
    check(
        "shared rhs",
        &matmul(&up(&dev, &a), &up(&dev, &shared)).unwrap(),
        &a.broadcast_matmul(&shared).unwrap(),
    );
    let bt = randn(&[2, 3, 21, 19]);
    check(
        "transposed rhs, scaled",
        &matmul_scaled(&up(&dev, &a), &up(&dev, &bt), true, 0.25).unwrap(),
        &(a.matmul(&bt.t().unwrap()).unwrap() * 0.25).unwrap(),
    );
    let x = randn(&[2, 5, 19]);
    let w = randn(&[7, 19]);
    let bias = randn(&[7]);
    let cpu = candle_nn::Linear::new(w.clone(), Some(bias.clone()));
    let want = candle_core::Module::forward(&cpu, &x).unwrap();
    check(
        "linear",
        &linear(&up(&dev, &x), &up(&dev, &w), Some(&up(&dev, &bias)), None).unwrap(),
        &want,
    );
    // A skip connection added in the bias's pass, with and without a bias.
    let residual = randn(&[2, 5, 7]);
    let (gx, gw, gr) = (up(&dev, &x), up(&dev, &w), up(&dev, &residual));
    check(
        "linear + residual",
        &linear(&gx, &gw, Some(&up(&dev, &bias)), Some(&gr)).unwrap(),
        &(&want + &residual).unwrap(),
    );
    check(
        "linear without bias + residual",
        &linear(&gx, &gw, None, Some(&gr)).unwrap(),
        &(x.broadcast_matmul(&w.t().unwrap()).unwrap() + &residual).unwrap(),
    );
    assert!(linear(&gx, &gw, None, Some(&up(&dev, &randn(&[2, 5, 6])))).is_err());
    assert!(matmul(&up(&dev, &a), &up(&dev, &a)).is_err());
}

/// The register-blocked kernel on shapes off its tiles: single elements, odd sizes, several tiles with
/// ragged edges, k shorter and longer than a shared-memory slice, batches, shared and transposed B.
#[test]
fn tiled_matmul_matches_cpu_on_odd_shapes() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    on_both_engines(|| tiled_matmul_matches_cpu_on_odd_shapes_on(&dev));
}

fn tiled_matmul_matches_cpu_on_odd_shapes_on(dev: &GpuDevice) {
    let dev = dev.clone();
    // (batch dims, m, k, n)
    for (batch, m, k, n) in [
        (vec![], 1, 1, 1),
        (vec![], 7, 13, 5),
        (vec![3], 7, 13, 5),
        (vec![2, 2], 65, 17, 63),
        (vec![], 130, 70, 150),
        (vec![], 1, 300, 129),
        (vec![2], 64, 16, 64),
    ] {
        let shape = |r: usize, c: usize| [batch.clone(), vec![r, c]].concat();
        let a = randn(&shape(m, k));
        let b = randn(&shape(k, n));
        let want = a.matmul(&b).unwrap();
        let what = format!("matmul {batch:?} {m}x{k}x{n}");
        check_within(
            &what,
            &matmul(&up(&dev, &a), &up(&dev, &b)).unwrap(),
            &want,
            1e-5,
        );
        let bt = b.t().unwrap().contiguous().unwrap();
        check_within(
            &format!("{what}, transposed rhs"),
            &matmul_scaled(&up(&dev, &a), &up(&dev, &bt), true, 1.0).unwrap(),
            &want,
            1e-5,
        );
        let shared = randn(&[k, n]);
        check_within(
            &format!("{what}, shared rhs"),
            &matmul(&up(&dev, &a), &up(&dev, &shared)).unwrap(),
            &a.broadcast_matmul(&shared).unwrap(),
            1e-5,
        );
    }
}

/// f16 weights (packed two per word, unpacked in the kernel) with f32 arithmetic: exactly the CPU product
/// with the weights rounded to f16, and within 1e-2 of the f32 product.
#[test]
fn f16_weights_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    on_both_engines(|| f16_weights_match_cpu_on(&dev));
}

fn f16_weights_match_cpu_on(dev: &GpuDevice) {
    let dev = dev.clone();
    let half_dev = GpuDevice::with_precision(dev.context().clone(), Precision::F16);
    // Odd element counts leave half a word unused.
    let x = randn(&[2, 5, 19]);
    let w = randn(&[7, 19]);
    let bias = randn(&[7]);
    let gw = half_dev.cached_matrix(&w).unwrap();
    assert!(gw.is_f16() && gw.storage_bytes() == (7 * 19usize).div_ceil(2) * 4);
    check_within("f16 weight read-back", &gw, &rounded_f16(&w), 0.0);
    let gx = up(&half_dev, &x);
    let gbias = up(&half_dev, &bias);
    let got = linear(&gx, &gw, Some(&gbias), None).unwrap();
    let cpu = |w: Tensor| {
        candle_core::Module::forward(&candle_nn::Linear::new(w, Some(bias.clone())), &x).unwrap()
    };
    check_within(
        "f16 linear vs rounded weights",
        &got,
        &cpu(rounded_f16(&w)),
        1e-5,
    );
    let rel = check_within("f16 linear vs f32", &got, &cpu(w.clone()), 1e-2);
    assert!(rel > 0.0, "the weights were rounded");

    let x = randn(&[2, 5, 9, 7]);
    let weight = randn(&[6, 5, 3, 3]);
    let gw = half_dev.cached_matrix(&weight).unwrap();
    let want = |w: &Tensor| {
        crate::kernels::conv2d(&x, w, Some(&bias.narrow(0, 0, 6).unwrap()), 1, 1).unwrap()
    };
    // im2col's product unpacks the weights as it reads them; the direct kernel reads an f32 copy.
    for path in [ConvPath::Im2col, ConvPath::Direct] {
        let got = with_conv_path(path, || {
            conv2d(
                &up(&half_dev, &x),
                &gw,
                Some(&narrow(&gbias, 0, 0, 6).unwrap()),
                1,
                1,
                Addend::None,
            )
        })
        .unwrap();
        check_within(
            &format!("f16 conv2d ({path}) vs rounded weights"),
            &got,
            &want(&rounded_f16(&weight)),
            1e-5,
        );
        check_within(
            &format!("f16 conv2d ({path}) vs f32"),
            &got,
            &want(&weight),
            1e-2,
        );
    }
    // An f32 device keeps f32 matrix weights.
    assert!(!dev.cached_matrix(&weight).unwrap().is_f16());
}

/// The tensor-core path's operands (activations narrowed to f16, weights read as stored, f32 sums), on
/// the library's unit routine so it runs without tensor cores: exactly the CPU product of the rounded
/// operands, up to the order of the sums. Skipped where the device has no native f16 (the WGSL path).
#[test]
fn f16_operands_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let half_dev = GpuDevice::with_precision(dev.context().clone(), Precision::F16);
    if with_matmul_path(MatmulPath::UnitF16, || matmul_path(&half_dev)) != MatmulPath::UnitF16 {
        eprintln!("skipped: {} has no native f16", dev.context().describe());
        return;
    }
    with_matmul_path(MatmulPath::UnitF16, || {
        let (x, w, bias) = (randn(&[2, 5, 19]), randn(&[7, 19]), randn(&[7]));
        let gw = half_dev.cached_matrix(&w).unwrap();
        let got = linear(&up(&half_dev, &x), &gw, Some(&up(&half_dev, &bias)), None).unwrap();
        let want = candle_core::Module::forward(
            &candle_nn::Linear::new(rounded_f16(&w), Some(bias.clone())),
            &rounded_f16(&x),
        )
        .unwrap();
        check_within("f16-operand linear", &got, &want, 1e-5);
        // Activation × activation, transposed and scaled (attention-shaped).
        let (a, bt) = (randn(&[2, 3, 17, 19]), randn(&[2, 3, 21, 19]));
        let got = matmul_scaled(&up(&half_dev, &a), &up(&half_dev, &bt), true, 0.5).unwrap();
        let want = (rounded_f16(&a)
            .matmul(&rounded_f16(&bt).t().unwrap())
            .unwrap()
            * 0.5)
            .unwrap();
        check_within("f16-operand transposed product", &got, &want, 1e-5);
        let conv_w = randn(&[6, 5, 3, 3]);
        let xi = randn(&[2, 5, 9, 7]);
        // On im2col, whose product takes the f16 operands (the direct kernel computes in f32).
        let got = with_conv_path(ConvPath::Im2col, || {
            conv2d(
                &up(&half_dev, &xi),
                &half_dev.cached_matrix(&conv_w).unwrap(),
                None,
                1,
                1,
                Addend::None,
            )
        })
        .unwrap();
        let want =
            crate::kernels::conv2d(&rounded_f16(&xi), &rounded_f16(&conv_w), None, 1, 1).unwrap();
        check_within("f16-operand conv2d", &got, &want, 1e-5);
        // Attention as products: the softmax writes its probabilities as f16 for the second product.
        let (q, k, v) = (
            randn(&[2, 3, 29, 16]),
            randn(&[2, 3, 33, 16]),
            randn(&[2, 3, 33, 12]),
        );
        let got = with_attention_path(AttentionPath::Products, || {
            attention(
                &up(&half_dev, &q),
                &up(&half_dev, &k),
                &up(&half_dev, &v),
                0.25,
            )
        })
        .unwrap();
        let scores = (rounded_f16(&q)
            .matmul(&rounded_f16(&k).t().unwrap())
            .unwrap()
            * 0.25)
            .unwrap();
        let probs = crate::kernels::softmax_last_dim(&scores).unwrap();
        let want = rounded_f16(&probs).matmul(&rounded_f16(&v)).unwrap();
        check_within("f16-operand attention", &got, &want, 1e-3);
    });
    // The library takes these products itself (no silent fallback to the f32 routine).
    let (m, k, n) = (17, 19, 21);
    let a = up(&half_dev, &randn(&[1, m, k]));
    let b = half_dev.cached_matrix(&randn(&[k, n])).unwrap();
    let g = Gemm {
        batch: 1,
        m,
        n,
        k,
        a_strides: [m * k, k, 1],
        b_strides: [0, n, 1],
        alpha: 1.0,
    };
    assert!(library_gemm_on(&a, &b, &g, &[1, m, n], MatmulPath::UnitF16).is_some());
}

/// im2col's f16 columns (what an f16-operand product reads) are exactly its f32 columns rounded: one
/// kernel, only the store narrows. Elementwise, so it also runs on Mesa 25's SPIR-V path (f16, no
/// workgroup memory); skipped where the device has no native f16.
#[test]
fn f16_im2col_is_the_f32_columns_rounded() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let f16 = cubecl::ir::ElemType::Float(cubecl::ir::FloatKind::F16);
    if !dev.client().properties().supports_type(f16) {
        eprintln!("skipped: {} has no native f16", dev.context().describe());
        return;
    }
    // Output rows 1..3 of the second image, stride 2 and padding 1: a 7×6 input gives 4×3 outputs.
    let x = up(&dev, &randn(&[2, 3, 7, 6]));
    let window = ConvWindow {
        kh: 3,
        kw: 3,
        stride: 2,
        padding: 1,
        n0: 1,
        images: 1,
        oy0: 1,
        rows: 2,
        ow: 3,
    };
    let (full, half) = (
        im2col(&x, &window, false).unwrap(),
        im2col(&x, &window, true).unwrap(),
    );
    assert!(half.is_f16() && !full.is_f16());
    assert_eq!(half.dims(), [1, 27, 6]);
    let values = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let want = full
        .to_cpu()
        .unwrap()
        .to_dtype(candle_core::DType::F16)
        .unwrap()
        .to_dtype(candle_core::DType::F32)
        .unwrap();
    assert_eq!(values(half.to_cpu().unwrap()), values(want));
}

#[test]
fn im2col_strides_past_a_small_grid() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    // Images 1..3 of three, 2 channels, 3×3 taps: 360 output pixels (two cubes of 256) in the first
    // window, 5×4 from rows 1.. at stride 2 in the second. Grids of 1 and 2 cubes per dimension make
    // units walk several pixels, channels and images.
    let (cin, h, w) = (2, 20, 18);
    let cpu = randn(&[3, cin, h, w]);
    let x = up(&dev, &cpu);
    let values = cpu.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for (stride, padding, oy0, rows, ow) in [(1, 1, 0, 20, 18), (2, 1, 1, 5, 4)] {
        let window = ConvWindow {
            kh: 3,
            kw: 3,
            stride,
            padding,
            n0: 1,
            images: 2,
            oy0,
            rows,
            ow,
        };
        // The columns by their definition: image n0 + i, channel c, tap (ky, kx), output pixel p.
        let mut want = Vec::new();
        for image in 1..3 {
            for r in 0..cin * 9 {
                let (c, ky, kx) = (r / 9, r / 3 % 3, r % 3);
                for p in 0..rows * ow {
                    let y = ((oy0 + p / ow) * stride + ky) as isize - padding as isize;
                    let x = (p % ow * stride + kx) as isize - padding as isize;
                    let inside = (0..h as isize).contains(&y) && (0..w as isize).contains(&x);
                    want.push(if inside {
                        values[((image * cin + c) * h + y as usize) * w + x as usize]
                    } else {
                        0.0
                    });
                }
            }
        }
        // Every result stays alive, so no run can land in a buffer an earlier one filled.
        let mut kept = Vec::new();
        for limit in [1, 2, GRID_LIMIT] {
            let got = im2col_on_grid(&x, &window, false, limit).unwrap();
            assert_eq!(got.dims(), [2, cin * 9, rows * ow]);
            let got_values = got.to_cpu().unwrap().flatten_all().unwrap();
            let got_values = got_values.to_vec1::<f32>().unwrap();
            assert!(got_values == want, "stride {stride}, grid limit {limit}");
            kept.push(got);
        }
    }
}

#[test]
fn coalesced_walks_keep_every_offset() {
    // Offsets of every index along (shape, strides) and along the coalesced walk must agree.
    fn offsets(shape: &[usize], strides: &[usize]) -> Vec<usize> {
        let count: usize = shape.iter().product();
        (0..count)
            .map(|mut i| {
                let mut offset = 0;
                for d in (0..shape.len()).rev() {
                    offset += (i % shape[d]) * strides[d];
                    i /= shape[d];
                }
                offset
            })
            .collect()
    }
    /// Shape, two stride sets, the coalesced rank.
    type Case<'a> = (&'a [usize], &'a [usize], &'a [usize], usize);
    let cases: [Case; 6] = [
        // Equal shapes: one dimension.
        (&[2, 3, 4, 5], &[60, 20, 5, 1], &[60, 20, 5, 1], 1),
        // A per-channel bias over [batch, channels, h, w]: [batch, channels, h·w].
        (&[2, 3, 4, 5], &[60, 20, 5, 1], &[0, 1, 0, 0], 3),
        // A time embedding [batch, channels, 1, 1]: [batch·channels, h·w].
        (&[2, 3, 4, 5], &[60, 20, 5, 1], &[3, 1, 0, 0], 2),
        // A permute [0, 2, 3, 1] read from a contiguous [2, 3, 4, 5].
        (&[2, 4, 5, 3], &[60, 5, 1, 20], &[60, 15, 3, 1], 3),
        // Size-1 dimensions vanish; a broadcast of a scalar.
        (&[1, 6, 1, 7], &[42, 7, 7, 1], &[0, 0, 0, 0], 1),
        (&[1, 1], &[1, 1], &[1, 1], 1),
    ];
    for (shape, a, b, rank) in cases {
        let (walk, [wa, wb]) = coalesce(shape, [a, b]);
        assert_eq!(walk.len(), rank, "{shape:?} {a:?} {b:?} → {walk:?}");
        assert_eq!(
            walk.iter().product::<usize>(),
            shape.iter().product::<usize>()
        );
        assert_eq!(offsets(&walk, &wa), offsets(shape, a), "{shape:?} {a:?}");
        assert_eq!(offsets(&walk, &wb), offsets(shape, b), "{shape:?} {b:?}");
    }
}

/// The library product's finishing pass on its own (a product made up, so it also runs where the library
/// cannot: SPIR-V on lavapipe): scale, each bias mode, the residual, and a bias of the wrong length.
#[test]
fn product_epilogue_matches_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let (batch, m, n) = (3, 5, 7);
    let product = randn(&[batch, m, n]);
    let g = |alpha: f32| Gemm {
        batch,
        m,
        n,
        k: 1,
        a_strides: [0; 3],
        b_strides: [0; 3],
        alpha,
    };
    let (columns, rows, batch_rows) = (randn(&[n]), randn(&[m]), randn(&[batch, m]));
    let residual = randn(&[batch, m, n]);
    let (gc, gr, gbr) = (up(&dev, &columns), up(&dev, &rows), up(&dev, &batch_rows));
    let g_residual = up(&dev, &residual);
    let scaled = (&product * 0.5).unwrap();
    let cases = [
        ("scale", GemmBias::None, scaled.clone()),
        (
            "per column",
            GemmBias::PerColumn(&gc),
            scaled.broadcast_add(&columns).unwrap(),
        ),
        (
            "per row",
            GemmBias::PerRow(&gr),
            scaled
                .broadcast_add(&rows.reshape((m, 1)).unwrap())
                .unwrap(),
        ),
        (
            "per image and row",
            GemmBias::PerBatchRow(&gbr),
            scaled
                .broadcast_add(&batch_rows.reshape((batch, m, 1)).unwrap())
                .unwrap(),
        ),
    ];
    for (what, bias, want) in cases {
        let got = finish_product(up(&dev, &product), bias, None, &g(0.5)).unwrap();
        check(&format!("epilogue, {what}"), &got, &want);
        let got = finish_product(up(&dev, &product), bias, Some(&g_residual), &g(0.5)).unwrap();
        check(
            &format!("epilogue, {what} + residual"),
            &got,
            &(&want + &residual).unwrap(),
        );
    }
    let got = finish_product(
        up(&dev, &product),
        GemmBias::None,
        Some(&g_residual),
        &g(1.0),
    );
    check(
        "epilogue, residual alone",
        &got.unwrap(),
        &(&product + &residual).unwrap(),
    );
    assert!(finish_product(up(&dev, &product), GemmBias::PerRow(&gc), None, &g(1.0)).is_err());
}

#[test]
fn conv2d_matches_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    on_both_engines(|| conv2d_matches_cpu_on(&dev, &[ConvPath::Im2col, ConvPath::Direct]));
}

/// The direct kernel alone (no product, no workgroup memory: it runs on Mesa 25's SPIR-V path too).
#[test]
fn direct_conv2d_matches_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    conv2d_matches_cpu_on(&dev, &[ConvPath::Direct]);
}

/// Without a forced path a convolution takes the tuner's: the first call (the tuning round's output plus
/// the addend in a pass of its own) and the next (the settled path, the addend fused where that is
/// im2col) both agree with the CPU, and the problem is among the settled ones after the first.
#[test]
fn tuned_conv2d_matches_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    if let Some(path) = forced_conv_path() {
        eprintln!("skipped: VCEDIT_GPU_CONV forces {path}");
        return;
    }
    // A shape no other test takes, so that this test's first call is the one that settles it.
    let (n, cin, cout, h, w) = (2, 12, 20, 11, 13);
    let x = randn(&[n, cin, h, w]);
    let weight = randn(&[cout, cin, 3, 3]);
    let bias = randn(&[cout]);
    let residual = randn(&[n, cout, h, w]);
    let plain = crate::kernels::conv2d(&x, &weight, Some(&bias), 1, 1).unwrap();
    let want = (&plain + &residual).unwrap();
    let (gx, gw, gb, gr) = (
        up(&dev, &x),
        up(&dev, &weight),
        up(&dev, &bias),
        up(&dev, &residual),
    );
    let described = "x 2x12x11x13 w 20x12x3x3 s1 p1 +bias";
    for call in ["first", "second"] {
        let got = conv2d(&gx, &gw, Some(&gb), 1, 1, Addend::Residual(&gr)).unwrap();
        check(&format!("tuned conv2d, {call} call"), &got, &want);
        let settled = tuned_conv_paths();
        assert!(
            settled.iter().any(|(key, _)| key.starts_with(described)),
            "{described} not among the settled problems {settled:?}"
        );
    }
}

/// Convolutions on each of `paths` against the CPU's; im2col's blocks too where `paths` has it.
/// Pointwise convolutions are products on every path, so they are left out where im2col is.
fn conv2d_matches_cpu_on(dev: &GpuDevice, paths: &[ConvPath]) {
    let dev = dev.clone();
    let im2col = paths.contains(&ConvPath::Im2col);
    // (batch, cin, cout, h, w, kernel, stride, padding, bias)
    for (n, cin, cout, h, w, k, stride, padding, with_bias) in [
        (1, 3, 5, 9, 7, 3, 1, 1, true),
        (2, 4, 6, 9, 8, 3, 2, 1, false),
        (2, 5, 3, 6, 6, 1, 1, 0, true),
        (1, 2, 4, 5, 7, 3, 2, 0, true),
        // Output channels and rows past the small cases' (the product's tiles and im2col's bands).
        (2, 3, 11, 12, 10, 3, 1, 1, true),
        // Channels the direct kernel reads and writes as vectors of four (above: one at a time).
        (2, 8, 12, 7, 9, 3, 1, 1, true),
        (1, 8, 8, 9, 9, 3, 2, 1, false),
    ] {
        if k == 1 && !im2col {
            continue;
        }
        let x = randn(&[n, cin, h, w]);
        let weight = randn(&[cout, cin, k, k]);
        let bias = with_bias.then(|| randn(&[cout]));
        let plain = crate::kernels::conv2d(&x, &weight, bias.as_ref(), stride, padding).unwrap();
        let gbias = bias.as_ref().map(|b| up(&dev, b));
        let (oh, ow) = (plain.dims()[2], plain.dims()[3]);
        // What the convolution adds in its finishing pass: nothing, a skip connection, a time embedding.
        let residual = randn(&[n, cout, oh, ow]);
        let per_channel = randn(&[n, cout]);
        let (g_residual, g_per_channel) = (up(&dev, &residual), up(&dev, &per_channel));
        let addends = [
            ("", Addend::None, plain.clone()),
            (
                " + residual",
                Addend::Residual(&g_residual),
                (&plain + &residual).unwrap(),
            ),
            (
                " + per channel",
                Addend::PerChannel(&g_per_channel),
                plain
                    .broadcast_add(&per_channel.reshape((n, cout, 1, 1)).unwrap())
                    .unwrap(),
            ),
        ];
        let (gx, gw) = (up(&dev, &x), up(&dev, &weight));
        for (what, addend, want) in &addends {
            for &path in paths {
                let got = with_conv_path(path, || {
                    conv2d(&gx, &gw, gbias.as_ref(), stride, padding, *addend)
                })
                .unwrap();
                check(
                    &format!("conv2d ({path}) c{cin}→{cout} k{k} s{stride} p{padding}{what}"),
                    &got,
                    want,
                );
            }
            if !im2col {
                continue;
            }
            // Blocked: one image per block, then bands of one and of three output rows (the last band
            // shorter where the rows do not divide).
            let per_row = cin * k * k * ow * 4;
            for cap in [per_row * oh, per_row, 3 * per_row] {
                let got = conv2d_blocked(&gx, &gw, gbias.as_ref(), stride, padding, *addend, cap)
                    .unwrap();
                check(
                    &format!("conv2d k{k} s{stride} p{padding}{what}, im2col cap {cap}"),
                    &got,
                    want,
                );
            }
        }
    }
}

#[test]
fn norms_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    // Offset inputs test the two-pass variance. Groups of 70, 256 and 600 elements: cubes of 32, 64
    // and 128 units.
    for (shape, groups) in [
        (&[2usize, 8, 5, 7][..], 4),
        (&[2, 16, 8, 8][..], 4),
        (&[1, 6, 300][..], 3),
    ] {
        let c = shape[1];
        let x = randn(shape).affine(2.0, 3.0).unwrap();
        let (w, b) = (randn(&[c]), randn(&[c]));
        for silu in [false, true] {
            let want = crate::kernels::group_norm(&x, &w, &b, groups, 1e-5, silu).unwrap();
            let got = group_norm_on(
                &up(&dev, &x),
                &up(&dev, &w),
                &up(&dev, &b),
                groups,
                1e-5,
                silu,
                false,
            )
            .unwrap();
            check(
                &format!("group_norm {shape:?} / {groups} silu={silu}"),
                &got,
                &want,
            );
        }
    }
    let x = randn(&[2, 8, 5, 7]);
    let w = randn(&[8]);
    let short_bias = up(&dev, &randn(&[7]));
    assert!(group_norm(&up(&dev, &x), &up(&dev, &w), &short_bias, 4, 1e-5, false).is_err());
    // Groups large enough to split over cubes: channels of two chunks (the second short), of one
    // partial chunk, and a 3D input; offset and scaled per channel so the combined statistics matter.
    for (shape, groups) in [
        (&[2usize, 8, 64, 70][..], 4),
        (&[1, 32, 30, 30][..], 2),
        (&[3, 6, 5000][..], 3),
    ] {
        let c = shape[1];
        let offsets = Tensor::arange(0f32, c as f32, &Device::Cpu).unwrap();
        let mut per_channel = vec![1usize; shape.len()];
        per_channel[1] = c;
        let x = randn(shape)
            .broadcast_mul(
                &offsets
                    .affine(0.5, 1.0)
                    .unwrap()
                    .reshape(per_channel.clone())
                    .unwrap(),
            )
            .unwrap()
            .broadcast_add(
                &offsets
                    .affine(3.0, -4.0)
                    .unwrap()
                    .reshape(per_channel)
                    .unwrap(),
            )
            .unwrap();
        let (w, b) = (randn(&[c]), randn(&[c]));
        let (gx, gw, gb) = (up(&dev, &x), up(&dev, &w), up(&dev, &b));
        for (silu, split) in [(false, true), (true, true), (true, false)] {
            let want = crate::kernels::group_norm(&x, &w, &b, groups, 1e-5, silu).unwrap();
            let got = group_norm_on(&gx, &gw, &gb, groups, 1e-5, silu, split).unwrap();
            check(
                &format!("group_norm {shape:?} / {groups} silu={silu} split={split}"),
                &got,
                &want,
            );
        }
    }
    // Rows on every cube width: 32 units (5, 64 wide), 64 (256), 128 (300, 2000).
    for width in [5, 64, 256, 300, 2000] {
        let x = (randn(&[3, 4, width]) + 1.0).unwrap();
        let (w, b) = (randn(&[width]), randn(&[width]));
        let want = crate::kernels::layer_norm(&x, &w, &b, 1e-5).unwrap();
        check(
            &format!("layer_norm {width} wide"),
            &layer_norm(&up(&dev, &x), &up(&dev, &w), &up(&dev, &b), 1e-5).unwrap(),
            &want,
        );
    }
    assert_eq!(
        [5, 64, 128, 256, 300, 2000].map(row_units),
        [32, 32, 32, 64, 128, 128]
    );
}

#[test]
fn softmax_and_geglu_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    // Cubes of 32 (1, 7), 64 (200) and 128 units (300).
    for width in [1, 7, 200, 300] {
        let x = (randn(&[3, 5, width]) * 4.0).unwrap();
        let want = crate::kernels::softmax_last_dim(&x).unwrap();
        check(
            &format!("softmax width {width}"),
            &softmax_last_dim(&up(&dev, &x)).unwrap(),
            &want,
        );
    }
    let x = randn(&[2, 6, 40]);
    check(
        "geglu",
        &geglu(&up(&dev, &x)).unwrap(),
        &crate::kernels::geglu(&x).unwrap(),
    );
    assert!(geglu(&up(&dev, &randn(&[2, 3]))).is_err());
}

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
    let want_probs =
        crate::kernels::softmax_last_dim(&(q.matmul(&k.t().unwrap()).unwrap() * scale).unwrap())
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

/// The library takes the products the networks make (were it to decline them all, every product would
/// silently fall back to our kernel): batched, shared and transposed B, f16 weights.
#[test]
fn the_library_takes_the_networks_products() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    let (m, k, n) = (17, 19, 21);
    let a = up(&dev, &randn(&[2, m, k]));
    let gemm = |b_strides: [usize; 3]| Gemm {
        batch: 2,
        m,
        n,
        k,
        a_strides: [m * k, k, 1],
        b_strides,
        alpha: 1.0,
    };
    let batched = up(&dev, &randn(&[2, k, n]));
    let shared = up(&dev, &randn(&[k, n]));
    let transposed = up(&dev, &randn(&[2, n, k]));
    let half_dev = GpuDevice::with_precision(dev.context().clone(), Precision::F16);
    let half = half_dev.cached_matrix(&randn(&[k, n])).unwrap();
    assert!(half.is_f16());
    for (what, b, strides) in [
        ("batched", &batched, [k * n, n, 1]),
        ("shared", &shared, [0, n, 1]),
        ("transposed", &transposed, [n * k, 1, k]),
        ("f16 weight", &half, [0, n, 1]),
    ] {
        let out = library_gemm(&a, b, &gemm(strides), &[2, m, n]);
        assert!(out.is_some(), "{what}: the library declined");
    }
    assert!(with_own_matmul(|| library_gemm(&a, &shared, &gemm([0, n, 1]), &[2, m, n])).is_none());
    // Each product records how it ran (no read-back: see .ci/run on Mesa 25).
    let weight = up(&dev, &randn(&[n, k]));
    linear(&a, &weight, None, None).unwrap();
    let expected = match matmul_path(&dev) {
        MatmulPath::TensorCores => DEFAULT_TENSOR_CORE_ROUTINE,
        MatmulPath::UnitF16 => "unit-f16",
        _ => "unit",
    };
    assert_eq!(last_product_route(), expected);
    with_own_matmul(|| linear(&a, &weight, None, None)).unwrap();
    assert_eq!(last_product_route(), "own");
}

#[test]
fn tensor_core_routines_are_known_by_their_library_names() {
    for name in TENSOR_CORE_ROUTINES {
        let strategy = tensor_core_strategy(name).to_string();
        // The tile-DSL family names its routines without the prefix.
        let library_name = match name.strip_prefix("tiled_") {
            Some(tiled) => tiled.to_string(),
            None => format!("matmul_{name}"),
        };
        assert!(strategy.starts_with(&library_name), "{name}: {strategy}");
        assert_eq!(
            with_tensor_core_routine(name, tensor_core_routine).unwrap(),
            name
        );
    }
    assert_eq!(tensor_core_routine(), DEFAULT_TENSOR_CORE_ROUTINE);
    let unknown = with_tensor_core_routine("fastest", || ()).unwrap_err();
    assert!(unknown
        .to_string()
        .contains("unknown tensor-core routine 'fastest'"));
}

/// A bench that catches one routine's or tiling's panic goes on with the thread's own choice.
#[test]
fn routine_and_tiling_overrides_end_with_a_panic() {
    let tiling = Tiling::parse("planes=4,k=2").unwrap();
    let caught = std::panic::catch_unwind(|| {
        with_matmul_tiling(tiling, || {
            assert_eq!(matmul_tiling(), tiling);
            with_tensor_core_routine("double_cyclic_cmma", || {
                assert_eq!(tensor_core_routine(), "double_cyclic_cmma");
                panic!("a kernel the card cannot compile")
            })
        })
    });
    assert!(caught.is_err());
    assert!(matmul_tiling().is_default());
    assert_eq!(tensor_core_routine(), DEFAULT_TENSOR_CORE_ROUTINE);
}

#[test]
fn vgg_feature_loss_ops_match_cpu() {
    let Some(dev) = device_or_skip() else {
        return;
    };
    use crate::kernels::vgg;
    // Odd sides: the pool drops the last row and column.
    let x = randn(&[2, 3, 7, 9]);
    let gx = up(&dev, &x);
    let pooled = vgg::max_pool2x2(&x).unwrap();
    check("max_pool2x2", &max_pool2x2(&gx).unwrap(), &pooled);
    let g = randn(pooled.dims());
    check(
        "max_pool2x2_backward",
        &max_pool2x2_backward(&gx, &up(&dev, &g)).unwrap(),
        &vgg::max_pool2x2_backward(&x, &g).unwrap(),
    );
    let out = x.relu().unwrap();
    let gr = randn(x.dims());
    check(
        "relu_backward",
        &relu_backward(&up(&dev, &out), &up(&dev, &gr)).unwrap(),
        &vgg::relu_backward(&out, &gr).unwrap(),
    );
    check(
        "normalize_channels",
        &normalize_channels(&gx, 1e-10).unwrap(),
        &vgg::normalize_channels(&x, 1e-10).unwrap(),
    );
    let t = vgg::normalize_channels(&randn(x.dims()), 1e-10).unwrap();
    let lin = randn(&[3]).abs().unwrap();
    let lin_gpu = up(&dev, &lin);
    for with_grad in [false, true] {
        let (map, grad) =
            lpips_distance(&up(&dev, &out), &up(&dev, &t), &lin_gpu, 1e-10, with_grad).unwrap();
        let (want_map, want_grad) = vgg::lpips_distance(&out, &t, &lin, 1e-10, with_grad).unwrap();
        check("lpips_distance map", &map, &want_map);
        assert_eq!(grad.is_some(), with_grad);
        if let (Some(grad), Some(want)) = (grad, want_grad) {
            check("lpips_distance grad", &grad, &want);
        }
    }
}
