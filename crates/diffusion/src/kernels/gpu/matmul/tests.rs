//! The products against their CPU twins, on both engines (the library and our kernel).

use candle_core::Tensor;

use super::*;
use crate::kernels::gpu::ops::*;
use crate::kernels::gpu::testing::*;

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
        crate::kernels::conv2d(
            &x,
            &w.clone().into(),
            Some(&bias.narrow(0, 0, 6).unwrap()),
            1,
            1,
        )
        .unwrap()
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
            crate::kernels::conv2d(&rounded_f16(&xi), &rounded_f16(&conv_w).into(), None, 1, 1)
                .unwrap();
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
