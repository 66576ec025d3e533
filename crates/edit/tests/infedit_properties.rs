//! Properties of the InfEdit sampler and its token alignment that hold whatever the model weights.

use std::path::PathBuf;

use candle_core::{IndexOp, Tensor};
use diffusion::tokenizer::ClipTokenizer;
use edit::sampler::{
    align_prompts, global_align, AlignInputs, EditModel, EditPlan, EditPrompts, InfEditSettings,
    NoiseSource, SeededNoise,
};
use testkit::diff::tensor_max_abs_diff;
use testkit::paths::fixtures;

fn test_image(size: usize) -> Tensor {
    let v: Vec<f32> = (0..3 * size * size)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    Tensor::from_vec(v, (1, 3, size, size), &candle_core::Device::Cpu).unwrap()
}

/// With identical prompts and guidance, the target branch sees exactly what the source sees (same latents,
/// same attention after control), so every x̂0_T is the source latents x0: the edit reproduces its input.
#[test]
fn identical_prompts_reproduce_the_source() {
    let model = EditModel::load(&fixtures().join("models/tiny-lcm"), None).unwrap();
    let prompts = EditPrompts::new("a red sphere on a table", "a red sphere on a table");
    let settings = InfEditSettings {
        steps: 6,
        guidance_source: 2.0,
        guidance_target: 2.0,
        ..Default::default()
    };
    let plan = EditPlan::new(&model, &prompts, &settings, (64, 64)).unwrap();
    let mut noise = SeededNoise::new(5);
    let x0 = model.encode(&test_image(64), &mut noise).unwrap();
    let init = noise.sample(&plan.latent_shape()).unwrap();
    let mut view = plan.initial_state(x0.clone(), &init).unwrap();
    for i in 0..plan.timesteps.len() {
        plan.step(&model, &mut view, i, &mut noise).unwrap();
        let err = tensor_max_abs_diff(view.pred_t.as_ref().unwrap(), &x0);
        assert!(err < 1e-4, "step {i}: x̂0_T differs from x0 by {err}");
        assert!(
            tensor_max_abs_diff(&view.z_t, &view.z_s) < 1e-4,
            "step {i}: target latents left the source's"
        );
    }
}

/// With cross_replace = 1 the stored (refined) target maps are exactly the source maps gathered through the
/// token mapper: for "a man" → "a clown" every token is mapped, so the stored target-blend maps equal the
/// source maps token for token.
#[test]
fn full_cross_replace_stores_the_mapped_source_maps() {
    let model = EditModel::load(&fixtures().join("models/tiny-lcm"), None).unwrap();
    let prompts = EditPrompts::new("a man", "a clown");
    let settings = InfEditSettings {
        steps: 3,
        cross_replace: 1.0,
        ..Default::default()
    };
    let plan = EditPlan::new(&model, &prompts, &settings, (64, 64)).unwrap();
    assert!(
        plan.alignment.alphas.iter().all(|&a| a == 1.0),
        "{:?}",
        &plan.alignment.alphas[..5]
    );
    let mut noise = SeededNoise::new(1);
    let x0 = model.encode(&test_image(64), &mut noise).unwrap();
    let init = noise.sample(&plan.latent_shape()).unwrap();
    let mut view = plan.initial_state(x0, &init).unwrap();
    view.controller.start_recording();
    plan.predict(&model, &mut view, 0).unwrap();
    let recorded = view.controller.finish_recording();
    assert!(!recorded.is_empty());
    for rec in &recorded {
        // [3 branches, heads, N, tokens]: the target's maps after control = source maps through the mapper.
        let maps = rec.maps.to_cpu().unwrap();
        let src = maps.i(0).unwrap();
        let tgt = maps.i(1).unwrap();
        let mapper: Vec<u32> = plan
            .alignment
            .mapper
            .iter()
            .map(|m| m.unwrap() as u32)
            .collect();
        let idx = Tensor::new(mapper, &candle_core::Device::Cpu).unwrap();
        let mapped = src.index_select(&idx, 2).unwrap();
        assert!(tensor_max_abs_diff(&mapped, &tgt) < 1e-6, "{}", rec.layer);
    }
}

fn real_tokenizer() -> Option<ClipTokenizer> {
    let vocab = testkit::paths::shared_asset("clip-bpe/vocab.json")?;
    Some(ClipTokenizer::from_dir(vocab.parent().unwrap()).unwrap())
}

/// Hidden states that make the similarity pass pick, in each unmatched run, the pair (target t, source s)
/// with the smallest |t − s| (row p is a unit vector at angle p / 10).
fn positional_hidden(len: usize) -> Vec<Vec<f32>> {
    (0..len)
        .map(|p| vec![(p as f32 / 10.0).cos(), (p as f32 / 10.0).sin()])
        .collect()
}

#[test]
fn alignment_on_the_real_vocabulary() {
    let Some(tok) = real_tokenizer() else { return };
    let h = positional_hidden(77);
    let align = |src: &str, tgt: &str, local: &str| {
        align_prompts(&AlignInputs {
            source_ids: &tok.encode_unpadded(src),
            target_ids: &tok.encode_unpadded(tgt),
            local_ids: &tok.encode_unpadded(local),
            mutual_ids: &tok.encode_unpadded(""),
            source_hidden: &h,
            target_hidden: &h,
            max_len: 77,
        })
        .unwrap()
    };

    // "a man" → "a clown": "clown" replaces "man" and is matched to it by similarity.
    let a = align("a man", "a clown", "clown");
    assert_eq!(tok.encode_unpadded("a man"), vec![49406, 320, 786, 49407]);
    assert_eq!(&a.mapper[..4], &[Some(0), Some(1), Some(2), Some(3)]);
    assert_eq!(&a.alphas[..4], &[1.0; 4]);
    assert_eq!(&a.alpha_e[..4], &[0.0, 0.0, 1.0, 0.0]);

    // "a photo of a cat" → "a photo of a dog wearing a hat": the shared words align, the new run gets one
    // similarity match, the rest keep their own maps.
    let src = tok.encode_unpadded("a photo of a cat");
    let tgt = tok.encode_unpadded("a photo of a dog wearing a hat");
    assert_eq!(src, vec![49406, 320, 1125, 539, 320, 2368, 49407]);
    let a = align(
        "a photo of a cat",
        "a photo of a dog wearing a hat",
        "dog wearing a hat",
    );
    assert_eq!(&a.mapper[..4], &[Some(0), Some(1), Some(2), Some(3)]);
    assert_eq!(
        a.mapper[tgt.len() - 1],
        Some(src.len() - 1),
        "EOT aligns with EOT"
    );
    let matched = a.alphas[..tgt.len()].iter().filter(|&&x| x == 1.0).count();
    let base_matched = global_align(&src, &tgt)
        .iter()
        .filter(|m| m.is_some())
        .count();
    assert_eq!(
        matched,
        base_matched + 1,
        "one similarity match in the unmatched run"
    );
    // Blend words: dog, wearing, a, hat → 4 target tokens flagged.
    assert_eq!(a.alpha_e.iter().sum::<f32>(), 4.0);

    // Reordered words: the alignment keeps the longest common subsequence in order.
    let src = tok.encode_unpadded("a red vase on a table");
    let tgt = tok.encode_unpadded("a table with a red vase");
    let g = global_align(&src, &tgt);
    let pairs: Vec<(usize, usize)> = g
        .iter()
        .enumerate()
        .filter_map(|(t, s)| s.map(|s| (t, s)))
        .collect();
    assert!(
        pairs.windows(2).all(|w| w[0].1 < w[1].1),
        "monotone alignment: {pairs:?}"
    );
    for (t, s) in pairs {
        assert_eq!(tgt[t], src[s], "aligned tokens are equal");
    }
}

/// Everything a view's step leaves that anyone reads: the recorded CCM maps (when the step records),
/// the guided ε of every branch, x̂0_T and x̂0_M, the accumulated blend-layer maps and the blend maps.
fn sample_trace(
    model: &EditModel,
    settings: &InfEditSettings,
    size: usize,
    skip_unread: bool,
    recording_steps: &[usize],
) -> Vec<(String, Tensor)> {
    let prompts = EditPrompts::new("a red sphere on a table", "a blue cube on a table");
    let mut plan = EditPlan::new(model, &prompts, settings, (size, size)).unwrap();
    plan.skip_unread = skip_unread;
    let mut noise = SeededNoise::new(3);
    let x0 = model.encode(&test_image(size), &mut noise).unwrap();
    let init = noise.sample(&plan.latent_shape()).unwrap();
    let mut view = plan.initial_state(x0, &init).unwrap();
    let mut trace = Vec::new();
    for i in 0..plan.timesteps.len() {
        if recording_steps.contains(&i) {
            let recorded = plan
                .record_views(model, &mut [&mut view], i)
                .unwrap()
                .0
                .remove(0);
            assert!(!recorded.is_empty());
            // Substitute them (scaled, as CCM substitutes other maps) so the replacing pass is traced too.
            let mut maps = std::collections::HashMap::new();
            for rec in recorded {
                trace.push((
                    format!("step {i} recorded {}", rec.layer),
                    rec.maps.to_cpu().unwrap(),
                ));
                maps.insert(rec.layer, rec.maps.affine(0.9, 0.0).unwrap());
            }
            view.controller.set_consistent_maps(maps);
        }
        let eps = plan.predict(model, &mut view, i).unwrap();
        for (b, e) in ["S", "T", "M"].iter().zip(eps.iter()) {
            trace.push((format!("step {i} eps_{b}"), e.clone()));
        }
        view.controller.end_step();
        let n = noise.sample(&plan.latent_shape()).unwrap();
        plan.update(&mut view, i, &eps, &n).unwrap();
        trace.push((format!("step {i} x0_T"), view.pred_t.clone().unwrap()));
        trace.push((format!("step {i} x0_M"), view.pred_m.clone().unwrap()));
        if i > 0 {
            let maps = plan.local_blend(&mut view, i).unwrap();
            trace.push((format!("step {i} blend maps"), maps));
            for (layer, store) in view.controller.blend_store().unwrap() {
                trace.push((format!("step {i} blend store {layer}"), store));
            }
        }
    }
    trace
}

/// The largest difference of two traces, relative to each entry's largest magnitude.
fn trace_difference(a: &[(String, Tensor)], b: &[(String, Tensor)]) -> f32 {
    assert_eq!(a.len(), b.len());
    let mut worst = 0f32;
    for ((name_a, x), (name_b, y)) in a.iter().zip(b) {
        assert_eq!(name_a, name_b);
        let scale = testkit::diff::tensor_max_abs(x).max(1e-6);
        let rel = tensor_max_abs_diff(x, y) / scale;
        assert!(rel < 1e-4, "{name_a}: relative difference {rel}");
        worst = worst.max(rel);
    }
    worst
}

/// Leaving out the UNet samples nobody reads (`BatchLayout`) changes nothing read: every branch's ε and
/// x̂0, the recorded and substituted CCM maps and the blend maps equal those of the batch of six to float
/// rounding, in both phases of the self-attention swap, with and without source guidance and CFG.
#[test]
fn unread_samples_left_out_change_nothing_read() {
    let model = EditModel::load(&fixtures().join("models/tiny-lcm"), None).unwrap();
    let base = InfEditSettings {
        steps: 6,
        self_replace: 0.5,
        cross_replace: 0.5,
        ..Default::default()
    };
    // At 64² every layer of the tiny model is small (recorded); the demo model's test below has a
    // last up block without attention, after which its recording passes stop.
    let cases = [
        ("default guidance", base.clone(), 64),
        (
            "source guidance 2",
            InfEditSettings {
                guidance_source: 2.0,
                ..base.clone()
            },
            64,
        ),
        (
            "no CFG",
            InfEditSettings {
                guidance_target: 1.0,
                ..base.clone()
            },
            64,
        ),
    ];
    for (name, settings, size) in cases {
        let all = sample_trace(&model, &settings, size, false, &[1, 4]);
        let needed = sample_trace(&model, &settings, size, true, &[1, 4]);
        let worst = trace_difference(&all, &needed);
        eprintln!("tiny model, {name}: largest relative difference {worst:e}");
    }
}

/// The same on the demo model (models/demo) with the demo's settings (target guidance 3, blend level 1).
#[test]
fn unread_samples_left_out_change_nothing_read_on_the_demo_model() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../models/demo");
    let model = EditModel::load(&dir, None).unwrap();
    let settings = InfEditSettings {
        steps: 5,
        cross_replace: 0.3,
        thresh_e: 0.3,
        guidance_target: 3.0,
        blend_level: Some(1),
        self_replace: 0.5,
        ..Default::default()
    };
    let all = sample_trace(&model, &settings, 64, false, &[1, 3]);
    let needed = sample_trace(&model, &settings, 64, true, &[1, 3]);
    let worst = trace_difference(&all, &needed);
    eprintln!("demo model: largest relative difference {worst:e}");
}
