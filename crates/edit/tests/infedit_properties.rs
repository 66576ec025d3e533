//! Properties of the InfEdit sampler and its token alignment that hold whatever the model weights.

use std::path::PathBuf;

use candle_core::{IndexOp, Tensor};
use diffusion::tokenizer::ClipTokenizer;
use edit::sampler::{
    align_prompts, global_align, AlignInputs, EditModel, EditPlan, EditPrompts, InfEditSettings,
    NoiseSource, SeededNoise,
};

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    a.sub(b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

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
        let eps = plan.predict(&model, &mut view, i).unwrap();
        view.controller.end_step();
        let n = noise.sample(&plan.latent_shape()).unwrap();
        plan.update(&mut view, i, &eps, &n).unwrap();
        if i > 0 {
            plan.local_blend(&mut view, i).unwrap();
        }
        let err = max_abs(view.pred_t.as_ref().unwrap(), &x0);
        assert!(err < 1e-4, "step {i}: x̂0_T differs from x0 by {err}");
        assert!(
            max_abs(&view.z_t, &view.z_s) < 1e-4,
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
        let src = rec.maps.i(0).unwrap();
        let tgt = rec.maps.i(1).unwrap();
        let mapper: Vec<u32> = plan
            .alignment
            .mapper
            .iter()
            .map(|m| m.unwrap() as u32)
            .collect();
        let idx = Tensor::new(mapper, &candle_core::Device::Cpu).unwrap();
        let mapped = src.index_select(&idx, 2).unwrap();
        assert!(max_abs(&mapped, &tgt) < 1e-6, "{}", rec.layer);
    }
}

fn real_tokenizer() -> Option<ClipTokenizer> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/assets/clip-bpe");
    if !dir.join("vocab.json").is_file() {
        eprintln!("skipping: {} not present", dir.display());
        return None;
    }
    Some(ClipTokenizer::from_dir(&dir).unwrap())
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
